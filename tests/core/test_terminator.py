"""Cycles' shadow terminator rule for smooth-shaded low-poly faces (core.sampling.terminator)."""
import numpy as np

from core.pipeline.prepare import prepare
from core.sampling.terminator import lift_amount, smooth_surface_offsets
from core.scene import Light, Material, Mesh, Scene
from core.settings import BakeSettings
from core.transport.direct import lamp_irradiance


def _prism(segments=6, radius=0.5, height=1.0, smooth=True):
    """An open low-poly cylinder around z, its faces outward; smooth: vertex normals radial."""
    angles = 2 * np.pi * np.arange(segments) / segments
    ring = np.stack([radius * np.cos(angles), radius * np.sin(angles), np.zeros(segments)], axis=1)
    positions = np.concatenate([ring, ring + [0, 0, height]])
    triangles, normals, uvs = [], [], []
    for i in range(segments):
        j = (i + 1) % segments
        for tri in ([i, j, segments + j], [i, segments + j, segments + i]):
            triangles.append(tri)
            corner = positions[tri] * [1, 1, 0]
            radial = corner / np.linalg.norm(corner, axis=1, keepdims=True)
            normals.append(radial)
            u = np.array([(i + (1 if c in (j, segments + j) else 0)) / segments for c in tri])
            v = np.array([1.0 if c >= segments else 0.0 for c in tri])
            uvs.append(np.stack([u, v], axis=1))
    triangles = np.array(triangles, np.int32)
    normals = np.array(normals, np.float32)
    if not smooth:
        face = np.cross(positions[triangles[:, 1]] - positions[triangles[:, 0]],
                        positions[triangles[:, 2]] - positions[triangles[:, 0]])
        face /= np.linalg.norm(face, axis=1, keepdims=True)
        normals = np.repeat(face[:, None, :], 3, axis=1).astype(np.float32)
    uv = np.array(uvs, np.float32) * 0.98 + 0.01
    return Mesh(name="Prism", positions=positions, triangles=triangles, corner_normals=normals,
                material_index=np.zeros(len(triangles), np.int32), materials=[Material()],
                uv_maps={"UVMap": uv}, bake_uv_map="UVMap", resolution=(64, 16))


def test_flat_faces_get_no_lift_and_smooth_ones_are_lifted_outwards():
    for smooth in (False, True):
        mesh = _prism(smooth=smooth)
        face = np.cross(mesh.positions[mesh.triangles[:, 1]] - mesh.positions[mesh.triangles[:, 0]],
                        mesh.positions[mesh.triangles[:, 2]] - mesh.positions[mesh.triangles[:, 0]])
        face /= np.linalg.norm(face, axis=1, keepdims=True)
        tri = np.arange(len(mesh.triangles))
        weights = np.tile([1 / 3, 1 / 3, 1 / 3], (len(tri), 1))
        lift = smooth_surface_offsets(mesh.positions, mesh.triangles, mesh.corner_normals, face[tri], tri, weights)
        if not smooth:
            np.testing.assert_allclose(lift, 0.0, atol=1e-7)  # float32 normals of a flat face
            continue
        height = np.einsum("kd,kd->k", lift, face)
        # Outwards, by about the circle's bulge over the chord, r (1 - cos(pi / 6)) = 0.067.
        assert np.all(height > 0.03) and np.all(height < 0.1)


def test_lift_amount_follows_cycles_formula():
    cutoff = np.full(5, 0.1)
    shading = np.array([0.5, 0.05, 0.05, 0.5, -0.3])
    geometric = np.array([0.5, -0.02, 0.08, 0.02, 0.3])
    amount = lift_amount(shading, geometric, cutoff)
    np.testing.assert_allclose(amount, [0.0, 1.0, 0.7, 0.8, 1.0], atol=1e-12)
    assert np.all(lift_amount(shading, geometric, np.zeros(5)) == 0.0)


def test_a_smooth_low_poly_cylinder_is_lit_past_its_flat_faces_horizon():
    sun = Light("Sun", "SUN", np.ones(3), 1.0, direction=np.array([-1.0, 0.0, 0.0]))
    results = {}
    for smooth in (False, True):
        mesh = _prism(smooth=smooth)
        p = prepare(Scene([mesh], []), BakeSettings(directions=8, bounces=0, footprint_samples=1),
                    table_needed=False)
        irradiance, _ = lamp_irradiance(p.sample_set(), p.shadowing(), [sun])
        facing_away = p.geometric[:, 0] <= 0.0  # faces whose flat plane does not see the sun
        shading_lit = p.normal[:, 0] > 0.05
        results[smooth] = (irradiance[:, 0], facing_away & shading_lit, p.sample_set().terminator)
    flat, _, no_lift = results[False]
    smooth, terminator_band, lift = results[True]
    assert no_lift is None and lift is not None
    assert np.any(terminator_band)
    # Flat faces are dark past their horizon; smooth ones are lit there by their shading
    # normal where the lifted shadow ray clears the mesh, as Cycles lights them.
    assert np.all(flat[results[False][1] if np.any(results[False][1]) else slice(0)] == 0.0)
    assert np.any(smooth[terminator_band] > 0.0)
