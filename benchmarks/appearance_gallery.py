"""Two micro-geometry tiles and the Principled BSDFs fitted to them, rendered in Cycles (issue 18).

For each tile -- a plain weave of coloured glossy fibres (``brdf_tiles.woven_tile``) and grey-blue
V-grooves (``brdf_tiles.v_groove_tile``) -- this script goes the way an artist's tile goes through
VisiBake, in one bpy session:

1. The tile is a mesh object (one period) with a Blender material. ``BRDFJob`` of
   ``operators/adapter/tile_io.py`` reads it (``read_tile``: the micro-BRDF from the material),
   simulates its BRDF on 64 light x 64 view hemisphere directions, with 128 global directions,
   2 bounces and resolution 48 (``core.appearance.gonio.simulate_brdf``), and fits Blender's Principled BSDF to it
   (``core.appearance.fit.fit_principled``); ``make_material`` turns the fit into a material. The
   fit and its error are printed. (The extension is imported from this tree as the package
   ``visibake``, not registered; the job writes its table into a temporary folder.)
2. Cycles renders, under one sun (45 degrees up) and a dim sky, four panels per tile:
   (a) the micro-geometry: the tile repeated 8 x 8 times, close up at an angle;
   (b) the micro-geometry from far: a folded sheet covered with the tile (instanced), its period
       about half a pixel, so that each pixel averages the tile as a gonioreflectometer does;
   (c) the fitted material on the same folded sheet, same camera: compare (b) and (c);
   (d) the fitted material on a sphere.
   Cycles uses as many bounces as the simulation (2), so that (b) and (c) count
   inter-reflections alike; OpenImageDenoise where this bpy has it. Camera rays that miss (or
   pass through the weave's pores) see a plain grey backdrop, which lights nothing. The JSON
   compares (b) and (c) pixel for pixel over the sheet.
   Each panel is 320 x 320 pixels, 32 samples per pixel.
3. Writes the panels side by side with captions into one PNG, and a JSON with the machine, the
   date, the settings, the times and each tile's fit (parameters and relative RMSE).

Reproduce
---------
    export NUMBA_CACHE_DIR=/tmp/numba-cache     # any writable folder
    .venv/bin/python benchmarks/appearance_gallery.py            # docs/appearance/gallery.{png,json}
    .venv/bin/python benchmarks/appearance_gallery.py --quick    # small and fast: benchmarks/results/

About 4 minutes on 2 cores, most of it the woven tile's glossy simulation; --quick (16 x 16
directions, 64 global ones, resolution 24, 160-pixel panels at 8 samples) under a minute once
the kernels are compiled.

Directions: z up is the tile's (and the scene's) macro normal; the sun and the cameras are given
by azimuth (from +x towards +y) and elevation.
"""
from __future__ import annotations

import argparse
import contextlib
import importlib
import importlib.util
import json
import math
import os
import shutil
import sys
import tempfile
import time
from datetime import datetime, timezone

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if ROOT not in sys.path:
    sys.path.insert(0, ROOT)

import bpy  # noqa: E402

import bmesh  # noqa: E402
from mathutils import Vector  # noqa: E402

from benchmarks import brdf_tiles  # noqa: E402
from benchmarks.brdf_reference import _machine  # noqa: E402

# Light and cameras (degrees).
SUN = {"azimuth": 200.0, "elevation": 45.0, "strength": 3.0, "angle": 1.0}
SKY = {"colour": (0.55, 0.65, 0.85), "strength": 0.12}
BACKDROP = (0.30, 0.30, 0.30)  # linear grey that camera rays see where they miss
CAMERA_AZIMUTH = 250.0  # the cameras stand on the -y side (a little towards -x)
CLOSE_ELEVATION = 42.0
FAR_ELEVATION = 38.0
ARRAY = 8  # periods per side of the close-up
CLOSE_HALF = 2.6  # the close-up frames the central +-CLOSE_HALF periods
FAR_PERIOD_PX = 0.5  # the tile's period in pixels at the folded sheet's centre

# Speculars of the micro-materials: Specular IOR Level 0.69 at IOR 1.5 gives the GGX lobe a
# weight of 0.100 in VisiBake's micro-BRDF (tile_io.micro_material: F0 = 0.04 x 2 x 0.69,
# weight F0 + (1 - F0) / 21).
TILES = {
    "woven": {
        "title": "woven, fibres (0.55, 0.12, 0.08) GGX roughness 0.4",
        "build": lambda: brdf_tiles.woven_tile(),
        "smooth": True,
        "material": {"shader": "principled", "base_color": (0.55, 0.12, 0.08), "roughness": 0.4,
                     "specular_ior_level": 0.69},
    },
    "vgroove": {
        "title": "V-grooves (45-degree walls), Lambert (0.30, 0.40, 0.55)",
        "build": lambda: brdf_tiles.v_groove_tile(0.25, 1.0, 2),
        "smooth": False,
        "material": {"shader": "diffuse", "base_color": (0.30, 0.40, 0.55)},
    },
}


@contextlib.contextmanager
def quiet():
    """Cycles prints a line per render on the C stdout: send fd 1 to /dev/null meanwhile."""
    sys.stdout.flush()
    saved = os.dup(1)
    null = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(null, 1)
        yield
    finally:
        sys.stdout.flush()
        os.dup2(saved, 1)
        os.close(saved)
        os.close(null)


def load_visibake():
    """This tree as the package ``visibake`` (imported, not registered: no operators, no CLI,
    the kernel cache where NUMBA_CACHE_DIR says). Returns its tile_io module."""
    if "visibake" not in sys.modules:
        spec = importlib.util.spec_from_file_location("visibake", os.path.join(ROOT, "__init__.py"),
                                                      submodule_search_locations=[ROOT])
        module = importlib.util.module_from_spec(spec)
        sys.modules["visibake"] = module
        spec.loader.exec_module(module)
    return importlib.import_module("visibake.operators.adapter.tile_io")


def direction(azimuth: float, elevation: float) -> Vector:
    a, e = math.radians(azimuth), math.radians(elevation)
    return Vector((math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)))


# --------------------------------------------------------------------------- scene


def new_mesh(name: str, positions, faces, smooth: bool, corners: int = 3):
    positions = np.asarray(positions, np.float64).reshape(-1, 3)
    faces = np.asarray(faces, np.int32).reshape(-1, corners)
    mesh = bpy.data.meshes.new(name)
    mesh.vertices.add(len(positions))
    mesh.vertices.foreach_set("co", positions.astype(np.float32).ravel())
    mesh.loops.add(faces.size)
    mesh.loops.foreach_set("vertex_index", faces.ravel())
    mesh.polygons.add(len(faces))
    mesh.polygons.foreach_set("loop_start", np.arange(0, faces.size, corners, dtype=np.int32))
    mesh.polygons.foreach_set("use_smooth", np.full(len(faces), bool(smooth)))
    mesh.update(calc_edges=True)
    mesh.validate(verbose=False)
    return mesh


def link(scene, name: str, data):
    obj = bpy.data.objects.new(name, data)
    scene.collection.objects.link(obj)
    return obj


def micro_material(name: str, spec: dict):
    """The tile's own material: what VisiBake simulates and what the close-up renders."""
    material = bpy.data.materials.new(name)
    if material.node_tree is None:  # 4.x makes none until asked
        material.use_nodes = True
    tree = material.node_tree
    tree.nodes.clear()
    out = tree.nodes.new("ShaderNodeOutputMaterial")
    colour = (*spec["base_color"], 1.0)
    if spec["shader"] == "diffuse":
        bsdf = tree.nodes.new("ShaderNodeBsdfDiffuse")
        bsdf.inputs["Color"].default_value = colour
    else:
        bsdf = tree.nodes.new("ShaderNodeBsdfPrincipled")
        bsdf.inputs["Base Color"].default_value = colour
        bsdf.inputs["Roughness"].default_value = spec["roughness"]
        bsdf.inputs["Specular IOR Level"].default_value = spec["specular_ior_level"]
    tree.links.new(bsdf.outputs["BSDF"], out.inputs["Surface"])
    return material


def tile_array(positions, triangles, period, count: int):
    """``count`` x ``count`` copies of the tile as one mesh, the copies' shared borders merged
    (so that smooth normals run across them as on the periodic surface)."""
    offsets = np.array([(i * period[0], j * period[1], 0.0) for i in range(count) for j in range(count)])
    pos = (positions[None] + offsets[:, None]).reshape(-1, 3)
    tri = (triangles[None] + len(positions) * np.arange(len(offsets))[:, None, None]).reshape(-1, 3)
    return pos, tri


def merge_borders(mesh, distance: float) -> None:
    bm = bmesh.new()
    bm.from_mesh(mesh)
    bmesh.ops.remove_doubles(bm, verts=bm.verts, dist=distance)
    bm.to_mesh(mesh)
    bm.free()
    mesh.update()


def fold_profile(half_width: float = 1.0, amplitude: float = 0.12, wavelength: float = 1.0, n: int = 20001):
    """A folded sheet's profile z(x) = amplitude cos(2 pi x / wavelength) over [-half_width,
    half_width]: (x, z, arc length) sampled finely."""
    x = np.linspace(-half_width, half_width, n)
    z = amplitude * np.cos(2 * np.pi * x / wavelength)
    s = np.concatenate([[0.0], np.cumsum(np.hypot(np.diff(x), np.diff(z)))])
    return x, z, s


def fold_mesh(profile, half_depth: float, across: int = 400, along: int = 60):
    """The folded sheet as a smooth quad grid (normals up): for the fitted material."""
    x, z, s = profile
    arc = np.linspace(0.0, s[-1], across + 1)
    px, pz = np.interp(arc, s, x), np.interp(arc, s, z)
    y = np.linspace(-half_depth, half_depth, along + 1)
    positions = np.stack([np.repeat(px, along + 1), np.tile(y, across + 1), np.repeat(pz, along + 1)], -1)
    u, v = np.meshgrid(np.arange(across), np.arange(along), indexing="ij")
    a = u * (along + 1) + v
    quads = np.stack([a, a + along + 1, a + along + 2, a + 1], -1).reshape(-1, 4)
    return positions, quads


def fold_instances(profile, half_depth: float, period: float):
    """Where the tile's copies go on the folded sheet, each scaled to ``period``: (K, 3) corners
    (the tile's origin) and (K, 4) quaternions (w, x, y, z) turning the tile's x along the
    profile's chord over one period (a turn about y, so the tile's y stays along the folds)."""
    x, z, s = profile
    count = int(s[-1] / period)
    arc = np.arange(count + 1) * period
    px, pz = np.interp(arc, s, x), np.interp(arc, s, z)
    beta = np.arctan2(-(pz[1:] - pz[:-1]), px[1:] - px[:-1])  # rotation about +y: x -> (cos b, 0, -sin b)
    rows = int(2 * half_depth / period)
    y = -half_depth + np.arange(rows) * period
    corners = np.stack([np.repeat(px[:-1], rows), np.tile(y, count), np.repeat(pz[:-1], rows)], -1)
    quats = np.stack([np.cos(beta / 2), np.zeros(count), np.sin(beta / 2), np.zeros(count)], -1)
    return corners, np.repeat(quats, rows, axis=0)


def instancer(scene, name: str, tile_obj, corners, quats, scale: float):
    """A points object whose geometry nodes put a copy of ``tile_obj`` at every point, turned by
    its "rotation" attribute and scaled by ``scale`` (Cycles instances them: one BVH)."""
    mesh = bpy.data.meshes.new(name)
    mesh.vertices.add(len(corners))
    mesh.vertices.foreach_set("co", corners.astype(np.float32).ravel())
    attribute = mesh.attributes.new("rotation", "QUATERNION", "POINT")
    attribute.data.foreach_set("value", quats.astype(np.float32).ravel())
    mesh.update()
    tree = bpy.data.node_groups.new(name, "GeometryNodeTree")
    tree.interface.new_socket("Geometry", in_out="INPUT", socket_type="NodeSocketGeometry")
    tree.interface.new_socket("Geometry", in_out="OUTPUT", socket_type="NodeSocketGeometry")
    nodes = tree.nodes
    group_in, group_out = nodes.new("NodeGroupInput"), nodes.new("NodeGroupOutput")
    info = nodes.new("GeometryNodeObjectInfo")
    info.inputs["Object"].default_value = tile_obj
    rotation = nodes.new("GeometryNodeInputNamedAttribute")
    rotation.data_type = "QUATERNION"
    rotation.inputs["Name"].default_value = "rotation"
    on_points = nodes.new("GeometryNodeInstanceOnPoints")
    on_points.inputs["Scale"].default_value = (scale, scale, scale)
    tree.links.new(group_in.outputs[0], on_points.inputs["Points"])
    tree.links.new(info.outputs["Geometry"], on_points.inputs["Instance"])
    tree.links.new(rotation.outputs["Attribute"], on_points.inputs["Rotation"])
    tree.links.new(on_points.outputs["Instances"], group_out.inputs[0])
    obj = link(scene, name, mesh)
    obj.modifiers.new(name, "NODES").node_group = tree
    return obj


def sphere(scene, name: str, radius: float = 1.0):
    mesh = bpy.data.meshes.new(name)
    bm = bmesh.new()
    bmesh.ops.create_uvsphere(bm, u_segments=96, v_segments=48, radius=radius)
    bm.to_mesh(mesh)
    bm.free()
    mesh.polygons.foreach_set("use_smooth", np.ones(len(mesh.polygons), bool))
    mesh.update()
    return link(scene, name, mesh)


def aim(camera_obj, camera, target: Vector, azimuth: float, elevation: float, coords, margin: float) -> float:
    """Point the camera at ``target`` from (azimuth, elevation), at the nearest distance where
    every point of ``coords`` is in the frame with ``margin`` (a share of the half frame) to
    spare. Returns that distance."""
    view = direction(azimuth, elevation)  # from the target towards the camera
    rotation = (-view).to_track_quat("-Z", "Y")
    matrix = rotation.to_matrix()
    right, up = matrix.col[0], matrix.col[1]
    half = math.tan(camera.angle / 2.0) * (1.0 - margin)  # a square image: the same both ways
    distance = 0.0
    for point in coords:
        rel = Vector(point) - target
        # in frame when |rel . axis| <= half * (distance - rel . view)
        distance = max(distance, abs(rel.dot(right)) / half + rel.dot(view), abs(rel.dot(up)) / half + rel.dot(view))
    camera_obj.rotation_mode = "QUATERNION"
    camera_obj.rotation_quaternion = rotation
    camera_obj.location = target + view * distance
    return distance


def setup_render(scene, args, path: str) -> dict:
    import _cycles

    scene.render.engine = "CYCLES"
    cycles = scene.cycles
    cycles.device = "CPU"
    cycles.samples = args.samples
    cycles.use_adaptive_sampling = False
    denoise = bool(getattr(_cycles, "with_openimagedenoise", False)) and not args.no_denoise
    cycles.use_denoising = denoise
    if denoise:
        cycles.denoiser = "OPENIMAGEDENOISE"
        cycles.denoising_input_passes = "RGB_ALBEDO_NORMAL"
    # As many bounces as the simulation: (b) and (c) then count inter-reflections alike.
    cycles.max_bounces = args.bounces
    cycles.diffuse_bounces = cycles.glossy_bounces = cycles.transmission_bounces = args.bounces
    cycles.transparent_max_bounces = 8
    cycles.sample_clamp_indirect = 0.0
    cycles.seed = 1
    render = scene.render
    render.resolution_x = render.resolution_y = args.size
    render.resolution_percentage = 100
    render.film_transparent = False
    render.use_compositing = False
    render.use_sequencer = False
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    render.image_settings.file_format = "PNG"
    render.image_settings.color_mode = "RGB"
    render.image_settings.color_depth = "8"
    render.filepath = path
    return {"engine": "CYCLES (CPU)", "samples": args.samples, "resolution": [args.size, args.size],
            "denoiser": "OpenImageDenoise (albedo + normal)" if denoise else None, "bounces": args.bounces,
            "view_transform": "Standard", "sun": SUN, "sky": SKY,
            "backdrop": {"colour": BACKDROP, "note": "seen by camera rays only; it lights nothing"}}


def lights(scene) -> None:
    """The sun and the dim sky; camera rays that miss everything (or pass through the weave's
    pores) see a plain grey backdrop instead of the sky, which lights nothing."""
    world = bpy.data.worlds.new("Gallery sky")
    if world.node_tree is None:
        world.use_nodes = True
    tree = world.node_tree
    tree.nodes.clear()
    sky = tree.nodes.new("ShaderNodeBackground")
    sky.inputs["Color"].default_value = (*SKY["colour"], 1.0)
    sky.inputs["Strength"].default_value = SKY["strength"]
    backdrop = tree.nodes.new("ShaderNodeBackground")
    backdrop.inputs["Color"].default_value = (*BACKDROP, 1.0)
    backdrop.inputs["Strength"].default_value = 1.0
    path = tree.nodes.new("ShaderNodeLightPath")
    mix = tree.nodes.new("ShaderNodeMixShader")
    out = tree.nodes.new("ShaderNodeOutputWorld")
    tree.links.new(path.outputs["Is Camera Ray"], mix.inputs["Fac"])
    tree.links.new(sky.outputs["Background"], mix.inputs[1])
    tree.links.new(backdrop.outputs["Background"], mix.inputs[2])
    tree.links.new(mix.outputs["Shader"], out.inputs["Surface"])
    scene.world = world
    sun_data = bpy.data.lights.new("Gallery sun", "SUN")
    sun_data.energy = SUN["strength"]
    sun_data.angle = math.radians(SUN["angle"])
    sun = link(scene, "Gallery sun", sun_data)
    sun.rotation_mode = "QUATERNION"
    sun.rotation_quaternion = direction(SUN["azimuth"], SUN["elevation"]).to_track_quat("Z", "Y")


def read_png(path: str) -> np.ndarray:
    """(H, W, channels) float32 in [0, 1], row 0 at the top."""
    image = bpy.data.images.load(path, check_existing=False)
    try:
        w, h = image.size
        pixels = np.empty(w * h * image.channels, np.float32)
        image.pixels.foreach_get(pixels)
    finally:
        bpy.data.images.remove(image)
    return pixels.reshape(h, w, -1)[::-1]  # Blender's rows run bottom-up


def render(scene, path: str, visible: list, everything: list) -> tuple[np.ndarray, float]:
    """Render with only ``visible`` of ``everything``; (H, W, 3) uint8 and the seconds."""
    for obj in everything:
        obj.hide_render = obj not in visible
    scene.render.filepath = path
    start = time.perf_counter()
    with quiet():
        bpy.ops.render.render(write_still=True, scene=scene.name)
    seconds = time.perf_counter() - start
    rgb = read_png(path)[..., :3]
    return np.clip(np.round(rgb * 255.0), 0, 255).astype(np.uint8), seconds


def coverage(scene, path: str, visible: list, everything: list) -> np.ndarray:
    """(H, W) the share of each pixel that ``visible`` covers: a transparent-film render, 16
    samples, no denoising (the settings are put back)."""
    cycles, settings = scene.cycles, scene.render.image_settings
    saved = (cycles.samples, cycles.use_denoising, scene.render.film_transparent, settings.color_mode)
    cycles.samples, cycles.use_denoising, scene.render.film_transparent, settings.color_mode = 16, False, True, "RGBA"
    try:
        for obj in everything:
            obj.hide_render = obj not in visible
        scene.render.filepath = path
        with quiet():
            bpy.ops.render.render(write_still=True, scene=scene.name)
        return read_png(path)[..., 3]
    finally:
        cycles.samples, cycles.use_denoising, scene.render.film_transparent, settings.color_mode = saved


# --------------------------------------------------------------------------- BRDF and fit


def simulate_and_fit(tile_io, scene, tile_obj, label: str, args, workdir: str, log):
    """BRDFJob as the panel runs it: read the tile object, simulate, fit. Returns (job, report)."""
    from visibake.core.appearance.gonio import GonioSettings

    settings = GonioSettings(directions=args.directions, bounces=args.bounces, resolution=args.resolution,
                             view_rays=args.view_rays)
    job = tile_io.BRDFJob(lambda: tile_io.read_tile(scene, tile_obj.name), os.path.join(workdir, f"{label}.npz"),
                          "table", args.lights, args.views, settings, overwrite=True)
    start = time.perf_counter()
    report = job.run().report
    report["wall_s"] = round(time.perf_counter() - start, 2)
    simulated = float(report["stats"].get("total_s", float("nan")))
    log(f"[{label}] BRDF {args.lights} x {args.views}: {report['samples']} samples, simulation {simulated:.1f} s, "
        f"with the fit {report['wall_s']:.1f} s; mean transparency {float(job.result.transparency.mean()):.4f}")
    for warning in report["warnings"]:
        log(f"[{label}] warning: {warning}")
    log(job.fit.describe())
    return job, report


def tile_panels(label: str, spec: dict, scene, camera_obj, camera, tile_io, args, workdir: str, log):
    """The tile's simulation, fit and four renders: (panels, the JSON entry)."""
    entry = {"title": spec["title"], "micro_material": spec["material"]}
    positions, triangles, period = spec["build"]()
    material = micro_material(f"{label} micro", spec["material"])
    tile_obj = link(scene, label, new_mesh(label, positions, triangles, spec["smooth"]))
    tile_obj.data.materials.append(material)
    tile_obj.hide_render = True  # one period: read by the job, instanced by (b)
    entry.update(triangles=int(len(triangles)), period=period.tolist(), smooth=spec["smooth"])

    job, report = simulate_and_fit(tile_io, scene, tile_obj, label, args, workdir, log)
    fit = report["principled_fit"]
    fitted = tile_io.make_material(f"{label} (VisiBake)", fit)
    entry["fit"] = fit
    entry["fit_relative_rmse"] = fit["relative_rmse"]
    entry["fit_candidates"] = {k: float(v) for k, v in job.fit.candidates.items()}
    entry["brdf"] = {k: report.get(k) for k in ("samples", "stats", "max_directional_albedo", "mean_brdf",
                                                "max_transparency", "warnings", "wall_s")}
    entry["brdf"]["mean_transparency"] = float(job.result.transparency.mean())
    entry["brdf"]["fit_and_write_s"] = round(report["wall_s"] - float(report["stats"].get("total_s", 0.0)), 2)

    build = time.perf_counter()
    # (a) the tile repeated ARRAY x ARRAY times, centred on the origin
    pos, tri = tile_array(positions, triangles, period, ARRAY)
    array_mesh = new_mesh(f"{label} array", pos, tri, spec["smooth"])
    merge_borders(array_mesh, 1e-6 * float(period.min()))
    array_mesh.materials.append(material)
    array_obj = link(scene, f"{label} array", array_mesh)
    array_obj.location = (-ARRAY * period[0] / 2, -ARRAY * period[1] / 2, 0.0)
    # (b), (c) the folded sheet: the tile instanced over it, and the fitted material on it
    profile = fold_profile()
    half_width, half_depth, amplitude = 1.0, 1.0, 0.12
    sheet_mesh = new_mesh(f"{label} sheet", *fold_mesh(profile, half_depth), True, corners=4)
    sheet_mesh.materials.append(fitted)
    sheet = link(scene, f"{label} sheet", sheet_mesh)
    # (d) a sphere
    ball = sphere(scene, f"{label} sphere", 1.0)
    ball.data.materials.append(fitted)
    origin = Vector((0.0, 0.0, 0.0))
    sheet_box = [(x, y, z) for x in (-half_width, half_width) for y in (-half_depth, half_depth)
                 for z in (-amplitude, amplitude)]
    far_distance = aim(camera_obj, camera, origin, CAMERA_AZIMUTH, FAR_ELEVATION, sheet_box, 0.03)
    far_camera = (camera_obj.location.copy(), camera_obj.rotation_quaternion.copy())
    # the tile's period: FAR_PERIOD_PX pixels at the sheet's centre
    pixel = 2.0 * far_distance * math.tan(camera.angle / 2.0) / args.size
    tile_period = FAR_PERIOD_PX * pixel
    corners, quats = fold_instances(profile, half_depth, tile_period)
    far = instancer(scene, f"{label} far", tile_obj, corners, quats, tile_period / float(period[0]))
    entry["far"] = {"tile_period_scene_units": tile_period, "tile_period_px_at_centre": FAR_PERIOD_PX,
                    "instances": int(len(corners)),
                    "sheet": f"z = {amplitude} cos(2 pi x), x in [-{half_width}, {half_width}], y in [-{half_depth}, "
                             f"{half_depth}]; the tile's x along the profile, its y along the folds"}
    entry["scene_build_s"] = round(time.perf_counter() - build, 2)

    everything = [array_obj, sheet, ball, far]
    panels, times = [], {}

    def shoot(key: str, obj) -> None:
        image, times[key] = render(scene, os.path.join(workdir, f"{label}_{key}.png"), [obj], everything)
        panels.append(image)

    close = CLOSE_HALF
    box = [(x, y, 0.0) for x in (-close, close) for y in (-close, close)]
    aim(camera_obj, camera, origin, CAMERA_AZIMUTH, CLOSE_ELEVATION, box, 0.0)
    shoot("a_close_up_s", array_obj)
    camera_obj.location, camera_obj.rotation_quaternion = far_camera
    shoot("b_far_micro_s", far)
    shoot("c_far_fitted_s", sheet)
    inside = (coverage(scene, os.path.join(workdir, f"{label}_mask.png"), [sheet], everything) > 0.99).ravel()
    box = [(x, y, z) for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (-1.0, 1.0)]
    aim(camera_obj, camera, origin, CAMERA_AZIMUTH, FAR_ELEVATION, box, 0.06)
    shoot("d_sphere_s", ball)
    for obj in everything:
        obj.hide_render = True
    entry["render_s"] = {k: round(v, 2) for k, v in times.items()}
    log(f"[{label}] renders: " + ", ".join(f"{k} {v:.1f} s" for k, v in times.items()))
    # (b) against (c): the same camera, sun and sky, so their 8-bit colours compare pixel for pixel
    # over the sheet (the weave's pores show a few per cent of the backdrop in (b))
    b, c = (panels[k].reshape(-1, 3).astype(np.float64) for k in (1, 2))
    entry["far_b_c"] = {"pixels": int(inside.sum()), "mean_rgb_b": b[inside].mean(0).round(2).tolist(),
                        "mean_rgb_c": c[inside].mean(0).round(2).tolist(),
                        "rms_difference_8bit": round(float(np.sqrt(np.mean((b - c)[inside] ** 2))), 2),
                        "note": "sRGB 8-bit levels (Standard view transform) over the pixels the fitted sheet "
                                "covers fully (a transparent-film render of (c), alpha > 0.99)"}
    return panels, entry


# --------------------------------------------------------------------------- picture


def compose(rows, captions, headers, path: str) -> str:
    """Panels (rows of (H, W, 3) uint8) side by side with a header per row and a caption under
    each panel; PNG. Returns how it was written."""
    try:
        from PIL import Image, ImageDraw, ImageFont
    except ImportError:  # no Pillow: the panels alone, through Blender's image writer
        picture = np.concatenate([np.concatenate(row, axis=1) for row in rows], axis=0)
        h, w = picture.shape[:2]
        image = bpy.data.images.new("gallery", w, h, alpha=False)
        rgba = np.concatenate([picture[::-1], np.full((h, w, 1), 255, np.uint8)], -1)
        image.pixels.foreach_set((rgba.astype(np.float32) / 255.0).ravel())
        image.filepath_raw = path
        image.file_format = "PNG"
        image.save()
        return "bpy (no captions: Pillow is missing)"
    try:
        font = ImageFont.load_default(size=13)
        big = ImageFont.load_default(size=15)
    except TypeError:  # an old Pillow: its bitmap font
        font = big = ImageFont.load_default()
    h, w = rows[0][0].shape[:2]
    header, caption, gap = 24, 20, 6
    width = w * len(rows[0]) + gap * (len(rows[0]) - 1)
    height = sum(header + h + caption for _ in rows) + gap * (len(rows) - 1)
    canvas = Image.new("RGB", (width, height), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    top = 0
    for row, texts, title in zip(rows, captions, headers):
        draw.text((4, top + 4), title, fill=(0, 0, 0), font=big)
        for k, (panel, text) in enumerate(zip(row, texts)):
            left = k * (w + gap)
            canvas.paste(Image.fromarray(panel), (left, top + header))
            draw.text((left + 4, top + header + h + 3), text, fill=(40, 40, 40), font=font)
        top += header + h + caption + gap
    canvas.save(path, optimize=True)
    return "Pillow"


# --------------------------------------------------------------------------- main


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--quick", action="store_true", help="small settings, writes to benchmarks/results/")
    parser.add_argument("--out", default=None, help="the PNG (default docs/appearance/gallery.png); the JSON "
                                                    "goes beside it")
    parser.add_argument("--no-denoise", action="store_true", help="no OpenImageDenoise even where bpy has it")
    args = parser.parse_args(argv)
    quick = args.quick
    args.lights = args.views = 16 if quick else 64
    args.directions = 64 if quick else 128
    args.bounces = 2
    args.resolution = 24 if quick else 48
    args.view_rays = 64 if quick else 128
    args.size = 160 if quick else 320
    args.samples = 8 if quick else 32
    folder = os.path.join(ROOT, "benchmarks", "results") if quick else os.path.join(ROOT, "docs", "appearance")
    args.out = os.path.abspath(args.out or os.path.join(folder, "gallery_quick.png" if quick else "gallery.png"))
    json_path = os.path.splitext(args.out)[0] + ".json"
    os.makedirs(os.path.dirname(args.out), exist_ok=True)

    def log(message):
        print(message, flush=True)

    started = time.perf_counter()
    load = {"start": [round(x, 2) for x in os.getloadavg()]}
    tile_io = load_visibake()
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    workdir = tempfile.mkdtemp(prefix="visibake-gallery-")
    result = {
        "what": "two micro-geometry tiles, their simulated BRDFs' Principled BSDF fits, rendered in Cycles",
        "date": datetime.now(timezone.utc).isoformat(timespec="seconds"), "machine": _machine(),
        "command": " ".join([".venv/bin/python benchmarks/appearance_gallery.py",
                             *(argv if argv is not None else sys.argv[1:])]),
        "quick": quick,
        "simulation": {"lights": args.lights, "views": args.views, "directions": args.directions,
                       "bounces": args.bounces, "resolution": args.resolution, "view_rays": args.view_rays,
                       "lights_and_views": "core.appearance.gonio.hemisphere_directions",
                       "how": "operators.adapter.tile_io.BRDFJob (read_tile, simulate_brdf, fit_principled; format "
                              "table), then make_material"},
        "panels": [f"(a) the tile repeated {ARRAY} x {ARRAY}, close up", f"(b) the tile instanced on a folded sheet, "
                   f"period {FAR_PERIOD_PX} px at its centre", "(c) the fitted Principled BSDF on the same sheet, "
                   "same camera", "(d) the fitted Principled BSDF on a sphere"],
        "fit_error": "relative RMSE of the fitted Principled BSDF against the simulated samples, weighted by "
                     "cos theta_l cos theta_v (core.appearance.fit.weighted_rmse)",
        "tiles": {},
    }
    try:
        lights(scene)
        result["render"] = setup_render(scene, args, os.path.join(workdir, "render.png"))
        camera = bpy.data.cameras.new("Gallery camera")
        camera.lens = 50.0
        camera.clip_start, camera.clip_end = 0.01, 1000.0
        camera_obj = link(scene, "Gallery camera", camera)
        scene.camera = camera_obj
        result["render"]["camera"] = {"lens_mm": camera.lens, "azimuth": CAMERA_AZIMUTH,
                                      "elevation_close_up": CLOSE_ELEVATION, "elevation_far": FAR_ELEVATION}
        rows, captions, headers = [], [], []
        for label, spec in TILES.items():
            panels, entry = tile_panels(label, spec, scene, camera_obj, camera, tile_io, args, workdir, log)
            result["tiles"][label] = entry
            rows.append(panels)
            fit = entry["fit"]
            headers.append(f"{spec['title']}  |  fit: {fit['model']}, relative RMSE {100 * fit['relative_rmse']:.1f}%")
            captions.append([f"(a) tile, {ARRAY} x {ARRAY}, close up", f"(b) tile, period {FAR_PERIOD_PX:g} px",
                             "(c) fitted material", "(d) fitted material"])
        result["compose"] = compose(rows, captions, headers, args.out)
    finally:
        shutil.rmtree(workdir, ignore_errors=True)
    result["total_s"] = round(time.perf_counter() - started, 1)
    load["end"] = [round(x, 2) for x in os.getloadavg()]
    result["load_average_1_5_15_min"] = load  # above 2 on 2 cores: other jobs shared the machine
    result["png_bytes"] = os.path.getsize(args.out)
    with open(json_path, "w") as fh:
        json.dump(result, fh, indent=1, default=float)
    for label, entry in result["tiles"].items():
        fit = entry["fit"]
        log(f"[{label}] fit {fit['model']}: base colour {np.round(fit['base_color'], 3).tolist()}, roughness "
            f"{fit['roughness']:.3f}, specular IOR level {fit['specular_ior_level']:.3f}, relative RMSE "
            f"{100 * fit['relative_rmse']:.2f}%")
    log(f"wrote {args.out} ({result['png_bytes'] / 1024:.0f} KB) and {json_path} in {result['total_s']:.0f} s")
    return 0


if __name__ == "__main__":
    status = main()
    from tools.blender_compat import compat  # bpy is loaded by now

    compat.end_module_process(status)
