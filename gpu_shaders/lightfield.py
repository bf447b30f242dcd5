"""A light field's views rasterised with Blender's gpu module: the twin of core.lightfield.raycast.

What a pixel shows and the pixel filter are defined in core.lightfield.scene. Per view:

1. the surfaces: one indexed draw per lighting image (meshes sharing an image, and all
   untextured meshes, are merged), into an RGBA32F supersample target of
   ``(height * s + 2 r) x (width * s + 2 r)`` with a 32-bit float depth buffer (and, for the
   depth, an R32F target of clip w, the depth along the optical axis);
2. the world: one triangle at the far plane, depth-tested LESS_EQUAL, so only the samples
   no surface covers evaluate the equirectangular lookup (a uniform world is the clear colour,
   no pass);
3. the resolve: the separable Blackman-Harris filter in two fragment passes (along x into
   ``width x rows``, then along y into ``width x height``), so only the final image is read back.

The projection is extended by the filter's margin of r supersamples on every side (the rays
there continue the frustum) and flipped vertically, so that the framebuffer's first row in
memory is the image's top row: everything reads back with row 0 at the top, no copy to flip.
The samples sit at the fragment centres, exactly where the CPU twin's rays go.

Geometry and textures are uploaded once (corners shared where all their attributes agree, so
each is shaded once); a view changes the matrix uniforms and reads back one (height, width, 3)
float image. Blender's global GPU state (depth test, depth mask, blending) is restored after
each view; face culling is left off (Blender's default).

Cost on Mesa llvmpipe (2 cores; benchmarks/lightfield_render.py, 50k triangles, 1024^2 atlas):
~50 ms a 256^2 view and ~130 ms a 512^2 view at s = 3, ~40 and ~75 ms at s = 2. llvmpipe's
per-triangle setup dominates at 256^2 (~15 ms of the surface pass is there at any s), the
fragments at 512^2; the world and the resolve take ~15% each. Not measured on a real GPU.
"""
from __future__ import annotations

import os

import numpy as np

from ..core.errors import DeviceError
from ..core.lightfield import scene as lfscene
from . import runtime

# Resolve shaders are compiled per (taps, supersampling, weights); a few at most per session.
_programs: dict = {}


def _source(name: str) -> str:
    with open(os.path.join(runtime.SHADER_FOLDER, f"lightfield_{name}.glsl"), encoding="utf-8") as handle:
        return handle.read()


def _compile(key, build):
    if key in _programs:
        return _programs[key]
    import gpu

    info = gpu.types.GPUShaderCreateInfo()
    build(info)
    try:
        program = gpu.shader.create_from_info(info)
    except Exception as error:  # noqa: BLE001  (the gpu module raises a bare Exception)
        raise RuntimeError(f"light field shader {key} did not compile (the log is on stdout): {error}") from None
    _programs[key] = program
    return program


def _surface_program(textured: bool, want_depth: bool):
    def build(info):
        import gpu

        interface = gpu.types.GPUStageInterfaceInfo(f"lightfield_surface_{int(textured)}{int(want_depth)}")
        if textured:
            interface.smooth("VEC2", "v_uv")
        interface.smooth("VEC3", "v_radiance")
        info.vertex_in(0, "VEC3", "position")
        if textured:
            info.vertex_in(1, "VEC2", "uv")
        info.vertex_in(2, "VEC3", "radiance")
        info.vertex_out(interface)
        info.push_constant("MAT4", "view_projection")
        if textured:
            info.sampler(0, "FLOAT_2D", "lighting")
            info.define("TEXTURED", "1")
        info.fragment_out(0, "VEC4", "color")
        if want_depth:
            info.fragment_out(1, "FLOAT", "depth")
            info.define("WANT_DEPTH", "1")
        info.vertex_source(_source("surface_vert"))
        info.fragment_source(_source("surface_frag"))

    return _compile(("surface", textured, want_depth), build)


def _world_program(want_depth: bool):
    def build(info):
        info.vertex_in(0, "VEC2", "corner")
        info.fragment_out(0, "VEC4", "color")
        if want_depth:
            info.fragment_out(1, "FLOAT", "depth")
            info.define("WANT_DEPTH", "1")
        info.push_constant("MAT3", "ndc_to_direction")
        info.push_constant("VEC4", "pixel_to_ndc")
        info.sampler(0, "FLOAT_2D", "world")
        info.vertex_source(_source("fullscreen_vert"))
        info.fragment_source(_source("world_frag"))

    return _compile(("world", want_depth), build)


def _resolve_program(axis: int, supersampling: int, weights: np.ndarray):
    taps = len(weights)
    # float32 values written with 9 significant digits round-trip exactly.
    constants = ", ".join(f"{float(w):.9e}" for w in weights)

    def build(info):
        info.vertex_in(0, "VEC2", "corner")
        info.sampler(0, "FLOAT_2D", "source")
        info.fragment_out(0, "VEC4", "color")
        info.define("TAPS", str(taps))
        step = f"ivec2({supersampling}, 1)" if axis == 0 else f"ivec2(1, {supersampling})"
        info.define("STEP", step)
        info.define("AXIS", "ivec2(1, 0)" if axis == 0 else "ivec2(0, 1)")
        info.vertex_source(_source("fullscreen_vert"))
        info.fragment_source(f"const float WEIGHTS[TAPS] = float[TAPS]({constants});\n" + _source("resolve_frag"))

    return _compile(("resolve", axis, supersampling, tuple(float(w) for w in weights)), build)


def _indexed(columns: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Shared corners of triangles given with unshared ones.

    columns : (n, c_i) float32 arrays of the same n = 3 * triangles (a corner's attributes).
    Returns ((m, sum c_i) float32 unique rows in order of first use, (n / 3, 3) int32 indices).
    Rows are compared bitwise (-0.0 and 0.0 stay apart: only less sharing). Drawing indexed
    shades each shared corner once: llvmpipe's vertex stage then costs half or less.
    """
    rows = np.ascontiguousarray(np.concatenate(columns, axis=1), np.float32)
    keys = rows.view(np.dtype((np.void, rows.dtype.itemsize * rows.shape[1]))).ravel()
    _, first, inverse = np.unique(keys, return_index=True, return_inverse=True)
    # First-use order keeps neighbouring triangles' corners together (the vertex cache's locality).
    order = np.argsort(first, kind="stable")
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    return rows[first[order]], rank[inverse.ravel()].reshape(-1, 3).astype(np.int32)


def _rgba(image: np.ndarray) -> np.ndarray:
    out = np.ones(image.shape[:2] + (4,), np.float32)
    out[..., :3] = image
    return out


class ViewRenderer:
    """Views of a :class:`core.lightfield.scene.DrawScene` on the GPU.

    Parameters
    ----------
    scene : DrawScene
    width, height : the views' size in pixels
    supersampling : s, samples per pixel along each axis (s * s per pixel)
    filter_width : Cycles' Blackman-Harris filter width in pixels (1.5 is Blender's default)

    Uploads everything once (GPUUnavailable if there is no GPU context, DeviceError for
    textures over the GPU's limits); :meth:`render` draws one view. Use as a context manager
    or call :meth:`close` to free the GPU memory. Main thread only (the gpu module's context).
    """

    def __init__(self, scene: lfscene.DrawScene, width: int, height: int, supersampling: int = 3,
                 filter_width: float = 1.5):
        self.width, self.height = lfscene.check_size(width, height)
        self.weights = lfscene.pixel_filter_weights(supersampling, filter_width)
        self.supersampling = int(supersampling)
        self.filter_width = float(filter_width)
        self.columns, self.rows, self.margin = lfscene.extended_size(self.width, self.height, self.supersampling,
                                                                      self.filter_width)
        if max(self.columns, self.rows) > runtime.MAX_TEXTURE_SIZE:
            raise DeviceError(f"light field views of {self.width}x{self.height} at {self.supersampling}x"
                              f"{self.supersampling} supersamples need a {self.columns}x{self.rows} target, over the "
                              f"GPU limit of {runtime.MAX_TEXTURE_SIZE}; use fewer supersamples or the CPU")
        runtime.ensure_context()
        import gpu
        from gpu_extras.batch import batch_for_shader

        self._gpu = gpu
        self.centre = lfscene.scene_centre(scene)
        self._resident = runtime.TextureSet()
        self._draws = []  # (program, batch, texture or None); textured ones first
        self._build_meshes(scene, batch_for_shader)
        uniform = scene.uniform_world
        self._world_color = None if uniform is None else (float(uniform[0]), float(uniform[1]), float(uniform[2]), 1.0)
        self._world_texture = None if uniform is not None else self._resident.upload(_rgba(scene.world))
        corners = {"corner": np.array([[-1.0, -1.0], [3.0, -1.0], [-1.0, 3.0]], np.float32)}
        self._fullscreen = batch_for_shader(_resolve_program(0, self.supersampling, self.weights), "TRIS", corners)
        self._resolve = [_resolve_program(axis, self.supersampling, self.weights) for axis in (0, 1)]
        self._color = self._resident.empty(self.columns, self.rows)
        self._depth_buffer = self._resident.empty(self.columns, self.rows, fmt="DEPTH_COMPONENT32F")
        self._across = self._resident.empty(self.width, self.rows)
        self._final = self._resident.empty(self.width, self.height)
        self._linear_depth = None  # made on the first view that wants depth
        self._fb_surfaces = gpu.types.GPUFrameBuffer(depth_slot=self._depth_buffer, color_slots=(self._color,))
        self._fb_depth = None
        self._fb_across = gpu.types.GPUFrameBuffer(color_slots=(self._across,))
        self._fb_final = gpu.types.GPUFrameBuffer(color_slots=(self._final,))

    def _build_meshes(self, scene: lfscene.DrawScene, batch_for_shader) -> None:
        # One draw per distinct image (identity), one for every untextured mesh together.
        groups: dict[int, list] = {}
        plain = []
        for mesh in scene.meshes:
            if not len(mesh.positions):
                continue
            if mesh.image is not None:
                groups.setdefault(id(mesh.image), []).append(mesh)
            else:
                plain.append(mesh)
        centre = self.centre
        for meshes in groups.values():
            positions = np.concatenate([(m.positions - centre).astype(np.float32) for m in meshes])
            rows, indices = _indexed([positions, np.concatenate([m.uv for m in meshes]),
                                      np.concatenate([m.radiance for m in meshes])])
            program = _surface_program(True, False)
            batch = batch_for_shader(program, "TRIS", {"position": rows[:, :3], "uv": rows[:, 3:5],
                                                       "radiance": rows[:, 5:8]}, indices=indices)
            texture = self._resident.upload(_rgba(meshes[0].image))
            self._draws.append((True, batch, texture))
        if plain:
            positions = np.concatenate([(m.positions - centre).astype(np.float32) for m in plain])
            rows, indices = _indexed([positions, np.concatenate([m.radiance for m in plain])])
            program = _surface_program(False, False)
            batch = batch_for_shader(program, "TRIS", {"position": rows[:, :3], "radiance": rows[:, 3:6]},
                                     indices=indices)
            self._draws.append((False, batch, None))

    def __enter__(self) -> "ViewRenderer":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        """Free the GPU resources (textures, framebuffers, batches); the renderer is then unusable."""
        self._draws = []
        self._fullscreen = None
        self._fb_surfaces = self._fb_depth = self._fb_across = self._fb_final = None
        self._color = self._depth_buffer = self._across = self._final = self._linear_depth = None
        self._world_texture = None
        if getattr(self, "_resident", None) is not None:
            self._resident.__exit__(None, None, None)
        self._resident = None

    def _depth_framebuffer(self):
        if self._fb_depth is None:
            self._linear_depth = self._resident.empty(self.columns, self.rows, fmt="R32F")
            self._fb_depth = self._gpu.types.GPUFrameBuffer(depth_slot=self._depth_buffer,
                                                            color_slots=(self._color, self._linear_depth))
        return self._fb_depth

    def render(self, view_matrix: np.ndarray, projection_matrix: np.ndarray, clip_start: float, clip_end: float,
               want_depth: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
        """One view.

        view_matrix : (4, 4) world-to-camera; projection_matrix : (4, 4) OpenGL projection built
            with ``clip_start`` and ``clip_end`` (metres; the projection does the clipping).

        Returns
        -------
        radiance : (height, width, 3) float32 linear, row 0 at the top
        depth : (height * s, width * s) float32 metres along the optical axis (clip w), inf where
            the world is seen, row 0 at the top; or None unless ``want_depth``
        """
        if self._resident is None:
            raise RuntimeError("the ViewRenderer is closed")
        view, projection = lfscene.check_view(view_matrix, projection_matrix, clip_start, clip_end)
        gpu = self._gpu
        from mathutils import Matrix

        # The margin and the flip (core.lightfield.scene.supersample_ndc): NDC' = diag(ax, ay) NDC.
        extend = np.diag([self.width * self.supersampling / self.columns,
                          -self.height * self.supersampling / self.rows, 1.0, 1.0])
        projection = extend @ projection
        to_centre = np.eye(4)
        to_centre[:3, 3] = self.centre
        view_projection = Matrix((projection @ view @ to_centre).tolist())
        framebuffer = self._depth_framebuffer() if want_depth else self._fb_surfaces

        saved = (gpu.state.depth_test_get(), gpu.state.depth_mask_get(), gpu.state.blend_get())
        try:
            gpu.state.blend_set("NONE")
            gpu.state.face_culling_set("NONE")
            uniform = self._world_color is not None
            if uniform and want_depth:
                # A uniform world is the clear colour; the depth target's sentinel 0 means "no surface".
                self._color.clear(format="FLOAT", value=self._world_color)
                self._linear_depth.clear(format="FLOAT", value=(0.0,))
            with framebuffer.bind():
                if uniform and not want_depth:
                    framebuffer.clear(color=self._world_color, depth=1.0)
                else:
                    framebuffer.clear(depth=1.0)
                gpu.state.depth_test_set("LESS_EQUAL")
                gpu.state.depth_mask_set(True)
                for textured, batch, texture in self._draws:
                    program = _surface_program(textured, want_depth)
                    program.bind()
                    program.uniform_float("view_projection", view_projection)
                    if texture is not None:
                        program.uniform_sampler("lighting", texture)
                    batch.draw(program)
                if not uniform:
                    gpu.state.depth_mask_set(False)
                    self._draw_world(view, projection, want_depth)
            gpu.state.depth_test_set("NONE")
            for axis, (source, target) in enumerate(((self._color, self._fb_across), (self._across, self._fb_final))):
                with target.bind():
                    program = self._resolve[axis]
                    program.bind()
                    program.uniform_sampler("source", source)
                    self._fullscreen.draw(program)
            radiance = np.empty((self.height, self.width, 3), np.float32)
            self._fb_final.read_color(0, 0, self.width, self.height, 3, 0, "FLOAT",
                                      data=gpu.types.Buffer("FLOAT", radiance.size, radiance.ravel()))
            depth = None
            if want_depth:
                s, r = self.supersampling, self.margin
                depth = np.empty((self.height * s, self.width * s), np.float32)
                framebuffer.read_color(r, r, self.width * s, self.height * s, 1, 1, "FLOAT",
                                       data=gpu.types.Buffer("FLOAT", depth.size, depth.ravel()))
                depth[depth <= 0.0] = np.inf
        finally:
            gpu.state.depth_test_set(saved[0])
            gpu.state.depth_mask_set(saved[1])
            gpu.state.blend_set(saved[2])
        return radiance, depth

    def _draw_world(self, view: np.ndarray, projection: np.ndarray, want_depth: bool) -> None:
        from mathutils import Matrix

        program = _world_program(want_depth)
        program.bind()
        program.uniform_float("ndc_to_direction", Matrix(lfscene.direction_matrix(view, projection).tolist()))
        program.uniform_float("pixel_to_ndc", (2.0 / self.columns, 2.0 / self.rows, -1.0, -1.0))
        program.uniform_sampler("world", self._world_texture)
        self._fullscreen.draw(program)
