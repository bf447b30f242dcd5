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
        self._meshes = [mesh for mesh in scene.meshes if len(mesh.positions)]
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
        near, far = float(clip_start), float(clip_end)
        directions = self._directions(view, projection)
        count = len(directions)
        eye = lfscene.camera_position(view)
        # Depth along the optical axis is clip w (row 3 of projection @ view), affine in the point.
        w_row = (projection @ view)[3]
        rate = directions @ w_row[:3]  # d(depth)/d(distance) along each unit direction
        forward = rate > 0.0
        colors = np.empty((count, 3), np.float32)
        depth = np.full(count, np.inf)
        hit = np.zeros(count, bool)
        if self._ray_scene is not None and forward.any():
            index = np.flatnonzero(forward)
            start = (near - (eye @ w_row[:3] + w_row[3])) / rate[index]
            stop = (far - (eye @ w_row[:3] + w_row[3])) / rate[index]
            # embree's tnear is 0: the rays start on the near plane and end on the far one.
            origins = eye + directions[index] * start[:, None]
            geometry, triangle, bary, distance = self._ray_scene.intersect(
                origins, directions[index].astype(np.float32), (stop - start).astype(np.float32))
            found = geometry >= 0
            rays = index[found]
            hit[rays] = True
            colors[rays] = self._shade(geometry[found], triangle[found], bary[found])
            points = origins[found] + directions[rays] * distance[found, None].astype(np.float64)
            depth[rays] = points @ w_row[:3] + w_row[3]
        missed = ~hit
        if missed.any():
            colors[missed] = lfscene.world_lookup(self.scene.world, directions[missed])
        grid = colors.reshape(self.rows, self.columns, 3)
        radiance = lfscene.resolve(grid, self.supersampling, self.weights)
        depth_image = None
        if want_depth:
            s, r = self.supersampling, self.margin
            depth_image = depth.reshape(self.rows, self.columns)[r:r + self.height * s,
                                                                 r:r + self.width * s].astype(np.float32)
        return radiance, depth_image

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
