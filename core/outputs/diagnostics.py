"""Where vertex tables are too coarse: triangles whose light varies inside them.

A vertex-mode object shows light interpolated between its vertices, so a shadow edge
or a highlight that falls inside a large triangle is lost. This check evaluates the
lamps' direct light (exact shadows) at every triangle's middle and at its three
corners' samples, and flags the triangle when the middle differs from the corners'
mean by more than a set share: the triangles to subdivide, or the objects to bake
as an atlas.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .. import tolerances as tol
from ..geometry import mesh_face_normals, triangle_areas
from ..transport.contract import SampleSet, Shadowing
from ..transport.direct import lamp_irradiance


@dataclass
class TessellationCheck:
    """The verdict on one vertex-mode object.

    flagged : triangles whose middle's light differs from the corners' mean
    triangles : triangles checked (the valid ones)
    area_share : flagged area over the object's area
    worst : the largest difference, relative to the larger of the two values
    """

    flagged: int
    triangles: int
    area_share: float
    worst: float
    flagged_triangles: np.ndarray = None  # (flagged,) int64 indices into the mesh's triangles


def _direct_light(shadowing: Shadowing, lights, samples: SampleSet) -> np.ndarray:
    """Lamp irradiance (K, 3) at ``samples`` with exact shadows, through the CPU backend's direct light."""
    irradiance, _ = lamp_irradiance(samples, shadowing, lights)
    return irradiance


def check_vertex_objects(meshes, object_samples, sample_offset: np.ndarray, position: np.ndarray,
                         normal: np.ndarray, shadowing: Shadowing, lights) -> dict[int, TessellationCheck]:
    """Check every vertex-mode object with outputs under ``lights``.

    meshes : the bake's core.scene.Mesh objects; object_samples : their
    core.sampling.samples.ObjectSamples; sample_offset : (objects + 1,) int64 first
    sample of each; position, normal : (K, 3) float64 every sample's position and shading
    normal; shadowing : exact shadows (its ray scene).

    Returns object index -> TessellationCheck (no entry without lamps or such objects).
    """
    checks = {}
    if not lights:
        return checks
    for index, mesh in enumerate(meshes):
        if mesh.mode != "vertex" or not mesh.output:
            continue
        object_sample = object_samples[index]
        a = sample_offset[index]
        normals, valid = mesh_face_normals(mesh)
        used = np.nonzero(valid & np.all(object_sample.corner_sample >= 0, axis=1))[0]
        if len(used) == 0:
            continue
        corners = mesh.positions[mesh.triangles[used]].astype(np.float64)
        middle = corners.mean(axis=1)
        at_middle = _direct_light(shadowing, lights, SampleSet.on_surface(middle, normals[used])).sum(axis=1)
        rows = a + object_sample.corner_sample[used]
        own = slice(a, a + len(object_sample))
        at_vertices = _direct_light(shadowing, lights,
                                    SampleSet.on_surface(position[own], normal[own])).sum(axis=1)
        interpolated = at_vertices[rows - a].mean(axis=1)
        larger = np.maximum(at_middle, interpolated)
        floor = tol.TESSELLATION_FLOOR * max(float(larger.max()), 1e-30)
        difference = np.abs(at_middle - interpolated) / np.maximum(larger, floor)
        flagged = (difference > tol.TESSELLATION_DIFFERENCE) & (larger > floor)
        areas = triangle_areas(corners)
        checks[index] = TessellationCheck(flagged=int(np.count_nonzero(flagged)), triangles=len(used),
                                          area_share=float(areas[flagged].sum() / max(areas.sum(), 1e-30)),
                                          worst=float(difference[larger > floor].max(initial=0.0)),
                                          flagged_triangles=used[flagged].astype(np.int64))
    return checks
