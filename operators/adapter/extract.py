"""Blender -> core: evaluated meshes, materials, lights and world as plain arrays."""
from __future__ import annotations

from dataclasses import dataclass

import bpy

import numpy as np

from ...core.errors import BakeRefused
from ...core.lights import environment
from ...core.lights.lamps import cycles_strength
from ...core.outputs.images import srgb_to_linear
from ...core.scene import Light, Material, Mesh, World
from . import compat, world_capture


def _matrix(matrix) -> np.ndarray:
    return np.array([list(row) for row in matrix], dtype=np.float64)


def _native_dtype(dtype) -> np.dtype:
    """The dtype Blender stores a property of ``dtype``'s kind in (32-bit floats and ints):
    foreach_get into it is a copy, into any other a conversion per value, 5-20x slower."""
    kind = np.dtype(dtype).kind
    return np.dtype(np.float32 if kind == "f" else np.int32 if kind in "iu" else dtype)


def read_values(collection, attribute: str, count: int, width: int, dtype) -> np.ndarray:
    """(count, width) (or (count,) for width 1) ``dtype`` values of ``attribute`` of every item
    of a bpy collection; read in Blender's own dtype, so the values are exactly Blender's."""
    data = np.empty(count * width, dtype=_native_dtype(dtype))
    if count:
        collection.foreach_get(attribute, data)
    data = data.astype(dtype, copy=False)
    return data.reshape(count, width) if width > 1 else data


@dataclass
class MeshTriangles:
    """A mesh's vertices and loop triangles, read from Blender as stored.

    positions : (n, 3) float64 object-space vertex positions
    triangles : (m, 3) int32 vertex indices of each loop triangle
    loops : (m, 3) int64 face-corner (loop) indices of each loop triangle
    material_index : (m,) int32 material slot of each loop triangle's face
    corners_in_order : every face is a triangle, so ``loops`` is 0, 1, 2, ... in order
    """

    positions: np.ndarray
    triangles: np.ndarray
    loops: np.ndarray
    material_index: np.ndarray
    corners_in_order: bool = False

    def per_corner(self, values: np.ndarray) -> np.ndarray:
        """(m, 3, ...) the per-face-corner ``values`` (c, ...) at each loop triangle's corners."""
        return _at_corners(values, self.loops, self.corners_in_order)


def _at_corners(values: np.ndarray, loops: np.ndarray, in_order: bool) -> np.ndarray:
    """``values`` (c, ...) at the corners ``loops`` (m, 3): a reshaped view where the corners are
    0, 1, 2, ... in order (``in_order``), else gathered."""
    return values.reshape(len(loops), 3, *values.shape[1:]) if in_order else values[loops]


def _attribute_values(mesh: bpy.types.Mesh, name: str, domain: str, field: str, count: int, width: int, dtype):
    """(count, width) values of the mesh attribute ``name`` on ``domain``, or None where the
    mesh has no such attribute of that size. Attribute arrays are read in one copy; the
    per-element collections (``mesh.loop_triangles``, ``mesh.loops``) go through RNA per
    element, 50-90 ms a property on a 200k-triangle mesh (bpy 5.0.1, docs/benchmarks.md part 14)."""
    attribute = mesh.attributes.get(name)
    if attribute is None or attribute.domain != domain or len(attribute.data) != count:
        return None
    return read_values(attribute.data, field, count, width, dtype)


def read_triangles(mesh: bpy.types.Mesh) -> MeshTriangles:
    """The vertices and loop triangles of ``mesh``, whose loop triangles the caller has made
    current (``calc_loop_triangles``, where the mesh is its own to change).

    The triangles' vertex and material indices come from the corner and face attributes
    through the triangles' corners and faces, which is what Blender's own loop-triangle
    properties return, in two array reads instead of per-triangle ones. Where every face is a
    triangle, Blender's loop triangles are the faces themselves, corners in order (its
    mesh_tessellate.cc), so the per-triangle read of their corners (18 ms of a 200k-triangle
    mesh: docs/benchmarks.md, speed part 20) is not made."""
    count = len(mesh.loop_triangles)
    positions = _attribute_values(mesh, "position", "POINT", "vector", len(mesh.vertices), 3, np.float64)
    if positions is None:
        positions = read_values(mesh.vertices, "co", len(mesh.vertices), 3, np.float64)
    # Each face has at least three corners, so three per face means triangles only.
    corners_in_order = len(mesh.loops) == 3 * len(mesh.polygons) == 3 * count
    if corners_in_order:
        loops = np.arange(3 * count, dtype=np.int64).reshape(count, 3)
    else:
        loops = read_values(mesh.loop_triangles, "loops", count, 3, np.int64)
    corner_vertex = _attribute_values(mesh, ".corner_vert", "CORNER", "value", len(mesh.loops), 1, np.int32)
    if corner_vertex is not None:
        triangles = _at_corners(corner_vertex, loops, corners_in_order)
    else:
        triangles = read_values(mesh.loop_triangles, "vertices", count, 3, np.int32)
    if not hasattr(mesh, "loop_triangle_polygons"):
        material_index = read_values(mesh.loop_triangles, "material_index", count, 1, np.int32)
    else:
        face_material = _attribute_values(mesh, "material_index", "FACE", "value", len(mesh.polygons), 1, np.int32)
        material_index = (np.zeros(count, np.int32) if face_material is None else
                          face_material[read_values(mesh.loop_triangle_polygons, "value", count, 1, np.int64)])
    return MeshTriangles(positions, triangles, loops, material_index, corners_in_order)


def mesh_corner_uv(mesh: bpy.types.Mesh, read: MeshTriangles) -> dict[str, np.ndarray]:
    """UV maps of ``mesh`` per triangle corner of ``read`` (its read_triangles): name -> (m, 3, 2) float32."""
    return {layer.name: read.per_corner(read_values(layer.uv, "vector", len(mesh.loops), 2, np.float32))
            for layer in mesh.uv_layers}


# Byte images in these colour spaces hold linear values already; Cycles reads them as stored.
_LINEAR_COLORSPACES = {"non-color", "linear rec.709", "scene_linear", "linear"}


def _image_pixels(image: bpy.types.Image, warnings: list[str] | None = None) -> np.ndarray | None:
    """Linear RGB pixels of ``image``: (h, w, 3) float32, row 0 at the bottom; None if it has none."""
    width, height = image.size
    if width == 0 or height == 0:
        return None
    pixels = np.empty(width * height * image.channels, np.float32)
    image.pixels.foreach_get(pixels)
    pixels = pixels.reshape(height, width, image.channels)
    if image.channels < 3:
        pixels = np.repeat(pixels[..., :1], 3, axis=2)
    rgb = pixels[..., :3]
    # Float buffers are scene linear whatever the colour space says (Blender converts
    # them on load; Cycles reads them as they are, checked for sRGB, ACEScg, AgX).
    # Byte images hold their colour space's encoded values.
    if not image.is_float:
        space = image.colorspace_settings.name
        if space.lower().startswith("srgb"):
            rgb = srgb_to_linear(rgb)
        elif not (image.colorspace_settings.is_data or space.lower() in _LINEAR_COLORSPACES) and warnings is not None:
            warnings.append(f"image {image.name!r}: colour space {space!r} is read as linear values; Cycles "
                            "converts it, so colours differ (use sRGB, Non-Color or a float image)")
    return np.ascontiguousarray(rgb, np.float32)


def _surface_node(material: bpy.types.Material):
    tree = material.node_tree
    if tree is None:
        return None
    outputs = [n for n in tree.nodes if n.bl_idname == "ShaderNodeOutputMaterial"]
    output = next((n for n in outputs if n.is_active_output and n.target in {"ALL", "CYCLES"}), None)
    output = output or next(iter(outputs), None)
    if output is None or not output.inputs["Surface"].is_linked:
        return None
    return output.inputs["Surface"].links[0].from_node


def _linked_texture(socket):
    """The image, and the UV map it is looked up with, of an Image Texture node linked to ``socket``."""
    if not socket.is_linked:
        return None, None
    node = socket.links[0].from_node
    if node.bl_idname != "ShaderNodeTexImage" or node.image is None:
        return None, None
    uv_map = ""
    vector = node.inputs["Vector"]
    if vector.is_linked and vector.links[0].from_node.bl_idname == "ShaderNodeUVMap":
        uv_map = vector.links[0].from_node.uv_map
    return node.image, uv_map


def read_material(material, default_uv_map: str, warnings: list[str]) -> Material:
    """Lambert albedo and emission of a Blender material (Principled, Diffuse or Emission)."""
    if material is None:
        return Material(name="none")
    node = _surface_node(material) if compat.uses_nodes(material) else None
    if node is None:
        return Material(name=material.name, base_color=np.array(material.diffuse_color[:3], np.float64))
    result = Material(name=material.name)
    if node.bl_idname in {"ShaderNodeBsdfPrincipled", "ShaderNodeBsdfDiffuse"}:
        color_socket = node.inputs["Base Color" if node.bl_idname == "ShaderNodeBsdfPrincipled" else "Color"]
        image, uv_map = _linked_texture(color_socket)
        if image is not None:
            result.base_color_texture = _image_pixels(image, warnings)
            result.texture_uv_map = uv_map or default_uv_map
        elif color_socket.is_linked:
            warnings.append(f"material {material.name!r}: base colour comes from a "
                            f"{color_socket.links[0].from_node.bl_idname} node; using its default value")
        result.base_color = np.array(color_socket.default_value[:3], np.float64)
        if node.bl_idname == "ShaderNodeBsdfPrincipled":
            strength = float(node.inputs["Emission Strength"].default_value)
            result.emission = np.array(node.inputs["Emission Color"].default_value[:3], np.float64) * strength
            if node.inputs["Metallic"].default_value > 0 or node.inputs["Transmission Weight"].default_value > 0:
                warnings.append(f"material {material.name!r}: metallic and transmission are ignored (Lambert only)")
            if node.inputs["Specular IOR Level"].default_value > 0:
                # Cycles' diffuse lobe loses what the dielectric layer reflects (about
                # 1-4% at normal incidence); VisiBake treats base colour as albedo.
                warnings.append(f"material {material.name!r}: its specular layer is ignored, so VisiBake is a few "
                                "percent brighter than Cycles' diffuse bake (set Specular IOR Level to 0 to match)")
    elif node.bl_idname == "ShaderNodeEmission":
        strength = float(node.inputs["Strength"].default_value)
        result.base_color = np.zeros(3)
        result.emission = np.array(node.inputs["Color"].default_value[:3], np.float64) * strength
    else:
        warnings.append(f"material {material.name!r}: surface shader {node.bl_idname} is not supported; "
                        "baked as grey diffuse")
    brightest = max(float(np.max(result.base_color[:3], initial=0.0)),
                    float(np.nanmax(result.base_color_texture, initial=0.0))
                    if result.base_color_texture is not None else 0.0)
    if brightest > 1.0:
        # Cycles keeps it (its diffuse closures clamp at 0 only), and so does VisiBake.
        warnings.append(f"material {material.name!r}: base colour above 1 (up to {brightest:.3g}) reflects more "
                        "light than it receives, as in Cycles; every bounce off it adds energy")
    return result


def read_mesh(obj: bpy.types.Object, depsgraph, bake_uv_map: str, resolution: tuple[int, int],
              output: bool, warnings: list[str]) -> Mesh:
    """The evaluated mesh of ``obj`` (modifiers applied) in world space, triangulated."""
    _viewport_difference(obj, warnings)
    evaluated = obj.evaluated_get(depsgraph)
    mesh = evaluated.to_mesh()
    try:
        mesh.calc_loop_triangles()
        read = read_triangles(mesh)
        positions, triangles, loops, material_index = read.positions, read.triangles, read.loops, read.material_index
        normals = read_values(mesh.corner_normals, "vector", len(mesh.corner_normals), 3, np.float64)
        uv_maps = mesh_corner_uv(mesh, read)
        vertex_count, loop_count = len(mesh.vertices), len(mesh.loops)
        default_uv = next((layer.name for layer in mesh.uv_layers if layer.active_render), "")
        materials = [read_material(slot.material, default_uv, warnings) for slot in evaluated.material_slots]
    finally:
        evaluated.to_mesh_clear()

    if not evaluated.is_evaluated and any(m.show_render for m in obj.modifiers):
        warnings.append(f"object {obj.name!r} is hidden in the viewport, so its modifiers are not evaluated; "
                        "VisiBake reads it without them (Cycles renders them): show it to bake them")
    matrix = world_matrix(obj, evaluated)
    linear = matrix[:3, :3]
    with np.errstate(invalid="ignore", over="ignore"):  # NaN/Inf vertices stay NaN/Inf; core drops them
        positions = positions @ linear.T + matrix[:3, 3]
    normal_matrix = np.linalg.inv(linear).T if abs(np.linalg.det(linear)) > 1e-30 else linear
    # One (3m, 3) product, not m stacked 3 x 3 ones: the same values, 4-9x sooner.
    corner_normals = (read.per_corner(normals).reshape(-1, 3) @ normal_matrix.T).astype(np.float32).reshape(-1, 3, 3)
    if np.linalg.det(linear) < 0:
        # A mirroring transform turns the winding around; restore counter-clockwise
        # fronts so face normals still point where Blender shows them.
        order = [0, 2, 1]
        triangles = triangles[:, order]
        corner_normals = corner_normals[:, order]
        uv_maps = {name: uv[:, order] for name, uv in uv_maps.items()}
        # The corners' loops turn with them, or face-corner results land on the wrong corners.
        loops = loops[:, order]
    return Mesh(name=obj.name, positions=positions, triangles=triangles, corner_normals=corner_normals,
                material_index=material_index, materials=materials, uv_maps=uv_maps,
                bake_uv_map=bake_uv_map, resolution=resolution, output=output,
                light_group=getattr(obj, "lightgroup", ""), corner_loops=loops, vertex_count=vertex_count,
                loop_count=loop_count, casts_shadow=bool(getattr(obj, "visible_shadow", True)),
                terminator_offset=_terminator_offset(obj))


def _terminator_offset(obj) -> float:
    """The object's Shadow Terminator > Geometry Offset (Cycles' default 0.1 where absent)."""
    value = float(getattr(obj, "shadow_terminator_geometry_offset", 0.1))
    return value if np.isfinite(value) and value > 0 else 0.0


def read_light(obj: bpy.types.Object, warnings: list[str] | None = None, mesh_names=None) -> Light:
    """A Blender lamp in Cycles' units (energy already includes the lamp's exposure), with
    its extent (sun angle, point and spot radius), shadow switch, light and shadow linking
    and its node tree's emission.

    warnings : where what is approximated is said (None: not said)
    mesh_names : the scene's meshes, so that linking which excludes objects can name the
        ones that are left; None: linking that only excludes is ignored, with a warning
    """
    warnings = [] if warnings is None else warnings
    light = obj.data
    matrix = _matrix(obj.matrix_world)
    axes = matrix[:3, :3]
    scale = np.linalg.norm(axes, axis=0)
    safe = np.where(scale > 0, scale, 1.0)
    axis_x, axis_y, axis_z = (axes[:, i] / safe[i] for i in range(3))
    extent = {}
    if light.type == "AREA":
        size_y = light.size_y if light.shape in {"RECTANGLE", "ELLIPSE"} else light.size
        extent = {"area_shape": light.shape, "size": float(light.size), "size_y": float(size_y),
                  "scale": (scale[0], scale[1])}
    elif light.type == "SUN":
        extent = {"sun_angle": float(light.angle)}
    strength = cycles_strength(light.type, float(light.energy), float(compat.lamp_setting(light, "exposure", 0.0)),
                               compat.lamp_setting(light, "normalize", True), **extent)
    color = np.array(light.color[:3], np.float64)
    if compat.lamp_setting(light, "use_temperature", False):
        color = color * np.array(light.temperature_color[:3], np.float64)
    emission_color, emission_strength = _lamp_emission(obj, warnings)
    result = Light(name=obj.name, kind=light.type, color=color * emission_color,
                   strength=strength * emission_strength, position=matrix[:3, 3].copy(), direction=-axis_z,
                   group=getattr(obj, "lightgroup", ""), casts_shadows=bool(light.use_shadow))
    if light.type == "SUN":
        result.angle = max(float(light.angle), 0.0)
    if light.type in {"POINT", "SPOT"}:
        result.radius = max(float(light.shadow_soft_size), 0.0)
        result.sphere = not compat.lamp_setting(light, "use_soft_falloff", True)
    linking = getattr(obj, "light_linking", None)
    if linking is not None:
        result.receivers = _linked_objects(obj, linking.receiver_collection, "light", mesh_names, warnings)
        result.blockers = _linked_objects(obj, linking.blocker_collection, "shadow", mesh_names, warnings)
    if light.type == "SPOT":
        result.spot_size = float(light.spot_size)
        result.spot_blend = float(light.spot_blend)
    if light.type == "AREA":
        result.area_shape = light.shape
        result.size_x = float(light.size) * scale[0]
        result.size_y = float(size_y) * scale[1]
        result.axis_x, result.axis_y = axis_x, axis_y
    return result


def _linked_objects(lamp, collection, kind: str, mesh_names, warnings: list[str]):
    """The object names a light- or shadow-linking collection leaves in, or None (no linking).

    As Cycles: objects set to Include (directly or through a child collection) are the only
    ones in when there is any; objects set to Exclude are out; with only exclusions, every
    other object is in.
    """
    if collection is None:
        return None
    included, excluded = set(), set()

    def walk(owner, inherited=None, depth=0):
        """A child collection's state applies to everything inside it."""
        # collection_objects and collection_children run parallel to objects and children.
        for obj, entry in zip(owner.objects, owner.collection_objects):
            state = inherited or entry.light_linking.link_state
            (included if state == "INCLUDE" else excluded).add(obj.name)
        for child, entry in zip(owner.children, owner.collection_children) if depth < 64 else ():
            walk(child, inherited or entry.light_linking.link_state, depth + 1)

    walk(collection)
    if included:
        return tuple(sorted(included - excluded))
    if mesh_names is None:
        warnings.append(f"light {lamp.name!r}: its {kind} linking only excludes objects, which needs the scene's "
                        "objects; it was ignored")
        return None
    return tuple(name for name in mesh_names if name not in excluded)


def _lamp_emission(obj, warnings: list[str]) -> tuple[np.ndarray, float]:
    """What a lamp's node tree multiplies its colour (3,) and power by, as Cycles does:
    the Emission node's Color and Strength at the Light Output, through reroutes.

    Anything else (a texture, Blackbody or IES feeding the Emission node, another shader)
    cannot be baked from constants: it is warned about, naming the value used.
    """
    light = obj.data
    if not compat.lamp_uses_nodes(light):
        return np.ones(3), 1.0
    outputs = [n for n in light.node_tree.nodes if n.bl_idname == "ShaderNodeOutputLight"
               and getattr(n, "target", "ALL") in {"ALL", "CYCLES"}]
    output = next((n for n in outputs if n.is_active_output), outputs[0] if outputs else None)
    if output is None:
        warnings.append(f"light {obj.name!r}: its node tree has no Light Output; baked with its colour and power")
        return np.ones(3), 1.0
    node, _ = _link_source(output.inputs["Surface"])
    if node is None:
        # Nothing reaches the output: Cycles' lamp then emits nothing.
        return np.zeros(3), 0.0
    if node.bl_idname != "ShaderNodeEmission":
        warnings.append(f"light {obj.name!r}: its node tree feeds a {node.bl_idname} node to the Light Output, "
                        "which is not supported; baked with its colour and power alone")
        return np.ones(3), 1.0
    color_socket, strength_socket = node.inputs["Color"], node.inputs["Strength"]
    color = np.array(color_socket.default_value[:3], np.float64)
    strength = float(strength_socket.default_value)
    for socket, used in ((color_socket, f"its Color value {tuple(round(c, 4) for c in color)}"),
                         (strength_socket, f"its Strength value {strength:g}")):
        source, _ = _link_source(socket)
        if source is not None:
            warnings.append(f"light {obj.name!r}: a {source.bl_idname} node drives the Emission node's "
                            f"{socket.name}, which is not evaluated; {used} was used")
    return color, strength


def _link_source(socket):
    """The node and output socket feeding ``socket``, through reroutes; (None, None) if unlinked.

    A muted link passes nothing: the socket then uses its own value, as in Cycles.
    """
    for _ in range(64):  # a reroute chain cannot be longer than the tree; bounded anyway
        links = [link for link in socket.links if not link.is_muted] if socket.is_linked else []
        if not links:
            return None, None
        node, output = links[0].from_node, links[0].from_socket
        if node.bl_idname != "NodeReroute":
            return node, output
        socket = node.inputs[0]
    return None, None


def read_world(scene: bpy.types.Scene, warnings: list[str]) -> World:
    """World radiance as Cycles renders it.

    Read from the nodes, exactly and without rendering: no world or no output (black), a
    world without nodes, a Background node's colour * strength, or its equirectangular
    Environment Texture (times strength) with the rotation of a Mapping node. Every other
    tree (Sky Texture, procedural textures, Mix Shaders, a linked strength, ...) is
    rendered once through Cycles (``world_capture``); if that fails, the node reading
    stands, with its warnings and one saying why.
    """
    world = scene.world
    if world is None:
        return World()
    if not compat.uses_nodes(world):
        return World(np.array(world.color[:3], np.float64))
    notes: list[str] = []
    result = _read_world_nodes(world, notes)
    if all(note in _EXACT_WORLD_NOTES for note in notes):
        warnings.extend(notes)
        return _with_sun_lamp(result)
    warn_non_finite_world_images(world.node_tree, warnings)
    try:
        image = world_capture.capture_world(scene)
    except world_capture.CaptureFailed as error:
        warnings.append(f"world: Cycles could not render the world for a capture ({error}); it is read from its "
                        "nodes instead")
        warnings.extend(notes)
        return result
    if _tree_has(world.node_tree, "ShaderNodeLightPath"):
        warnings.append("world: the world uses a Light Path node; it was captured as camera rays see it, "
                        "while the bake's light arrives by diffuse rays")
    return _with_sun_lamp(World(image=image))


def _with_sun_lamp(world: World) -> World:
    """``world`` with a sun disc of its image (a sky's sun, an HDRI's) taken out as a lamp:
    it then lights from its own direction and casts its own shadow, not a cell's."""
    if world.image is None:
        return world
    image, sun = environment.split_sun(world.image)
    if sun is None:
        return world
    # The image is looked up at R d; the disc's direction in the world is R^T of it
    # (R is a rotation, or one mirrored by a negative uniform scale: orthogonal either way).
    sun.direction = np.asarray(world.rotation, np.float64).T @ sun.direction
    return World(color=world.color, image=image, rotation=world.rotation, suns=[sun])


# What the node reading says about worlds it still reads exactly, as Cycles renders them
# (a missing image is black by choice: Cycles' magenta lights nothing usefully).
_NO_IMAGE_NOTE = ("world: the environment texture has no image (or it could not be loaded); "
                  "the world is treated as black")
_CONSTANT_VECTOR_NOTE = ("world: nothing is linked to the mapping node's vector, so the environment shows one "
                         "constant colour (as in Cycles); link a Texture Coordinate (Generated) to rotate it")
_EXACT_WORLD_NOTES = {_NO_IMAGE_NOTE, _CONSTANT_VECTOR_NOTE}


def _tree_has(tree, bl_idname: str, seen: set | None = None) -> bool:
    """Whether ``tree`` or a node group inside it has a node of type ``bl_idname``."""
    seen = set() if seen is None else seen
    if tree is None or tree.name_full in seen:
        return False
    seen.add(tree.name_full)
    return any(node.bl_idname == bl_idname
               or (getattr(node, "node_tree", None) is not None and _tree_has(node.node_tree, bl_idname, seen))
               for node in tree.nodes)


def _read_world_nodes(world: bpy.types.World, warnings: list[str]) -> World:
    """World radiance from the nodes: colour * strength of the Background node, or its
    equirectangular Environment Texture (times strength) with the rotation of a Mapping node.
    Anything else is approximated, with a warning."""
    output = next((n for n in world.node_tree.nodes
                   if n.bl_idname == "ShaderNodeOutputWorld" and n.is_active_output), None)
    if output is None:
        return World()
    node, _ = _link_source(output.inputs["Surface"])
    if node is None:
        return World()
    if node.bl_idname != "ShaderNodeBackground":
        warnings.append(f"world: {node.bl_idname} is not supported; the world is treated as black")
        return World()
    strength = float(node.inputs["Strength"].default_value)
    strength_source, _ = _link_source(node.inputs["Strength"])
    if strength_source is not None:
        warnings.append(f"world: the background strength comes from a {strength_source.bl_idname} node; "
                        f"using its value {strength:g}")
    color = np.array(node.inputs["Color"].default_value[:3], np.float64)
    source, _ = _link_source(node.inputs["Color"])
    if source is None:
        return World(color * strength)
    if source.bl_idname != "ShaderNodeTexEnvironment" or source.mute:
        warnings.append(f"world: the background colour comes from a {source.bl_idname} node"
                        f"{' (muted)' if source.mute else ''}; using its colour value")
        return World(color * strength)
    return _environment_world(source, strength, warnings)


def _non_finite_texel_note(image: bpy.types.Image, pixels: np.ndarray) -> str | None:
    """The warning for an image whose texels (pixels (h, w, 3)) include NaN or infinite
    ones, or None: the world's light leaves them out (core.lights.environment sets them to 0)."""
    bad = int(np.count_nonzero(~np.all(np.isfinite(pixels), axis=-1)))
    if not bad:
        return None
    return (f"world: image {image.name!r} has {bad:,} texel{'s' if bad > 1 else ''} that {'are' if bad > 1 else 'is'} "
            "infinite or NaN; they light nothing (replace them with finite values to keep their light)")


def warn_non_finite_world_images(tree, warnings: list[str], seen: set | None = None) -> None:
    """A warning for each image of the world ``tree`` (or a node group in it) with NaN or
    infinite texels: the capture through Cycles leaves out the pixels they reach."""
    seen = set() if seen is None else seen
    if tree is None or ("tree", tree.name_full) in seen:
        return
    seen.add(("tree", tree.name_full))
    for node in tree.nodes:
        if getattr(node, "node_tree", None) is not None:
            warn_non_finite_world_images(node.node_tree, warnings, seen)
        image = getattr(node, "image", None) if node.bl_idname in ("ShaderNodeTexEnvironment",
                                                                   "ShaderNodeTexImage") else None
        if image is None or ("image", image.name_full) in seen or not image.is_float:
            continue  # a byte image holds finite values only
        seen.add(("image", image.name_full))
        pixels = _image_pixels(image)
        note = _non_finite_texel_note(image, pixels) if pixels is not None else None
        if note:
            warnings.append(note)


def _environment_world(node, strength: float, warnings: list[str]) -> World:
    """World from an Environment Texture node feeding the Background colour."""
    image = node.image
    pixels = _image_pixels(image, warnings) if image is not None else None
    if pixels is None:
        # Cycles shows a missing image as magenta; lighting a bake with that helps nobody.
        warnings.append(_NO_IMAGE_NOTE)
        return World()
    note = _non_finite_texel_note(image, pixels)
    if note:
        warnings.append(note)
    pixels = pixels * np.float32(strength)
    if node.projection != "EQUIRECTANGULAR":
        warnings.append(f"world: {node.projection.replace('_', ' ').lower()} environment images are not "
                        "supported; using the image's mean as a uniform world (same total light, no direction)")
        return World(environment.mirror_ball_mean(pixels))
    vector = _environment_vector(node, warnings)
    if isinstance(vector, np.ndarray) and vector.shape == (3,):
        return World(environment.constant_lookup(pixels, vector))
    return World(image=pixels, rotation=vector)


def _environment_vector(node, warnings: list[str]):
    """How the Environment Texture turns a world direction d into its lookup vector.

    Returns a (3, 3) world-to-texture matrix, or a (3,) constant vector when the
    lookup does not depend on d (a Mapping node with nothing linked to its Vector).
    Measured with Cycles bakes: Texture Coordinate Generated and Object (no object)
    are d itself; Mapping computes POINT: M(s d) + loc, VECTOR: M(s d) and
    TEXTURE: M^T (d - loc) / s, M = Rz Ry Rx of its rotation (``svm_mapping``; NORMAL,
    normalize(M (d / s)), is taken from that source unmeasured); the texture
    normalises the result.
    """
    source, socket = _link_source(node.inputs["Vector"])
    if source is None:
        return np.eye(3)
    if source.bl_idname == "ShaderNodeTexCoord":
        return _texture_coordinate_check(source, socket, warnings)
    if source.bl_idname != "ShaderNodeMapping":
        warnings.append(f"world: the environment texture's vector comes from a {source.bl_idname} node, which "
                        "is not supported; using the plain view direction")
        return np.eye(3)

    mapping = source
    if mapping.mute:
        # A muted Mapping passes its vector through unchanged.
        return np.eye(3)
    # Blender drops the sockets a vector type does not use (Location for VECTOR and NORMAL).
    inputs = {name: socket for name in ("Vector", "Location", "Rotation", "Scale")
              if (socket := mapping.inputs.get(name)) is not None and socket.enabled}
    for name in ("Location", "Rotation", "Scale"):
        if name in inputs and _link_source(inputs[name])[0] is not None:
            warnings.append(f"world: the mapping node's {name.lower()} is linked; using its value")

    def value(name, default):
        return np.array(inputs[name].default_value[:3], np.float64) if name in inputs else np.array(default, float)

    kind = mapping.vector_type
    matrix = environment.euler_xyz_matrix(value("Rotation", (0.0, 0.0, 0.0)))
    if kind == "TEXTURE":
        matrix = matrix.T
    scale = value("Scale", (1.0, 1.0, 1.0))
    location = value("Location", (0.0, 0.0, 0.0))

    vector_source, vector_socket = _link_source(inputs["Vector"]) if "Vector" in inputs else (None, None)
    if vector_source is None:
        # Mapping's own Vector value is a constant, not the direction: every ray sees
        # the same texel, as Cycles shows it.
        constant = value("Vector", (0.0, 0.0, 0.0))
        if kind == "POINT":
            constant = matrix @ (constant * scale) + location
        elif kind == "VECTOR":
            constant = matrix @ (constant * scale)
        elif kind == "TEXTURE":
            safe = np.where(scale != 0, scale, 1.0)
            constant = np.where(scale != 0, matrix @ (constant - location) / safe, 0.0)
        else:
            safe = np.where(scale != 0, scale, 1.0)
            constant = matrix @ np.where(scale != 0, constant / safe, 0.0)
        warnings.append(_CONSTANT_VECTOR_NOTE)
        return constant
    if vector_source.bl_idname == "ShaderNodeTexCoord":
        _texture_coordinate_check(vector_source, vector_socket, warnings)
    else:
        warnings.append(f"world: the mapping node's vector comes from a {vector_source.bl_idname} node, which "
                        "is not supported; using the plain view direction")

    if np.any(location != 0) and kind in {"POINT", "TEXTURE"}:
        warnings.append("world: the mapping node's location cannot be represented for a world at infinity; "
                        "it is ignored")
    if np.all(scale == scale[0]) and scale[0] != 0:
        # A uniform scale vanishes when the texture normalises; a negative one
        # mirrors every direction through the origin.
        matrix = matrix * np.sign(scale[0])
    else:
        warnings.append(f"world: the mapping node's scale {tuple(round(float(s), 4) for s in scale)} is not "
                        "uniform (or is zero); it is ignored (only the rotation is used)")
    return matrix


def _texture_coordinate_check(node, socket, warnings: list[str]) -> np.ndarray:
    """Identity for the Texture Coordinate outputs that give the world direction."""
    if socket.name in {"Generated", "Object"} and not (socket.name == "Object" and node.object is not None):
        return np.eye(3)
    detail = f"object {node.object.name!r}" if socket.name == "Object" else f"output {socket.name!r}"
    warnings.append(f"world: the texture coordinate {detail} is not supported for the environment; "
                    "using the plain view direction")
    return np.eye(3)


def scene_lights(scene: bpy.types.Scene) -> list[bpy.types.Object]:
    """The lamps Cycles renders (:func:`render_visible`, as for meshes), in ``scene.objects`` order."""
    visible = render_visible(scene)
    return [o for o in scene.objects if o.type == "LIGHT" and o.as_pointer() in visible
            and o.data.type in {"SUN", "POINT", "SPOT", "AREA"}]


def emitter_linking_warnings(scene: bpy.types.Scene, meshes, warnings: list[str]) -> None:
    """Say where an emissive object's own light or shadow linking is ignored: VisiBake links
    lamps only, so such an object's light reaches, and is shadowed by, every object."""
    for mesh in meshes:
        obj = scene.objects.get(mesh.name)
        linking = getattr(obj, "light_linking", None)
        if linking is None or (linking.receiver_collection is None and linking.blocker_collection is None):
            continue
        if any(m is not None and np.any(np.asarray(m.emission) > 0) for m in mesh.materials):
            warnings.append(f"object {mesh.name!r}: light and shadow linking of emissive objects is not supported; "
                            "its emission lights every object and every object shadows it")


def scene_meshes(scene: bpy.types.Scene) -> list[bpy.types.Object]:
    """The mesh objects Cycles renders (the bake's possible targets), in ``scene.objects`` order."""
    visible = render_visible(scene)
    return [o for o in scene.objects if o.type == "MESH" and o.as_pointer() in visible]


def _view_layer(scene: bpy.types.Scene):
    """The view layer a bake of ``scene`` renders: the context's when it shows this scene."""
    layer = getattr(bpy.context, "view_layer", None)
    if layer is not None and getattr(bpy.context, "scene", None) == scene:
        return layer
    return scene.view_layers[0]


def render_visible(scene: bpy.types.Scene) -> set[int]:
    """Pointers (``as_pointer()``) of the objects Cycles renders in the bake's view layer.

    An object renders when its own Disable in Renders is off and at least one collection
    holding it is reached from the scene collection through collections that are
    neither excluded from the view layer nor disabled in renders (measured: a Cycles bake
    ignores an occluder in such a collection, and still sees one hidden only in the viewport).
    """
    found: dict[int, bpy.types.Object] = {}

    def walk(layer_collection) -> None:
        for obj in layer_collection.collection.objects:
            found[obj.as_pointer()] = obj
        for child in layer_collection.children:
            if not child.exclude and not child.collection.hide_render:
                walk(child)

    walk(_view_layer(scene).layer_collection)
    return {pointer for pointer, obj in found.items() if not obj.hide_render}


def world_matrix(obj, evaluated=None) -> np.ndarray:
    """(4, 4) float64 world matrix of ``obj`` as Cycles places it.

    The depsgraph writes ``matrix_world`` only for objects it evaluates; one hidden in
    the viewport keeps a stale matrix (measured: identity after a move), so its matrix is
    composed from its parents (constraints and drivers aside) the way Blender does.
    """
    if evaluated is not None and evaluated.is_evaluated:
        return _matrix(evaluated.matrix_world)
    local = _matrix(obj.matrix_basis)
    if obj.parent is None or obj.parent_type != "OBJECT":
        return local if obj.parent is None else _matrix(obj.matrix_world)
    parent = obj.parent.evaluated_get(bpy.context.evaluated_depsgraph_get())
    return world_matrix(obj.parent, parent) @ _matrix(obj.matrix_parent_inverse) @ local


def _viewport_difference(obj, warnings: list[str]) -> None:
    """Warn where ``obj`` evaluates differently in the viewport (what VisiBake reads) and in renders.

    Python gets only the viewport's depsgraph; Cycles' bake evaluates with render settings
    (measured: an Array modifier shown in renders only casts its shadow in a Cycles bake).
    """
    differences = []
    for modifier in getattr(obj, "modifiers", []):
        if modifier.show_viewport != modifier.show_render:
            differences.append(f"modifier {modifier.name!r} is {'on' if modifier.show_render else 'off'} in renders "
                               f"only")
        elif modifier.show_render and modifier.type in {"SUBSURF", "MULTIRES"} \
                and modifier.levels != modifier.render_levels:
            differences.append(f"modifier {modifier.name!r} has {modifier.levels} viewport and "
                               f"{modifier.render_levels} render levels")
    data = obj.data
    if obj.type in {"CURVE", "FONT", "SURFACE"} and data.render_resolution_u not in {0, data.resolution_u}:
        differences.append(f"its render resolution is {data.render_resolution_u}, its viewport one {data.resolution_u}")
    if obj.type == "META" and data.render_resolution != data.resolution:
        differences.append(f"its render resolution is {data.render_resolution:g}, its viewport one "
                           f"{data.resolution:g}")
    if differences:
        warnings.append(f"object {obj.name!r}: {'; '.join(differences)}; VisiBake reads the viewport's geometry, "
                        "Cycles renders with the render settings")


def _seen_by_light(obj) -> bool:
    """Whether diffuse or shadow rays see ``obj`` (both off: it takes no part in a diffuse bake)."""
    return bool(getattr(obj, "visible_diffuse", True) or getattr(obj, "visible_shadow", True))


# Object types whose evaluated geometry is a mesh Cycles renders besides mesh objects.
_MESH_LIKE = {"CURVE": "curve", "FONT": "text object", "SURFACE": "surface", "META": "metaball"}
# Rendered by Cycles, but as points or hair, which VisiBake does not read.
_UNREAD_TYPES = {"POINTCLOUD": "point cloud", "CURVES": "hair curves"}
# Instanced and non-mesh geometry reflects light through one sample per vertex; past this
# many samples in all, further groups only occlude (a scatter of many rocks would
# otherwise cost more table than the objects being baked).
REFLECTING_GEOMETRY_SAMPLES = 1 << 18
# Instances placed per step of the vectorised transform, bounding its temporaries.
_PLACE_CHUNK_CORNERS = 1 << 21


@dataclass
class _Prototype:
    """One evaluated mesh in its own space, read once however many instances share it.

    positions : (n, 3) float64; triangles : (m, 3) int32; normals : (m, 3, 3) float32
    corner normals; material_index : (m,) int32; uv_maps : name -> (m, 3, 2) float32
    """

    name: str
    positions: np.ndarray
    triangles: np.ndarray
    normals: np.ndarray
    material_index: np.ndarray
    uv_maps: dict
    materials: list


@dataclass
class _Group:
    """The instances of one prototype under one instancer: what becomes one core mesh."""

    name: str
    kind: str  # what the report counts it as: 'instance', 'curve', 'text', ...
    prototype: _Prototype
    matrices: list  # (4, 4) float64 world matrices
    casts_shadow: bool = True
    light_group: str = ""  # the instancer's group, or its name: all its instances' emission is one group


@dataclass
class SceneGeometry:
    """What Cycles renders besides the mesh objects: instances and non-mesh geometry.

    meshes : core meshes (output False) that occlude, and reflect while under
        :data:`REFLECTING_GEOMETRY_SAMPLES`; counts : kind -> how many instances or objects
    """

    meshes: list
    counts: dict


def _read_prototype(name: str, mesh: bpy.types.Mesh, material_slots, materials_read: dict,
                    warnings: list[str]) -> _Prototype:
    """The triangles of an evaluated mesh (read, never changed: it belongs to the depsgraph)."""
    read = read_triangles(mesh)
    materials = []
    for slot in material_slots:
        key = slot.material.as_pointer() if slot.material is not None else 0
        if key not in materials_read:
            default_uv = next((layer.name for layer in mesh.uv_layers if layer.active_render), "")
            materials_read[key] = read_material(slot.material, default_uv, warnings)
        materials.append(materials_read[key])
    normals = read_values(mesh.corner_normals, "vector", len(mesh.corner_normals), 3, np.float32)
    return _Prototype(name=name, positions=read.positions, triangles=read.triangles, normals=read.per_corner(normals),
                      material_index=read.material_index, uv_maps=mesh_corner_uv(mesh, read),
                      materials=materials)


def _place(group: _Group, reflects: bool) -> Mesh:
    """All instances of ``group`` in world space as one occluder mesh, transformed in bulk.

    Each instance's triangles follow the previous one's; a mirroring matrix turns its
    winding back to counter-clockwise, as :func:`read_mesh` does for an object. Only a
    group that ``reflects`` gets samples, and so shading normals and texture UVs: the
    others need positions and triangles alone (normals would be 36 bytes per triangle).
    """
    proto = group.prototype
    matrices = np.asarray(group.matrices, np.float64).reshape(-1, 4, 4)
    k, n, m = len(matrices), len(proto.positions), len(proto.triangles)
    if k * n > np.iinfo(np.int32).max:
        raise BakeRefused(f"{group.name}: {k} instances of {n} vertices are more than VisiBake can trace")
    linear = matrices[:, :3, :3]
    det = np.linalg.det(linear)
    positions = np.empty((k, n, 3))
    normals = np.empty((k, m, 3, 3), np.float32) if reflects else None
    if reflects:
        normal_matrix = linear.copy()
        invertible = np.abs(det) > 1e-30
        normal_matrix[invertible] = np.linalg.inv(linear[invertible]).transpose(0, 2, 1)
        normal_matrix = normal_matrix.transpose(0, 2, 1).astype(np.float32)
        flat_normals = proto.normals.reshape(-1, 3)
    step = max(1, _PLACE_CHUNK_CORNERS // max(3 * m, n, 1))
    with np.errstate(invalid="ignore", over="ignore"):  # NaN/Inf vertices stay NaN/Inf; core drops them
        for a in range(0, k, step):
            b = min(k, a + step)
            positions[a:b] = proto.positions @ linear[a:b].transpose(0, 2, 1) + matrices[a:b, None, :3, 3]
            if reflects:
                normals[a:b] = (flat_normals @ normal_matrix[a:b]).reshape(-1, m, 3, 3)
    triangles = proto.triangles[None] + (np.arange(k, dtype=np.int32) * np.int32(n))[:, None, None]
    uv_maps = {name: np.broadcast_to(uv, (k, *uv.shape)).copy() for name, uv in proto.uv_maps.items()} \
        if reflects else {}
    mirrored = det < 0
    if mirrored.any():
        order = [0, 2, 1]
        triangles[mirrored] = triangles[mirrored][:, :, order]
        if reflects:
            normals[mirrored] = normals[mirrored][:, :, order]
        for uv in uv_maps.values():
            uv[mirrored] = uv[mirrored][:, :, order]
    count = k * m
    mesh = Mesh(name=group.name, positions=positions.reshape(-1, 3), triangles=triangles.reshape(-1, 3),
                corner_normals=normals.reshape(-1, 3, 3) if reflects else _no_normals(count),
                material_index=np.tile(proto.material_index, k), materials=proto.materials,
                uv_maps={name: uv.reshape(-1, 3, 2) for name, uv in uv_maps.items()}, bake_uv_map="",
                resolution=(0, 0), output=False, mode="vertex", vertex_count=k * n, casts_shadow=group.casts_shadow,
                light_group=group.light_group)
    if not reflects:
        # No samples of its own: a 1x1 atlas no texel centre falls in, so rays stop at it
        # and find no light there.
        mesh.mode, mesh.resolution, mesh.bake_uv_map = "atlas", (1, 1), "__visibake_occluder__"
        mesh.uv_maps[mesh.bake_uv_map] = np.zeros((count, 3, 2), np.float32)
    return mesh


def _no_normals(count: int) -> np.ndarray:
    """(count, 3, 3) float32 zeros that take no memory, for meshes without samples."""
    return np.broadcast_to(np.zeros((1, 3, 3), np.float32), (count, 3, 3))


def scene_geometry(depsgraph, scene: bpy.types.Scene, warnings: list[str]) -> SceneGeometry:
    """The instances and non-mesh geometry Cycles renders, as occluder meshes (no outputs).

    Cycles sees the depsgraph's object instances: collection instances, geometry-nodes
    instances, and the meshes curves (bevel, extrusion), text, surfaces and metaballs
    evaluate to. Each is kept if its instancer renders (:func:`render_visible`) and light
    rays see it. Instances of one mesh under one instancer are read once and placed with
    their matrices in bulk. Mesh objects themselves are read by :func:`read_mesh`.

    The depsgraph is the viewport's (the one Python can get): objects hidden in the
    viewport are not evaluated there, so their instances cannot be read, and modifiers
    use their viewport settings; both are warned about.
    """
    visible = render_visible(scene)
    groups: dict[tuple, _Group] = {}
    prototypes: dict[int, _Prototype] = {}
    materials_read: dict[int, Material] = {}
    listed: set[int] = set()
    checked: set[int] = set()  # instancers whose viewport/render difference was looked at
    unread: dict[str, set] = {}  # object name -> what of it Cycles renders that VisiBake cannot read
    for instance in depsgraph.object_instances:
        obj = instance.object
        if not instance.is_instance:
            listed.add(obj.original.as_pointer())
            if obj.type in _UNREAD_TYPES and obj.original.as_pointer() in visible:
                unread.setdefault(obj.original.name, set()).add(_UNREAD_TYPES[obj.type])
            continue
        parent = instance.parent.original if instance.parent is not None else None
        source = instance.instance_object.original if instance.instance_object is not None else parent
        if parent is None or parent.as_pointer() not in visible or source.hide_render \
                or not (_seen_by_light(parent) and _seen_by_light(source)):
            continue
        if obj.type != "MESH":
            # Curves, text and metaballs come again as the MESH they evaluate to.
            if obj.type in _UNREAD_TYPES:
                unread.setdefault(parent.name, set()).add(_UNREAD_TYPES[obj.type])
            continue
        data = obj.data
        key = (parent.as_pointer(), data.as_pointer(), tuple(s.material.as_pointer() if s.material else 0
                                                             for s in obj.material_slots))
        group = groups.get(key)
        if group is None:
            prototype = prototypes.get(data.as_pointer())
            if prototype is None:
                prototype = prototypes[data.as_pointer()] = _read_prototype(
                    data.name, data, obj.material_slots, materials_read, warnings)
            if parent.as_pointer() not in checked:
                checked.add(parent.as_pointer())
                _viewport_difference(parent, warnings)
            own = source == parent and parent.type in _MESH_LIKE
            kind = _MESH_LIKE[parent.type] if own else "instance"
            name = parent.name if own else f"{parent.name} > {source.name if source != parent else data.name}"
            shadow = bool(getattr(parent, "visible_shadow", True) and getattr(source, "visible_shadow", True))
            group = groups[key] = _Group(name, kind, prototype, [], shadow,
                                         getattr(parent, "lightgroup", "") or parent.name)
        group.matrices.append(np.array(instance.matrix_world, np.float64))
    _not_evaluated(depsgraph, scene, visible, listed, groups, warnings)
    for name, kinds in unread.items():
        warnings.append(f"object {name!r}: its {' and '.join(sorted(kinds))} (which Cycles renders) are not read by "
                        "VisiBake; they cast no shadow and reflect no light")
    return _scene_geometry(list(groups.values()), warnings)


def _not_evaluated(depsgraph, scene, visible: set[int], listed: set[int], groups: dict, warnings: list[str]) -> None:
    """Add what the viewport depsgraph does not list (hidden in the viewport) but Cycles renders."""
    for obj in scene.objects:
        if obj.as_pointer() not in visible or obj.as_pointer() in listed or not _seen_by_light(obj):
            continue
        if obj.type in _MESH_LIKE:
            _viewport_difference(obj, warnings)
            evaluated = obj.evaluated_get(depsgraph)
            mesh = evaluated.to_mesh()
            try:
                if mesh is None or len(mesh.polygons) == 0:
                    continue
                mesh.calc_loop_triangles()
                prototype = _read_prototype(obj.name, mesh, evaluated.material_slots, {}, warnings)
            finally:
                evaluated.to_mesh_clear()
            groups[("hidden", obj.as_pointer())] = _Group(obj.name, _MESH_LIKE[obj.type], prototype,
                                                          [world_matrix(obj, evaluated)],
                                                          bool(getattr(obj, "visible_shadow", True)),
                                                          getattr(obj, "lightgroup", ""))
        elif makes_instances(obj):
            warnings.append(f"object {obj.name!r} is hidden in the viewport, so any instances it makes are not "
                            "evaluated and cast no shadow in VisiBake (Cycles renders them); show it to bake them")


def _scene_geometry(groups: list[_Group], warnings: list[str]) -> SceneGeometry:
    """Core meshes of ``groups``: reflecting while the vertex samples last, then occluding only."""
    meshes, counts, budget, dark = [], {}, REFLECTING_GEOMETRY_SAMPLES, []
    used_names: set[str] = set()
    for group in groups:
        if not len(group.prototype.triangles):
            continue
        name, suffix = group.name, 1
        while name in used_names:
            suffix += 1
            name = f"{group.name} ({suffix})"
        used_names.add(name)
        group.name = name
        samples = len(group.prototype.positions) * len(group.matrices)
        reflects = samples <= budget
        budget -= samples if reflects else 0
        if not reflects:
            dark.append(name)
        meshes.append(_place(group, reflects))
        counts[group.kind] = counts.get(group.kind, 0) + len(group.matrices)
    if counts:
        parts = ", ".join(f"{count} {kind}{'s' if count > 1 else ''}"
                          for kind, count in sorted(counts.items()))
        warnings.append(f"scene geometry: {parts} occlude and reflect light but are not bake targets (no UV maps "
                        "or colour attributes of their own); convert them to mesh objects to bake them")
    if dark:
        warnings.append(f"scene geometry: {', '.join(dark[:5])}{' and more' if len(dark) > 5 else ''} only occlude "
                        f"light (more than {REFLECTING_GEOMETRY_SAMPLES} vertices of instances in all); they reflect "
                        "none")
    return SceneGeometry(meshes, counts)


def makes_instances(obj) -> bool:
    """Whether ``obj`` may instance geometry: instancing is on, or geometry nodes may make them."""
    return obj.instance_type != "NONE" or any(mod.type == "NODES" for mod in getattr(obj, "modifiers", []))


def why_not_a_target(obj) -> str | None:
    """Why a selected object gets no output of its own, or None for a mesh object that does."""
    if obj.type == "MESH":
        return None
    if obj.type in _MESH_LIKE:
        return (f"object {obj.name!r} is a {_MESH_LIKE[obj.type]}: it occludes and reflects light but is not a "
                "bake target (convert it to a mesh to bake it)")
    if obj.instance_type != "NONE":
        return (f"object {obj.name!r} instances other objects: the instances occlude and reflect light but share "
                "their data, so they are not bake targets (make them real to bake them)")
    return None
