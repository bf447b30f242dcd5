"""Cycles DIFFUSE bakes: the independent accuracy reference for VisiBake.

Used by tests and benchmarks only; never shipped in the extension.

Units measured with this module (bpy 5.0.1, Cycles on CPU; numbers filled in below)
------------------------------------------------------------------------------------
UNITS_PLACEHOLDER
"""
from __future__ import annotations

import contextlib
from collections.abc import Iterable, Iterator, Sequence

import bpy
import numpy as np

__all__ = ["bake_diffuse", "reference_settings"]

_LIVE_VALUE_TYPES = {"bpy_prop_array", "Vector", "Color", "Euler", "Quaternion"}


class _Restorer:
    """Sets attributes and puts the old values back in reverse order.

    Restoring in reverse matters: several Cycles settings clamp each other
    (max_bounces vs diffuse_bounces), so undoing in the order of setting could
    leave a clamped value behind.
    """

    def __init__(self) -> None:
        self._undo: list[tuple[object, str, object]] = []

    def set(self, owner: object, attr: str, value: object) -> None:
        old = getattr(owner, attr)
        if isinstance(old, (set, frozenset)):
            old = set(old)
        elif type(old).__name__ in _LIVE_VALUE_TYPES:
            # These are views into the owner; without a copy "old" would change too.
            old = tuple(old)
        self._undo.append((owner, attr, old))
        setattr(owner, attr, value)

    def restore(self) -> None:
        while self._undo:
            owner, attr, old = self._undo.pop()
            setattr(owner, attr, old)


@contextlib.contextmanager
def reference_settings(
    scene: bpy.types.Scene,
    bounces: int,
    samples: int,
    margin: int = 0,
    seed: int = 0,
    threads: int = 0,
) -> Iterator[None]:
    """Put ``scene`` in the reference bake configuration for the duration of the block.

    Everything that could bias the comparison with VisiBake (clamping, denoising,
    adaptive sampling, glossy/caustic paths, colour management) is switched off; the
    previous values are restored on exit, even after an exception.
    """
    r = _Restorer()
    cy = scene.cycles
    try:
        r.set(scene.render, "engine", "CYCLES")
        r.set(cy, "device", "CPU")
        # Adaptive sampling would stop early on flat regions, making noise (and so
        # the test tolerances) depend on the scene instead of on `samples`.
        r.set(cy, "use_adaptive_sampling", False)
        r.set(cy, "samples", int(samples))
        r.set(cy, "seed", int(seed))
        r.set(cy, "use_animated_seed", False)
        r.set(cy, "sample_offset", 0)
        r.set(cy, "use_sample_subset", False)
        r.set(cy, "use_denoising", False)
        r.set(cy, "sample_clamp_direct", 0.0)
        r.set(cy, "sample_clamp_indirect", 0.0)
        r.set(cy, "use_fast_gi", False)
        r.set(cy, "use_guiding", False)
        r.set(cy, "caustics_reflective", False)
        r.set(cy, "caustics_refractive", False)
        r.set(cy, "film_exposure", 1.0)
        r.set(cy, "min_light_bounces", 0)
        r.set(cy, "min_transparent_bounces", 0)
        # max_bounces first: diffuse_bounces is clamped by it in the path tracer.
        r.set(cy, "max_bounces", max(int(bounces), 0))
        r.set(cy, "diffuse_bounces", int(bounces))
        r.set(cy, "glossy_bounces", 0)
        r.set(cy, "transmission_bounces", 0)
        r.set(cy, "volume_bounces", 0)
        r.set(cy, "transparent_max_bounces", 0)
        r.set(scene.view_settings, "view_transform", "Standard")
        r.set(scene.view_settings, "look", "None")
        r.set(scene.view_settings, "exposure", 0.0)
        r.set(scene.view_settings, "gamma", 1.0)
        r.set(scene.render, "threads_mode", "FIXED" if threads > 0 else "AUTO")
        if threads > 0:
            r.set(scene.render, "threads", int(threads))
        bake = scene.render.bake
        r.set(bake, "margin", int(margin))
        r.set(bake, "target", "IMAGE_TEXTURES")
        r.set(bake, "save_mode", "INTERNAL")
        r.set(bake, "use_selected_to_active", False)
        r.set(bake, "use_clear", True)
        r.set(bake, "use_split_materials", False)
        yield
    finally:
        r.restore()


def _material_groups(objects: Sequence[bpy.types.Object]) -> list[list[bpy.types.Object]]:
    """Split objects into groups in which no two objects share a material.

    A material has one active image node, so two objects sharing it in the same
    bake call would both write into one image. Greedy colouring is enough here.
    """
    groups: list[tuple[set, list]] = []
    for ob in objects:
        mats = {s.material for s in ob.material_slots if s.material is not None}
        for used, members in groups:
            if not (used & mats):
                used |= mats
                members.append(ob)
                break
        else:
            groups.append((set(mats), [ob]))
    return [members for _, members in groups]


@contextlib.contextmanager
def _bake_targets(
    objects: Sequence[bpy.types.Object], uv_map: str, width: int, height: int
) -> Iterator[dict[str, bpy.types.Image]]:
    """Temporary float images, image nodes, fallback materials and active UV maps.

    Yields {object name: image}. On exit every node, image and material added here
    is removed and every active node / active UV map / empty slot is restored.
    """
    r = _Restorer()
    images: list[bpy.types.Image] = []
    fallback: list[bpy.types.Material] = []
    emptied_slots: list[bpy.types.MaterialSlot] = []
    appended_meshes: list[bpy.types.Mesh] = []
    targets: dict[str, bpy.types.Image] = {}
    try:
        for ob in objects:
            if ob.type != "MESH":
                raise TypeError(f"{ob.name!r} is a {ob.type}, only meshes can be baked")
            mesh = ob.data
            uv = mesh.uv_layers.get(uv_map)
            if uv is None:
                raise KeyError(f"{ob.name!r} has no UV map {uv_map!r}")
            # Bake reads the active (not active_render) UV layer.
            r.set(mesh.uv_layers, "active", uv)

            img = bpy.data.images.new(
                f".visibake_ref_{ob.name}", width, height, alpha=True, float_buffer=True
            )
            # Non-Color before any pixel access so nothing is colour managed.
            img.colorspace_settings.name = "Non-Color"
            images.append(img)
            targets[ob.name] = img

            if not ob.material_slots:
                # Cycles shades material-less objects with a plain 0.8 grey diffuse;
                # bake needs a node tree to find its target, so mimic that shader.
                mat = bpy.data.materials.new(".visibake_ref_default")
                fallback.append(mat)
                mesh.materials.append(mat)
                appended_meshes.append(mesh)
            for slot in ob.material_slots:
                if slot.material is None:
                    mat = bpy.data.materials.new(".visibake_ref_default")
                    fallback.append(mat)
                    slot.material = mat
                    emptied_slots.append(slot)
        for mat in fallback:
            bsdf = mat.node_tree.nodes.get("Principled BSDF")
            if bsdf is not None:
                bsdf.inputs["Specular IOR Level"].default_value = 0.0
        yield targets
    finally:
        for slot in emptied_slots:
            slot.material = None
        for mesh in appended_meshes:
            # pop() leaves the object's slot count behind; the mesh had no
            # materials before, and clear() resyncs the objects using it.
            mesh.materials.clear()
        r.restore()
        for mat in fallback:
            bpy.data.materials.remove(mat)
        for img in images:
            bpy.data.images.remove(img)


def _point_materials_at(
    group: Sequence[bpy.types.Object], targets: dict[str, bpy.types.Image], r: _Restorer,
    added: list[tuple[bpy.types.NodeTree, bpy.types.Node]],
) -> None:
    for ob in group:
        for slot in ob.material_slots:
            tree = slot.material.node_tree
            node = tree.nodes.new("ShaderNodeTexImage")
            node.name = node.label = ".visibake_ref_target"
            node.image = targets[ob.name]
            added.append((tree, node))
            r.set(tree.nodes, "active", node)


def _selection_override(scene: bpy.types.Scene, group: Sequence[bpy.types.Object]) -> dict:
    view_layer = scene.view_layers[0] if bpy.context.scene != scene else bpy.context.view_layer
    return dict(
        scene=scene,
        view_layer=view_layer,
        selected_objects=list(group),
        selected_editable_objects=list(group),
        active_object=group[0],
        object=group[0],
    )


def bake_diffuse(
    objects: Iterable[bpy.types.Object],
    uv_map: str,
    width: int,
    height: int,
    bounces: int,
    samples: int,
    pass_filter: Iterable[str] = ("DIRECT", "INDIRECT", "COLOR"),
    margin: int = 0,
    seed: int = 0,
    threads: int = 0,
) -> dict[str, np.ndarray]:
    """Bake Cycles DIFFUSE lighting of each mesh object into its own float image.

    Parameters
    ----------
    objects : mesh objects in the current scene (evaluated geometry is baked).
    uv_map : name of the UV map to bake on; every object must have it.
    width, height : image size in texels.
    bounces : Cycles diffuse bounces (0 = direct light only).
    samples : exact samples per texel (adaptive sampling is off).
    pass_filter : subset of {'DIRECT', 'INDIRECT', 'COLOR', 'EMIT'}.
    margin : bake margin in texels (0 = texels not covered by the UV map keep the
        cleared value).
    seed : Cycles seed.
    threads : CPU threads, 0 = automatic.

    Returns
    -------
    {object name: (height, width, 4) float32}, Blender pixel order (row 0 is v = 0).

    The scene is left as it was: temporary images, nodes and materials are removed
    and every changed setting (engine, samples, bounces, active UV map, active
    node, ...) is restored.
    """
    objects = list(objects)
    if not objects:
        return {}
    scene = bpy.context.scene
    missing = [ob.name for ob in objects if scene.objects.get(ob.name) is not ob]
    if missing:
        raise ValueError(f"objects not in the current scene: {missing}")
    passes = set(pass_filter)
    out: dict[str, np.ndarray] = {}
    with reference_settings(scene, bounces, samples, margin, seed, threads), \
            _bake_targets(objects, uv_map, width, height) as targets:
        for group in _material_groups(objects):
            r = _Restorer()
            added: list[tuple[bpy.types.NodeTree, bpy.types.Node]] = []
            try:
                _point_materials_at(group, targets, r, added)
                with bpy.context.temp_override(**_selection_override(scene, group)):
                    result = bpy.ops.object.bake(
                        type="DIFFUSE",
                        pass_filter=passes,
                        margin=int(margin),
                        target="IMAGE_TEXTURES",
                        save_mode="INTERNAL",
                        use_selected_to_active=False,
                        use_clear=True,
                        uv_layer=uv_map,
                    )
                if "FINISHED" not in result:
                    raise RuntimeError(f"Cycles bake returned {result}")
            finally:
                r.restore()
                for tree, node in reversed(added):
                    tree.nodes.remove(node)
            for ob in group:
                img = targets[ob.name]
                px = np.empty(width * height * 4, np.float32)
                img.pixels.foreach_get(px)
                out[ob.name] = px.reshape(height, width, 4)
    return out
