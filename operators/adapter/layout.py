"""Blender side of the atlas: which UV map each object bakes on, and unwrapping.

A user's UV map is used when it is valid for baking; otherwise the mesh gets a new
UV map named ``VisiBake`` (unwrapped with xatlas on the base mesh, so modifiers
interpolate it like any other UV map). Maps VisiBake created are marked on the
mesh, and only those are ever rewritten or removed.
"""
from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import bpy

import numpy as np

from ...core.errors import LayoutError, UnwrapFailed
from ...core.geometry import triangle_areas
from ...core.sampling import layout as policy
from ...core.sampling.atlas import UnwrapResult, loop_uvs, unwrap, uv_layout_problems

# Kept importable from here for the tests that name the policy's limits through the adapter.
from ...core.sampling.layout import TYPICAL_PACKED_UV_AREA
from ...core.sampling.unwrap_child import ChildUnavailable, UnwrapHung, UnwrapWorker, unwrap_in_child
from ...core.sampling.unwrap_memo import UnwrapMemo, unwrap_key
from .extract import read_triangles

UV_MAP_NAME = "VisiBake"
INTERNAL_UV_MAP = "__visibake_internal__"
OWNED_UV_KEY = "visibake_uv_map"
# The in-memory unwraps of objects without outputs, kept for the session (they get no UV map
# to keep them in): a re-bake of the same scene does not unwrap them again.
IN_MEMORY_UNWRAPS = UnwrapMemo()


@dataclass
class PendingUnwrap:
    """An unwrap chosen on the main thread and run later, anywhere: it needs no bpy.

    ``loops`` is None for an object without outputs, whose unwrap stays in memory.
    """

    positions: np.ndarray
    triangles: np.ndarray
    loops: np.ndarray | None
    resolution: int
    result: UnwrapResult | None = None
    error: str | None = None

    @cached_property
    def key(self) -> str:
        """What identifies this unwrap in IN_MEMORY_UNWRAPS (hashed once: looked up when planned,
        stored when completed)."""
        return unwrap_key(self.positions, self.triangles, self.resolution)

    def run(self, in_child: bool = False, cancelled=None, worker: UnwrapWorker | None = None) -> None:
        """Unwrap in a child process: cancellable (``cancelled``, asked while it runs, with
        ``in_child``), leaving the UI free, and safe from xatlas's rare hang. xatlas's task
        scheduler can miss its shutdown signal and wait forever when an atlas is destroyed
        (seen in this project's test runs, a few times in a thousand unwraps); a child that
        runs far past its expected time is killed and the unwrap tried once more. Where no
        child can run, the unwrap runs here, blocking but correct. ``worker``: an open
        UnwrapWorker whose child runs it (one child for all of a scene's unwraps)."""
        deadline = UNWRAP_DEADLINE_SECONDS + UNWRAP_DEADLINE_FACTOR * policy.unwrap_seconds(len(self.triangles))
        try:
            for attempt in range(2):
                try:
                    self.result = unwrap_in_child(self.positions, self.triangles, self.resolution,
                                                  cancelled if in_child else None, deadline_seconds=deadline,
                                                  worker=worker)
                    return
                except UnwrapHung:
                    if attempt:
                        raise
                except ChildUnavailable:
                    break  # no interpreter to run it: unwrap here, blocking but correct
            self.result = unwrap(self.positions, self.triangles, self.resolution)
        except (RuntimeError, ValueError) as error:
            self.error = str(error)


# A child unwrap is killed (and tried once more) when it runs longer than this plus
# UNWRAP_DEADLINE_FACTOR times its expected time (core.sampling.layout.unwrap_seconds).
UNWRAP_DEADLINE_SECONDS = 60.0
UNWRAP_DEADLINE_FACTOR = 10.0


@dataclass
class LayoutPlan:
    """How one object is laid out: the UV map to bake on and why it was chosen."""

    uv_map: str
    resolution: tuple[int, int]
    reason: str
    internal_uv: np.ndarray | None = None  # (m, 3, 2) for objects that get no UV map written
    created: bool = False  # the UV map did not exist before this bake
    written: bool = False  # the UV map was (re)written by this bake
    mode: str = "atlas"  # or "vertex": samples at vertices, results as colour attributes
    pending: PendingUnwrap | None = None  # an unwrap still to run; see complete_layout


def vertex_plan(reason: str) -> LayoutPlan:
    return LayoutPlan(uv_map="", resolution=(0, 0), reason=reason, mode="vertex")


def auto_vertex_reason(obj, evaluated_positions, evaluated_triangles, evaluated_loop_count: int,
                       settings) -> str | None:
    """Why mode auto should bake ``obj`` with vertex tables before trying an atlas, or None
    (core.sampling.layout.auto_vertex_reason).

    Only where the results can be written to the mesh: vertex colours live on the base
    mesh, so its modifiers must keep the vertices and corners as they are.
    """
    mesh = obj.data
    if len(evaluated_positions) != len(mesh.vertices) or evaluated_loop_count != len(mesh.loops):
        return None
    return policy.auto_vertex_reason(evaluated_positions, evaluated_triangles, *_own_size(obj), settings)


def owns_uv_map(mesh: bpy.types.Mesh, name: str) -> bool:
    return mesh.get(OWNED_UV_KEY) == name and name in mesh.uv_layers


def _own_size(obj) -> tuple[int, float]:
    """The object's own resolution and texel density (0: none of its own)."""
    if not hasattr(obj, "visibake"):
        return 0, 0.0
    return obj.visibake.resolution, obj.visibake.texel_density


def object_resolution(obj, settings, world_area: float, uv_area: float, view_density: float = 0.0) -> tuple[int, int]:
    """Atlas size of ``obj`` (core.sampling.layout.object_resolution)."""
    return policy.object_resolution(*_own_size(obj), settings, world_area, uv_area, view_density)


def planned_resolution(obj, settings, positions: np.ndarray, triangles: np.ndarray,
                       view_density: float = 0.0) -> tuple[int, int]:
    """The atlas size ``obj`` will get, known before its UV map is looked at
    (core.sampling.layout.planned_resolution)."""
    return policy.planned_resolution(*_own_size(obj), settings, positions, triangles, view_density)


def _base_triangles(mesh: bpy.types.Mesh):
    mesh.calc_loop_triangles()
    read = read_triangles(mesh)
    return read.positions, read.triangles, read.loops


def write_uv_map(mesh: bpy.types.Mesh, positions: np.ndarray, triangles: np.ndarray, loops: np.ndarray,
                 corner_uv: np.ndarray) -> bool:
    """Write per-corner UVs into the owned ``VisiBake`` map; True if the map was created now."""
    created = UV_MAP_NAME not in mesh.uv_layers
    if created:
        active = mesh.uv_layers.active_index if len(mesh.uv_layers) else -1
        layer = mesh.uv_layers.new(name=UV_MAP_NAME, do_init=False)
        if layer is None:
            raise LayoutError(f"mesh {mesh.name!r} cannot hold another UV map (Blender allows 8); delete one, "
                              "or bake the object with Mode Vertex")
        mesh[OWNED_UV_KEY] = UV_MAP_NAME
        if active >= 0:
            mesh.uv_layers.active_index = active
    layer = mesh.uv_layers[UV_MAP_NAME]
    per_loop, _ = loop_uvs(positions, triangles, loops, corner_uv, len(mesh.loops))
    layer.uv.foreach_set("vector", per_loop.ravel())
    mesh.update()
    return created


def plan_layout(obj, evaluated_uv: dict[str, np.ndarray], evaluated_positions, evaluated_triangles,
                settings, output: bool, view_density: float = 0.0) -> LayoutPlan:
    """Choose the UV layout ``obj`` bakes on, changing nothing yet.

    ``evaluated_*`` describe the evaluated mesh in world space, as the bake sees it;
    ``view_density``: see core.sampling.layout.object_resolution. A plan that needs an unwrap
    carries it as ``pending``: run it, then :func:`complete_layout` writes the UV map.
    """
    plan, rejected, world_area = _existing_layout(obj, evaluated_uv, evaluated_positions, evaluated_triangles,
                                                  settings, view_density)
    if plan is not None:
        return plan
    return _new_layout(obj, evaluated_positions, evaluated_triangles, settings, output, rejected, world_area,
                       view_density)


def existing_layout(obj, evaluated_uv, evaluated_positions, evaluated_triangles, settings,
                    view_density: float = 0.0) -> LayoutPlan | None:
    """The layout of a UV map the object already has and that is valid for baking, or None."""
    return _existing_layout(obj, evaluated_uv, evaluated_positions, evaluated_triangles, settings, view_density)[0]


def _existing_layout(obj, evaluated_uv, evaluated_positions, evaluated_triangles, settings, view_density):
    mesh = obj.data
    measured = policy.needs_areas(*_own_size(obj), settings, view_density)
    world_area = policy.surface_area(evaluated_positions, evaluated_triangles) if measured else 0.0
    candidates = []
    if owns_uv_map(mesh, UV_MAP_NAME):
        candidates.append(UV_MAP_NAME)
    active = next((layer.name for layer in mesh.uv_layers if layer.active_render), None)
    if active and active not in candidates and active != UV_MAP_NAME:
        candidates.append(active)
    rejected = []
    for name in candidates:
        corner_uv = evaluated_uv.get(name)
        if corner_uv is None:
            continue
        uv_area = float(np.sum(triangle_areas(corner_uv.astype(np.float64)))) if measured else 0.0
        resolution = object_resolution(obj, settings, world_area, uv_area, view_density)
        problems = uv_layout_problems(corner_uv, *resolution)
        if not problems:
            why = "VisiBake's own UV map" if name == UV_MAP_NAME else "the mesh's UV map is valid for baking"
            return LayoutPlan(name, resolution, why), rejected, world_area
        rejected.append(f"UV map {name!r}: {'; '.join(problems)}")
    return None, rejected, world_area


def _new_layout(obj, evaluated_positions, evaluated_triangles, settings, output, rejected, world_area, view_density):
    mesh = obj.data
    if UV_MAP_NAME in mesh.uv_layers and not owns_uv_map(mesh, UV_MAP_NAME) and output:
        raise LayoutError(f"object {obj.name!r}: it has a UV map named {UV_MAP_NAME!r} that VisiBake did not "
                          "create; rename it so VisiBake can add its own")
    reason = "; ".join(rejected) if rejected else "the mesh has no UV map"
    resolution = object_resolution(obj, settings, world_area, TYPICAL_PACKED_UV_AREA, view_density)
    if output:
        positions, triangles, loops = _base_triangles(mesh)
        if len(triangles) == 0:
            raise LayoutError(f"object {obj.name!r} has no faces; deselect it or give it faces")
        return LayoutPlan(UV_MAP_NAME, resolution, f"unwrapped with xatlas ({reason})", written=True,
                          pending=PendingUnwrap(positions, triangles, loops, resolution[0]))
    # Objects without outputs still reflect light, through an atlas nobody sees: unwrap
    # the evaluated mesh in memory and leave the user's mesh alone.
    pending = PendingUnwrap(evaluated_positions, evaluated_triangles, None, resolution[0])
    kept = IN_MEMORY_UNWRAPS.get(pending.key)
    if kept is not None:
        return LayoutPlan(INTERNAL_UV_MAP, resolution, "the in-memory unwrap of an earlier bake in this session, "
                          f"no UV map written ({reason})", internal_uv=kept.corner_uv)
    return LayoutPlan(INTERNAL_UV_MAP, resolution, f"unwrapped in memory, no UV map written ({reason})",
                      pending=pending)


def complete_layout(obj, plan: LayoutPlan) -> LayoutPlan:
    """Apply a plan's finished unwrap: write the ``VisiBake`` UV map, or keep the UVs in memory.

    Raises :class:`UnwrapFailed` if the unwrap failed.
    """
    pending = plan.pending
    if pending is None:
        return plan
    if pending.result is None:
        raise UnwrapFailed(f"object {obj.name!r}: unwrapping failed at {pending.resolution}x{pending.resolution} "
                           f"({pending.error or 'it did not run'}); raise its resolution")
    if pending.loops is None:
        IN_MEMORY_UNWRAPS.put(pending.key, pending.result)
        plan.internal_uv = pending.result.corner_uv
    else:
        plan.created = write_uv_map(obj.data, pending.positions, pending.triangles, pending.loops,
                                    pending.result.corner_uv)
    plan.pending = None
    return plan


def remove_created_uv_maps(created: list[tuple[bpy.types.Mesh, str]]) -> None:
    """Undo :func:`write_uv_map` for maps created during a bake that did not finish."""
    for mesh, name in created:
        layer = mesh.uv_layers.get(name)
        if layer is not None:
            mesh.uv_layers.remove(layer)
        if mesh.get(OWNED_UV_KEY) == name:
            del mesh[OWNED_UV_KEY]
