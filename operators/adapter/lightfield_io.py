"""Light fields of a baked scene (issue 19, the paper's section 7.3): the scene as the bake
left it, seen from the HCI benchmark's grid of parallel off-axis cameras around a camera of
the user's, written in the HCI layout (core.lightfield.hci) or the Stanford one.

What a view shows: each object's baked ``lighting`` (its image through the bake's UV map,
or its ``VB_lighting`` colour attribute), plus the emission of its materials (the lighting
pass leaves out an emitter's own radiance), and the world where no surface is hit, as
Cycles renders it (operators.adapter.world_capture). The views are rasterised with
Blender's gpu module (gpu_shaders.lightfield), or ray cast with embree where no GPU
context exists (core.lightfield.raycast), both with Cycles' pixel filter.

Everything runs on the main thread (the gpu module's context lives there); the modal
operator advances one row of views per step, so Esc cancels between rows. A run that fails
or is cancelled takes back the files and folders it wrote.
"""
from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass

import bpy

import numpy as np

from ...core.errors import BakeRefused, OutputRefused
from ...core.lightfield import coverage, hci
from ...core.lightfield.cameras import CentreCamera, LightFieldGrid, grid_views
from ...core.lightfield.scene import DrawMesh, DrawScene
from ...core.outputs.atomic import atomic_file
from ...core.outputs.images import write_exr
from ...core.outputs.ownership import StagedWrites, is_leftover, record_files, refuse_foreign, remove_leftovers
from . import compat, extract, layout, writeback
from .modal import SteppedJob

MANIFEST = "lightfield.json"
FORMAT_NAME = "visibake-lightfield"
# The default of the Supersamples setting: 3 x 3 is within 0.3% of a 4 x 4 render on 4 x 4
# blocks (docs/benchmarks.md, "Light fields, part 2").
SUPERSAMPLING = 3
# Cycles' default pixel filter: Blackman-Harris, 1.5 pixels wide.
FILTER_WIDTH = 1.5
# What view_densities gives an object no probe view sees: far below any real density, so
# core.sampling.layout gives it its smallest camera-sized atlas.
HIDDEN_DENSITY = 1e-9


class LightFieldRefused(BakeRefused):
    """A light field that cannot be made as asked (the message says why)."""


@dataclass
class LightFieldOutcome:
    """A written light field: its report (also in the folder's lightfield.json)."""

    report: dict


def centre_camera(camera_obj, width: int, height: int, warnings: list[str]) -> CentreCamera:
    """The HCI centre camera of a Blender camera object for views of ``width`` x ``height``.

    HCI's sensor spans the larger image dimension (Blender's sensor fit 'AUTO'): a camera
    fitted otherwise is converted so that its field of view stays the same.
    """
    if camera_obj is None or camera_obj.type != "CAMERA":
        raise LightFieldRefused("the light field needs a camera: give --camera NAME (a camera object) or set the "
                                "scene's camera")
    camera = camera_obj.data
    if camera.type != "PERSP":
        raise LightFieldRefused(f"camera {camera_obj.name!r} is {camera.type.lower()}: a light field's views are "
                                "perspective cameras")
    matrix = np.array(camera_obj.matrix_world, np.float64)
    axes = matrix[:3, :3]
    rotation = axes / np.linalg.norm(axes, axis=0, keepdims=True)
    # Gram-Schmidt against a sheared matrix (a parent's non-uniform scale): the view's axes.
    u, _, vt = np.linalg.svd(rotation)
    rotation = u @ vt
    fit = camera.sensor_fit
    if fit == "HORIZONTAL":
        sensor = camera.sensor_width * (1.0 if width >= height else height / width)
    elif fit == "VERTICAL":
        sensor = camera.sensor_height * (1.0 if height >= width else width / height)
    else:
        sensor = camera.sensor_width
    if camera.shift_x or camera.shift_y:
        warnings.append(f"camera {camera_obj.name!r}: its lens shift is not part of the HCI camera model; the "
                        "centre view is rendered without it")
    return CentreCamera(matrix[:3, 3], rotation, camera.lens, sensor, width, height)


def _corner_values(mesh, attribute, corners: np.ndarray) -> np.ndarray:
    """(n, 3) float32: a colour attribute at the loop triangles' corners ``corners`` (n,) of
    loop indices (the attribute on points or on corners)."""
    data = np.empty(len(attribute.data) * 4, np.float32)
    attribute.data.foreach_get("color", data)
    data = data.reshape(-1, 4)[:, :3]
    if attribute.domain == "CORNER":
        return data[corners]
    points = np.empty(len(mesh.loops), np.int32)
    mesh.loops.foreach_get("vertex_index", points)
    return data[points[corners]]


def _bake_uv_map(mesh) -> str | None:
    if layout.owns_uv_map(mesh, layout.UV_MAP_NAME):
        return layout.UV_MAP_NAME
    return next((uv.name for uv in mesh.uv_layers if uv.active_render), None)


def _image_radiance(image) -> np.ndarray:
    """(h, w, 3) float32 linear pixels of a baked image, row 0 at the bottom."""
    width, height = image.size
    pixels = np.empty(width * height * image.channels, np.float32)
    image.pixels.foreach_get(pixels)
    return pixels.reshape(height, width, image.channels)[:, :, :3].copy()


def _corner_positions(obj, evaluated, mesh, corners: np.ndarray) -> np.ndarray:
    """(len(corners), 3) float32 world positions of the evaluated ``mesh``'s loop ``corners``."""
    points = np.empty(len(mesh.loops), np.int32)
    mesh.loops.foreach_get("vertex_index", points)
    coordinates = np.empty(len(mesh.vertices) * 3, np.float32)
    mesh.vertices.foreach_get("co", coordinates)
    matrix = extract.world_matrix(obj, evaluated)
    local = coordinates.reshape(-1, 3)[points[corners]].astype(np.float64)
    return (local @ matrix[:3, :3].T + matrix[:3, 3]).astype(np.float32)


def _triangle_corners(obj, depsgraph) -> np.ndarray:
    """(3 n, 3) float32 world positions of the corners of ``obj``'s evaluated triangles."""
    evaluated = obj.evaluated_get(depsgraph)
    mesh = evaluated.to_mesh()
    try:
        mesh.calc_loop_triangles()
        corners = np.empty(len(mesh.loop_triangles) * 3, np.int32)
        mesh.loop_triangles.foreach_get("loops", corners)
        return _corner_positions(obj, evaluated, mesh, corners)
    finally:
        evaluated.to_mesh_clear()


def view_densities(objects, camera: CentreCamera, views, grid: tuple[int, int], clip: tuple[float, float],
                   warnings: list[str]) -> dict:
    """{object name: texels per unit of surface} a bake of ``objects`` needs for these views
    (core.lightfield.coverage: a texel per pixel where the probe views see the object
    nearest); an object that no probe sees gets a tiny density, so the smallest atlas."""
    depsgraph = bpy.context.evaluated_depsgraph_get()
    width, height = camera.resolution_x_px, camera.resolution_y_px
    depths = coverage.nearest_depths([_triangle_corners(obj, depsgraph) for obj in objects],
                                     coverage.probe_views(views, *grid), clip, width, height)
    densities = coverage.texel_densities(depths, coverage.focal_pixels(views[0].projection_matrix, width, height))
    hidden = [obj.name for obj, density in zip(objects, densities) if density <= 0]
    if hidden:
        warnings.append(f"{len(hidden)} object(s) in the views' frusta are hidden in the grid's corner and centre "
                        f"views and get the smallest atlas: {', '.join(hidden[:5])}{' ...' if len(hidden) > 5 else ''}")
    return {obj.name: float(density) if density > 0 else HIDDEN_DENSITY for obj, density in zip(objects, densities)}


def draw_scene(scene, objects, warnings: list[str]) -> tuple[DrawScene, dict]:
    """The baked scene as the view renderer draws it, and what went into it.

    objects : the mesh objects to draw (those Cycles renders). Returns (DrawScene, counts:
    {"atlas": [...], "vertex": [...], "unbaked": [...], "emitters": [...]} of object names).
    """
    depsgraph = bpy.context.evaluated_depsgraph_get()
    meshes, counts = [], {"atlas": [], "vertex": [], "unbaked": [], "emitters": []}
    lighting_attribute = writeback.attribute_name("lighting")
    for obj in objects:
        evaluated = obj.evaluated_get(depsgraph)
        mesh = evaluated.to_mesh()
        try:
            mesh.calc_loop_triangles()
            triangles = len(mesh.loop_triangles)
            if triangles == 0:
                continue
            corners = np.empty(triangles * 3, np.int32)
            mesh.loop_triangles.foreach_get("loops", corners)
            positions = _corner_positions(obj, evaluated, mesh, corners)
            radiance = np.zeros((triangles * 3, 3), np.float32)
            uv = image = None
            source = writeback.find_image(obj.name, "lighting")
            uv_name = _bake_uv_map(obj.data)  # VisiBake's mark is on the object's own mesh
            if lighting_attribute in mesh.color_attributes:
                radiance += _corner_values(mesh, mesh.color_attributes[lighting_attribute], corners)
                counts["vertex"].append(obj.name)
            elif source is not None and uv_name is not None and uv_name in mesh.uv_layers:
                layer = mesh.uv_layers[uv_name]
                coordinates_uv = np.empty(len(mesh.loops) * 2, np.float32)
                layer.data.foreach_get("uv", coordinates_uv)
                uv = coordinates_uv.reshape(-1, 2)[corners]
                image = _image_radiance(source)
                counts["atlas"].append(obj.name)
            else:
                counts["unbaked"].append(obj.name)
            slots = np.empty(triangles, np.int32)
            mesh.loop_triangles.foreach_get("material_index", slots)
            materials = [slot.material for slot in obj.material_slots] or [None]
            for slot in np.unique(slots):
                material = materials[min(int(slot), len(materials) - 1)]
                emission = extract.read_material(material, "", []).emission if material is not None else None
                if emission is not None and np.any(emission > 0):
                    rows = np.repeat(slots == slot, 3)
                    radiance[rows] += emission.astype(np.float32)
                    if obj.name not in counts["emitters"]:
                        counts["emitters"].append(obj.name)
            meshes.append(DrawMesh(positions, radiance, uv, image))
        finally:
            evaluated.to_mesh_clear()
    if counts["unbaked"]:
        warnings.append(f"{len(counts['unbaked'])} object(s) have no baked lighting and show black (or only their "
                        f"emission): {', '.join(counts['unbaked'][:5])}{' ...' if len(counts['unbaked']) > 5 else ''}"
                        " (bake first, or pass --bake-first)")
    return DrawScene(meshes, _world(scene, warnings)), counts


def _world(scene, warnings: list[str]) -> np.ndarray:
    """(H, W, 3) float32 equirectangular radiance of the world as Cycles renders it."""
    if scene.world is None or scene.render.film_transparent:
        if scene.world is not None:
            warnings.append("the film is transparent: the world is not seen in the views (black)")
        return np.zeros((1, 1, 3), np.float32)
    from . import world_capture

    if compat.uses_nodes(scene.world):
        extract.warn_non_finite_world_images(scene.world.node_tree, warnings)
    try:
        return np.asarray(world_capture.capture_world(scene), np.float32)
    except world_capture.CaptureFailed as error:
        raise LightFieldRefused(f"the world could not be rendered for the views' background: {error}") from None


def plan_views(scene, camera_name: str | None, grid: tuple[int, int], baseline_mm: float, focus_m: float,
               image_size: tuple[int, int], warnings: list[str]):
    """(CentreCamera, LightFieldGrid, [GridView] in HCI order, (clip_start, clip_end)) of the
    grid around camera ``camera_name`` (None: the scene's camera)."""
    # The cameras and the objects' boxes are read from matrix_world, which a script's recent
    # move leaves stale until the view layer is evaluated.
    (bpy.context.view_layer if scene == bpy.context.scene else scene.view_layers[0]).update()
    camera_obj = scene.objects.get(camera_name) if camera_name else scene.camera
    if camera_name and camera_obj is None:
        raise LightFieldRefused(f"--camera {camera_name!r}: no object of that name in the scene")
    try:
        camera = centre_camera(camera_obj, *image_size, warnings)
        lattice = LightFieldGrid(*grid, baseline_mm, focus_m)
        clip = (float(camera_obj.data.clip_start), float(camera_obj.data.clip_end))
        return camera, lattice, grid_views(camera, lattice, *clip), clip
    except ValueError as error:
        raise LightFieldRefused(str(error)) from None


def objects_in_views(objects, views, clip_start: float, clip_end: float) -> tuple[list, list]:
    """(seen, unseen) ``objects`` split by whether any view's frustum may hold part of their
    bounding box (a box whose eight corners all lie beyond one clip plane of every view is
    unseen; the test is conservative: an object near a frustum's corner may count as seen)."""
    seen, unseen = [], []
    for obj in objects:
        matrix = np.array(obj.matrix_world, np.float64)
        corners = np.array(obj.bound_box, np.float64) @ matrix[:3, :3].T + matrix[:3, 3]
        homogeneous = np.column_stack([corners, np.ones(8)])
        visible = False
        for view in views:
            clip = homogeneous @ (view.projection_matrix @ view.view_matrix).T
            w = clip[:, 3:4]
            outside = np.concatenate([clip[:, :3] > w, clip[:, :3] < -w], axis=1)
            if not np.any(np.all(outside, axis=0)):
                visible = True
                break
        (seen if visible else unseen).append(obj)
    return seen, unseen


class _DisplayImages:
    """PNGs through the scene's view transform, as Blender saves a render: a temporary scene
    carries a copy of the colour management (the user's scene is not touched) and a
    temporary float image takes each view's pixels."""

    def __init__(self, scene, width: int, height: int):
        self.scene = bpy.data.scenes.new("VisiBake light field display")
        self.image = None
        source, target = scene.view_settings, self.scene.view_settings
        self.scene.display_settings.display_device = scene.display_settings.display_device
        for name in ("view_transform", "look", "exposure", "gamma", "use_curve_mapping"):
            setattr(target, name, getattr(source, name))
        # No dither: a dataset's views are deterministic (Blender's default adds noise of one code).
        self.scene.render.dither_intensity = 0.0
        settings = self.scene.render.image_settings
        settings.file_format = "PNG"
        settings.color_mode = "RGB"
        settings.color_depth = "8"
        self.image = bpy.data.images.new("VisiBake light field view", width, height, alpha=False, float_buffer=True)

    def write(self, path: str, radiance: np.ndarray) -> None:
        """radiance : (height, width, 3) float32 linear, row 0 at the top."""
        height, width = radiance.shape[:2]
        rgba = np.ones((height, width, 4), np.float32)
        rgba[:, :, :3] = radiance[::-1]
        self.image.pixels.foreach_set(rgba.ravel())
        self.image.save_render(path, scene=self.scene)

    def close(self) -> None:
        if self.image is not None and self.image.name in bpy.data.images:
            bpy.data.images.remove(self.image)
        if self.scene is not None and self.scene.name in bpy.data.scenes:
            bpy.data.scenes.remove(self.scene)
        self.image = self.scene = None


def view_stem(view, output_format: str) -> str:
    """The file name, without extension, of ``view`` (a core.lightfield.cameras.GridView)."""
    if output_format == "stanford":
        # The Stanford archive's out_<row>_<column>_<y>_<x>_: the camera's place in mm.
        up, right = (float(x) * 1000.0 for x in view.offset_m[::-1])
        return f"out_{view.row:02d}_{view.column:02d}_{up:.6f}_{right:.6f}_"
    return os.path.splitext(hci.view_file_name(view.index))[0]


class LightFieldJob(SteppedJob):
    """Render and write a light field of ``scene`` (see the module's docstring).

    grid : (columns, rows); image_size : (width, height); output_format : 'hci' or 'stanford';
    device : 'auto', 'gpu' or 'cpu' (the embree twin); supersampling : s, s x s samples per
    pixel. ``progress(stage, fraction)`` may raise core.errors.Cancelled.
    """

    needs_main_thread = True

    def __init__(self, scene, camera_name: str | None, out_dir: str, grid: tuple[int, int], baseline_mm: float,
                 focus_m: float, image_size: tuple[int, int], output_format: str = "hci", device: str = "auto",
                 overwrite: bool = False, progress=None, extra_report: dict | None = None,
                 supersampling: int = SUPERSAMPLING, cluster=None):
        """cluster: core.distributed.engine.ClusterOptions, or None: the views are ray cast on
        the CPU in parts on a Dask cluster (the same bits as the CPU device here)."""
        self.cluster = cluster
        self.rendered: dict = {}
        self.scene = scene
        self.camera_name = camera_name
        self.out_dir = os.path.abspath(out_dir)
        self.columns, self.rows = (int(v) for v in grid)
        self.baseline_mm, self.focus_m = float(baseline_mm), float(focus_m)
        self.width, self.height = (int(v) for v in image_size)
        self.output_format = output_format
        self.supersampling = int(supersampling)
        self.device = device
        self.overwrite = overwrite
        self.progress = progress
        self.started = time.perf_counter()
        self.written: list[str] = []
        # What this run made, and how to take it back (core.outputs.ownership).
        self.staged = StagedWrites(self.out_dir)
        self.renderer = self.display = None
        self.warnings: list[str] = []
        self.times = {"render_s": 0.0, "write_s": 0.0}
        self.report = {"command": "lightfield", "warnings": self.warnings, **(extra_report or {})}

    def modal_steps(self) -> list:
        """(name, step, on a worker thread) for ModalBake: the views a row at a time."""
        return ([("read", self.read, False)]
                + ([("views on the cluster", self.render_on_cluster, False)] if self.cluster is not None else [])
                + [(f"views, row {row + 1}", lambda row=row: self.render_row(row), False) for row in range(self.rows)]
                + [("finish", self.finish, False)])

    def abort(self) -> None:
        self._close()
        self.staged.rollback()
        self.written.clear()

    def _close(self) -> None:
        if self.renderer is not None:
            self.renderer.close()
            self.renderer = None
        if self.display is not None:
            self.display.close()
            self.display = None

    def _say(self, stage: str, fraction: float) -> None:
        if self.progress is not None:
            self.progress(stage, fraction)

    def read(self) -> None:
        """The camera, the grid, the output folder, the scene to draw and the renderer."""
        if self.output_format not in ("hci", "stanford"):
            raise LightFieldRefused(f"unknown light field layout {self.output_format!r}: use hci or stanford")
        self.camera, self.grid, self.views, self.clip = plan_views(
            self.scene, self.camera_name, (self.columns, self.rows), self.baseline_mm, self.focus_m,
            (self.width, self.height), self.warnings)
        self._claim_folder()
        self._say("reading the baked scene", 0.0)
        seen, unseen = objects_in_views(extract.scene_meshes(self.scene), self.views, *self.clip)
        drawn, self.counts = draw_scene(self.scene, seen, self.warnings)
        self.counts["unseen"] = [obj.name for obj in unseen]
        if self.cluster is not None:
            if self.device == "gpu":
                raise LightFieldRefused("--device gpu: views on a cluster are ray cast on the workers' CPUs")
            self.drawn, self.renderer_name = drawn, "cpu (embree), on a cluster"
        else:
            self.renderer, self.renderer_name = self._renderer(drawn)
        self.display = _DisplayImages(self.scene, self.width, self.height)

    def planned_files(self) -> list[str]:
        """The absolute paths this run writes: each view's .exr and .png, the ground truth, the
        parameters and the manifest."""
        names = [view_stem(view, self.output_format) + ext for view in self.views for ext in (".exr", ".png")]
        names += [hci.DEPTH_FILE, hci.DISPARITY_FILE, hci.PARAMETERS_FILE, MANIFEST]
        return [os.path.join(self.out_dir, name) for name in names]

    def _claim_folder(self) -> None:
        """The output folder: new, empty, or an earlier VisiBake light field (whose files this
        run replaces); a folder holding anything else is refused, unless ``overwrite`` (then
        those files are kept, and one named as a file this run writes is refused all the same)."""
        folder = self.out_dir
        if os.path.lexists(folder) and not os.path.isdir(folder):
            raise OutputRefused(f"--out {folder}: not a folder")
        if not os.path.isdir(folder):
            parent = os.path.dirname(folder)
            if not os.path.isdir(parent):
                raise OutputRefused(f"--out {folder}: its parent folder does not exist")
            self.staged.make_folder(folder)
            return
        # A killed run's temporaries are VisiBake's: neither a refusal nor kept (removed below).
        present = {name for name in os.listdir(folder) if not is_leftover(os.path.join(folder, name))}
        ours = {os.path.relpath(path, folder) for path in record_files(folder, MANIFEST) or ()}
        foreign = sorted(present - ours)
        if foreign and not self.overwrite:
            raise OutputRefused(f"--out {folder} holds files VisiBake did not write ({', '.join(foreign[:3])}"
                                f"{' ...' if len(foreign) > 3 else ''}): choose an empty folder, or pass --overwrite "
                                "to write beside them (they are kept)")
        refuse_foreign(self.planned_files(), "--overwrite writes beside your files, never over one; rename it or "
                                             "choose another folder")
        remove_leftovers(folder, depth=1)
        # The earlier light field's views go first: a view missing from this one must not stay.
        for name in sorted(ours - {MANIFEST}):
            path = os.path.join(folder, name)
            if os.path.isfile(path) and not os.path.islink(path):
                os.remove(path)

    def _renderer(self, drawn: DrawScene):
        if self.device != "cpu":
            try:
                from ...gpu_shaders import lightfield as gpu_lightfield
                from ...gpu_shaders import runtime

                runtime.ensure_context()
                return (gpu_lightfield.ViewRenderer(drawn, self.width, self.height, self.supersampling, FILTER_WIDTH),
                        f"gpu ({runtime.device_info().renderer})")
            except Exception as error:  # noqa: BLE001  (no GPU context here: the CPU twin draws the same)
                if self.device == "gpu":
                    raise LightFieldRefused(f"--device gpu: no GPU context ({error})") from None
                self.warnings.append(f"no GPU context ({error}); the views are ray cast on the CPU")
        from ...core.lightfield.raycast import RaycastRenderer

        return RaycastRenderer(drawn, self.width, self.height, self.supersampling, FILTER_WIDTH), "cpu (embree)"

    def render_on_cluster(self) -> None:
        """Every view, ray cast in parts of contiguous views on the cluster (kept for render_row)."""
        from ...core.distributed.engine import run_in_parts
        from ...core.transport.contract import direction_chunks

        mark = time.perf_counter()
        centre = self.grid.centre_index
        specs = [(view.index, view.view_matrix, view.projection_matrix, view.index == centre) for view in self.views]

        def parts_of(parts, threads):
            chunks = direction_chunks(len(specs), parts)
            return [(self.drawn, (self.width, self.height), self.supersampling, FILTER_WIDTH,
                     specs[chunk.start:chunk.stop], self.clip, threads) for chunk in chunks]

        done, parts = run_in_parts(self.cluster, "lightfield_part", parts_of, progress=self._say, stage="views")
        self.rendered = {index: (radiance, depth) for part in done for index, radiance, depth in part}
        self.report["split"] = {"parts": parts, "cluster": self.cluster.describe()}
        self.times["render_s"] += time.perf_counter() - mark

    def render_row(self, row: int) -> None:
        """Render and write the views of one row (the centre view with its depth)."""
        centre = self.grid.centre_index
        for view in self.views[row * self.columns:(row + 1) * self.columns]:
            mark = time.perf_counter()
            if self.cluster is not None:
                radiance, depth = self.rendered.pop(view.index)
            else:
                radiance, depth = self.renderer.render(view.view_matrix, view.projection_matrix, *self.clip,
                                                       want_depth=view.index == centre)
            self.times["render_s"] += time.perf_counter() - mark
            if not np.all(np.isfinite(radiance)):
                raise RuntimeError(f"view {view.index} has non-finite pixels (a bug)")
            mark = time.perf_counter()
            stem = os.path.join(self.out_dir, view_stem(view, self.output_format))
            rgba = np.ones((self.height, self.width, 4), np.float32)
            rgba[:, :, :3] = radiance[::-1]
            for ext in (".exr", ".png"):
                self.written.append(stem + ext)
                with self.staged.staged(stem + ext) as temporary:
                    if ext == ".exr":
                        write_exr(temporary, rgba)
                    else:
                        self.display.write(temporary, radiance)
            if depth is not None:
                self.centre_depth = _block_median(depth, self.supersampling)
            self.times["write_s"] += time.perf_counter() - mark
        self._say("views", (row + 1) / self.rows)

    def finish(self) -> LightFieldOutcome:
        self._close()
        mark = time.perf_counter()
        for name in (hci.DEPTH_FILE, hci.DISPARITY_FILE, hci.PARAMETERS_FILE):
            self.written.append(os.path.join(self.out_dir, name))
            self.staged.claim(os.path.join(self.out_dir, name))  # written whole by core.outputs.atomic
        disp_min, disp_max = hci.write_ground_truth(self.out_dir, self.centre_depth, self.camera, self.grid,
                                                    far_m=self.clip[1])
        hci.write_parameters(os.path.join(self.out_dir, hci.PARAMETERS_FILE), self.camera, self.grid,
                             disp_min=disp_min, disp_max=disp_max,
                             scene=bpy.path.clean_name(self.scene.name), category="visibake")
        self.times["write_s"] += time.perf_counter() - mark
        files = sorted(os.path.relpath(path, self.out_dir) for path in self.written)
        self.report.update({
            "output": self.out_dir, "format": self.output_format, "views": len(self.views),
            "grid": [self.columns, self.rows], "image_size": [self.width, self.height],
            "baseline_mm": self.baseline_mm, "focus_distance_m": self.focus_m, "renderer": self.renderer_name,
            "supersampling": self.supersampling, "pixel_filter": f"Blackman-Harris, {FILTER_WIDTH} px",
            "disparity_range": [disp_min, disp_max], "objects": self.counts,
            "render_s": round(self.times["render_s"], 3), "write_s": round(self.times["write_s"], 3),
            "seconds": round(time.perf_counter() - self.started, 3), "files": len(files)})
        self.written.append(os.path.join(self.out_dir, MANIFEST))
        self.staged.claim(os.path.join(self.out_dir, MANIFEST))
        with atomic_file(os.path.join(self.out_dir, MANIFEST), "w", encoding="utf-8") as handle:
            json.dump({"format": FORMAT_NAME, "version": 1, "files": files, "report": self.report}, handle, indent=1,
                      default=float)
        return LightFieldOutcome(self.report)


def _block_median(depth: np.ndarray, factor: int) -> np.ndarray:
    """(h, w) float64: the median of each ``factor`` x ``factor`` block of ``depth`` (h *
    factor, w * factor), as HCI makes its low-resolution ground truth from a larger render."""
    height, width = depth.shape[0] // factor, depth.shape[1] // factor
    blocks = depth[:height * factor, :width * factor].reshape(height, factor, width, factor)
    return np.median(blocks.transpose(0, 2, 1, 3).reshape(height, width, -1), axis=2).astype(np.float64)
