"""Blender -> core: evaluated meshes, materials, lights and world as plain arrays."""
from __future__ import annotations

import bpy

import numpy as np

from ...core.lights import environment
from ...core.lights.lamps import cycles_strength
from ...core.outputs.images import srgb_to_linear
from ...core.scene import Light, Material, Mesh, World
from . import compat


def _matrix(matrix) -> np.ndarray:
    return np.array([list(row) for row in matrix], dtype=np.float64)


def _read(collection, attribute: str, count: int, width: int, dtype) -> np.ndarray:
    data = np.empty(count * width, dtype=dtype)
    if count:
        collection.foreach_get(attribute, data)
    return data.reshape(count, width) if width > 1 else data


def mesh_corner_uv(mesh: bpy.types.Mesh, loops: np.ndarray) -> dict[str, np.ndarray]:
    """UV maps of ``mesh`` per triangle corner: name -> (m, 3, 2) float32."""
    maps = {}
    for layer in mesh.uv_layers:
        uv = _read(layer.uv, "vector", len(mesh.loops), 2, np.float32)
        maps[layer.name] = uv[loops]
    return maps


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
    return result


def read_mesh(obj: bpy.types.Object, depsgraph, bake_uv_map: str, resolution: tuple[int, int],
              output: bool, warnings: list[str]) -> Mesh:
    """The evaluated mesh of ``obj`` (modifiers applied) in world space, triangulated."""
    evaluated = obj.evaluated_get(depsgraph)
    mesh = evaluated.to_mesh()
    try:
        mesh.calc_loop_triangles()
        count = len(mesh.loop_triangles)
        positions = _read(mesh.vertices, "co", len(mesh.vertices), 3, np.float64)
        triangles = _read(mesh.loop_triangles, "vertices", count, 3, np.int32)
        loops = _read(mesh.loop_triangles, "loops", count, 3, np.int64)
        material_index = _read(mesh.loop_triangles, "material_index", count, 1, np.int32)
        normals = _read(mesh.corner_normals, "vector", len(mesh.corner_normals), 3, np.float64)
        uv_maps = mesh_corner_uv(mesh, loops)
        vertex_count, loop_count = len(mesh.vertices), len(mesh.loops)
        default_uv = next((layer.name for layer in mesh.uv_layers if layer.active_render), "")
        materials = [read_material(slot.material, default_uv, warnings) for slot in evaluated.material_slots]
    finally:
        evaluated.to_mesh_clear()

    matrix = _matrix(obj.matrix_world)
    linear = matrix[:3, :3]
    with np.errstate(invalid="ignore", over="ignore"):  # NaN/Inf vertices stay NaN/Inf; core drops them
        positions = positions @ linear.T + matrix[:3, 3]
    normal_matrix = np.linalg.inv(linear).T if abs(np.linalg.det(linear)) > 1e-30 else linear
    corner_normals = (normals[loops] @ normal_matrix.T).astype(np.float32)
    if np.linalg.det(linear) < 0:
        # A mirroring transform turns the winding around; restore counter-clockwise
        # fronts so face normals still point where Blender shows them.
        order = [0, 2, 1]
        triangles = triangles[:, order]
        corner_normals = corner_normals[:, order]
        uv_maps = {name: uv[:, order] for name, uv in uv_maps.items()}
    return Mesh(name=obj.name, positions=positions, triangles=triangles, corner_normals=corner_normals,
                material_index=material_index, materials=materials, uv_maps=uv_maps,
                bake_uv_map=bake_uv_map, resolution=resolution, output=output,
                light_group=getattr(obj, "lightgroup", ""), corner_loops=loops, vertex_count=vertex_count,
                loop_count=loop_count)


def read_light(obj: bpy.types.Object) -> Light:
    """A Blender lamp in Cycles' units (energy already includes the lamp's exposure)."""
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
    result = Light(name=obj.name, kind=light.type, color=color,
                   strength=strength, position=matrix[:3, 3].copy(), direction=-axis_z,
                   group=getattr(obj, "lightgroup", ""))
    if light.type == "SPOT":
        result.spot_size = float(light.spot_size)
        result.spot_blend = float(light.spot_blend)
    if light.type == "AREA":
        result.area_shape = light.shape
        result.size_x = float(light.size) * scale[0]
        result.size_y = float(size_y) * scale[1]
        result.axis_x, result.axis_y = axis_x, axis_y
    return result


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
    """World radiance: colour * strength of the Background node, or its equirectangular
    Environment Texture (times strength) with the rotation of a Mapping node."""
    world = scene.world
    if world is None:
        return World()
    if not compat.uses_nodes(world):
        return World(np.array(world.color[:3], np.float64))
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


def _environment_world(node, strength: float, warnings: list[str]) -> World:
    """World from an Environment Texture node feeding the Background colour."""
    image = node.image
    pixels = _image_pixels(image, warnings) if image is not None else None
    if pixels is None:
        # Cycles shows a missing image as magenta; lighting a bake with that helps nobody.
        warnings.append("world: the environment texture has no image (or it could not be loaded); "
                        "the world is treated as black")
        return World()
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
        warnings.append("world: nothing is linked to the mapping node's vector, so the environment shows one "
                        "constant colour (as in Cycles); link a Texture Coordinate (Generated) to rotate it")
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
    return [o for o in scene.objects if o.type == "LIGHT" and not o.hide_render
            and o.data.type in {"SUN", "POINT", "SPOT", "AREA"}]


def scene_meshes(scene: bpy.types.Scene) -> list[bpy.types.Object]:
    return [o for o in scene.objects if o.type == "MESH" and not o.hide_render]
