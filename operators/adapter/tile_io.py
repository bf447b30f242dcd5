"""The Blender side of the appearance tools (core.appearance): a tile object or collection read
into a core Tile, and the BRDF job that simulates it and writes its table."""
from __future__ import annotations

import json
import os
import time

import bpy

import numpy as np

from ...core.appearance import gonio
from ...core.appearance.tile import Tile
from ...core.errors import AppearanceRefused, OutputRefused
from . import compat
from .extract import _linked_texture, _surface_node, world_matrix

# Fresnel reflectance of Blender's default dielectric (IOR 1.5) at normal incidence.
DEFAULT_F0 = 0.04


def tile_objects(scene: bpy.types.Scene, name: str) -> list:
    """The mesh objects of the tile ``name``: an object, or every mesh in a collection (and
    its children). Refuses a name that is neither."""
    obj = scene.objects.get(name)
    if obj is not None:
        if obj.type != "MESH":
            raise AppearanceRefused(f"--tile {name!r} is a {obj.type.lower()} object; a tile is a mesh object or a "
                                    "collection of them")
        return [obj]
    collection = bpy.data.collections.get(name)
    if collection is not None:
        meshes = [o for o in collection.all_objects if o.type == "MESH"]
        if not meshes:
            raise AppearanceRefused(f"--tile {name!r}: the collection holds no mesh object")
        return meshes
    raise AppearanceRefused(f"--tile {name!r}: no object or collection of that name in the scene")


def _fresnel_average(f0: float) -> float:
    """The hemispherical average of Schlick's Fresnel term for reflectance ``f0`` at normal
    incidence: f0 + (1 - f0) / 21."""
    return f0 + (1.0 - f0) / 21.0


def micro_material(material, warnings: list[str]) -> tuple[np.ndarray, float, float]:
    """(albedo (3,), specular weight, GGX roughness) of the micro-BRDF for a Blender material.

    A Principled BSDF gives its base colour as the Lambert albedo, its roughness to the GGX
    lobe, and the lobe's weight is its dielectric layer's average reflectance (Schlick, from
    IOR and Specular IOR Level: about 0.086 at the defaults); a Diffuse BSDF is Lambert only.
    A linked image's mean colour stands for a textured base colour.
    """
    if material is None:
        return np.full(3, 0.8), 0.0, 0.5
    node = _surface_node(material) if compat.uses_nodes(material) else None
    if node is None:
        return np.array(material.diffuse_color[:3], np.float64), 0.0, 0.5
    if node.bl_idname not in {"ShaderNodeBsdfPrincipled", "ShaderNodeBsdfDiffuse"}:
        warnings.append(f"material {material.name!r}: surface shader {node.bl_idname} is not supported in a tile; "
                        "simulated as grey diffuse")
        return np.full(3, 0.8), 0.0, 0.5
    principled = node.bl_idname == "ShaderNodeBsdfPrincipled"
    socket = node.inputs["Base Color" if principled else "Color"]
    albedo = np.array(socket.default_value[:3], np.float64)
    image, _ = _linked_texture(socket)
    if image is not None and image.size[0] > 0:
        pixels = np.empty(image.size[0] * image.size[1] * image.channels, np.float32)
        image.pixels.foreach_get(pixels)
        albedo = pixels.reshape(-1, image.channels)[:, :3].mean(axis=0).astype(np.float64)
        warnings.append(f"material {material.name!r}: its base colour texture is simulated as its mean colour")
    if not principled:
        return albedo, 0.0, 0.5
    ior = float(node.inputs["IOR"].default_value)
    level = float(node.inputs["Specular IOR Level"].default_value)
    f0 = ((ior - 1.0) / (ior + 1.0)) ** 2 * 2.0 * level if ior > 0 else DEFAULT_F0
    specular = _fresnel_average(min(max(f0, 0.0), 1.0)) if level > 0 else 0.0
    if node.inputs["Metallic"].default_value > 0 or node.inputs["Transmission Weight"].default_value > 0:
        warnings.append(f"material {material.name!r}: metallic and transmission are not simulated in a tile yet")
    roughness = float(node.inputs["Roughness"].default_value)
    return albedo, specular, roughness


def read_tile(scene: bpy.types.Scene, name: str, period=None, phong=None) -> Tile:
    """The tile ``name`` (an object or a collection) in world space as a core Tile.

    period : (2,) the repeat in X and Y, or None for the bounding box in XY
    phong : (ks, exponent) for the paper's Phong micro-BRDF on every face, or None for the
        materials' own (core.appearance.tile)
    """
    warnings: list[str] = []
    depsgraph = bpy.context.evaluated_depsgraph_get()
    positions, triangles, albedo, specular, roughness, smooth, material = [], [], [], [], [], [], []
    offset = 0
    materials: dict = {}
    for obj in tile_objects(scene, name):
        evaluated = obj.evaluated_get(depsgraph)
        mesh = evaluated.to_mesh()
        try:
            mesh.calc_loop_triangles()
            count = len(mesh.vertices)
            corners = np.empty(count * 3, np.float32)
            mesh.vertices.foreach_get("co", corners)
            matrix = world_matrix(obj, evaluated)
            points = corners.reshape(-1, 3).astype(np.float64) @ matrix[:3, :3].T + matrix[:3, 3]
            faces = len(mesh.loop_triangles)
            indices = np.empty(faces * 3, np.int32)
            mesh.loop_triangles.foreach_get("vertices", indices)
            slots = np.empty(faces, np.int32)
            mesh.loop_triangles.foreach_get("material_index", slots)
            shading = np.empty(faces, bool)
            mesh.loop_triangles.foreach_get("use_smooth", shading)
            if np.linalg.det(matrix[:3, :3]) < 0:
                indices = indices.reshape(-1, 3)[:, ::-1].ravel()  # a mirroring transform turns faces inside out
            slot_materials = [slot.material for slot in obj.material_slots] or [None]
            for slot in np.unique(slots):
                chosen = slot_materials[min(int(slot), len(slot_materials) - 1)]
                key = chosen.name if chosen is not None else ""
                if key not in materials:
                    materials[key] = (len(materials), *micro_material(chosen, warnings))
                index, rgb, weight, rough = materials[key]
                rows = slots == slot
                albedo.append(np.tile(rgb, (int(rows.sum()), 1)))
                specular.append(np.full(int(rows.sum()), weight))
                roughness.append(np.full(int(rows.sum()), rough))
                material.append(np.full(int(rows.sum()), index))
                triangles.append(indices.reshape(-1, 3)[rows] + offset)
                smooth.append(shading[rows])
            positions.append(points)
            offset += count
        finally:
            evaluated.to_mesh_clear()
    if not triangles or sum(len(t) for t in triangles) == 0:
        raise AppearanceRefused(f"--tile {name!r} has no faces: give it a mesh with at least one face")
    albedo = np.concatenate(albedo)
    if np.any(albedo > 1.0) or np.any(albedo < 0.0):
        warnings.append("base colours outside [0, 1] are clipped to it in the tile")
        albedo = np.clip(albedo, 0.0, 1.0)
    specular = np.concatenate(specular)
    roughness = np.concatenate(roughness)
    exponent = 8.0
    if phong is not None:
        specular = np.full_like(specular, float(phong[0]))
        roughness = np.full_like(roughness, -1.0)
        exponent = float(phong[1])
    tile = Tile.of(np.concatenate(positions), np.concatenate(triangles), period, None, albedo, specular, roughness,
                   np.concatenate(smooth), np.concatenate(material), exponent)
    tile.warnings[:0] = warnings
    return tile


def _refuse_foreign_file(path: str, overwrite: bool) -> None:
    if os.path.lexists(path) and not overwrite:
        raise OutputRefused(f"{path} exists; VisiBake does not overwrite a file it may not have written "
                            "(remove it, choose another path, or pass --overwrite)")
    folder = os.path.dirname(path) or "."
    if not os.path.isdir(folder):
        raise OutputRefused(f"the folder {folder} does not exist")


def run_brdf(tile: Tile, out_path: str, output_format: str, lights: int, views: int, settings: gonio.GonioSettings,
             overwrite: bool = False, progress=None) -> dict:
    """Simulate the tile's BRDF on ``lights`` x ``views`` hemisphere directions and write it as
    a MERL ``.binary`` (isotropic, filled by core.appearance.merl.fill_from_samples) or a
    tabulated ``.npz`` (core.appearance.tabulated). Returns the report (a JSON-able dict)."""
    from ...core.appearance import merl, tabulated

    out_path = os.path.abspath(out_path)
    _refuse_foreign_file(out_path, overwrite)
    if not 1 <= lights <= 10_000 or not 1 <= views <= 10_000:
        raise AppearanceRefused(f"--lights and --views take 1 to 10000 directions, got {lights} and {views}")
    started = time.perf_counter()
    light_set = gonio.hemisphere_directions(lights)
    view_set = gonio.hemisphere_directions(views)
    result = gonio.simulate_brdf(tile, light_set, view_set, settings, progress)
    if progress is not None:
        progress("writing", 0.0)
    written_settings = {"directions": settings.directions, "bounces": settings.bounces,
                        "resolution": settings.resolution, "view_rays": settings.view_rays, "seed": settings.seed,
                        "lights": lights, "views": views}
    if output_format == "merl":
        pairs_light = np.repeat(result.light, len(result.view), axis=0)
        pairs_view = np.tile(result.view, (len(result.light), 1))
        table = merl.fill_from_samples(pairs_light, pairs_view, result.values.reshape(-1, 3))
        merl.write_merl(out_path, table)
    else:
        bsdf = tabulated.TabulatedBSDF(result.light.astype(np.float32), result.view.astype(np.float32),
                                       result.values.astype(np.float32),
                                       np.repeat(result.transparency[:, None], 3, axis=1).astype(np.float32),
                                       tile.period, "m", json.dumps(written_settings))
        tabulated.save_tabulated(out_path, bsdf)
    # Directional albedo per light: the reflected share, over the view set's equal-area cells.
    albedo = (result.values * result.view[None, :, 2, None]).sum(axis=1) * 2 * np.pi / len(result.view)
    return {"output": out_path, "format": output_format, "settings": written_settings,
            "samples": result.stats.get("samples"), "stats": result.stats, "warnings": result.warnings,
            "max_directional_albedo": float(albedo.max()),
            "mean_brdf": [float(x) for x in result.values.mean(axis=(0, 1))],
            "max_transparency": float(result.transparency.max(initial=0.0)),
            "seconds": round(time.perf_counter() - started, 3)}


def run_btf(tile: Tile, out_dir: str, image_format: str, image_size: int, settings: gonio.GonioSettings,
            per_pixel: int = 4, overwrite: bool = False, progress=None) -> dict:
    """Simulate the tile's BTF on the 81 x 81 directions of Bonn's UBO2003 and write it in
    the UTIA folder layout (core.appearance.btf). Returns the report (a JSON-able dict)."""
    from ...core.appearance import btf

    if not 8 <= image_size <= 4096:
        raise AppearanceRefused(f"--image-size takes 8 to 4096 pixels, got {image_size}")
    started = time.perf_counter()
    thetas, phis = btf.ubo_directions()
    directions = btf.unit_vector(thetas, phis)
    written_settings = {"directions": settings.directions, "bounces": settings.bounces,
                        "resolution": settings.resolution, "seed": settings.seed, "rays_per_pixel": per_pixel,
                        "pixel_value": "pi * radiance / sun irradiance (a white Lambert plane lit from above is 1; "
                                       "the BRDF is the value over pi cos(theta_l))"}
    try:
        writer = btf.BTFWriter(out_dir, image_format, image_size, image_size, tile.period, overwrite=overwrite,
                               settings=written_settings)
    except ValueError as error:
        raise OutputRefused(str(error)) from None
    stats = gonio.simulate_btf(tile, directions, directions, (image_size, image_size), writer.write, settings,
                               per_pixel, progress)
    manifest = writer.finish()
    return {"output": os.path.abspath(out_dir), "manifest": manifest, "format": image_format,
            "images": stats["images"], "image_size": image_size, "settings": written_settings,
            "samples": stats.get("samples"), "stats": stats, "warnings": list(tile.warnings),
            "seconds": round(time.perf_counter() - started, 3)}
