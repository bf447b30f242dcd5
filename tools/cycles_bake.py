"""Cycles DIFFUSE bakes: the independent accuracy reference for VisiBake.

Used by tests and benchmarks only; never shipped in the extension.

Units measured with this module (bpy 5.0.1, Cycles on CPU, 2 cores)
--------------------------------------------------------------------
Baked value = DIFFUSE with pass filter {DIRECT, INDIRECT, COLOR} = rho * E / pi
(outgoing Lambert radiance); without COLOR it is E / pi; COLOR alone is rho.
"ratio" = baked / formula. Lights at their defaults: normalize=True, exposure=0.

Material. A Principled BSDF is exactly Lambert only with Specular IOR Level = 0 (and
Diffuse Roughness = 0, the default):
    Principled, base colour 1, Specular IOR Level 0        ratio 1.00000 (sun 0 and 60 deg)
    Principled defaults (Spec. IOR Level 0.5, IOR 1.5),
      Roughness 1                                         ratio 0.98621 (0 and 60 deg)
    Diffuse Roughness 1 (or Diffuse BSDF roughness 1)     ratio 0.95655 at 60 deg (Oren-Nayar)
    Diffuse BSDF roughness 0                              ratio 1.00000
The specular layer takes its albedo off the diffuse weight, so with default
Principled materials Cycles is ~1.4% (Roughness 1) darker than rho * E / pi.
Objects without a material: Cycles' own default surface (a default Principled, Roughness
0.5) bakes 0.96262 * 0.8 * E / pi (sun 0 deg, vertex bake); both bakes here give such
objects and empty slots a temporary Specular-IOR-Level-0 Principled instead: exactly 0.8.

Sun, strength S:           E = S * cos(theta).      S=3, angle 0: 0 deg 0.954929 vs
                           0.954930, 60 deg 0.477465 vs 0.477465 (no noise at all: a
                           zero-angle sun on a plane is deterministic). angle=10 deg: 0.99999.
Point, power P, radius 0:  E = P * cos / (4 pi d^2). P=1000, 2 m above a 4 x 4 m plane,
                           8 x 8 texels, 1024 spp: ratio to the texel-centre value mean
                           0.9995, min 0.9961, max 1.0024 (the extremes are texels on the
                           quad's diagonal, see "sampling" below). Radius 0.1: 1.0001.
Spot:                      same as a point light of equal power inside the cone (ratio
                           0.996-1.003, 90 deg cone, blend 0), 0 outside.
Area (square/rect/disk):   radiance L = P / (pi * A), A = s^2, s_x*s_y or pi/4*s^2.
                           Square s=0.5, 5 m above: ratio 0.9995 to the exact integral of
                           L over the square (12.684 vs far-field P/(pi d^2) = 12.732);
                           s=1: 0.9995; disk s=0.5: 0.9970 and rect 0.5x0.25: 0.9974 of
                           P/(pi d^2). Noise 0.03% at 1024 spp.
Emission (mesh light):     L = Emission Color * Emission Strength (ratio 0.997 for a
                           0.5 m quad 2 m away, the same texel-extent effect as area lights).
Blender 5 light properties that change these:
    exposure             multiplies by 2**exposure (sun 2.000, point 2.004 at exposure 1).
    use_temperature      multiplies by light.temperature_color (6500 K: 1.043, 0.984, 1.035).
    normalize=False      sun: E = S * (solid angle of the sun disc), e.g. angle 0.2 rad
                         gives 0.0313 S (and S for angle 0); point: x4.00 at radius 0,
                         x3.11 at radius 0.5; area: L = P / pi, independent of A
                         (ratio 0.2499 for A = 0.25, 0.0399 for A = 0.04).
    diffuse_factor       no effect in Cycles (EEVEE only).
    use_soft_falloff     no effect at radius 0.

Bounces: diffuse_bounces = N gives paths with up to N diffuse reflections before the
baked surface (0 = direct only). Floor rho 0.5 under a sun S = pi, a 400 m ceiling rho 0.8
1 m above it, invisible to shadow rays: centre values 0.5000, 0.5000, 0.6998, 0.6998,
0.7771 for N = 0..4 (infinite planes: 0.5, 0.5, 0.7, 0.7, 0.78).

Sampling inside a texel: Cycles jitters the texel-centre position uniformly over a box,
retrying until the sample lies in the texel-centre's triangle. The box depends on the
Blender: HALF a texel in 4.2 to 5.2.0 (Blender's bake differentials were half the true
ones; a point light 0.3 m above a plane fits a width of 0.50 best: RMS 0.25%, against 0.42%
for 0.55 and 6% for a full texel), the whole texel from 5.2.1 (a sharp shadow edge: RMS 0.022
against 0.146 for half; tests/blender/test_cycles_bake.py). VisiBake's footprint follows the
running Blender's (operators.adapter.compat.CYCLES_BAKE_FOOTPRINT_WIDTH).

Coverage: the image is cleared to (0, 0, 0, 0); with margin = 0 texels no triangle covers
stay (0, 0, 0, 0), so alpha > 0 is the coverage mask. Up to 5.2, a texel is covered where a
triangle covers its centre; 5.3 also bakes every texel a triangle only touches (a triangle
of 304 centre texels at 32^2 gets 354), which VisiBake fills by its margin instead: compare
the texels both cover. Margins use
margin_type EXTEND (copies, alpha 1); the default ADJACENT_FACES fades the margin of an
island without UV neighbours to half value and half alpha.

Vertex colours (bake_diffuse_vertex_colors, bake target VERTEX_COLORS). Blender bakes
one "pixel" per face corner, at the corner's vertex (barycentric (1, 0), (0, 1) or (0, 0)
of the first triangle using that corner) with zero differentials: NO jitter, 1 and 16 spp
give identical values (to 1e-7) under a point light. Cycles nudges that point towards the
triangle's centroid by min(|to centroid|, 1e-4 * max(1, max |P|_world)) against
self-intersection: 1e-4 m near the origin. Point light P=100 0.3 m above a vertex of a
2 x 2 m, 4 x 4 segment grid: ratio to rho*E/pi at the vertex 1.0000000 below the light,
0.99995-1.00035 over the grid. The nudge grows with the distance from the world origin:
the same scene at x = 100 m is off by up to 4% (0.9983 below the light = a 1 cm nudge), at
x = 1000 m by up to 43% (0.8537 = 10 cm); keep vertex-mode test scenes near the origin.
Units as for images: an 8 x 8 segment grid, rho 0.6, sun S=2 gives 0.38197187 (0 deg) and
0.19098592 (60 deg) at every vertex and corner (float32 rounding only), alpha 1.
CORNER: one value per loop, shaded with the face normal when flat shaded (a flat cube
under a 30 deg sun: rho*S*max(cos_face, 0)/pi to 3e-8), with the interpolated vertex
normal when smooth. POINT: the plain mean of the vertex's corners (Blender averages after
the bake), so a flat-shaded cube corner gets the mean of its three faces, not the value
for its vertex normal; compare per-vertex-normal evaluations with smooth-shaded meshes or
with CORNER. Corners of one vertex share one random sequence (seed = vertex index): they
differ by 3e-4 relative where the noise is 0.6% (area light, 16 spp), so POINT averaging
does not reduce noise. Modifiers: the evaluated mesh is baked and each original corner
takes the first evaluated corner at the same original vertex and face (subdivision: limit
surface position and normal); from the source, unmatched corners get (0, 0, 0, 1) and
count as such in POINT means, vertices without faces get 0. One bake call bakes every
selected object in turn into its own mesh's active colour attribute (Blender's
mesh.active_color_attribute, a colour attribute on POINT or CORNER), so objects sharing a
mesh need separate calls. Cost: ~0.015 s per small object (10 grids, 16 spp: 0.15 s).

Cost: one bake call costs ~0.07 s of scene sync per object even when several objects
are baked in one call. The demo room (10 objects, 5.1k triangles), 64 x 64 per object,
16 spp: 1.1-3.2 s with 0 bounces, 4.3 s with 2; 128 x 128, 64 spp, 2 bounces: 39 s.
"""
from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterable, Iterator, Sequence

import bpy

import numpy as np

from tools.blender_compat import compat

__all__ = ["bake_diffuse", "bake_diffuse_vertex_colors", "reference_settings"]

_LIVE_VALUE_TYPES = {"bpy_prop_array", "Vector", "Color", "Euler", "Quaternion"}


class _Restorer:
    """Sets attributes and puts the old values back in reverse order.

    Reverse order matters when one attribute is set twice (a mesh shared by two
    objects, a material used in two slots): the last undo restores the original.
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

    def set_where_present(self, owner: object, attr: str, value: object) -> None:
        """:meth:`set`, for a setting that not every supported Blender has (a newer
        Cycles option): where it is missing there is nothing to switch off."""
        if hasattr(owner, attr):
            self.set(owner, attr, value)

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
    target: str = "IMAGE_TEXTURES",
) -> Iterator[None]:
    """Put ``scene`` in the reference bake configuration for the duration of the block.

    ``target`` is the bake target, 'IMAGE_TEXTURES' or 'VERTEX_COLORS'.

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
        r.set_where_present(cy, "use_sample_subset", False)
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
        # A path stops at whichever of max_bounces and the per-type limit comes first.
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
        # ADJACENT_FACES (the default) fades the outer margin texels of an island that
        # has no UV neighbours to half value and half alpha; EXTEND copies texels.
        r.set(bake, "margin_type", "EXTEND")
        r.set(bake, "target", target)
        r.set(bake, "save_mode", "INTERNAL")
        r.set(bake, "use_selected_to_active", False)
        r.set(bake, "use_clear", True)
        r.set(bake, "use_split_materials", False)
        yield
    finally:
        r.restore()


def _disjoint_groups(
    objects: Sequence[bpy.types.Object], keys: Callable[[bpy.types.Object], set]
) -> list[list[bpy.types.Object]]:
    """Split objects into groups in which no two objects share a key (greedy colouring)."""
    groups: list[tuple[set, list]] = []
    for ob in objects:
        own = keys(ob)
        for used, members in groups:
            if not (used & own):
                used |= own
                members.append(ob)
                break
        else:
            groups.append((set(own), [ob]))
    return [members for _, members in groups]


def _objects_in_scene(objects) -> list:
    """``objects`` as a list; ValueError naming any that are not in the current scene."""
    objects = list(objects)
    scene = bpy.context.scene
    missing = [ob.name for ob in objects if scene.objects.get(ob.name) is not ob]
    if missing:
        raise ValueError(f"objects not in the current scene: {missing}")
    return objects


def _material_groups(objects: Sequence[bpy.types.Object]) -> list[list[bpy.types.Object]]:
    """Split objects into groups in which no two objects share a material.

    A material has one active image node, so two objects sharing it in the same
    bake call would both write into one image. Greedy colouring is enough here.
    """
    return _disjoint_groups(objects, lambda ob: {s.material for s in ob.material_slots if s.material is not None})


@contextlib.contextmanager
def _fallback_materials(objects: Sequence[bpy.types.Object]) -> Iterator[None]:
    """Give material-less objects and empty slots a temporary 0.8 grey Lambert material.

    Cycles' own default surface is a default Principled BSDF (specular layer on), 3.7%
    darker than 0.8 / pi under a sun; VisiBake treats a missing material as a 0.8 Lambert,
    and image bakes need a node tree to find their target. On exit every slot is emptied
    again and the materials are removed.
    """
    fallback: list[bpy.types.Material] = []
    emptied_slots: list[bpy.types.MaterialSlot] = []
    appended_meshes: list[bpy.types.Mesh] = []
    try:
        for ob in objects:
            mesh = ob.data
            if not ob.material_slots:
                mat = bpy.data.materials.new(".visibake_ref_default")
                compat.ensure_node_tree(mat)
                fallback.append(mat)
                mesh.materials.append(mat)
                appended_meshes.append(mesh)
            for slot in ob.material_slots:
                if slot.material is None:
                    mat = bpy.data.materials.new(".visibake_ref_default")
                    compat.ensure_node_tree(mat)
                    fallback.append(mat)
                    slot.material = mat
                    emptied_slots.append(slot)
        for mat in fallback:
            bsdf = mat.node_tree.nodes.get("Principled BSDF")
            if bsdf is not None:
                bsdf.inputs["Specular IOR Level"].default_value = 0.0
        yield
    finally:
        for slot in emptied_slots:
            slot.material = None
        for mesh in appended_meshes:
            # pop() leaves the object's slot count behind; the mesh had no
            # materials before, and clear() resyncs the objects using it.
            mesh.materials.clear()
        for mat in fallback:
            bpy.data.materials.remove(mat)


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
        with _fallback_materials(objects):
            yield targets
    finally:
        r.restore()
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


def _selection_override(group: Sequence[bpy.types.Object]) -> dict:
    """Context members the bake operator reads, so the user's selection is not touched."""
    return dict(
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
    pass_filter : subset of {'DIRECT', 'INDIRECT', 'COLOR'}; COLOR alone gives the albedo.
    margin : bake margin in texels, filled by copying (EXTEND). With 0, texels whose
        centre no triangle covers stay (0, 0, 0, 0): alpha > 0 is the coverage mask.
    seed : Cycles seed.
    threads : CPU threads, 0 = automatic.

    Returns
    -------
    {object name: (height, width, 4) float32}, Blender pixel order (row 0 is v = 0).

    The scene is left as it was: temporary images, nodes and materials are removed
    and every changed setting (engine, samples, bounces, active UV map, active
    node, ...) is restored.
    """
    objects = _objects_in_scene(objects)
    if not objects:
        return {}
    scene = bpy.context.scene
    passes = set(pass_filter)
    out: dict[str, np.ndarray] = {}
    with reference_settings(scene, bounces, samples, margin, seed, threads), \
            _bake_targets(objects, uv_map, width, height) as targets:
        for group in _material_groups(objects):
            r = _Restorer()
            added: list[tuple[bpy.types.NodeTree, bpy.types.Node]] = []
            try:
                _point_materials_at(group, targets, r, added)
                with bpy.context.temp_override(**_selection_override(group)):
                    result = bpy.ops.object.bake(
                        type="DIFFUSE",
                        pass_filter=passes,
                        margin=int(margin),
                        margin_type="EXTEND",
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


_COLOR_DOMAINS = ("POINT", "CORNER")


@contextlib.contextmanager
def _color_targets(objects: Sequence[bpy.types.Object], domain: str) -> Iterator[dict[str, str]]:
    """A temporary FLOAT_COLOR attribute on each object's mesh, made the active colour.

    Yields {mesh name: attribute name}. Cycles bakes into ``mesh.active_color_attribute``
    (the active, not the render colour), so only the active colour is switched; the
    render (default) colour, which a Color Attribute node with an empty name reads, is
    kept as it was even when the mesh had no colour attribute before (adding the first
    one would otherwise make it the default). On exit the attributes are removed and
    the active / default colour and active attribute index are put back (removing the
    active colour makes Blender pick another one).
    """
    created: list[tuple[bpy.types.Mesh, str, str, str, int]] = []
    names: dict[str, str] = {}
    try:
        for ob in objects:
            if ob.type != "MESH":
                raise TypeError(f"{ob.name!r} is a {ob.type}, only meshes can be baked")
            mesh = ob.data
            if mesh.name in names:  # a mesh shared by several objects
                continue
            colors = mesh.color_attributes
            active, default = colors.active_color_name, colors.default_color_name
            index = mesh.attributes.active_index
            attr = colors.new("visibake_ref_color", "FLOAT_COLOR", domain)
            # The name is made unique if the user has one of that name; re-find by name
            # from now on (Python references to attributes go stale when layers change).
            name = attr.name
            created.append((mesh, name, active, default, index))
            names[mesh.name] = name
            colors.active_color_name = name
            colors.default_color_name = default
        yield names
    finally:
        for mesh, name, active, default, index in reversed(created):
            colors = mesh.color_attributes
            attr = colors.get(name)
            if attr is not None:
                colors.remove(attr)
            colors.active_color_name = active
            colors.default_color_name = default
            if mesh.attributes.active_index != index:
                mesh.attributes.active_index = index


def bake_diffuse_vertex_colors(
    objects: Iterable[bpy.types.Object],
    bounces: int,
    samples: int,
    domain: str = "POINT",
    pass_filter: Iterable[str] = ("DIRECT", "INDIRECT", "COLOR"),
    seed: int = 0,
    threads: int = 0,
) -> dict[str, np.ndarray]:
    """Bake Cycles DIFFUSE lighting of each mesh object into a temporary colour attribute.

    Parameters
    ----------
    objects : mesh objects in the current scene (evaluated geometry is baked, the values
        land on the original mesh's vertices / corners).
    bounces : Cycles diffuse bounces (0 = direct light only).
    samples : exact samples per vertex / corner (adaptive sampling is off).
    domain : 'POINT' (one value per vertex: the mean of its corners' values) or
        'CORNER' (one value per face corner, in loop order).
    pass_filter : subset of {'DIRECT', 'INDIRECT', 'COLOR'}; COLOR alone gives the albedo.
    seed : Cycles seed.
    threads : CPU threads, 0 = automatic.

    Returns
    -------
    {object name: (n, 4) float32}, n = len(mesh.vertices) for 'POINT' and
    len(mesh.loops) for 'CORNER'; alpha is 1 (0 only at vertices without faces).

    The scene is left as it was: the temporary attributes are removed, the active and
    render colour attributes are restored and the user's own attributes are never
    written (see "Vertex colours" in the module docstring for what is sampled where).
    """
    if domain not in _COLOR_DOMAINS:
        raise ValueError(f"domain must be one of {_COLOR_DOMAINS}, not {domain!r}")
    objects = _objects_in_scene(objects)
    if not objects:
        return {}
    scene = bpy.context.scene
    passes = set(pass_filter)
    out: dict[str, np.ndarray] = {}
    with reference_settings(scene, bounces, samples, 0, seed, threads, target="VERTEX_COLORS"), \
            _color_targets(objects, domain) as names, _fallback_materials(objects):
        # One bake call bakes every selected object in turn, each into its mesh's active
        # colour; objects sharing a mesh would overwrite each other, so they go apart.
        for group in _disjoint_groups(objects, lambda ob: {ob.data.name}):
            with bpy.context.temp_override(**_selection_override(group)):
                result = bpy.ops.object.bake(
                    type="DIFFUSE",
                    pass_filter=passes,
                    target="VERTEX_COLORS",
                    use_selected_to_active=False,
                    use_clear=False,
                )
            if "FINISHED" not in result:
                raise RuntimeError(f"Cycles bake returned {result}")
            for ob in group:
                attr = ob.data.color_attributes[names[ob.data.name]]
                values = np.empty(len(attr.data) * 4, np.float32)
                attr.data.foreach_get("color", values)
                out[ob.name] = values.reshape(-1, 4)
    return out
