"""Converged Cycles references for the benchmarks, cached on disk by a hash of the scene.

A reference is Cycles' DIFFUSE bake with Direct + Indirect + Color (``tools/cycles_bake.py``,
which fixes every other render setting) of each baked object on the UV map VisiBake
baked it on. It is baked as two independent halves (seeds 1 and 2): their mean is the
reference and half the RMS of their difference is its own noise, the floor below which
no error measured against it means anything.

The cache file is ``<cache_dir>/<scene_key(...)>.npz``. The key covers the scene
(geometry, UVs, materials, lamps, world) and the bake settings, but not the code of
``tools/cycles_bake.py``: **bump FORMAT_VERSION whenever the Cycles settings of
``reference_settings``/``bake_diffuse`` (or the way halves are combined) change**, or
old references will be served for the new settings.

What the key does not see (documented limits): objects hidden only through a
collection's render toggle, instances (particles, geometry-node instances), and
modifiers whose render settings differ from their viewport settings (the viewport
depsgraph is hashed; keep ``levels == render_levels``).
"""
from __future__ import annotations

import hashlib
import os
import struct
import tempfile
import time
from dataclasses import dataclass

import bpy

import numpy as np

from tools.blender_compat import compat
from tools.cycles_bake import bake_diffuse

__all__ = ["FORMAT_VERSION", "Reference", "scene_key", "cached_reference", "relative_errors", "block_errors",
           "hidden_texels", "without_hidden"]

# Bump when the Cycles settings in tools/cycles_bake.py, the seeds or the layout of
# the cache file change: every cached reference then becomes a miss.
FORMAT_VERSION = 2  # 2: the two halves are stored too (noise of any metric)

_SEEDS = (1, 2)
# Object types Cycles renders as surfaces; their geometry occludes and reflects light.
_SURFACE_TYPES = {"MESH", "CURVE", "SURFACE", "META", "FONT"}
_VISIBILITY = ("visible_camera", "visible_diffuse", "visible_glossy", "visible_transmission",
               "visible_volume_scatter", "visible_shadow", "is_holdout", "is_shadow_catcher")
_LIGHT_ATTRS = ("type", "energy", "color", "exposure", "normalize", "use_temperature", "temperature",
                "shadow_soft_size", "angle", "spot_size", "spot_blend", "shape", "size", "size_y", "spread",
                "use_shadow")
_LIGHT_CYCLES_ATTRS = ("max_bounces", "use_multiple_importance_sampling", "is_portal", "is_caustics_light")
# Node properties that describe the editor, not the shading.
_UI_NODE_PROPS = frozenset(p.identifier for p in bpy.types.ShaderNode.bl_rna.properties) | {"rna_type"}


@dataclass
class Reference:
    """A converged Cycles bake.

    images : {object name: (H, W, 4) float32}, Blender pixel order (row 0 is v = 0);
        alpha > 0 marks covered texels
    seconds : float, Cycles bake time (both halves), as measured when it was baked
    noise : float | None, relative noise of ``images`` (RMS noise / mean value over
        covered texels); None when baked in one piece
    cached : bool, True when read from the cache instead of baked now
    halves : (images of seed 1, images of seed 2), same layout as ``images``, or None
        when baked in one piece; the noise of any error metric comes from them
    """

    images: dict[str, np.ndarray]
    seconds: float
    noise: float | None
    cached: bool
    halves: tuple[dict[str, np.ndarray], dict[str, np.ndarray]] | None = None


# --------------------------------------------------------------------------- key


class _Hasher:
    """sha256 over tagged values; tags keep two fields from hashing like one."""

    def __init__(self) -> None:
        self._h = hashlib.sha256()

    def tag(self, text: str) -> None:
        data = text.encode()
        self._h.update(struct.pack("<I", len(data)) + data)

    def value(self, value) -> None:
        if isinstance(value, np.ndarray):
            self.array(value)
        elif isinstance(value, (bool, int, float)):
            self.tag(type(value).__name__)
            self._h.update(np.asarray(value, np.float64).tobytes())
        elif isinstance(value, str):
            self.tag(value)
        elif value is None:
            self.tag("None")
        elif isinstance(value, (set, frozenset)):
            self.tag(repr(sorted(value)))
        elif isinstance(value, bpy.types.ID):
            self.tag(f"ID {type(value).__name__} {value.name}")
        else:  # bpy arrays, mathutils vectors, colours and matrices
            try:
                self.array(np.asarray(value, np.float64))
            except (TypeError, ValueError):
                self.tag(repr(value))

    def array(self, array: np.ndarray) -> None:
        array = np.ascontiguousarray(array)
        self.tag(f"{array.dtype.str}{array.shape}")
        self._h.update(array.tobytes())

    def hexdigest(self) -> str:
        return self._h.hexdigest()


def _image(h: _Hasher, image: bpy.types.Image, seen: dict) -> None:
    if image.name in seen:
        h.tag(seen[image.name])
        return
    pixels = np.empty(len(image.pixels), np.float32)
    if len(pixels):
        image.pixels.foreach_get(pixels)
    digest = hashlib.sha256(pixels.tobytes()).hexdigest()
    seen[image.name] = f"{digest}{tuple(image.size)}{image.colorspace_settings.name}{image.alpha_mode}"
    h.tag(seen[image.name])


def _struct_props(h: _Hasher, owner, seen: dict, depth: int) -> None:
    """Every shading-relevant property of a node (or of a struct it points to)."""
    for prop in owner.bl_rna.properties:
        key = prop.identifier
        if key in _UI_NODE_PROPS or key in {"inputs", "outputs", "internal_links"}:
            continue
        value = getattr(owner, key, None)
        h.tag(key)
        if prop.type == "POINTER":
            if isinstance(value, bpy.types.Image):
                _image(h, value, seen)
            elif isinstance(value, bpy.types.NodeTree):
                _whole_tree(h, value, seen)
            elif isinstance(value, bpy.types.ID):
                h.tag(value.name)
            elif value is not None and depth > 0:
                _struct_props(h, value, seen, depth - 1)
        elif prop.type == "COLLECTION":
            continue
        else:
            h.value(value)


def _node(h: _Hasher, node, seen: dict) -> None:
    h.tag(f"node {node.bl_idname} {node.name} mute={node.mute}")
    _struct_props(h, node, seen, depth=1)
    for socket in node.inputs:
        h.tag(f"in {socket.identifier} {socket.enabled}")
        if not socket.is_linked and hasattr(socket, "default_value"):
            h.value(socket.default_value)


def _link(h: _Hasher, link) -> None:
    h.tag(f"link {link.from_node.name}.{link.from_socket.identifier} -> "
          f"{link.to_node.name}.{link.to_socket.identifier} muted={link.is_muted}")


def _whole_tree(h: _Hasher, tree, seen: dict) -> None:
    """A node group: all its nodes and links (it has no single output to start from)."""
    h.tag(f"tree {tree.bl_idname}")
    for node in sorted(tree.nodes, key=lambda n: n.name):
        _node(h, node, seen)
    for link in sorted(tree.links, key=lambda k: (k.to_node.name, k.to_socket.identifier, k.from_node.name)):
        _link(h, link)


def _shader_tree(h: _Hasher, tree, seen: dict) -> None:
    """The nodes that reach the active Cycles output, so unlinked extras (for example
    the image node VisiBake writes into) do not change the key."""
    if tree is None:
        h.tag("no tree")
        return
    output = tree.get_output_node("CYCLES")
    if output is None:
        h.tag("no output")
        return
    stack, visited = [output], set()
    while stack:
        node = stack.pop()
        if node.name in visited:
            continue
        visited.add(node.name)
        _node(h, node, seen)
        for socket in node.inputs:
            for link in socket.links:
                _link(h, link)
                stack.append(link.from_node)


def _renders(obj) -> bool:
    return not obj.hide_render


def _geometry(h: _Hasher, obj, evaluated, uv_map: str | None, seen: dict) -> None:
    """World-space triangles, shading normals, material slots and (if baked) UVs."""
    h.tag(f"object {obj.name} {obj.type} baked={uv_map}")
    for attr in _VISIBILITY:
        h.value(getattr(obj, attr, None))
    mesh = evaluated.to_mesh()
    try:
        if mesh is None:
            h.tag("no mesh")
            return
        co = np.empty(3 * len(mesh.vertices), np.float32)
        mesh.vertices.foreach_get("co", co)
        matrix = np.array(evaluated.matrix_world, np.float64)
        world = co.reshape(-1, 3).astype(np.float64) @ matrix[:3, :3].T + matrix[:3, 3]
        h.array(world.astype(np.float32))
        count = len(mesh.loop_triangles)
        tri_verts = np.empty(3 * count, np.int32)
        tri_loops = np.empty(3 * count, np.int32)
        tri_material = np.empty(count, np.int32)
        mesh.loop_triangles.foreach_get("vertices", tri_verts)
        mesh.loop_triangles.foreach_get("loops", tri_loops)
        mesh.loop_triangles.foreach_get("material_index", tri_material)
        h.array(tri_verts)
        h.array(tri_material)
        # Smooth shading, sharp edges and custom normals all end up here.
        normals = np.empty(3 * len(mesh.loops), np.float32)
        if len(mesh.loops):
            mesh.corner_normals.foreach_get("vector", normals)
        h.array(normals.reshape(-1, 3)[tri_loops])
        if uv_map is not None:
            layer = mesh.uv_layers.get(uv_map)
            if layer is None:
                raise KeyError(f"{obj.name!r} has no UV map {uv_map!r}")
            uv = np.empty(2 * len(mesh.loops), np.float32)
            if len(mesh.loops):
                layer.data.foreach_get("uv", uv)
            h.array(uv.reshape(-1, 2)[tri_loops])
        for slot in evaluated.material_slots:
            material = slot.material
            h.tag(f"slot {material.name if material else None}")
            if material is not None:
                _shader_tree(h, material.node_tree, seen)
    finally:
        evaluated.to_mesh_clear()


def _light(h: _Hasher, obj, evaluated, seen: dict) -> None:
    light = evaluated.data
    h.tag(f"light {obj.name}")
    for attr in _LIGHT_ATTRS:
        h.tag(attr)
        h.value(getattr(light, attr, None))
    # Hashed as its own attribute was (False without a node tree), without the 5.x deprecation.
    h.tag("use_nodes")
    h.value(compat.uses_nodes(light))
    for attr in _LIGHT_CYCLES_ATTRS:
        h.tag(attr)
        h.value(getattr(light.cycles, attr, None))
    for attr in _VISIBILITY:
        h.value(getattr(obj, attr, None))
    h.array(np.array(evaluated.matrix_world, np.float64))
    if compat.uses_nodes(light):
        _shader_tree(h, light.node_tree, seen)


def scene_key(objects, uv_maps: dict[str, str], resolution: int, bounces: int, samples: int,
              *, halves: bool = True) -> str:
    """sha256 hex digest of everything that changes a reference bake.

    Parameters
    ----------
    objects : mesh objects of the current scene; those named in ``uv_maps`` are baked
    uv_maps : {object name: UV map it is baked on}
    resolution : atlas width = height in texels
    bounces, samples : Cycles diffuse bounces and samples per texel
    halves : whether the reference is baked as two halves (see :func:`cached_reference`)

    Hashed: every rendered surface object of the scene (sorted by name; the baked ones
    and every occluder) with its evaluated world-space vertices, loop-triangle indices,
    shading normals, material indices, the UVs of its bake map per triangle corner,
    and the nodes that feed each material's output (socket values, image pixels);
    every lamp (type, power, colour, exposure, normalize, temperature, size, shape,
    spot cone, world matrix, ...); the world's node tree; the settings; FORMAT_VERSION.
    """
    scene = bpy.context.scene
    depsgraph = bpy.context.evaluated_depsgraph_get()
    objects = list(objects)
    names = {obj.name for obj in objects}
    missing = sorted(set(uv_maps) - names)
    if missing:
        raise ValueError(f"uv_maps names objects that were not given: {missing}")
    h = _Hasher()
    seen: dict = {}
    h.tag(f"visibake-reference v{FORMAT_VERSION} r{int(resolution)} b{int(bounces)} s{int(samples)} "
          f"halves={bool(halves)}")
    surfaces = {obj.name: obj for obj in scene.objects if obj.type in _SURFACE_TYPES and _renders(obj)}
    surfaces.update({obj.name: obj for obj in objects})
    for name in sorted(surfaces):
        obj = surfaces[name]
        _geometry(h, obj, obj.evaluated_get(depsgraph), uv_maps.get(name), seen)
    for obj in sorted((o for o in scene.objects if o.type == "LIGHT" and _renders(o)), key=lambda o: o.name):
        _light(h, obj, obj.evaluated_get(depsgraph), seen)
    world = scene.world
    h.tag(f"world {world is not None}")
    if world is not None:
        h.value(world.color)
        _shader_tree(h, world.node_tree, seen)
    return h.hexdigest()


# --------------------------------------------------------------------------- cache


def _bake(objects, uv_maps: dict[str, str], resolution: int, bounces: int, samples: int,
          seed: int) -> dict[str, np.ndarray]:
    images: dict[str, np.ndarray] = {}
    for uv_map in sorted(set(uv_maps.values())):
        group = [obj for obj in objects if uv_maps.get(obj.name) == uv_map]
        images.update(bake_diffuse(group, uv_map, resolution, resolution, bounces, samples, seed=seed))
    return images


def _noise(a: dict[str, np.ndarray], b: dict[str, np.ndarray], mean: dict[str, np.ndarray]) -> float | None:
    """0.5 * RMS(a - b) / mean: the relative noise of the mean of two independent halves."""
    squared, total, count = 0.0, 0.0, 0
    for name, reference in mean.items():
        covered = (a[name][..., 3] > 0) & (b[name][..., 3] > 0)
        difference = a[name][covered][:, :3].astype(np.float64) - b[name][covered][:, :3]
        squared += float(np.sum(difference ** 2))
        total += float(np.sum(reference[covered][:, :3], dtype=np.float64))
        count += difference.size
    if count == 0 or total <= 0.0:
        return None
    return 0.5 * float(np.sqrt(squared / count)) / (total / count)


def _load(path: str, key: str, names: set[str], resolution: int) -> Reference | None:
    """The cached reference, or None when the file is missing, truncated, corrupt or
    not the one asked for."""
    if not os.path.isfile(path):
        return None
    try:
        with np.load(path, allow_pickle=False) as data:
            if str(data["key"]) != key or int(data["format_version"]) != FORMAT_VERSION:
                return None
            stored = [str(n) for n in data["names"]]
            if set(stored) != names or len(stored) != len(names):
                return None
            # Reading every member checks every CRC: a damaged file raises here.
            images = {name: np.array(data[f"image_{i}"]) for i, name in enumerate(stored)}
            halves = None
            if "half0_0" in data.files:
                halves = tuple({name: np.array(data[f"half{h}_{i}"]) for i, name in enumerate(stored)}
                               for h in (0, 1))
            seconds = float(data["seconds"])
            noise = float(data["noise"])
    except Exception:  # noqa: BLE001 - zipfile, zlib, numpy and OS errors all mean "rebake"
        return None
    shape = (resolution, resolution, 4)
    if any(im.shape != shape or im.dtype != np.float32 or not np.isfinite(im).all() for im in images.values()):
        return None
    if not np.isfinite(seconds):
        return None
    return Reference(images=images, seconds=seconds, noise=None if np.isnan(noise) else noise, cached=True,
                     halves=halves)


def _save(path: str, key: str, reference: Reference) -> None:
    """Write atomically: an interrupted run leaves the old file or none, never half of one."""
    os.makedirs(os.path.dirname(path) or ".", exist_ok=True)
    names = sorted(reference.images)
    arrays = {f"image_{i}": reference.images[name] for i, name in enumerate(names)}
    for h, half in enumerate(reference.halves or ()):
        arrays.update({f"half{h}_{i}": half[name] for i, name in enumerate(names)})
    handle, temporary = tempfile.mkstemp(suffix=".npz.tmp", dir=os.path.dirname(path) or ".")
    try:
        with os.fdopen(handle, "wb") as stream:
            np.savez_compressed(stream, key=np.array(key), format_version=np.array(FORMAT_VERSION),
                                names=np.array(names, dtype=str), seconds=np.array(reference.seconds, np.float64),
                                noise=np.array(np.nan if reference.noise is None else reference.noise, np.float64),
                                **arrays)
        os.replace(temporary, path)
    except BaseException:
        if os.path.exists(temporary):
            os.remove(temporary)
        raise


def cached_reference(objects, uv_maps: dict[str, str], resolution: int, bounces: int, samples: int,
                     cache_dir: str, halves: bool = True) -> Reference:
    """The Cycles reference of ``objects`` named in ``uv_maps``, from the cache or baked now.

    Parameters
    ----------
    objects : mesh objects of the current scene (the others still occlude and reflect)
    uv_maps : {object name: UV map to bake it on}; objects on different maps are baked
        in one ``bake_diffuse`` call per map
    resolution : atlas width = height in texels
    bounces : Cycles diffuse bounces
    samples : samples per texel in total; with ``halves`` two bakes of ``samples // 2``
        (seeds 1 and 2) whose mean is the reference
    cache_dir : folder of ``<scene_key>.npz`` files, created if missing
    halves : bake two halves to estimate the reference's noise (else one bake, seed 1)

    Returns
    -------
    Reference with images {name: (resolution, resolution, 4) float32}. A cache file that
    cannot be read completely, or whose contents do not match, is baked again and
    overwritten.
    """
    objects = list(objects)
    if halves and samples < 2:
        raise ValueError(f"halves needs at least 2 samples, got {samples}")
    baked = [obj for obj in objects if obj.name in uv_maps]
    key = scene_key(objects, uv_maps, resolution, bounces, samples, halves=halves)
    path = os.path.join(cache_dir, f"{key}.npz")
    hit = _load(path, key, set(uv_maps), resolution)
    if hit is not None:
        return hit
    started = time.perf_counter()
    if halves:
        a = _bake(baked, uv_maps, resolution, bounces, samples // 2, _SEEDS[0])
        b = _bake(baked, uv_maps, resolution, bounces, samples // 2, _SEEDS[1])
        images = {name: ((a[name].astype(np.float64) + b[name]) / 2).astype(np.float32) for name in a}
        noise = _noise(a, b, images)
        halves = (a, b)
    else:
        images = _bake(baked, uv_maps, resolution, bounces, samples, _SEEDS[0])
        noise, halves = None, None
    reference = Reference(images=images, seconds=time.perf_counter() - started, noise=noise, cached=False,
                          halves=halves)
    _save(path, key, reference)
    return reference


# --------------------------------------------------------------------------- errors


def relative_errors(ours: dict[str, np.ndarray], reference: dict[str, np.ndarray]) -> dict:
    """Errors of ``ours`` against ``reference`` over the texels both cover, all objects pooled.

    Parameters
    ----------
    ours, reference : {object name: (H, W, 4) float}, RGB + coverage alpha; same names
        and shapes in both

    Returns
    -------
    dict with
        relative_rmse : RMS error over covered RGB values / mean reference value
        max_abs_error : largest |ours - reference| of a covered RGB value
        max_relative_error : largest |ours - reference| / reference where the reference
            exceeds 1% of its mean (dark values would make any ratio meaningless)
        bias : sum(ours) / sum(reference) - 1 over covered values
        reference_mean : mean covered reference value
        texels : number of covered texels (each has 3 values)
    All NaN (texels 0) when nothing is covered.
    """
    if set(ours) != set(reference):
        raise ValueError(f"objects differ: only ours {sorted(set(ours) - set(reference))}, "
                         f"only reference {sorted(set(reference) - set(ours))}")
    a_parts, b_parts = [], []
    for name in sorted(reference):
        a, b = np.asarray(ours[name]), np.asarray(reference[name])
        if a.shape != b.shape or a.ndim != 3 or a.shape[2] != 4:
            raise ValueError(f"{name!r}: shapes {a.shape} and {b.shape}, need equal (H, W, 4)")
        covered = (a[..., 3] > 0) & (b[..., 3] > 0)
        a_parts.append(a[covered][:, :3].astype(np.float64))
        b_parts.append(b[covered][:, :3].astype(np.float64))
    a = np.concatenate(a_parts) if a_parts else np.empty((0, 3))
    b = np.concatenate(b_parts) if b_parts else np.empty((0, 3))
    texels = len(a)
    nan = float("nan")
    if texels == 0:
        return dict(relative_rmse=nan, max_abs_error=nan, max_relative_error=nan, bias=nan,
                    reference_mean=nan, texels=0)
    mean = float(np.mean(b))
    error = a - b
    bright = b > 0.01 * mean
    return dict(
        relative_rmse=float(np.sqrt(np.mean(error ** 2)) / mean) if mean > 0 else nan,
        max_abs_error=float(np.max(np.abs(error))),
        max_relative_error=float(np.max(np.abs(error[bright]) / b[bright])) if bright.any() else nan,
        bias=float(np.sum(a) / np.sum(b) - 1.0) if np.sum(b) > 0 else nan,
        reference_mean=mean,
        texels=texels,
    )


def _block_means(image: np.ndarray, covered: np.ndarray, block: int) -> tuple[np.ndarray, np.ndarray]:
    """Means of RGB over the covered texels of each ``block`` x ``block`` block, (b, 3), and
    whether the block has at least half its texels covered, (b,) bool."""
    height, width = covered.shape
    h, w = height // block * block, width // block * block
    rgb = np.where(covered[:h, :w, None], image[:h, :w, :3], 0.0).astype(np.float64)
    rgb = rgb.reshape(h // block, block, w // block, block, 3).sum(axis=(1, 3)).reshape(-1, 3)
    count = covered[:h, :w].reshape(h // block, block, w // block, block).sum(axis=(1, 3)).reshape(-1)
    means = rgb / np.maximum(count, 1)[:, None]
    return means, count * 2 >= block * block


def block_errors(ours: dict[str, np.ndarray], reference: Reference, block: int = 4) -> dict:
    """Relative RMSE of ``block`` x ``block``-texel block means against ``reference``, and the
    reference's own noise on the same metric (from its halves).

    Only texels both cover count, and only blocks at least half covered. The block metric is
    the low-frequency error a denoiser cannot remove. The error with the reference's noise
    taken out is sqrt(e^2 - n^2) (the two are independent), reported beside the raw one.

    Returns dict with block_rmse, block_noise (None without halves), block_rmse_denoised
    (None without halves; 0 where e <= n), texel_noise (per texel, from the halves) and
    texel_rmse_denoised.
    """
    ours_parts, ref_parts, half_parts = [], [], ([], [])
    texel_ours, texel_ref, texel_halves = [], [], ([], [])
    for name in sorted(reference.images):
        mine, theirs = np.asarray(ours[name]), reference.images[name]
        covered = (mine[..., 3] > 0) & (theirs[..., 3] > 0)
        mine_means, usable = _block_means(mine, covered, block)
        ref_means, _ = _block_means(theirs, covered, block)
        ours_parts.append(mine_means[usable])
        ref_parts.append(ref_means[usable])
        texel_ours.append(mine[covered][:, :3].astype(np.float64))
        texel_ref.append(theirs[covered][:, :3].astype(np.float64))
        for h, half in enumerate(reference.halves or ()):
            half_parts[h].append(_block_means(half[name], covered, block)[0][usable])
            texel_halves[h].append(half[name][covered][:, :3].astype(np.float64))
    a, b = np.concatenate(ours_parts), np.concatenate(ref_parts)
    mean = float(np.mean(b)) if len(b) else float("nan")
    result = {"block_rmse": float(np.sqrt(np.mean((a - b) ** 2)) / mean) if len(b) else float("nan"),
              "block_noise": None, "block_rmse_denoised": None, "texel_noise": None, "texel_rmse_denoised": None}
    if reference.halves is not None and len(b):
        noise = 0.5 * float(np.sqrt(np.mean((np.concatenate(half_parts[0]) - np.concatenate(half_parts[1])) ** 2)))
        result["block_noise"] = noise / mean
        result["block_rmse_denoised"] = float(np.sqrt(max(result["block_rmse"] ** 2 - (noise / mean) ** 2, 0.0)))
        ta, tb = np.concatenate(texel_ours), np.concatenate(texel_ref)
        texel_mean = float(np.mean(tb))
        texel_noise = 0.5 * float(np.sqrt(np.mean((np.concatenate(texel_halves[0])
                                                   - np.concatenate(texel_halves[1])) ** 2))) / texel_mean
        texel_rmse = float(np.sqrt(np.mean((ta - tb) ** 2))) / texel_mean
        result["texel_noise"] = texel_noise
        result["texel_rmse_denoised"] = float(np.sqrt(max(texel_rmse ** 2 - texel_noise ** 2, 0.0)))
    return result


# --------------------------------------------------------------------------- hidden texels


def _uv_triangles(obj, uv_map: str, resolution: int) -> tuple[np.ndarray, np.ndarray]:
    """``obj``'s triangles as (T, 3, 2) float64 corners on ``uv_map`` in texels (texel centres
    at integers) and (T, 3, 3) float64 world corners."""
    depsgraph = bpy.context.evaluated_depsgraph_get()
    evaluated = obj.evaluated_get(depsgraph)
    mesh = evaluated.to_mesh()
    try:
        mesh.calc_loop_triangles()
        triangles = len(mesh.loop_triangles)
        loops = np.zeros(3 * triangles, np.int64)
        mesh.loop_triangles.foreach_get("loops", loops)
        verts = np.zeros(3 * triangles, np.int64)
        mesh.loop_triangles.foreach_get("vertices", verts)
        uv = np.zeros(2 * len(mesh.loops))
        mesh.uv_layers[uv_map].data.foreach_get("uv", uv)
        co = np.zeros(3 * len(mesh.vertices))
        mesh.vertices.foreach_get("co", co)
    finally:
        evaluated.to_mesh_clear()
    matrix = np.array(obj.matrix_world)
    co = co.reshape(-1, 3) @ matrix[:3, :3].T + matrix[:3, 3]
    return uv.reshape(-1, 2)[loops.reshape(-1, 3)] * resolution - 0.5, co[verts.reshape(-1, 3)]


def _texel_points(tri_uv: np.ndarray, tri_co: np.ndarray, resolution: int,
                  offsets: tuple[tuple[float, float], ...] = ((0.0, 0.0),)) -> tuple[list, np.ndarray, np.ndarray]:
    """For the texels whose centres the triangles (:func:`_uv_triangles`) cover: their world
    positions moved by each of ``offsets`` texels in u and v, in the plane of the centre's
    triangle (0.5, 0.5 is a corner), a list of (n, 3) float64, one per offset; the unit face
    normals (n, 3); and the (n, 2) int (row, column), Blender pixel order."""
    positions, normals, pixels = [[] for _ in offsets], [], []
    for corners_uv, corners in zip(tri_uv, tri_co):
        lo = np.maximum(np.ceil(corners_uv.min(axis=0)), 0).astype(int)
        hi = np.minimum(np.floor(corners_uv.max(axis=0)), resolution - 1).astype(int)
        if np.any(hi < lo):
            continue
        edge = np.array([corners_uv[1] - corners_uv[0], corners_uv[2] - corners_uv[0]]).T
        if abs(np.linalg.det(edge)) < 1e-12:
            continue
        xs, ys = np.meshgrid(np.arange(lo[0], hi[0] + 1), np.arange(lo[1], hi[1] + 1))
        p = np.stack([xs.ravel(), ys.ravel()], axis=1).astype(np.float64)
        w = np.linalg.solve(edge, (p - corners_uv[0]).T).T
        inside = (w >= -1e-9).all(axis=1) & (w.sum(axis=1) <= 1 + 1e-9)
        if not inside.any():
            continue
        for index, offset in enumerate(offsets):
            moved = np.linalg.solve(edge, (p[inside] + np.asarray(offset) - corners_uv[0]).T).T
            positions[index].append(corners[0] + moved[:, :1] * (corners[1] - corners[0])
                                    + moved[:, 1:] * (corners[2] - corners[0]))
        normal = np.cross(corners[1] - corners[0], corners[2] - corners[0])
        normals.append(np.repeat((normal / max(np.linalg.norm(normal), 1e-300))[None], inside.sum(), axis=0))
        pixels.append(p[inside][:, ::-1].astype(np.int64))
    if not normals:
        return [np.zeros((0, 3)) for _ in offsets], np.zeros((0, 3)), np.zeros((0, 2), np.int64)
    return [np.concatenate(part) for part in positions], np.concatenate(normals), np.concatenate(pixels)


# A texel's centre and its four corners: where hidden_texels looks.
_TEXEL_PROBES = ((0.0, 0.0), (-0.5, -0.5), (0.5, -0.5), (-0.5, 0.5), (0.5, 0.5))


def hidden_texels(objects, uv_maps: dict[str, str], resolution: int, contact: float = 1e-4) -> dict[str, np.ndarray]:
    """{object name: (H, W) bool} the texels no camera sees wholly, by the scene's geometry alone:
    those whose centre or a corner (in the plane of the centre's triangle) lies inside another
    object's closed mesh, or on another object's surface facing it (a box's bottom on the
    floor). Neither method's light there is seen as such, and each fills them its own way:
    Cycles lights the inside of an emissive strip and averages the dark inside of another
    object into a texel partly buried; VisiBake fills buried texels from their neighbours and
    lights a texel's exposed part only. So errors are also reported without them, as they are
    without the texels two away from island borders.

    ``contact`` (m): a point this close to another surface counts as touching it."""
    from mathutils import Vector
    from mathutils.bvhtree import BVHTree

    depsgraph = bpy.context.evaluated_depsgraph_get()
    meshes = [o for o in objects if o.type == "MESH"]
    trees, boxes = {}, {}
    for o in meshes:
        trees[o.name] = BVHTree.FromObject(o, depsgraph, deform=True)
        corners = np.array([o.matrix_world @ Vector(c) for c in o.bound_box])
        boxes[o.name] = (corners.min(axis=0) - contact, corners.max(axis=0) + contact)
    hidden = {}
    for o in meshes:
        if o.name not in uv_maps:
            continue
        mask = np.zeros((resolution, resolution), bool)
        probes, normals, pixels = _texel_points(*_uv_triangles(o, uv_maps[o.name], resolution), resolution,
                                                _TEXEL_PROBES)
        for positions in probes:
            for other in meshes:
                if other is not o:
                    _mark_hidden(mask, positions, normals, pixels, other, trees[other.name], boxes[other.name],
                                 contact)
        hidden[o.name] = mask
    return hidden


def _mark_hidden(mask: np.ndarray, positions: np.ndarray, normals: np.ndarray, pixels: np.ndarray, other,
                 tree, box, contact: float) -> None:
    """Set ``mask`` at ``pixels`` whose ``positions`` (n, 3), with face ``normals`` (n, 3), lie
    inside ``other`` (its BVHTree ``tree``, in its own frame, and world bounding ``box``), or
    within ``contact`` of its surface facing them."""
    from mathutils import Vector

    lo, hi = box
    candidates = np.nonzero(np.all((positions >= lo) & (positions <= hi), axis=1))[0]
    to_local = other.matrix_world.inverted()
    linear = np.array(other.matrix_world.to_3x3())
    normal_matrix = np.linalg.inv(linear).T  # normals of a scaled object
    for i in candidates:
        local = to_local @ Vector(positions[i])
        nearest, normal, _, _ = tree.find_nearest(local)
        if nearest is None:
            continue
        offset = np.array(local - nearest)
        if np.linalg.norm(linear @ offset) <= contact:
            world_normal = normal_matrix @ np.array(normal)
            if world_normal @ normals[i] < -0.9 * np.linalg.norm(world_normal):
                mask[tuple(pixels[i])] = True
        elif offset @ np.array(normal) < 0:  # behind the nearest face: inside (the sign holds in any frame)
            mask[tuple(pixels[i])] = True


def without_hidden(images: dict[str, np.ndarray], reference: Reference, hidden: dict[str, np.ndarray]
                   ) -> tuple[dict[str, np.ndarray], Reference]:
    """``images`` and ``reference`` (halves too) with the ``hidden`` texels uncovered (alpha 0),
    for :func:`relative_errors` and :func:`block_errors` over the texels a camera can see."""
    def masked(set_of_images):
        out = {}
        for name, image in set_of_images.items():
            image = np.array(image, copy=True)
            if name in hidden:
                image[hidden[name], 3] = 0.0
            out[name] = image
        return out

    halves = None if reference.halves is None else (masked(reference.halves[0]), masked(reference.halves[1]))
    return masked(images), Reference(masked(reference.images), reference.seconds, reference.noise,
                                     reference.cached, halves)
