"""The world as Cycles renders it: one equirectangular capture through Cycles itself.

Any world node tree (Sky Texture of every type, procedural textures, Mix Shaders of
backgrounds, node groups) is evaluated by rendering it once: a temporary scene with the
same world, no objects and an equirectangular panoramic camera at the origin, rendered
by Cycles to a temporary EXR and read back as linear radiance. The user's scene, its
window and ``bpy.data`` are left as they were (the temporary scene, camera, render
result and folder are removed again, also after an error).

Layout (checked against an Environment Texture whose pixels encode their own u, v:
every pixel came back as itself): with the camera rotated by Euler XYZ (90, 0, -90)
degrees, pixel (row, column) of the capture, row 0 at the bottom, is the direction
``environment.equirectangular_to_direction(u, v)`` at its centre, so the capture is a
``World(image=...)`` with the identity rotation.

Energy: the pixel filter is a box of one pixel, so a pixel is the mean radiance over its
area and the image integrates to the world's integral whatever the resolution. A sun
disc (the scattering skies' is 0.545 degrees: about two pixels at 1024 x 512, a million
times the sky) is the one place where the mean over a pixel needs many samples: the
pixels around it are rendered again, alone (a render border), with many more samples.
Measured on the 5.0 Multiple Scattering sky (sun 15 degrees up), 0.8 * irradiance / pi
of an upward plane, Cycles' bake 12.097 (two seeds within 0.01%): without the second
render 11.69, 12.16 and 12.32 at 512, 1024 and 2048 pixels wide (16 spp); with it 12.105
and 12.093 (0.07%). The disc then leaves the image as a lamp (``environment.split_sun``).

Cost (bpy 5.0.1, CPU, 2 cores): 1.2 s for 1024 x 512 at 4 spp on a lightly loaded
machine, 10-16 s with its load at 7-9; the second render is ~50k samples against the
first's 2M. A capture is kept per
process, keyed by a hash of the world tree's settings (1-12 ms), so a relight with an
unchanged world does not render again.
"""
from __future__ import annotations

import hashlib
import os
import shutil
import tempfile

import bpy

import numpy as np

from ...core.lights import environment
from . import compat

WIDTH = 1024
HEIGHT = 512
# A sky is smooth (16 spp at 256 x 128 and 1024 x 512 light a plane within 0.1% of each
# other) and a sun disc is rendered again below, so few samples per pixel suffice; the
# cells the transport forms average hundreds of pixels each.
SAMPLES = 4
# Pixels brighter than this times the mean are a sun disc (as environment.split_sun sees it).
HOT_FACTOR = environment.SUN_HOT_FACTOR
# Pixels around the hot ones rendered again, and how many samples they get.
HOT_MARGIN = 2
HOT_MAX_PIXELS = 64 * 64
HOT_SAMPLES = 1024
CAMERA_EULER = (np.pi / 2, 0.0, -np.pi / 2)

_cache: dict[str, np.ndarray] = {}


class CaptureFailed(RuntimeError):
    """Cycles could not render the world (no Cycles, out of memory, a render already running)."""


def capture_world(scene: bpy.types.Scene) -> np.ndarray:
    """Radiance of ``scene.world`` in every direction, as Cycles renders it.

    Returns
    -------
    image : (HEIGHT, WIDTH, 3) float32 linear RGB, finite and non-negative, row 0 at the
        bottom (the nadir), in ``core.lights.environment``'s equirectangular layout.
        The array is shared with the cache: do not modify it.

    Raises
    ------
    CaptureFailed
        when the render fails; nothing is left behind.
    """
    key = world_key(scene)
    cached = _cache.get(key)
    if cached is not None:
        return cached
    image = _render_world(scene)
    _cache.clear()  # one world at a time: a capture is 6 MB
    _cache[key] = image
    return image


def clear_cache() -> None:
    """Forget the kept capture (the next one renders again)."""
    _cache.clear()


def world_key(scene: bpy.types.Scene) -> str:
    """A hash of everything in ``scene.world`` that can change what Cycles renders."""
    hasher = hashlib.sha256()
    hasher.update(repr((compat.VERSION, WIDTH, HEIGHT, SAMPLES, HOT_FACTOR, HOT_SAMPLES)).encode())
    world = scene.world
    hasher.update(repr(world.name_full).encode())
    animated = world.animation_data is not None or (world.node_tree is not None
                                                    and world.node_tree.animation_data is not None)
    if animated:
        hasher.update(repr(scene.frame_current).encode())
    _hash_struct(hasher, world, set())
    if world.node_tree is not None:
        _hash_tree(hasher, world.node_tree, set())
    return hasher.hexdigest()


# Node settings that change how a tree looks in the editor, not what it renders.
_LAYOUT_PROPERTIES = {"location", "location_absolute", "width", "height", "select", "show_options",
                      "show_preview", "hide", "show_texture", "color", "use_custom_color", "label",
                      "warning_propagation", "rna_type", "dimensions", "parent",
                      # Deprecated in 5.x (a world always renders its nodes); a capture needs nodes anyway.
                      "use_nodes"}


def _hash_value(hasher, value, seen: set) -> None:
    if isinstance(value, bpy.types.ID):
        hasher.update(repr((type(value).__name__, value.name_full)).encode())
        if isinstance(value, bpy.types.Object):
            hasher.update(np.array(value.matrix_world, np.float64).tobytes())
        elif isinstance(value, bpy.types.Image):
            _hash_image(hasher, value)
        elif isinstance(value, bpy.types.NodeTree) and value.name_full not in seen:
            seen.add(value.name_full)
            _hash_tree(hasher, value, seen)
        return
    hasher.update(repr(_plain(value)).encode())


def _plain(value):
    """Arrays, vectors and colours of bpy as tuples (their repr shows no values)."""
    if isinstance(value, (str, bytes, int, float, bool)) or value is None:
        return value
    if isinstance(value, bpy.types.ID):
        return (type(value).__name__, value.name_full)
    if isinstance(value, (tuple, list)) or hasattr(value, "__len__"):
        try:
            return tuple(_plain(item) for item in value)
        except TypeError:
            pass
    return repr(value)


def _hash_image(hasher, image: bpy.types.Image) -> None:
    hasher.update(repr((image.source, image.filepath_raw, tuple(image.size), image.colorspace_settings.name,
                        image.alpha_mode)).encode())
    if image.source == "FILE" and image.filepath_raw and not image.is_dirty and image.packed_file is None:
        path = bpy.path.abspath(image.filepath_raw)
        if os.path.isfile(path):
            status = os.stat(path)
            hasher.update(repr((status.st_size, status.st_mtime_ns)).encode())
        return
    # Generated, packed or edited pixels: the pixels are what counts.
    width, height = image.size
    if width and height:
        pixels = np.empty(width * height * image.channels, np.float32)
        image.pixels.foreach_get(pixels)
        hasher.update(pixels.tobytes())


def _hash_struct(hasher, struct, seen: set) -> None:
    # A datablock's bookkeeping (users, tags, session ids) changes with no change to the world.
    bookkeeping = {prop.identifier for prop in bpy.types.ID.bl_rna.properties} - {"name"}
    for prop in struct.bl_rna.properties:
        name = prop.identifier
        if name in _LAYOUT_PROPERTIES or name in bookkeeping or prop.type == "COLLECTION":
            continue
        value = getattr(struct, name, None)
        if prop.type == "POINTER":
            if isinstance(value, bpy.types.ID):
                hasher.update(name.encode())
                _hash_value(hasher, value, seen)
            continue
        _hash_value(hasher, (name, value), seen)


def _hash_tree(hasher, tree: bpy.types.NodeTree, seen: set) -> None:
    for node in sorted(tree.nodes, key=lambda n: n.name):
        hasher.update(repr((node.name, node.bl_idname)).encode())
        _hash_struct(hasher, node, seen)
        for sockets in (node.inputs, node.outputs):
            for socket in sockets:
                value = getattr(socket, "default_value", None)
                _hash_value(hasher, (socket.identifier, socket.enabled, value), seen)
                if isinstance(value, bpy.types.ID):
                    _hash_value(hasher, value, seen)
    for link in tree.links:
        hasher.update(repr((link.from_node.name, link.from_socket.identifier, link.to_node.name,
                            link.to_socket.identifier, link.is_muted, link.is_valid)).encode())


def _render_world(user_scene: bpy.types.Scene) -> np.ndarray:
    if getattr(bpy.app, "is_job_running", None) and bpy.app.is_job_running("RENDER"):
        raise CaptureFailed("a render is already running")
    had_render_result = {image.name_full for image in bpy.data.images if image.type == "RENDER_RESULT"}
    scene = camera = camera_object = world_copy = folder = None
    try:
        folder = tempfile.mkdtemp(prefix="visibake-world-")
        scene = bpy.data.scenes.new("VisiBake World Capture")
        visibility = getattr(user_scene.world, "cycles_visibility", None)
        if visibility is not None and not visibility.camera:
            # Hidden from the camera, the world still lights the bake; a copy shows it.
            world_copy = user_scene.world.copy()
            world_copy.cycles_visibility.camera = True
        scene.world = world_copy or user_scene.world
        scene.frame_current = user_scene.frame_current
        camera = bpy.data.cameras.new("VisiBake World Capture")
        compat.set_equirectangular_panorama(camera)
        camera_object = bpy.data.objects.new("VisiBake World Capture", camera)
        camera_object.rotation_euler = CAMERA_EULER
        scene.collection.objects.link(camera_object)
        scene.camera = camera_object
        _render_settings(scene, user_scene)
        image = _render(scene, os.path.join(folder, "world.exr"), SAMPLES, seed=0)
        if image.shape[:2] != (HEIGHT, WIDTH):
            raise CaptureFailed(f"the capture came back {image.shape[1]} x {image.shape[0]}")
        _refine_hot_pixels(scene, image, folder)
        return image
    except CaptureFailed:
        raise
    except (RuntimeError, OSError, ValueError, KeyError, TypeError) as error:
        raise CaptureFailed(str(error).strip().splitlines()[-1] if str(error).strip() else type(error).__name__) \
            from error
    finally:
        if camera_object is not None:
            bpy.data.objects.remove(camera_object)
        if camera is not None:
            bpy.data.cameras.remove(camera)
        if scene is not None:
            bpy.data.scenes.remove(scene)
        if world_copy is not None:
            bpy.data.worlds.remove(world_copy)
        for image in list(bpy.data.images):
            if image.type == "RENDER_RESULT" and image.name_full not in had_render_result:
                bpy.data.images.remove(image)
        if folder is not None:
            shutil.rmtree(folder, ignore_errors=True)


def _render_settings(scene: bpy.types.Scene, user_scene: bpy.types.Scene) -> None:
    render = scene.render
    render.engine = "CYCLES"
    render.resolution_x, render.resolution_y, render.resolution_percentage = WIDTH, HEIGHT, 100
    render.film_transparent = False
    render.use_compositing = False
    render.use_sequencer = False
    render.threads_mode = user_scene.render.threads_mode
    render.threads = user_scene.render.threads
    render.image_settings.file_format = "OPEN_EXR"
    render.image_settings.color_depth = "32"
    render.image_settings.color_mode = "RGB"
    scene.view_settings.view_transform = "Standard"
    scene.view_settings.look = "None"
    scene.view_settings.exposure = 0.0
    scene.view_settings.gamma = 1.0
    cycles = scene.cycles
    cycles.device = "CPU"
    cycles.use_adaptive_sampling = False
    cycles.use_denoising = False
    # A box of one pixel: each pixel is the mean over its own area, so no energy moves.
    cycles.pixel_filter_type = "BOX"
    cycles.filter_width = 1.0
    cycles.sample_clamp_direct = 0.0
    cycles.sample_clamp_indirect = 0.0
    cycles.film_exposure = 1.0
    cycles.use_animated_seed = False


def _render(scene: bpy.types.Scene, path: str, samples: int, seed: int) -> np.ndarray:
    """Render ``scene`` to ``path`` and read it back: (h, w, 3) float32, row 0 at the bottom."""
    scene.cycles.samples = samples
    scene.cycles.seed = seed
    scene.render.filepath = path
    result = bpy.ops.render.render(write_still=True, scene=scene.name)
    if "FINISHED" not in result or not os.path.isfile(path):
        raise CaptureFailed("Cycles did not render the world")
    import OpenEXR

    with OpenEXR.File(path) as exr:
        channels = exr.channels()
        layer = channels.get("RGBA") or channels.get("RGB")
        if layer is None:
            raise CaptureFailed("the capture has no RGB channels")
        pixels = np.asarray(layer.pixels, np.float32)[::-1, :, :3]
    os.remove(path)
    return np.clip(np.nan_to_num(pixels, nan=0.0, posinf=0.0, neginf=0.0), 0.0, None)


def _refine_hot_pixels(scene: bpy.types.Scene, image: np.ndarray, folder: str) -> None:
    """Render the pixels of a sun disc (and their neighbours) again with many samples, in place."""
    luminance = image @ np.array([0.2126, 0.7152, 0.0722], np.float32)
    mean = float(luminance.mean())
    if not mean > 0:
        return
    rows, columns = np.nonzero(luminance > HOT_FACTOR * mean)
    if len(rows) == 0:
        return
    # Borders on whole pixels, so Blender's rounding of the border to pixels is exact.
    row0, row1 = max(0, rows.min() - HOT_MARGIN), min(HEIGHT, rows.max() + 1 + HOT_MARGIN)
    col0, col1 = max(0, columns.min() - HOT_MARGIN), min(WIDTH, columns.max() + 1 + HOT_MARGIN)
    if (row1 - row0) * (col1 - col0) > HOT_MAX_PIXELS:
        return  # scattered or wrapping around u = 0: the base capture stands
    render = scene.render
    render.use_border = True
    render.use_crop_to_border = True
    render.border_min_x, render.border_max_x = col0 / WIDTH, col1 / WIDTH
    render.border_min_y, render.border_max_y = row0 / HEIGHT, row1 / HEIGHT
    crop = _render(scene, os.path.join(folder, "sun.exr"), HOT_SAMPLES, seed=1)
    if crop.shape[:2] == (row1 - row0, col1 - col0):
        image[row0:row1, col0:col1] = crop
