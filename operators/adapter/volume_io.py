"""Volumes between Blender and core.volume: a Volume object's medium read through the bundled
openvdb (or a mesh's inside voxelised, for a mesh with a volume material), the baked grids
written as .vdb, and the Volume object that renders them.

Nothing of the user's is modified: the source object, its data, its material and its .vdb
file are only read. What VisiBake creates (the baked Volume object, its data and material)
carries :data:`OWNED_KEY`, and only such datablocks are ever replaced.
"""
from __future__ import annotations

import os
from dataclasses import dataclass

import bpy

import numpy as np

from ...core.errors import VolumeRefused
from ...core.volume.medium import Medium, check_density_values, check_grid_shape, make_medium
from ...core.volume.voxelise import fitted_grid, inside_fraction
from . import compat, extract

OWNED_KEY = "visibake_volume_of"
PRINCIPLED = "ShaderNodeVolumePrincipled"
# The grids each baked volume writes, and what they hold (FORMATS.md, "Rendering baked light").
OUTPUT_GRIDS = {
    "scattered": "in-scattered radiance S, direct plus indirect (W m^-2 sr^-1)",
    "direct": "in-scattered radiance of the light that reached the voxel without scattering",
    "indirect": "in-scattered radiance of the bounces",
    "emission": "what the baked volume emits per unit length: sigma_s S plus the medium's own emission",
    "density": "the medium's density, as the bake read it (resampled to the bake's grid)",
}


def is_volume_target(obj) -> bool:
    return obj.type == "VOLUME" and obj.get(OWNED_KEY) is None


def _material_output(obj):
    """The active Material Output (target All or Cycles) of the object's active material, or None."""
    material = obj.active_material
    if material is None or not compat.uses_nodes(material):
        return None
    for node in material.node_tree.nodes:
        if node.bl_idname == "ShaderNodeOutputMaterial" and node.is_active_output and \
                node.target in {"ALL", "CYCLES"}:
            return node
    return None


def _principled(obj, warnings: list[str]):
    """The Principled Volume node feeding the object's material output, or None."""
    node = _material_output(obj)
    if node is None:
        return None
    socket = node.inputs.get("Volume")
    if socket is None or not socket.is_linked:
        return None
    source = socket.links[0].from_node
    if source.bl_idname != PRINCIPLED:
        warnings.append(f"volume {obj.name!r}: its material's volume shader is a {source.bl_label}, not a "
                        "Principled Volume")
        return None
    return source


def is_mesh_volume(obj) -> bool:
    """Whether ``obj`` is a mesh that Cycles fills with a Principled Volume: a MESH object (not one
    VisiBake made) whose active material's active output takes its Volume from one."""
    return obj.type == "MESH" and obj.get(OWNED_KEY) is None and _principled(obj, []) is not None


def _value(node, name: str, default, obj_name: str, warnings: list[str]):
    socket = node.inputs.get(name)
    if socket is None:
        return default
    if socket.is_linked:
        warnings.append(f"volume {obj_name!r}: its Principled Volume's {name} is driven by nodes; its own value "
                        "was used")
    value = socket.default_value
    if isinstance(value, str):
        return value
    return np.array(value, np.float64) if hasattr(value, "__len__") else float(value)


def _index_to_local(transform) -> np.ndarray:
    """(4, 4) float64 the affine map of an openvdb linear transform (voxel index to object space)."""
    origin = np.array(transform.indexToWorld((0.0, 0.0, 0.0)), np.float64)
    matrix = np.eye(4)
    for axis in range(3):
        unit = [0.0, 0.0, 0.0]
        unit[axis] = 1.0
        matrix[:3, axis] = np.array(transform.indexToWorld(tuple(unit)), np.float64) - origin
    matrix[:3, 3] = origin
    return matrix


def _downsample(dense: np.ndarray, factor: int) -> np.ndarray:
    """Box average of ``factor``^3 voxels (the grid padded with zeros to a multiple of it)."""
    if factor <= 1:
        return dense
    shape = [-(-n // factor) * factor for n in dense.shape]
    padded = np.zeros(shape, np.float32)
    padded[:dense.shape[0], :dense.shape[1], :dense.shape[2]] = dense
    blocks = padded.reshape(shape[0] // factor, factor, shape[1] // factor, factor, shape[2] // factor, factor)
    return blocks.mean(axis=(1, 3, 5), dtype=np.float64).astype(np.float32)


@dataclass
class _PrincipledVolume:
    """A Principled Volume node's inputs, as read (the node's own values)."""

    density_name: str
    multiplier: float
    color: np.ndarray
    absorption: np.ndarray
    emission_strength: float
    emission_color: np.ndarray


def _read_principled(obj, node, warnings: list[str]) -> _PrincipledVolume:
    """The inputs of the Principled Volume ``node`` of ``obj``, with a warning for each that
    VisiBake leaves out or reads differently from Cycles."""
    density_name = _value(node, "Density Attribute", "density", obj.name, warnings) or "density"
    multiplier = max(float(_value(node, "Density", 1.0, obj.name, warnings)), 0.0)
    color = np.clip(np.asarray(_value(node, "Color", (0.5, 0.5, 0.5, 1.0), obj.name, warnings))[:3], 0.0, None)
    absorption = np.asarray(_value(node, "Absorption Color", (0.0, 0.0, 0.0, 1.0), obj.name, warnings))[:3]
    emission_strength = float(_value(node, "Emission Strength", 0.0, obj.name, warnings))
    emission_color = np.asarray(_value(node, "Emission Color", (1.0, 1.0, 1.0, 1.0), obj.name, warnings))[:3]
    if float(_value(node, "Anisotropy", 0.0, obj.name, warnings)) != 0.0:
        warnings.append(f"volume {obj.name!r}: its anisotropy was baked as isotropic scattering")
    if float(_value(node, "Blackbody Intensity", 0.0, obj.name, warnings)) > 0.0:
        warnings.append(f"volume {obj.name!r}: its blackbody (temperature) emission was left out")
    color_attribute = _value(node, "Color Attribute", "", obj.name, warnings)
    if color_attribute:
        warnings.append(f"volume {obj.name!r}: its colour grid {color_attribute!r} was left out; the node's colour "
                        "was used")
    return _PrincipledVolume(density_name, multiplier, color, absorption, emission_strength, emission_color)


def _principled_medium(obj, shader: _PrincipledVolume, warnings: list[str]):
    """(extinction per unit density, albedo (3,), emission (3,) or None) of a Principled Volume."""
    if np.any(shader.absorption > 0):
        warnings.append(f"volume {obj.name!r}: its absorption colour makes the extinction differ per channel; "
                        "the channels' mean was used")
    color = shader.color
    extinction_rgb = color + np.clip(1.0 - color, 0.0, None) * np.clip(
        1.0 - np.sqrt(np.clip(shader.absorption, 0, None)), 0.0, None)
    extinction = float(extinction_rgb.mean()) * shader.multiplier
    albedo = np.divide(color * shader.multiplier, extinction, out=np.zeros(3), where=extinction > 0)
    emission = shader.emission_strength * shader.emission_color if shader.emission_strength > 0 else None
    return extinction, albedo, emission


def read_medium(obj, resolution: int, warnings: list[str]) -> tuple[Medium, np.ndarray]:
    """The medium of a Volume object at the current frame, at most ``resolution`` voxels per side.

    Returns the medium (in world space) and its index-to-object matrix (4, 4) float64, which the
    baked grids are written with. Raises VolumeRefused for a missing file, a missing grid, a
    grid too large to read or unusable values.
    """
    vdb = compat.openvdb()
    volume = obj.data
    volume.grids.load()
    path = bpy.path.abspath(volume.grids.frame_filepath or volume.filepath)
    if not path or not os.path.isfile(path):
        raise VolumeRefused(f"volume {obj.name!r}: its file {volume.filepath!r} was not found")
    node = _principled(obj, warnings)
    if node is None:
        raise VolumeRefused(f"volume {obj.name!r}: its material has no Principled Volume as the volume shader; "
                            "VisiBake reads density, colour and emission from one")
    shader = _read_principled(obj, node, warnings)
    density_name = shader.density_name
    try:
        metadata = vdb.readAllGridMetadata(path)
    except Exception as error:  # noqa: BLE001 - openvdb raises its own kinds for unreadable files
        raise VolumeRefused(f"volume {obj.name!r}: {path} is not a readable OpenVDB file ({error})") from None
    names = [grid.name for grid in metadata]
    if density_name not in names:
        raise VolumeRefused(f"volume {obj.name!r}: {os.path.basename(path)} has no {density_name!r} grid "
                            f"(it has {', '.join(map(repr, names)) or 'none'})")
    info = dict(metadata[names.index(density_name)].metadata)
    if "file_bbox_min" not in info or info.get("file_voxel_count", 1) == 0:
        raise VolumeRefused(f"volume {obj.name!r}: its {density_name!r} grid is empty; there is nothing to light")
    low = np.array(info["file_bbox_min"], np.int64)
    shape = check_grid_shape(obj.name, np.array(info["file_bbox_max"], np.int64) - low + 1)
    def damaged(error: Exception) -> VolumeRefused:
        # A truncated or damaged file: its metadata read, its voxels do not ("Stream failure
        # reading the size of a blosc chunk").
        return VolumeRefused(f"volume {obj.name!r}: the {density_name!r} grid of {path} cannot be read; the file "
                             f"is damaged or cut short ({str(error).strip() or type(error).__name__})")

    try:
        grid = vdb.read(path, density_name)
    except (RuntimeError, OSError, ValueError) as error:
        raise damaged(error) from None
    if not isinstance(grid, vdb.FloatGrid):
        raise VolumeRefused(f"volume {obj.name!r}: its {density_name!r} grid holds {type(grid).__name__} values, "
                            "not floats")
    expected_voxels = info.get("file_voxel_count")
    if isinstance(expected_voxels, int) and grid.activeVoxelCount() != expected_voxels:
        # A file cut after its grid's header reads as a grid with fewer voxels, or none.
        raise damaged(RuntimeError(f"{grid.activeVoxelCount():,} voxels read of the {expected_voxels:,} it "
                                   "says it holds"))
    dense = np.zeros(shape, np.float32)
    try:
        grid.copyToArray(dense, ijk=tuple(int(v) for v in low))
    except (RuntimeError, OSError, ValueError) as error:
        raise damaged(error) from None
    # The grid as the file holds it: the box average below would hide a negative voxel.
    check_density_values(obj.name, dense)
    factor = max(1, -(-max(shape) // max(int(resolution), 1)))
    dense = _downsample(dense, factor)
    # Index t of the bake's grid is native index factor t + (factor - 1) / 2 + low.
    to_native = np.diag([float(factor)] * 3 + [1.0])
    to_native[:3, 3] = low + (factor - 1) / 2.0
    index_to_local = _index_to_local(grid.transform) @ to_native
    extinction, albedo, emission = _principled_medium(obj, shader, warnings)
    if emission is not None:
        warnings.append(f"volume {obj.name!r}: its emission was baked where its density is above zero only")
    world = np.array(obj.matrix_world, np.float64) @ index_to_local
    medium = make_medium(obj.name, dense, world, extinction, albedo, emission)
    return medium, index_to_local


def read_mesh_medium(obj, resolution: int, warnings: list[str]) -> tuple[Medium, np.ndarray]:
    """The medium Cycles renders inside a mesh whose material has a Principled Volume, at most
    ``resolution`` voxels per side.

    The mesh is read with its modifiers (the viewport's evaluation) and voxelised in object
    space on a grid fitted to its bounds (core.volume.voxelise): each voxel's density is the
    fraction of it inside the mesh. A mesh has no density grid, so Cycles' density is the
    node's Density throughout the inside (its Density Attribute finds no grid); as for a Volume
    object, that Density is the medium's extinction and the node's colour its albedo.

    Returns the medium (in world space) and its index-to-object matrix (4, 4) float64, which the
    baked grids are written with. Raises VolumeRefused for a material without a Principled
    Volume, a mesh without faces, or one that encloses nothing (it must be closed).
    """
    node = _principled(obj, warnings)
    if node is None:
        raise VolumeRefused(f"volume {obj.name!r}: its material has no Principled Volume as the volume shader; "
                            "VisiBake reads density, colour and emission from one")
    shader = _read_principled(obj, node, warnings)
    output = _material_output(obj)
    surface = output.inputs.get("Surface") if output is not None else None
    if surface is not None and surface.is_linked:
        warnings.append(f"volume {obj.name!r}: its material has a Surface shader too; only the medium inside the "
                        "mesh was baked, not the surface (which in Cycles also shades the mesh and can hide or "
                        "shadow the medium)")
    others = sorted({slot.material.name for slot in obj.material_slots
                     if slot.material is not None and slot.material != obj.active_material})
    if others:
        warnings.append(f"volume {obj.name!r}: only its active material {obj.active_material.name!r} was read; its "
                        f"other materials ({', '.join(map(repr, others))}) were not")
    extract._viewport_difference(obj, warnings)
    depsgraph = bpy.context.evaluated_depsgraph_get()
    evaluated = obj.evaluated_get(depsgraph)
    if not evaluated.is_evaluated and any(m.show_render for m in obj.modifiers):
        warnings.append(f"object {obj.name!r} is hidden in the viewport, so its modifiers are not evaluated; "
                        "VisiBake reads it without them (Cycles renders them): show it to bake them")
    mesh = evaluated.to_mesh()
    try:
        mesh.calc_loop_triangles()
        read = extract.read_triangles(mesh)
        count, positions, triangles = len(read.triangles), read.positions, read.triangles
        has_density_attribute = mesh.attributes.get(shader.density_name) is not None
    finally:
        evaluated.to_mesh_clear()
    if count == 0:
        raise VolumeRefused(f"volume {obj.name!r}: its mesh has no faces; a mesh volume fills the inside of a "
                            "closed mesh")
    if has_density_attribute:
        # Cycles finds it, but reads a volume's attribute from grids only: per vertex or face it
        # reads 0 (kernel/geom/volume.h), which empties the medium there.
        warnings.append(f"volume {obj.name!r}: its mesh has a {shader.density_name!r} attribute, the Principled "
                        "Volume's Density Attribute; VisiBake used the node's Density throughout the inside, but "
                        "Cycles may read the attribute as zero density: rename it or clear the Density Attribute")
    used = positions[np.unique(triangles)]
    used = used[np.all(np.isfinite(used), axis=1)]
    if len(used) == 0 or not float(np.ptp(used, axis=0).max()) > 0:
        raise VolumeRefused(f"volume {obj.name!r}: its mesh encloses nothing (its faces have no extent); a mesh "
                            "volume fills the inside of a closed mesh")
    shape, index_to_local = fitted_grid(used.min(axis=0), used.max(axis=0), max(int(resolution), 1))
    check_grid_shape(obj.name, shape)
    density = inside_fraction(positions, triangles, index_to_local, shape)
    if not density.any():
        raise VolumeRefused(f"volume {obj.name!r}: its mesh encloses nothing (a flat or open mesh, such as a "
                            "plane); the mesh must be closed for Cycles and VisiBake to fill it with its volume")
    extinction, albedo, emission = _principled_medium(obj, shader, warnings)
    if emission is not None:
        # Cycles emits throughout the inside; a voxel partly inside emits that part.
        emission = density[..., None] * emission.astype(np.float32)
    world = np.array(obj.matrix_world, np.float64) @ index_to_local
    medium = make_medium(obj.name, density, world, extinction, albedo, emission)
    return medium, index_to_local


def write_grids(vdb, path: str, grids: dict, index_to_local: np.ndarray) -> None:
    """Write ``grids`` {name: (nx, ny, nz) or (nx, ny, nz, 3) float32} to one .vdb at ``path``."""
    transform = vdb.createLinearTransform(np.asarray(index_to_local, np.float64).T.tolist())
    written = []
    for name, values in grids.items():
        values = np.ascontiguousarray(values, np.float32)
        if not np.all(np.isfinite(values)):
            raise RuntimeError(f"the {name!r} grid holds non-finite values (a bug)")
        grid = vdb.Vec3SGrid() if values.ndim == 4 else vdb.FloatGrid()
        grid.copyFromArray(values, ijk=(0, 0, 0))
        grid.name = name
        grid.transform = transform
        written.append(grid)
    vdb.write(path, grids=written)


def check_grids(vdb, path: str) -> None:
    """Raise unless ``path`` reads back as a whole .vdb (every grid's values): OpenVDB's
    writer says nothing when the disk fills, and leaves an empty or cut file."""
    grids, _ = vdb.readAll(path)
    if not grids:
        raise OSError(f"{path} holds no grid")


def baked_object_name(source_name: str) -> str:
    return f"{source_name} (VisiBake)"


def make_baked_object(source, path: str, extinction: float):
    """The Volume object that renders a baked volume: the file at ``path`` (grids ``density``
    and ``emission``), with an emission-absorption material, at the source's place. An
    existing object of that name is replaced only if VisiBake made it."""
    name = baked_object_name(source.name)
    existing = bpy.data.objects.get(name)
    if existing is not None and existing.get(OWNED_KEY) != source.name:
        raise VolumeRefused(f"an object named {name!r} exists and is not VisiBake's; rename it to bake "
                            f"{source.name!r}")
    if existing is not None:
        remove_baked_object(existing)
    volume = bpy.data.volumes.new(name)
    volume.filepath = path
    volume[OWNED_KEY] = source.name
    material = bpy.data.materials.new(name)
    material[OWNED_KEY] = source.name
    _emission_absorption(material, extinction)
    volume.materials.append(material)
    obj = bpy.data.objects.new(name, volume)
    obj[OWNED_KEY] = source.name
    obj.matrix_world = source.matrix_world
    collections = source.users_collection or (bpy.context.scene.collection,)
    collections[0].objects.link(obj)
    return obj


def _emission_absorption(material, extinction: float) -> None:
    """Absorption from the density grid times ``extinction``, emission from the emission grid
    (both Attribute nodes): no scattering, so Cycles and EEVEE render it as baked."""
    compat.ensure_node_tree(material)
    tree = material.node_tree
    tree.nodes.clear()
    output = tree.nodes.new("ShaderNodeOutputMaterial")
    density = tree.nodes.new("ShaderNodeAttribute")
    density.attribute_name = "density"
    scale = tree.nodes.new("ShaderNodeMath")
    scale.operation = "MULTIPLY"
    scale.inputs[1].default_value = float(extinction)
    absorb = tree.nodes.new("ShaderNodeVolumeAbsorption")
    absorb.inputs["Color"].default_value = (0.0, 0.0, 0.0, 1.0)
    glow = tree.nodes.new("ShaderNodeAttribute")
    glow.attribute_name = "emission"
    emit = tree.nodes.new("ShaderNodeEmission")
    emit.inputs["Strength"].default_value = 1.0
    add = tree.nodes.new("ShaderNodeAddShader")
    tree.links.new(density.outputs["Fac"], scale.inputs[0])
    tree.links.new(scale.outputs[0], absorb.inputs["Density"])
    tree.links.new(glow.outputs["Color"], emit.inputs["Color"])
    tree.links.new(absorb.outputs[0], add.inputs[0])
    tree.links.new(emit.outputs[0], add.inputs[1])
    tree.links.new(add.outputs[0], output.inputs["Volume"])


def remove_baked_object(obj) -> None:
    """Remove a Volume object VisiBake made, with its data and material."""
    volume = obj.data
    materials = [m for m in volume.materials if m is not None and m.get(OWNED_KEY) is not None]
    bpy.data.objects.remove(obj)
    if volume.users == 0:
        bpy.data.volumes.remove(volume)
    for material in materials:
        if material.users == 0:
            bpy.data.materials.remove(material)
