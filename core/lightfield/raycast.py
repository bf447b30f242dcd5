"""A light field's views ray cast with embree: the CPU twin of gpu_shaders.lightfield.ViewRenderer.

Same contract and the same picture (core.lightfield.scene): one ray per supersample of the
extended grid (s x s per pixel at the sub-pixel centres, plus the filter's margin), from the
view's position through the supersample's NDC point unprojected with the inverse of
``projection @ view`` (scene.direction_matrix), clipped to [clip_start, clip_end] along the
optical axis as the rasteriser clips; the nearest hit's image sample plus its per-corner
radiance, or the world; then scene.resolve. It is the fallback where no GPU context exists,
and the reference the GPU renderer is tested against.

Cost: embree on the CPU cores; ~1-3 s per 512 x 512 view at s = 3 on 2 cores (2.4 M rays).
"""
from __future__ import annotations

import numpy as np

from ..visibility.rays import RayScene
from . import scene as lfscene


class RaycastRenderer:
    """Views of a :class:`core.lightfield.scene.DrawScene` ray cast on the CPU.

    Parameters as gpu_shaders.lightfield.ViewRenderer; ``threads``: embree worker threads
    (0: one per core). :meth:`close` and the context manager exist for symmetry (nothing to free
    but memory).
    """

    def __init__(self, scene: lfscene.DrawScene, width: int, height: int, supersampling: int = 3,
                 filter_width: float = 1.5, threads: int = 0):
        self.width, self.height = lfscene.check_size(width, height)
        self.weights = lfscene.pixel_filter_weights(supersampling, filter_width)
        self.supersampling = int(supersampling)
        self.filter_width = float(filter_width)
        self.columns, self.rows, self.margin = lfscene.extended_size(self.width, self.height, self.supersampling,
                                                                      self.filter_width)
        self.ndc_x, self.ndc_y = lfscene.supersample_ndc(self.width, self.height, self.supersampling,
                                                         self.filter_width)
        self.scene = scene
        self._scene_index = [number for number, mesh in enumerate(scene.meshes) if len(mesh.positions)]
        self._meshes = [scene.meshes[number] for number in self._scene_index]
        self._ray_scene = None
        if self._meshes:
            self._ray_scene = RayScene(
                [(mesh.positions, np.arange(len(mesh.positions), dtype=np.int32).reshape(-1, 3))
                 for mesh in self._meshes], threads=threads, centre=lfscene.scene_centre(scene))

    def __enter__(self) -> "RaycastRenderer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._ray_scene = None
        self._meshes = []

    def render(self, view_matrix: np.ndarray, projection_matrix: np.ndarray, clip_start: float, clip_end: float,
               want_depth: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
        """One view: (radiance (height, width, 3) float32, row 0 at the top; depth
        (height * s, width * s) float32 metres along the optical axis, inf where the world is seen,
        or None unless ``want_depth``). See gpu_shaders.lightfield.ViewRenderer.render."""
        view, projection = lfscene.check_view(view_matrix, projection_matrix, clip_start, clip_end)
        directions = self._directions(view, projection)
        rays, geometry, triangle, bary, depth = self._first_hits(view, projection, directions, clip_start, clip_end)
        colors = np.empty((len(directions), 3), np.float32)
        colors[rays] = self._shade(geometry, triangle, bary)
        missed = np.ones(len(directions), bool)
        missed[rays] = False
        if missed.any():
            colors[missed] = lfscene.world_lookup(self.scene.world, directions[missed])
        grid = colors.reshape(self.rows, self.columns, 3)
        radiance = lfscene.resolve(grid, self.supersampling, self.weights)
        depth_image = None
        if want_depth:
            s, r = self.supersampling, self.margin
            depth_all = np.full(len(directions), np.inf)
            depth_all[rays] = depth
            depth_image = depth_all.reshape(self.rows, self.columns)[r:r + self.height * s,
                                                                     r:r + self.width * s].astype(np.float32)
        return radiance, depth_image

    def nearest_depths(self, view_matrix: np.ndarray, projection_matrix: np.ndarray, clip_start: float,
                       clip_end: float) -> np.ndarray:
        """(number of scene meshes,) float64: per mesh of the scene, the least depth along the
        optical axis (metres) at which one of this view's rays sees it first; inf where none does
        (meshes without triangles included)."""
        view, projection = lfscene.check_view(view_matrix, projection_matrix, clip_start, clip_end)
        _, geometry, _, _, depth = self._first_hits(view, projection, self._directions(view, projection),
                                                    clip_start, clip_end)
        nearest = np.full(len(self._meshes), np.inf)
        np.minimum.at(nearest, geometry, depth)
        out = np.full(len(self.scene.meshes), np.inf)
        out[self._scene_index] = nearest
        return out

    def _first_hits(self, view: np.ndarray, projection: np.ndarray, directions: np.ndarray, clip_start: float,
                    clip_end: float):
        """The rays along (n, 3) ``directions`` that hit a surface between the clip planes:
        (rays (h,) int64 indices into directions, geometry (h,) int32 into the drawn meshes,
        triangle (h,) int32, bary (h, 2) float32, depth (h,) float64 metres along the axis)."""
        near, far = float(clip_start), float(clip_end)
        eye = lfscene.camera_position(view)
        # Depth along the optical axis is clip w (row 3 of projection @ view), affine in the point.
        w_row = (projection @ view)[3]
        rate = directions @ w_row[:3]  # d(depth)/d(distance) along each unit direction
        index = np.flatnonzero(rate > 0.0)
        if self._ray_scene is None or not len(index):
            return (np.zeros(0, np.int64), np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros((0, 2), np.float32),
                    np.zeros(0))
        start = (near - (eye @ w_row[:3] + w_row[3])) / rate[index]
        stop = (far - (eye @ w_row[:3] + w_row[3])) / rate[index]
        # embree's tnear is 0: the rays start on the near plane and end on the far one.
        origins = eye + directions[index] * start[:, None]
        geometry, triangle, bary, distance = self._ray_scene.intersect(
            origins, directions[index].astype(np.float32), (stop - start).astype(np.float32))
        found = geometry >= 0
        rays = index[found]
        points = origins[found] + directions[rays] * distance[found, None].astype(np.float64)
        return rays, geometry[found], triangle[found], bary[found], points @ w_row[:3] + w_row[3]

    def _directions(self, view: np.ndarray, projection: np.ndarray) -> np.ndarray:
        """(rows * columns, 3) float64 unit directions of the extended grid's rays, row-major,
        row 0 at the top."""
        matrix = lfscene.direction_matrix(view, projection)
        directions = (self.ndc_x[None, :, None] * matrix[:, 0] + self.ndc_y[:, None, None] * matrix[:, 1]
                      + matrix[:, 2]).reshape(-1, 3)
        return directions / np.linalg.norm(directions, axis=1, keepdims=True)

    def _shade(self, geometry: np.ndarray, triangle: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """(n, 3) float32 radiance at the hits: image sample at the interpolated UV plus the
        interpolated per-corner radiance (embree's barycentrics: (1 - u - v) p0 + u p1 + v p2)."""
        out = np.empty((len(geometry), 3), np.float32)
        weights = np.stack([1.0 - bary[:, 0] - bary[:, 1], bary[:, 0], bary[:, 1]], axis=1).astype(np.float32)
        for number, mesh in enumerate(self._meshes):
            mine = np.flatnonzero(geometry == number)
            if not len(mine):
                continue
            corners = 3 * triangle[mine, None] + np.arange(3)
            w = weights[mine, :, None]
            value = (mesh.radiance[corners] * w).sum(axis=1)
            if mesh.image is not None:
                uv = (mesh.uv[corners] * w).sum(axis=1)
                value = lfscene.sample_bilinear_clamp(mesh.image, uv) + value
            out[mine] = value
        return out
