"""Light fields of the baked demo scene: their speed, and their views against Cycles (issue 19, part 1).

    export NUMBA_CACHE_DIR=/tmp/numba-cache     # any writable folder
    .venv/bin/python benchmarks/lightfield_vs_cycles.py [--samples 512] [--out docs/lightfield] [--work DIR]
    .venv/bin/python benchmarks/lightfield_vs_cycles.py --speed-only     # ~1 min: the bake and the timings
    make bench BENCH_PROFILE=lightfield

The scene: the built-in demo room (operators/adapter/demo_scene.py), baked by VisiBake at the
demo's own settings (core defaults: 128 directions, 2 bounces, 256^2 atlases, exact shadows,
interleaved rotations, footprints), objects the views see only (as ``lightfield --bake-first``);
the demo's camera is the centre camera. Focus distance: the median depth of the centre view
(rounded to 0.1 m) unless ``--focus-distance-m``; baseline ``--baseline-mm`` (50).

1. Speed. ``LightFieldJob`` (what the ``lightfield`` command runs) for 16 x 16 views at 256^2
   and 9 x 9 at 512^2, into ``--work`` (default: a temporary folder, removed at the end):
   its ``render_s`` (rendering) apart from its ``write_s`` (EXR + PNG per view, the ground
   truth). Before them, the renderer alone
   (``gpu_shaders.lightfield.ViewRenderer``, the job's supersampling and pixel filter):
   setup, the first view (shader compilation) and the mean of ``--views`` further views,
   with and without the depth; and the CPU twin (``core.lightfield.raycast``) on
   ``--cpu-views`` views, checked against the GPU's image of the same view.
2. Accuracy. The 9 x 9 grid at ``--accuracy-size`` (256^2: Cycles' cost), written by
   ``LightFieldJob``; its centre view (40, the demo camera) and corner view (0) against
   Cycles rendering the lit scene from the same cameras (a camera at the GridView's
   position and rotation with its shift_x / shift_y, sensor fit AUTO, sensor width =
   sensor_size_mm, the same lens, clip planes and resolution; Blackman-Harris 1.5 px,
   diffuse bounces = the bake's, no glossy / transmission / volume bounces, no clamping, no
   denoising, no adaptive sampling), each view as two halves of ``--samples / 2`` with two
   seeds. Error: relative RMSE on 4 x 4-pixel block means, RMS(VisiBake - reference) /
   mean(reference), and per pixel; the reference's own noise (half the RMS of the halves'
   difference, over sqrt 2 for their mean) beside it, and the error without it,
   sqrt(e^2 - noise^2). Also Cycles rendering the *baked* textures from the same cameras
   (emission of each object's ``lighting`` image or colour attribute plus its material's
   emission, no lamps, no bounces, ``--baked-samples``): against the light-field views it
   checks the cameras, the shift and the pixel filter alone (what Cycles does with the
   same textures); against the reference it is the bake's error alone, as a camera sees it.
   Per object (the pixels that see it alone, from an id render of the same views): the mean
   ratio of each to the reference.
3. Cycles' time at the bake's error. Cycles' noise on blocks falls as 1/sqrt(samples)
   (checked with a ``--low-samples`` render against the reference), so it needs
   (samples / 2) (noise_half / e)^2 samples per pixel to reach the light field's block
   error e (without the reference's noise); its seconds per view are fitted as
   t0 + t1 samples from the low and the half renders (t0 >= 0). Cycles' time for a grid is views x
   that, against VisiBake's bake + light field (render and files). For 512^2 views: the
   same samples per pixel give the same noise on 8 x 8-pixel blocks (the same solid angle as
   4 x 4 at 256^2), so t1 is taken 4 times (extrapolated, not rendered).
4. Pictures in ``--out``: the centre view side by side (VisiBake | Cycles | difference),
   the difference images of both views, a contact sheet of 5 x 5 of the 9 x 9 views at 512^2
   and the centre view's disparity in false colour; the numbers in lightfield_vs_cycles.json.
"""
from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

import numpy as np  # noqa: E402

BLOCK = 4
SPEED_GRIDS = ((16, 16, 256), (9, 9, 512))
TARGETS_S = {"16x16@256": 5.0, "9x9@512": 10.0}
CENTRE, CORNER = 40, 0  # the 9 x 9 grid's centre view (the demo's camera) and its top-left view


def read_exr(path: str) -> np.ndarray:
    """(h, w, 3) float64 linear pixels of an EXR, row 0 at the top."""
    import OpenEXR

    with OpenEXR.File(path) as exr:
        channels = exr.channels()
        if "RGBA" in channels:
            return np.array(channels["RGBA"].pixels, np.float64)[..., :3]
        return np.array(channels["RGB"].pixels, np.float64)


def blocks(image: np.ndarray, k: int = BLOCK) -> np.ndarray:
    height, width = image.shape[0] // k, image.shape[1] // k
    return image[:height * k, :width * k].reshape(height, k, width, k, -1).mean(axis=(1, 3))


def relative_rmse(ours: np.ndarray, reference: np.ndarray, k: int = BLOCK) -> float:
    """RMS over k x k-pixel block means (k = 1: pixels) and channels of ours - reference, over the
    reference's mean."""
    a, b = (blocks(ours, k), blocks(reference, k)) if k > 1 else (ours, reference)
    return float(np.sqrt(np.mean((a - b) ** 2)) / np.mean(b))


def without(error: float, noise: float) -> float:
    return float(np.sqrt(max(error ** 2 - noise ** 2, 0.0)))


def load_average() -> float:
    return round(os.getloadavg()[0], 2)


# --- the scene -------------------------------------------------------------------------------


def bake_demo(extension, grids, baseline_mm: float, focus_m: float, warnings: list) -> tuple[list, dict]:
    """Build the demo, bake what the views of ``grids`` see; (mesh objects, bake record)."""
    import importlib

    import bpy

    demo_scene = importlib.import_module(f"{extension.__name__}.operators.adapter.demo_scene")
    job = importlib.import_module(f"{extension.__name__}.operators.adapter.job")
    lightfield_io = importlib.import_module(f"{extension.__name__}.operators.adapter.lightfield_io")
    scene = bpy.context.scene
    objects = demo_scene.build_demo_scene(scene)
    # The camera's matrix_world (which the views are planned from) is only set by an update.
    bpy.context.view_layer.update()
    props = scene.visibake
    props.directions, props.bounces, props.resolution, props.shadows = 128, 2, 256, "exact"
    props.passes = {"lighting"}
    props.use_cache = False  # the bake traces its own table: its time is the method's
    seen = set()
    for columns, rows, size in grids:
        _, _, views, clip = lightfield_io.plan_views(scene, None, (columns, rows), baseline_mm, focus_m,
                                                     (size, size), warnings)
        inside, _ = lightfield_io.objects_in_views(objects, views, *clip)
        seen.update(o.name for o in inside)
    chosen = [o for o in objects if o.name in seen]
    started = time.perf_counter()
    outcome = job.run_bake(bpy.context, chosen)
    seconds = time.perf_counter() - started
    report = outcome.report
    settings = {k: report["settings"][k] for k in ("directions", "bounces", "shadows", "rotate", "interleave",
                                                   "footprint_samples", "sharp_contacts", "stitch_seams")}
    record = {"settings": {**settings, "resolution": props.resolution},
              "objects": [o.name for o in chosen], "skipped_unseen": sorted(o.name for o in objects if o not in chosen),
              "total_seconds": report["total_seconds"], "wall_seconds": round(seconds, 2),
              "stage_seconds": report["stage_seconds"],
              "uv_maps": {e["name"]: (e["uv_map"] if e.get("mode", "atlas") == "atlas" else None)
                          for e in report["objects"] if e["output"]}}
    print(f"bake: {record['total_seconds']:.1f} s (kernels {report['stage_seconds'].get('kernels', 0):.1f} s), "
          f"{len(chosen)} objects, skipped {record['skipped_unseen']}", flush=True)
    return objects, record


def centre_depth(extension, size: int, warnings: list) -> tuple[np.ndarray, object]:
    """The centre view's depth (metres along the axis, supersampled) and the drawn scene."""
    import importlib

    import bpy

    lightfield_io = importlib.import_module(f"{extension.__name__}.operators.adapter.lightfield_io")
    extract = importlib.import_module(f"{extension.__name__}.operators.adapter.extract")
    gpu_lightfield = importlib.import_module(f"{extension.__name__}.gpu_shaders.lightfield")
    scene = bpy.context.scene
    _, _, views, clip = lightfield_io.plan_views(scene, None, (1, 1), 50.0, 1.0, (size, size), warnings)
    objects = extract.scene_meshes(scene)
    drawn, _ = lightfield_io.draw_scene(scene, objects, warnings)
    # draw_scene keeps the objects' order (every demo object has triangles): mesh i is objects[i].
    drawn.names = [o.name for o in objects]
    with gpu_lightfield.ViewRenderer(drawn, size, size, lightfield_io.SUPERSAMPLING,
                                     lightfield_io.FILTER_WIDTH) as renderer:
        _, depth = renderer.render(views[0].view_matrix, views[0].projection_matrix, *clip, want_depth=True)
    return depth, drawn


# --- speed -----------------------------------------------------------------------------------


def time_renderer(extension, drawn, baseline_mm: float, focus_m: float, count: int, cpu_views: int,
                  warnings: list) -> list:
    """Seconds per view of the GPU renderer alone and of its CPU twin, per speed grid's size."""
    import importlib

    import bpy

    lightfield_io = importlib.import_module(f"{extension.__name__}.operators.adapter.lightfield_io")
    gpu_lightfield = importlib.import_module(f"{extension.__name__}.gpu_shaders.lightfield")
    raycast = importlib.import_module(f"{extension.__name__}.core.lightfield.raycast")
    s, width = lightfield_io.SUPERSAMPLING, lightfield_io.FILTER_WIDTH
    rows = []
    for columns, grid_rows, size in SPEED_GRIDS:
        _, _, views, clip = lightfield_io.plan_views(bpy.context.scene, None, (columns, grid_rows), baseline_mm,
                                                     focus_m, (size, size), warnings)

        def timed(renderer, chosen, want_depth=False):
            started = time.perf_counter()
            images = [renderer.render(v.view_matrix, v.projection_matrix, *clip, want_depth=want_depth)[0]
                      for v in chosen]
            return (time.perf_counter() - started) / len(chosen), images

        load = load_average()
        started = time.perf_counter()
        renderer = gpu_lightfield.ViewRenderer(drawn, size, size, s, width)
        setup = time.perf_counter() - started
        first, _ = timed(renderer, views[:1])
        per_view, gpu_images = timed(renderer, views[1:1 + count])
        with_depth, _ = timed(renderer, views[1:1 + max(1, count // 3)], want_depth=True)
        renderer.close()
        row = {"grid": f"{columns}x{grid_rows}@{size}", "size": size, "supersampling": s, "setup_s": round(setup, 4),
               "first_view_s": round(first, 4), "gpu_view_s": round(per_view, 4),
               "gpu_view_with_depth_s": round(with_depth, 4), "views_timed": count,
               "projected_grid_s": round(setup + columns * grid_rows * per_view, 2), "load_average_before": load}
        cpu_count = cpu_views if size <= 256 else max(1, cpu_views // 2)
        if cpu_count > 0:
            twin = raycast.RaycastRenderer(drawn, size, size, s, width)
            cpu_s, cpu_images = timed(twin, views[1:1 + cpu_count])
            difference = max(float(np.max(np.abs(a - b))) / float(np.mean(b)) for a, b in zip(cpu_images, gpu_images))
            rms = max(relative_rmse(a, b, 1) for a, b in zip(cpu_images, gpu_images))
            row.update(cpu_view_s=round(cpu_s, 3), cpu_views_timed=cpu_count,
                       cpu_vs_gpu_max_abs_over_mean=round(difference, 5), cpu_vs_gpu_relative_rmse=round(rms, 6))
        rows.append(row)
        print(f"renderer {row['grid']}: {row}", flush=True)
    return rows


def run_job(extension, folder: str, grid: tuple[int, int], size: int, baseline_mm: float, focus_m: float,
            supersampling: int | None = None) -> dict:
    import importlib

    import bpy

    lightfield_io = importlib.import_module(f"{extension.__name__}.operators.adapter.lightfield_io")
    load = load_average()
    report = lightfield_io.LightFieldJob(bpy.context.scene, None, folder, grid, baseline_mm, focus_m, (size, size),
                                         "hci", "auto", overwrite=True,
                                         supersampling=supersampling or lightfield_io.SUPERSAMPLING).run().report
    record = {k: report[k] for k in ("views", "grid", "image_size", "renderer", "supersampling", "pixel_filter",
                                     "disparity_range", "render_s", "write_s", "seconds", "files", "warnings")}
    record.update(load_average_before=load, load_average_after=load_average(), folder=folder)
    print(f"job {grid[0]}x{grid[1]}@{size} (s = {record['supersampling']}): render {record['render_s']:.2f} s, "
          f"write {record['write_s']:.2f} s, "
          f"total {record['seconds']:.2f} s; disparity {record['disparity_range']}", flush=True)
    return record


def supersampling_ladder(extension, work: str, baseline_mm: float, focus_m: float, grid=(16, 16),
                         size: int = 256) -> dict:
    """The 16 x 16 grid at s = 1, 2 and 4 supersamples beside the default's, timed; each view set
    against the s = 4 one (four views: two corners and two near the centre), per pixel and on
    4 x 4 blocks. What a lower s costs in anti-aliasing for what it saves."""
    import importlib

    lightfield_io = importlib.import_module(f"{extension.__name__}.operators.adapter.lightfield_io")
    hci = importlib.import_module(f"{extension.__name__}.core.lightfield.hci")
    count = grid[0] * grid[1]
    chosen = (0, count // 2 - grid[0] // 2 - 1, count // 2 + grid[0] // 2, count - 1)
    folders, rows = {}, {}
    for s in (1, 2, lightfield_io.SUPERSAMPLING, 4):
        if s in folders:
            continue
        folders[s] = os.path.join(work, f"lf_{grid[0]}x{grid[1]}_{size}_s{s}")
        rows[s] = run_job(extension, folders[s], grid, size, baseline_mm, focus_m, supersampling=s)
    finest = [read_exr(os.path.join(folders[4], hci.view_file_name(i, ".exr"))) for i in chosen]
    for s, row in rows.items():
        views = [read_exr(os.path.join(folders[s], hci.view_file_name(i, ".exr"))) for i in chosen]
        row["vs_s4_pixels"] = round(float(np.mean([relative_rmse(a, b, 1) for a, b in zip(views, finest)])), 5)
        row["vs_s4_blocks"] = round(float(np.mean([relative_rmse(a, b) for a, b in zip(views, finest)])), 5)
        print(f"s = {s}: render {row['render_s']:.2f} s; against s = 4: pixels {100 * row['vs_s4_pixels']:.2f}%, "
              f"blocks {100 * row['vs_s4_blocks']:.2f}%", flush=True)
    return {str(s): {k: row[k] for k in ("render_s", "write_s", "vs_s4_pixels", "vs_s4_blocks",
                                         "load_average_before", "load_average_after")} | {"views_compared": chosen}
            for s, row in rows.items()}


def object_masks(extension, drawn, views, clip, size: int) -> list[dict]:
    """{object name: (size, size) bool} per view: the pixels that see only that object, from a
    render of the same views with each object's radiance (i, i^2, 1): a filtered pixel that mixes
    objects (or the world) fails (i^2 = mean(i^2) only where i is constant, and 1 needs no world)."""
    import importlib

    lightfield_io = importlib.import_module(f"{extension.__name__}.operators.adapter.lightfield_io")
    lfscene = importlib.import_module(f"{extension.__name__}.core.lightfield.scene")
    gpu_lightfield = importlib.import_module(f"{extension.__name__}.gpu_shaders.lightfield")
    meshes = [lfscene.DrawMesh(m.positions, np.tile(np.float32([i + 1, (i + 1) ** 2, 1.0]), (len(m.positions), 1)))
              for i, m in enumerate(drawn.meshes)]
    ids = lfscene.DrawScene(meshes, np.zeros((1, 1, 3), np.float32))
    masks = []
    with gpu_lightfield.ViewRenderer(ids, size, size, lightfield_io.SUPERSAMPLING, lightfield_io.FILTER_WIDTH) as r:
        for view in views:
            image = r.render(view.view_matrix, view.projection_matrix, *clip)[0].astype(np.float64)
            number = np.rint(image[..., 0])
            pure = (np.abs(image[..., 2] - 1.0) < 1e-4) & (np.abs(image[..., 1] - image[..., 0] ** 2) < 1e-3 * number)
            masks.append({name: pure & (number == i + 1) for i, name in enumerate(drawn.names)})
    return masks


def per_object(masks: dict, ours, reference, halves, baked_render, minimum: int = 64) -> dict:
    """Per object seen by ``minimum`` pixels or more: its mean ratio to the reference (VisiBake's
    light field, and Cycles rendering the baked textures), the noise of that mean and the pixels."""
    rows = {}
    for name, mask in masks.items():
        if mask.sum() < minimum:
            continue
        total = float(reference[mask].sum())
        noise = abs(float(halves[0][mask].sum() - halves[1][mask].sum())) / 2.0 / total
        rows[name] = {"pixels": int(mask.sum()), "mean_ratio": round(float(ours[mask].sum()) / total, 4),
                      "mean_ratio_baked_render": round(float(baked_render[mask].sum()) / total, 4),
                      "reference_mean": round(total / mask.sum() / 3.0, 4), "mean_noise_estimate": round(noise, 4)}
    return rows


# --- Cycles ----------------------------------------------------------------------------------


def view_camera(view, camera, clip):
    """A Blender camera object at ``view`` (a GridView) of the HCI ``camera``: what Cycles renders from."""
    import bpy

    from mathutils import Matrix

    data = bpy.data.cameras.new(f"LF view {view.index}")
    data.type = "PERSP"
    data.lens = camera.focal_length_mm
    data.sensor_fit = "AUTO"
    data.sensor_width = camera.sensor_size_mm
    data.shift_x, data.shift_y = view.shift_x, view.shift_y
    data.clip_start, data.clip_end = clip
    obj = bpy.data.objects.new(f"LF view {view.index}", data)
    bpy.context.scene.collection.objects.link(obj)
    obj.matrix_world = Matrix(view.camera_to_world.tolist())
    return obj


def cycles_render(camera_obj, size: int, samples: int, seed: int, bounces: int, path: str) -> tuple[np.ndarray, float]:
    """Cycles' render from ``camera_obj`` as (size, size, 3) linear, row 0 at the top, and its seconds."""
    import bpy

    scene = bpy.context.scene
    scene.camera = camera_obj
    render, cycles = scene.render, scene.cycles
    render.engine = "CYCLES"
    render.resolution_x = render.resolution_y = size
    render.resolution_percentage = 100
    render.film_transparent = False
    cycles.device = "CPU"
    cycles.samples = samples
    cycles.seed = seed
    cycles.use_animated_seed = False
    cycles.use_adaptive_sampling = False
    cycles.use_denoising = False
    cycles.max_bounces = bounces
    cycles.diffuse_bounces = bounces
    cycles.glossy_bounces = cycles.transmission_bounces = cycles.volume_bounces = 0
    cycles.caustics_reflective = cycles.caustics_refractive = False
    cycles.sample_clamp_direct = cycles.sample_clamp_indirect = 0.0
    cycles.pixel_filter_type = "BLACKMAN_HARRIS"
    cycles.filter_width = 1.5
    render.image_settings.file_format = "OPEN_EXR"
    render.image_settings.color_depth = "32"
    render.filepath = path
    started = time.perf_counter()
    bpy.ops.render.render(write_still=True)
    return read_exr(path), time.perf_counter() - started


class BakedMaterials:
    """Every baked object shown through an emission of its baked lighting (image through the
    bake's UV map with Linear / Extend, or the VB_lighting attribute) plus its material's own
    emission, lamps hidden: Cycles then renders what the light field draws."""

    def __init__(self, extension, objects, uv_maps: dict):
        import importlib

        import bpy

        writeback = importlib.import_module(f"{extension.__name__}.operators.adapter.writeback")
        extract = importlib.import_module(f"{extension.__name__}.operators.adapter.extract")
        compat = importlib.import_module(f"{extension.__name__}.operators.adapter.compat")
        self.saved, self.created, self.hidden = [], [], []
        for obj in objects:
            if obj.name not in uv_maps:
                continue
            material = bpy.data.materials.new(f"__lf_baked_{obj.name}")
            self.created.append(material)
            nodes, links = compat.ensure_node_tree(material).nodes, material.node_tree.links
            nodes.clear()
            output = nodes.new("ShaderNodeOutputMaterial")
            light = nodes.new("ShaderNodeEmission")
            if uv_maps[obj.name] is None:
                source = nodes.new("ShaderNodeVertexColor")
                source.layer_name = writeback.attribute_name("lighting")
            else:
                source = nodes.new("ShaderNodeTexImage")
                source.image = writeback.find_image(obj.name, "lighting")
                source.interpolation, source.extension = "Linear", "EXTEND"
                uv = nodes.new("ShaderNodeUVMap")
                uv.uv_map = uv_maps[obj.name]
                links.new(uv.outputs["UV"], source.inputs["Vector"])
            links.new(source.outputs["Color"], light.inputs["Color"])
            surface = light.outputs["Emission"]
            original = obj.material_slots[0].material if obj.material_slots else None
            emission = extract.read_material(original, "", []).emission if original is not None else None
            if emission is not None and np.any(emission > 0):
                own = nodes.new("ShaderNodeEmission")
                own.inputs["Color"].default_value = (*map(float, emission), 1.0)
                add = nodes.new("ShaderNodeAddShader")
                links.new(surface, add.inputs[0])
                links.new(own.outputs["Emission"], add.inputs[1])
                surface = add.outputs["Shader"]
            links.new(surface, output.inputs["Surface"])
            for slot in obj.material_slots:
                self.saved.append((slot, slot.link, slot.material))
                slot.link = "OBJECT"
                slot.material = material
        for obj in bpy.context.scene.objects:
            if obj.type == "LIGHT" and not obj.hide_render:
                obj.hide_render = True
                self.hidden.append(obj)

    def close(self) -> None:
        import bpy

        for slot, link, material in reversed(self.saved):
            slot.link, slot.material = link, material
        for obj in self.hidden:
            obj.hide_render = False
        for material in self.created:
            bpy.data.materials.remove(material)


# --- pictures --------------------------------------------------------------------------------


def display(image: np.ndarray, white: float) -> np.ndarray:
    """sRGB-encoded 8-bit of linear ``image`` with ``white`` at 1 (clipped)."""
    c = np.clip(image / white, 0.0, 1.0)
    encoded = np.where(c <= 0.0031308, 12.92 * c, 1.055 * np.power(c, 1.0 / 2.4) - 0.055)
    return (encoded * 255.0 + 0.5).astype(np.uint8)


def difference_rgb(ours: np.ndarray, reference: np.ndarray, scale: float, k: int = 1) -> np.ndarray:
    """Signed (ours - reference) / mean(reference), luminance, on k x k blocks, blown back up to
    pixels, as a blue (darker) / red (brighter) map saturating at +-``scale``."""
    import matplotlib

    weights = np.array([0.2126, 0.7152, 0.0722])
    a, b = (blocks(ours, k), blocks(reference, k)) if k > 1 else (ours, reference)
    signed = ((a - b) @ weights) / float(np.mean(reference @ weights))
    if k > 1:
        signed = np.kron(signed, np.ones((k, k)))
    rgba = matplotlib.colormaps["RdBu_r"](np.clip(0.5 + 0.5 * signed / scale, 0.0, 1.0))
    return (rgba[..., :3] * 255.0 + 0.5).astype(np.uint8)


def save_png(path: str, pixels: np.ndarray) -> int:
    from PIL import Image

    Image.fromarray(pixels).save(path, optimize=True)
    return os.path.getsize(path)


def pictures(out: str, views: dict, folder_512: str, scale: float) -> dict:
    """The side-by-side, the difference images, the contact sheet and the disparity map."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from PIL import Image

    sizes = {}
    centre = views["centre"]
    white = float(np.percentile(centre["reference"], 98))
    gap = np.full((centre["ours"].shape[0], 4, 3), 255, np.uint8)
    side = np.concatenate([display(centre["ours"], white), gap, display(centre["reference"], white), gap,
                           difference_rgb(centre["ours"], centre["reference"], scale)], axis=1)
    sizes["centre_side_by_side.png"] = save_png(os.path.join(out, "centre_side_by_side.png"), side)
    # Both views: pixels and 4 x 4 blocks, VisiBake against Cycles.
    figure, axes = plt.subplots(2, 2, figsize=(6.4, 6.6))
    for r, name in enumerate(("centre", "corner")):
        view = views[name]
        for c, k in enumerate((1, BLOCK)):
            axis = axes[r, c]
            axis.imshow(difference_rgb(view["ours"], view["reference"], scale, k))
            axis.set_title(f"{name} view {view['index']}, {'pixels' if k == 1 else f'{k}x{k} blocks'}", fontsize=8)
            axis.axis("off")
    colour = plt.cm.ScalarMappable(cmap="RdBu_r", norm=matplotlib.colors.Normalize(-100 * scale, 100 * scale))
    figure.colorbar(colour, ax=axes, shrink=0.6, label="(VisiBake - Cycles) / mean, %")
    figure.savefig(os.path.join(out, "difference.png"), dpi=80)
    plt.close(figure)
    sizes["difference.png"] = os.path.getsize(os.path.join(out, "difference.png"))
    # 5 x 5 of the 9 x 9 views (every other row and column), from the PNGs the job wrote.
    tile, pad = 144, 4
    picks = (0, 2, 4, 6, 8)
    sheet = Image.new("RGB", (len(picks) * (tile + pad) - pad,) * 2, (255, 255, 255))
    for i, row in enumerate(picks):
        for j, column in enumerate(picks):
            with Image.open(os.path.join(folder_512, f"input_Cam{row * 9 + column:03d}.png")) as view:
                small = view.convert("RGB").resize((tile, tile), Image.LANCZOS)
            sheet.paste(small, (j * (tile + pad), i * (tile + pad)))
    sheet.save(os.path.join(out, "grid.png"), optimize=True)
    sizes["grid.png"] = os.path.getsize(os.path.join(out, "grid.png"))
    return sizes


def disparity_picture(out: str, folder: str, hci) -> dict:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    disparity = hci.read_pfm(os.path.join(folder, hci.DISPARITY_FILE))
    figure, axis = plt.subplots(figsize=(4.6, 3.8))
    shown = axis.imshow(disparity, cmap="viridis")
    axis.axis("off")
    axis.set_title("centre view's disparity (px between adjacent views)", fontsize=8)
    figure.colorbar(shown, ax=axis, shrink=0.8)
    figure.tight_layout()
    figure.savefig(os.path.join(out, "disparity.png"), dpi=110)
    plt.close(figure)
    finite = disparity[np.isfinite(disparity)]
    return {"disparity.png": os.path.getsize(os.path.join(out, "disparity.png")),
            "disparity_percentiles_1_50_99": [round(float(v), 3) for v in np.percentile(finite, [1, 50, 99])]}


# --- main ------------------------------------------------------------------------------------


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--baseline-mm", type=float, default=50.0)
    parser.add_argument("--focus-distance-m", type=float, default=None,
                        help="default: the centre view's median depth, rounded to 0.1 m")
    parser.add_argument("--views", type=int, default=12, help="views timed per size (renderer alone)")
    parser.add_argument("--cpu-views", type=int, default=2, help="views of the CPU twin at 256^2 (half at 512^2)")
    parser.add_argument("--accuracy-size", type=int, default=256, help="pixels per side of the views compared")
    parser.add_argument("--samples", type=int, default=512, help="Cycles samples of a reference view (two halves)")
    parser.add_argument("--low-samples", type=int, default=16, help="a cheaper Cycles render (noise and time)")
    parser.add_argument("--baked-samples", type=int, default=32, help="Cycles samples of the baked-texture renders")
    parser.add_argument("--difference-scale", type=float, default=0.25, help="the difference images' +- range")
    parser.add_argument("--out", default=os.path.join(ROOT, "docs", "lightfield"))
    parser.add_argument("--speed-only", action="store_true",
                        help="only the bake and the timings (-> benchmarks/results/lightfield_speed.json)")
    parser.add_argument("--work", default=None, help="folder for the light fields and renders (default: temporary)")
    args = parser.parse_args(argv)
    begun = time.perf_counter()

    from tools.visibake import load_extension

    extension = load_extension()
    import importlib

    import bpy

    from benchmarks.run import write_results

    lightfield_io = importlib.import_module(f"{extension.__name__}.operators.adapter.lightfield_io")
    hci = importlib.import_module(f"{extension.__name__}.core.lightfield.hci")
    runtime = importlib.import_module(f"{extension.__name__}.gpu_shaders.runtime")
    load_start = load_average()
    work = args.work or tempfile.mkdtemp(prefix="visibake-lightfield-")
    os.makedirs(work, exist_ok=True)
    os.makedirs(args.out, exist_ok=True)
    warnings: list = []
    runtime.ensure_context()
    info = runtime.device_info()
    print(f"GPU: {info.renderer} ({info.backend}); {os.cpu_count()} CPUs; load average {load_average()}", flush=True)

    bpy.ops.wm.read_homefile(use_empty=True)
    # The focus distance is needed to choose which objects to bake, but the views' objects do
    # not depend on it (the frusta's extent does, slightly): plan with the demo camera's own view.
    focus_guess = args.focus_distance_m or 3.0
    objects, bake = bake_demo(extension, [(c, r, s) for c, r, s in SPEED_GRIDS] + [(9, 9, args.accuracy_size)],
                              args.baseline_mm, focus_guess, warnings)
    depth, drawn = centre_depth(extension, 256, warnings)
    finite = depth[np.isfinite(depth)]
    focus = args.focus_distance_m or round(float(np.median(finite)), 1)
    depth_record = {"percentiles_1_50_99_m": [round(float(v), 3) for v in np.percentile(finite, [1, 50, 99])],
                    "min_m": round(float(finite.min()), 3), "max_m": round(float(finite.max()), 3),
                    "world_fraction": round(1.0 - finite.size / depth.size, 4)}
    print(f"centre view depth {depth_record}; focus {focus} m, baseline {args.baseline_mm} mm", flush=True)

    speed_rows = time_renderer(extension, drawn, args.baseline_mm, focus, args.views, args.cpu_views, warnings)
    jobs = {}
    for columns, rows, size in SPEED_GRIDS:
        folder = os.path.join(work, f"lf_{columns}x{rows}_{size}")
        jobs[f"{columns}x{rows}@{size}"] = run_job(extension, folder, (columns, rows), size, args.baseline_mm, focus)
    accuracy_key = f"9x9@{args.accuracy_size}"
    accuracy_folder = os.path.join(work, f"lf_9x9_{args.accuracy_size}")
    jobs[accuracy_key] = run_job(extension, accuracy_folder, (9, 9), args.accuracy_size, args.baseline_mm, focus)
    for key, target in TARGETS_S.items():
        jobs[key]["target_render_s"] = target
        jobs[key]["target_met"] = jobs[key]["render_s"] <= target
    ladder = supersampling_ladder(extension, work, args.baseline_mm, focus)
    if args.speed_only:
        path = os.path.join(ROOT, "benchmarks", "results", "lightfield_speed.json")
        write_results(path, {"gpu": {"renderer": info.renderer, "backend": info.backend},
                             "settings": {"baseline_mm": args.baseline_mm, "focus_distance_m": focus},
                             "bake": {k: v for k, v in bake.items() if k != "uv_maps"}, "renderer": speed_rows,
                             "jobs": jobs, "supersampling": ladder,
                             "load_average": {"start": load_start, "end": load_average()}})
        for key, job in jobs.items():
            print(f"{key}: render {job['render_s']:.2f} s, write {job['write_s']:.2f} s")
        if args.work is None:
            shutil.rmtree(work, ignore_errors=True)
        return 0

    # Accuracy: the centre and the corner view against Cycles from the same cameras.
    scene = bpy.context.scene
    demo_camera = scene.camera
    camera, grid, views, clip = lightfield_io.plan_views(scene, None, (9, 9), args.baseline_mm, focus,
                                                         (args.accuracy_size, args.accuracy_size), warnings)
    size, half = args.accuracy_size, args.samples // 2
    bounces = bake["settings"]["bounces"]
    compared, cycles_times = {}, []
    for name, index in (("centre", CENTRE), ("corner", CORNER)):
        view = views[index]
        obj = view_camera(view, camera, clip)
        halves = []
        for seed in (1, 2):
            path = os.path.join(work, f"cycles_{index}_{seed}.exr")
            image, seconds = cycles_render(obj, size, half, seed, bounces, path)
            halves.append(image)
            cycles_times.append((half, seconds))
            print(f"Cycles view {index} seed {seed}: {half} spp, {seconds:.1f} s", flush=True)
        reference = 0.5 * (halves[0] + halves[1])
        ours = read_exr(os.path.join(accuracy_folder, hci.view_file_name(index, ".exr")))
        entry = {"index": index, "row": view.row, "column": view.column, "shift_x": view.shift_x,
                 "shift_y": view.shift_y, "position_m": [round(float(v), 4) for v in view.position_m],
                 "ours": ours, "reference": reference, "halves": halves, "camera": obj}
        compared[name] = entry
    low_image, low_seconds = cycles_render(compared["centre"]["camera"], size, args.low_samples, 3, bounces,
                                           os.path.join(work, "cycles_low.exr"))
    cycles_times.append((args.low_samples, low_seconds))
    baked = BakedMaterials(extension, objects, bake["uv_maps"])
    try:
        for name, entry in compared.items():
            entry["baked_render"], _ = cycles_render(entry["camera"], size, args.baked_samples, 1, 0,
                                                     os.path.join(work, f"baked_{entry['index']}.exr"))
    finally:
        baked.close()
    scene.camera = demo_camera

    masks = object_masks(extension, drawn, [views[CENTRE], views[CORNER]], clip, size)
    accuracy = {}
    for (name, entry), view_masks in zip(compared.items(), masks):
        reference, ours, halves = entry["reference"], entry["ours"], entry["halves"]
        row = {k: entry[k] for k in ("index", "row", "column", "shift_x", "shift_y", "position_m")}
        for label, k in (("blocks", BLOCK), ("pixels", 1)):
            noise_half = relative_rmse(halves[0], halves[1], k) / np.sqrt(2.0)
            noise = noise_half / np.sqrt(2.0)  # of the mean of the two halves
            error = relative_rmse(ours, reference, k)
            baked_error = relative_rmse(entry["baked_render"], reference, k)
            row[label] = {"relative_rmse": round(error, 5), "reference_noise": round(noise, 5),
                          "relative_rmse_without_noise": round(without(error, noise), 5),
                          "cycles_noise_per_half": round(noise_half, 5),
                          "bake_alone_relative_rmse": round(baked_error, 5),
                          "bake_alone_without_noise": round(without(baked_error, noise), 5),
                          "lightfield_vs_cycles_of_baked_textures": round(relative_rmse(ours, entry["baked_render"], k),
                                                                          5)}
        row["mean_ratio"] = round(float(ours.mean() / reference.mean()), 4)
        row["mean_ratio_baked_render"] = round(float(entry["baked_render"].mean() / reference.mean()), 4)
        row["reference_mean"] = round(float(reference.mean()), 5)
        row["objects"] = per_object(view_masks, ours, reference, halves, entry["baked_render"])
        accuracy[name] = row
        print(f"{name}: {row}", flush=True)
    low = relative_rmse(low_image, compared["centre"]["reference"], BLOCK)
    centre_noise = accuracy["centre"]["blocks"]
    low_noise = without(low, centre_noise["reference_noise"])
    predicted_low = centre_noise["cycles_noise_per_half"] * np.sqrt(half / args.low_samples)

    # Cycles' samples and seconds at the light field's block error.
    samples = np.array([s for s, _ in cycles_times], float)
    seconds = np.array([t for _, t in cycles_times], float)
    t1, t0 = np.polyfit(samples, seconds, 1)
    t0 = max(float(t0), 0.0)  # the sync; under a varying load the fit can dip below zero
    pooled_error = float(np.sqrt(np.mean([accuracy[n]["blocks"]["relative_rmse_without_noise"] ** 2
                                          for n in accuracy])))
    pooled_noise = float(np.sqrt(np.mean([accuracy[n]["blocks"]["cycles_noise_per_half"] ** 2 for n in accuracy])))
    floor = max(pooled_error, 1e-3)
    equal_samples = half * (pooled_noise / floor) ** 2
    equal_time = {}
    for key, count, pixels in ((f"9x9@{size}", 81, size), ("16x16@256", 256, 256), ("9x9@512", 81, 512)):
        # Per view: the scene's sync, then samples over (pixels / size)^2 as many pixels.
        cycles_s = count * (t0 + (pixels / size) ** 2 * t1 * equal_samples)
        visibake_s = bake["total_seconds"] + jobs[key]["seconds"]
        equal_time[key] = {"views": count, "cycles_seconds_per_view": round(cycles_s / count, 2),
                           "cycles_seconds": round(cycles_s, 1), "visibake_bake_seconds": bake["total_seconds"],
                           "visibake_lightfield_seconds": jobs[key]["seconds"],
                           "visibake_seconds": round(visibake_s, 2),
                           "cycles_over_visibake": round(cycles_s / visibake_s, 1),
                           "cycles_time_from": f"the {size}^2 renders' fit" + (
                               "" if pixels == size else f", t1 x {(pixels / size) ** 2:.0f} for {pixels}^2")}
    cycles_record = {"samples_reference": args.samples, "samples_per_half": half, "seeds": [1, 2],
                     "low_samples": args.low_samples, "low_samples_block_error_without_noise": round(low_noise, 5),
                     "low_samples_block_noise_predicted": round(float(predicted_low), 5),
                     "renders_samples_seconds": [[int(s), round(t, 2)] for s, t in cycles_times],
                     "seconds_per_view_fit": {"t0": round(float(t0), 3), "t1_per_sample": round(float(t1), 5)},
                     "lightfield_block_error_without_noise_pooled": round(pooled_error, 5),
                     "cycles_block_noise_per_half_pooled": round(pooled_noise, 5),
                     "samples_to_equal_error": round(float(equal_samples), 1), "time_at_equal_error": equal_time}
    print(f"Cycles at the light field's error: {cycles_record}", flush=True)

    sizes = pictures(args.out, compared, jobs["9x9@512"]["folder"], args.difference_scale)
    sizes.update(disparity_picture(args.out, jobs["9x9@512"]["folder"], hci))
    result = {
        "blender": bpy.app.version_string, "gpu": {"renderer": info.renderer, "backend": info.backend},
        "load_average": {"start": load_start, "end": None},
        "scene": "built-in demo (operators/adapter/demo_scene.py), the demo camera as the centre camera",
        "settings": {"baseline_mm": args.baseline_mm, "focus_distance_m": focus,
                     "focus_rule": "given" if args.focus_distance_m else "median depth of the centre view, 0.1 m",
                     "supersampling": lightfield_io.SUPERSAMPLING, "filter_width_px": lightfield_io.FILTER_WIDTH,
                     "accuracy_grid": f"9x9@{size}", "accuracy_views": {"centre": CENTRE, "corner": CORNER},
                     "block_pixels": BLOCK, "centre_camera": {"focal_length_mm": camera.focal_length_mm,
                                                              "sensor_size_mm": camera.sensor_size_mm,
                                                              "position_m": [float(v) for v in camera.position_m]},
                     "cycles": {"bounces": bounces, "diffuse_bounces": bounces, "glossy_bounces": 0,
                                "clamping": "off", "pixel_filter": "BLACKMAN_HARRIS 1.5",
                                "baked_texture_samples": args.baked_samples}},
        "bake": {k: v for k, v in bake.items() if k != "uv_maps"}, "centre_view_depth": depth_record,
        "renderer": speed_rows, "jobs": jobs, "supersampling": ladder, "accuracy": accuracy, "cycles": cycles_record,
        "pictures_bytes": sizes,
        "warnings": warnings, "wall_seconds": None}
    result["load_average"]["end"] = load_average()
    result["wall_seconds"] = round(time.perf_counter() - begun, 1)
    write_results(os.path.join(args.out, "lightfield_vs_cycles.json"), result)
    summary(result)
    if args.work is None:
        shutil.rmtree(work, ignore_errors=True)  # ~0.7 GB of views and renders
    return 0


def summary(result: dict) -> None:
    print(f"\n{'grid':<12}{'render s':>10}{'write s':>9}{'target':>8}{'met':>5}{'disparity px':>16}")
    for key, job in result["jobs"].items():
        target = job.get("target_render_s")
        print(f"{key:<12}{job['render_s']:>10.2f}{job['write_s']:>9.2f}{target if target else '-':>8}"
              f"{str(job.get('target_met', '-')):>5}{job['disparity_range'][0]:>8.2f}{job['disparity_range'][1]:>8.2f}")
    for name, row in result["accuracy"].items():
        b = row["blocks"]
        print(f"{name}: blocks {b['relative_rmse']:.4f} (noise {b['reference_noise']:.4f}, without "
              f"{b['relative_rmse_without_noise']:.4f}; bake alone {b['bake_alone_relative_rmse']:.4f}; LF vs Cycles "
              f"of the baked textures {b['lightfield_vs_cycles_of_baked_textures']:.4f}); pixels "
              f"{row['pixels']['relative_rmse']:.4f}; mean ratio {row['mean_ratio']}")
    for key, entry in result["cycles"]["time_at_equal_error"].items():
        print(f"{key}: Cycles {entry['cycles_seconds']} s against VisiBake {entry['visibake_seconds']} s: "
              f"x{entry['cycles_over_visibake']}")
    print(f"wall {result['wall_seconds']} s")


if __name__ == "__main__":
    status = main()
    from tools.blender_compat import compat

    compat.end_module_process(status)
