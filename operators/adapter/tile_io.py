"""The Blender side of the appearance tools (core.appearance): a tile object or collection read
into a core Tile, and the BRDF job that simulates it and writes its table."""
from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass, field

import bpy

import numpy as np

from ...core.appearance import gonio
from ...core.appearance.tile import Tile
from ...core.errors import AppearanceRefused, OutputRefused
from ...core.outputs.ownership import SIDECAR_SUFFIX, StagedWrites, is_visibakes, refuse_foreign
from . import compat
from .extract import _linked_texture, _surface_node, world_matrix
from .modal import SteppedJob

# Fresnel reflectance of Blender's default dielectric (IOR 1.5) at normal incidence.
DEFAULT_F0 = 0.04


def preferred_threads() -> int:
    """The Threads preference (0: all cores)."""
    from .volume_job import preferred_threads as threads
    return threads()


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


def micro_material(material, warnings: list[str]) -> tuple[np.ndarray, float, float, float]:
    """(albedo (3,), specular weight, GGX roughness, transmission) of the micro-BRDF for a
    Blender material.

    A Principled BSDF gives its base colour as the Lambert albedo, its roughness to the GGX
    lobe, and the lobe's weight is its dielectric layer's average reflectance (Schlick, from
    IOR and Specular IOR Level: about 0.086 at the defaults); a Diffuse BSDF is Lambert only.
    Its Transmission Weight makes the face a thin translucent sheet, a fibre's wall: that
    share of the diffuse light passes to the other side, diffusely (core.appearance.tile).
    A linked image's mean colour stands for a textured base colour.
    """
    if material is None:
        return np.full(3, 0.8), 0.0, 0.5, 0.0
    node = _surface_node(material) if compat.uses_nodes(material) else None
    if node is None:
        return np.array(material.diffuse_color[:3], np.float64), 0.0, 0.5, 0.0
    if node.bl_idname not in {"ShaderNodeBsdfPrincipled", "ShaderNodeBsdfDiffuse"}:
        warnings.append(f"material {material.name!r}: surface shader {node.bl_idname} is not supported in a tile; "
                        "simulated as grey diffuse")
        return np.full(3, 0.8), 0.0, 0.5, 0.0
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
        return albedo, 0.0, 0.5, 0.0
    ior = float(node.inputs["IOR"].default_value)
    level = float(node.inputs["Specular IOR Level"].default_value)
    f0 = ((ior - 1.0) / (ior + 1.0)) ** 2 * 2.0 * level if ior > 0 else DEFAULT_F0
    specular = _fresnel_average(min(max(f0, 0.0), 1.0)) if level > 0 else 0.0
    if node.inputs["Metallic"].default_value > 0:
        warnings.append(f"material {material.name!r}: metallic is not simulated in a tile yet (simulated as a "
                        "dielectric)")
    transmission = min(max(float(node.inputs["Transmission Weight"].default_value), 0.0), 1.0)
    if transmission > 0:
        warnings.append(f"material {material.name!r}: its transmission is simulated as a thin translucent sheet "
                        "(light passes diffusely, as through a fibre's wall, not refracted as through glass)")
    roughness = float(node.inputs["Roughness"].default_value)
    return albedo, specular, roughness, transmission


def _refuse_non_finite(object_name: str, material_name: str, albedo: np.ndarray, specular: float, roughness: float,
                       transmission: float) -> None:
    """AppearanceRefused naming the object and material whose micro-BRDF (micro_material's
    values) is not finite: a NaN would run through the whole simulation to its end."""
    values = {"base colour": albedo, "specular (from IOR and Specular IOR Level)": specular,
              "roughness": roughness, "transmission weight": transmission}
    bad = [name for name, value in values.items() if not np.all(np.isfinite(value))]
    if bad:
        raise AppearanceRefused(f"tile object {object_name!r}, material {material_name or '(none)'!r}: its "
                                f"{', '.join(bad)} {'is' if len(bad) == 1 else 'are'} not a finite number "
                                "(NaN or infinite); set a number and simulate again")


def read_tile(scene: bpy.types.Scene, name: str, period=None, phong=None) -> Tile:
    """The tile ``name`` (an object or a collection) in world space as a core Tile.

    period : (2,) the repeat in X and Y, or None for the bounding box in XY
    phong : (ks, exponent) for the paper's Phong micro-BRDF on every face, or None for the
        materials' own (core.appearance.tile)
    """
    warnings: list[str] = []
    depsgraph = bpy.context.evaluated_depsgraph_get()
    positions, triangles, albedo, specular, roughness, smooth, material, normals = [], [], [], [], [], [], [], []
    transmission = []
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
            # The corner normals Cycles shades with (smooth, sharp edges, custom normals), to world space.
            split = np.empty(faces * 9, np.float32)
            mesh.loop_triangles.foreach_get("split_normals", split)
            inverse_transpose = np.linalg.inv(matrix[:3, :3]).T
            split = split.reshape(-1, 3).astype(np.float64) @ inverse_transpose.T
            split /= np.maximum(np.linalg.norm(split, axis=1, keepdims=True), 1e-300)
            split = split.reshape(-1, 3, 3)
            if np.linalg.det(matrix[:3, :3]) < 0:
                # A mirroring transform turns faces inside out.
                indices = indices.reshape(-1, 3)[:, ::-1].ravel()
                split = split[:, ::-1]
            slot_materials = [slot.material for slot in obj.material_slots] or [None]
            for slot in np.unique(slots):
                chosen = slot_materials[min(int(slot), len(slot_materials) - 1)]
                key = chosen.name if chosen is not None else ""
                if key not in materials:
                    materials[key] = (len(materials), *micro_material(chosen, warnings))
                    _refuse_non_finite(obj.name, key, *materials[key][1:])
                index, rgb, weight, rough, passed = materials[key]
                rows = slots == slot
                albedo.append(np.tile(rgb, (int(rows.sum()), 1)))
                specular.append(np.full(int(rows.sum()), weight))
                roughness.append(np.full(int(rows.sum()), rough))
                transmission.append(np.full(int(rows.sum()), passed))
                material.append(np.full(int(rows.sum()), index))
                triangles.append(indices.reshape(-1, 3)[rows] + offset)
                smooth.append(shading[rows])
                normals.append(split[rows])
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
                   np.concatenate(smooth), np.concatenate(material), exponent, np.concatenate(normals),
                   np.concatenate(transmission))
    tile.warnings[:0] = warnings
    return tile


# The most (light, view) pairs the Principled fit takes.
FIT_PAIRS = 2500
# merl: isotropic, hemisphere; table: light x view over the hemisphere; bsdf: over the sphere.
OUTPUT_FORMATS = ("merl", "table", "bsdf")


def directional_shares(result: gonio.BRDFSamples, sphere: bool) -> tuple[np.ndarray, np.ndarray]:
    """(reflected, transmitted) (L, 3) float64: the share of each light's power the tile sends
    to the light's side and, diffusely, to the other (the straight-through transparency
    apart), integrated over the view set's equal-area cells (2 pi / V on the hemisphere, 4 pi
    / V on the sphere)."""
    cell = (4 if sphere else 2) * np.pi / len(result.view)
    projected = result.values * np.abs(result.view[None, :, 2, None]) * cell
    same_side = (np.sign(result.light[:, None, 2]) == np.sign(result.view[None, :, 2]))[..., None]
    return (projected * same_side).sum(axis=1), (projected * ~same_side).sum(axis=1)
# Beside each file VisiBake writes: its report, which also marks the file as VisiBake's to replace.
SIDECAR = SIDECAR_SUFFIX


def _refuse_foreign_file(path: str, overwrite: bool) -> None:
    """The rule of core.outputs.ownership, and one exception: ``overwrite`` lets the file the
    user named (``--out FILE``) be replaced. Its report beside it is never written over a file
    VisiBake did not write, with or without ``overwrite``."""
    if os.path.lexists(path) and not overwrite and not is_visibakes(path):
        raise OutputRefused(f"{path} exists and VisiBake did not write it; VisiBake does not overwrite it (remove "
                            "it, choose another path, or pass --overwrite)")
    if os.path.lexists(path) and not os.path.isfile(path):
        raise OutputRefused(f"{path} is not a regular file; VisiBake does not replace it")
    refuse_foreign([path + SIDECAR], "its report goes there; remove or rename it, or choose another path")
    folder = os.path.dirname(path) or "."
    if not os.path.isdir(folder):
        raise OutputRefused(f"the folder {folder} does not exist")


@dataclass
class BRDFOutcome:
    """What a BRDF run wrote: the report (``report["files"]``), and how to take it back."""

    report: dict
    files: StagedWrites = field(default_factory=StagedWrites)

    def rollback(self) -> None:
        self.files.rollback()


class _TileJob(SteppedJob):
    """A tile's simulation as ModalBake's steps: ``read`` (main thread: the scene), ``compute``
    (a worker thread), ``finish`` (main thread: files); ``abort`` takes back what was written."""

    needs_main_thread = False

    def modal_steps(self) -> list:
        """(name, step, on a worker thread) for ModalBake."""
        return [("read", self.read, False), ("compute", self.compute, True), ("finish", self.finish, False)]


class BRDFJob(_TileJob):
    """Simulate a tile's BSDF on ``lights`` x ``views`` directions and write it as a MERL
    ``.binary`` (isotropic, filled by core.appearance.merl.fill_from_samples), or a tabulated
    ``.npz`` (core.appearance.tabulated) over the hemisphere ("table") or the whole sphere
    ("bsdf": lights and views below the tile too, its transmission), with its report beside it
    (FILE.visibake.json).

    ``tile`` is a core Tile, or a callable reading it on the main thread (the panel reads the
    scene there). ``progress(stage, fraction)`` may raise core.errors.Cancelled.
    """

    def __init__(self, tile, out_path: str, output_format: str, lights: int, views: int,
                 settings: gonio.GonioSettings, overwrite: bool = False, progress=None, make_folder: bool = False,
                 fit_material: bool = True, cluster=None):
        """make_folder: create the output's folder when it is missing (the panel's default
        folder beside the .blend); it goes again if the run fails. fit_material: fit Blender's
        Principled BSDF to the samples (core.appearance.fit), for the report and make_material.
        cluster: core.distributed.engine.ClusterOptions, or None: simulate the light batches
        in parts on a Dask cluster (the samples are the same bits)."""
        self.cluster = cluster
        self.make_folder = make_folder
        self.fit_material = fit_material
        self.tile_source = tile
        self.out_path = os.path.abspath(out_path)
        self.output_format = output_format
        self.lights, self.views = int(lights), int(views)
        self.settings = settings
        self.overwrite = overwrite
        self.progress = progress
        self.started = time.perf_counter()
        self.outcome = BRDFOutcome({"command": "brdf", "files": [], "warnings": []})

    def abort(self) -> None:
        self.outcome.rollback()

    def read(self) -> None:
        """Main thread: the tile (a callable reads it from the scene, and may refuse first)."""
        self.tile = self.tile_source() if callable(self.tile_source) else self.tile_source
        folder = os.path.dirname(self.out_path)
        if self.make_folder and not os.path.isdir(folder):
            if os.path.lexists(folder):
                raise OutputRefused(f"{folder} is not a folder")
        else:
            _refuse_foreign_file(self.out_path, self.overwrite)
        if self.output_format not in OUTPUT_FORMATS:
            raise AppearanceRefused(f"unknown BRDF format {self.output_format!r}: use {', '.join(OUTPUT_FORMATS)}")
        if not 1 <= self.lights <= 10_000 or not 1 <= self.views <= 10_000:
            raise AppearanceRefused(f"light and view directions take 1 to 10000 each, got {self.lights} and "
                                    f"{self.views}")
        self.settings.check()

    def direction_sets(self) -> tuple[np.ndarray, np.ndarray]:
        """(lights (L, 3), views (V, 3)) float64 unit: the sphere for a BSDF; for a MERL table,
        sets whose pairs fill its specular peak (core.appearance.merl.merl_direction_sets);
        else the hemisphere."""
        if self.output_format == "bsdf":
            return gonio.sphere_directions(self.lights), gonio.sphere_directions(self.views)
        if self.output_format == "merl":
            from ...core.appearance import merl
            return merl.merl_direction_sets(self.lights, self.views, seed=self.settings.seed)
        return gonio.hemisphere_directions(self.lights), gonio.hemisphere_directions(self.views)

    def simulate(self, light_set: np.ndarray, view_set: np.ndarray) -> gonio.BRDFSamples:
        """The samples, in this process or in parts on the cluster."""
        if self.cluster is None:
            return gonio.simulate_brdf(self.tile, light_set, view_set, self.settings, self.progress)
        from dataclasses import replace

        from ...core.distributed.engine import run_in_parts

        def parts_of(parts, threads):
            settings = replace(self.settings, threads=threads)
            return [(self.tile, light_set, view_set, settings, index, parts) for index in range(parts)]

        done, parts = run_in_parts(self.cluster, "brdf_part", parts_of, self.settings.threads, self.progress, "lights")
        self.outcome.report["split"] = {"parts": parts, "cluster": self.cluster.describe()}
        return gonio.join_brdf_parts(done)

    def compute(self) -> None:
        light_set, view_set = self.direction_sets()
        self.result = self.simulate(light_set, view_set)
        if self.progress is not None:
            self.progress("writing", 0.0)
        result = self.result
        if self.output_format != "bsdf" and (self.tile.translucent or result.transparency.max(initial=0.0) > 0.001):
            result.warnings.append("the tile lets light through (translucent faces or gaps): --format bsdf (BSDF "
                                   "(Sphere) in the panel) samples the whole sphere, its transmission included")
        pairs_light = np.repeat(result.light, len(result.view), axis=0)
        pairs_view = np.tile(result.view, (len(result.light), 1))
        if self.output_format == "merl":
            from ...core.appearance import merl
            self.table = merl.fill_from_samples(pairs_light, pairs_view, result.values.reshape(-1, 3))
        self.fit = None
        # The Principled fit models reflection: the pairs with the light and the view above.
        lit = (pairs_light[:, 2] > 0) & (pairs_view[:, 2] > 0)
        if self.fit_material and np.any(lit):
            from ...core.appearance.fit import fit_principled
            if self.progress is not None:
                self.progress("fitting a Principled BSDF", 0.0)
            # At most FIT_PAIRS pairs, every k-th (the fit's cost grows with them, its answer hardly).
            rows = np.nonzero(lit)[0]
            rows = rows[::max(1, len(rows) // FIT_PAIRS)]
            # Light through the gaps passes straight, not refracted: the material mixes in a
            # Transparent BSDF of that share, and the fitted surface is what the rest reflects.
            self.gaps = float(result.transparency[result.light[:, 2] > 0].mean())
            solid = max(1.0 - self.gaps, 1e-3)
            self.fit = fit_principled(pairs_light[rows], pairs_view[rows],
                                      result.values.reshape(-1, 3)[rows] / solid)

    def finish(self) -> BRDFOutcome:
        from ...core.appearance import merl, tabulated

        settings, result = self.settings, self.result
        written_settings = {"directions": settings.directions, "bounces": settings.bounces,
                            "resolution": settings.resolution, "view_rays": settings.view_rays,
                            "seed": settings.seed, "lights": self.lights, "views": self.views}
        folder = os.path.dirname(self.out_path)
        staged = self.outcome.files
        staged.root = folder
        if self.make_folder and not os.path.isdir(folder):
            staged.make_folder(folder)
        # The file and its report are both written whole before either is renamed into place
        # (the report's block inside the file's): a full disk leaves an earlier pair as it was.
        with staged.staged(self.out_path) as temporary:
            if self.output_format == "merl":
                merl.write_merl(temporary, self.table)
            else:  # "table" and "bsdf"
                bsdf = tabulated.TabulatedBSDF(result.light.astype(np.float32), result.view.astype(np.float32),
                                               result.values.astype(np.float32),
                                               np.repeat(result.transparency[:, None], 3, axis=1).astype(np.float32),
                                               self.tile.period, "m", json.dumps(written_settings))
                tabulated.save_tabulated(temporary, bsdf)
            self._write_report(result, written_settings)
        return self.outcome

    def _write_report(self, result, written_settings: dict) -> None:
        """The report, beside the file as FILE.visibake.json (which marks the file as VisiBake's)."""
        reflected, transmitted = directional_shares(result, self.output_format == "bsdf")
        report = self.outcome.report
        report.update({"output": self.out_path, "format": self.output_format, "settings": written_settings,
                       "samples": result.stats.get("samples"), "stats": result.stats,
                       "max_directional_albedo": float(reflected.max()),
                       "max_directional_transmittance": float(transmitted.max(initial=0.0)),
                       "mean_brdf": [float(x) for x in result.values.mean(axis=(0, 1))],
                       "max_transparency": float(result.transparency.max(initial=0.0)),
                       "seconds": round(time.perf_counter() - self.started, 3)})
        report["warnings"].extend(result.warnings)
        if self.fit is not None:
            fitted = self.fit
            report["principled_fit"] = {
                "model": fitted.model, "relative_rmse": float(fitted.rmse),
                "per_channel_rmse": [float(x) for x in fitted.per_channel_rmse],
                "base_color": [float(x) for x in fitted.base_color], "roughness": float(fitted.roughness),
                "specular_ior_level": float(fitted.specular_ior_level), "ior": float(fitted.ior),
                "anisotropic": float(fitted.anisotropic), "anisotropic_rotation": float(fitted.anisotropic_rotation),
                "sheen_weight": float(fitted.sheen_weight), "sheen_roughness": float(fitted.sheen_roughness),
                "sheen_tint": [float(x) for x in fitted.sheen_tint],
                "transmission_weight": float(fitted.transmission_weight), "metallic": float(fitted.metallic),
                "diffuse_roughness": float(fitted.diffuse_roughness),
                "transparency": self.gaps}
            if fitted.diffuse_roughness > 0 and bpy.app.version < (4, 3, 0):
                report["warnings"].append(
                    f"the fit uses Diffuse Roughness {fitted.diffuse_roughness:.2f}, which this Blender's Principled "
                    "BSDF does not have (4.3 and later do): a material made here has plain Lambert diffuse")
            if self.output_format == "bsdf" and np.any(result.light[:, 2] > 0):
                # What passes diffusely, as a Translucent BSDF's colour: the transmittance of
                # the lights from above (a Lambert sheet's f_t = colour / pi sends colour).
                colour = transmitted[result.light[:, 2] > 0].mean(axis=0)
                report["principled_fit"]["translucent_color"] = [float(x) for x in colour]
        report["files"] = [self.out_path, self.out_path + SIDECAR]
        with self.outcome.files.staged(self.out_path + SIDECAR) as temporary:
            with open(temporary, "w", encoding="utf-8") as handle:
                json.dump(report, handle, indent=1, default=float)


def run_brdf(tile: Tile, out_path: str, output_format: str, lights: int, views: int, settings: gonio.GonioSettings,
             overwrite: bool = False, progress=None, cluster=None) -> dict:
    """:class:`BRDFJob` at once (the command line); returns its report."""
    return BRDFJob(tile, out_path, output_format, lights, views, settings, overwrite, progress,
                   cluster=cluster).run().report


class BTFJob(_TileJob):
    """Simulate the tile's BTF on the 81 x 81 directions of Bonn's UBO2003 and write it in the
    UTIA folder layout (core.appearance.btf), as ModalBake's steps or at once (:meth:`run`).

    ``tile`` is a core Tile, or a callable reading it on the main thread. An error or a cancel
    leaves no half BTF behind (core.appearance.btf.BTFWriter.abort).
    """

    def __init__(self, tile, out_dir: str, image_format: str, image_size: int, settings: gonio.GonioSettings,
                 per_pixel: int = 4, overwrite: bool = False, progress=None, cluster=None):
        """cluster: core.distributed.engine.ClusterOptions, or None: simulate the light batches
        in parts on a Dask cluster, each writing its images into the folder (the same bits)."""
        self.cluster = cluster
        self.tile_source = tile
        self.out_dir = os.path.abspath(out_dir)
        self.image_format, self.image_size, self.per_pixel = image_format, int(image_size), int(per_pixel)
        self.settings = settings
        self.overwrite = overwrite
        self.progress = progress
        self.writer = None
        self.started = time.perf_counter()

    def abort(self) -> None:
        if self.writer is not None:
            self.writer.abort()

    def read(self) -> None:
        """Main thread: the tile, the checks, and the writer (which claims the folder)."""
        from ...core.appearance import btf

        self.tile = self.tile_source() if callable(self.tile_source) else self.tile_source
        if not 8 <= self.image_size <= 4096:
            raise AppearanceRefused(f"--image-size takes 8 to 4096 pixels, got {self.image_size}")
        if self.image_format not in ("exr", "png"):
            raise AppearanceRefused(f"unknown BTF image format {self.image_format!r}: use exr or png")
        self.settings.check()
        self.written_settings = {
            "directions": self.settings.directions, "bounces": self.settings.bounces,
            "resolution": self.settings.resolution, "seed": self.settings.seed, "rays_per_pixel": self.per_pixel,
            "pixel_value": "pi * radiance / sun irradiance (a white Lambert plane lit from above is 1; the BRDF is "
                           "the value over pi cos(theta_l))"}
        try:
            self.writer = btf.BTFWriter(self.out_dir, self.image_format, self.image_size, self.image_size,
                                        self.tile.period, overwrite=self.overwrite, settings=self.written_settings)
        except ValueError as error:
            raise OutputRefused(str(error)) from None

    def compute(self) -> None:
        from ...core.appearance import btf

        thetas, phis = btf.ubo_directions()
        directions = btf.unit_vector(thetas, phis)
        size = (self.image_size, self.image_size)
        if self.cluster is None:
            self.stats = gonio.simulate_btf(self.tile, directions, directions, size, self.writer.write, self.settings,
                                            self.per_pixel, self.progress)
            return
        from dataclasses import replace

        from ...core.distributed.engine import run_in_parts

        def parts_of(parts, threads):
            settings = replace(self.settings, threads=threads)
            return [(self.tile, directions, directions, size, settings, self.per_pixel, self.writer.folder,
                     self.image_format, index, parts) for index in range(parts)]

        done, parts = run_in_parts(self.cluster, "btf_part", parts_of, self.settings.threads, self.progress, "lights")
        for part in done:
            self.writer.adopt(part["written"])
        self.stats = dict(done[0]["stats"], images=sum(part["stats"]["images"] for part in done),
                          parts=[part["stats"] for part in done])
        self.split = {"parts": parts, "cluster": self.cluster.describe()}

    def finish(self) -> BRDFOutcome:
        manifest = self.writer.finish()
        stats = self.stats
        return BRDFOutcome({
            "command": "btf", "output": self.out_dir, "manifest": manifest, "format": self.image_format,
            "images": stats["images"], "image_size": self.image_size, "settings": self.written_settings,
            "samples": stats.get("samples"), "stats": stats, "warnings": list(self.tile.warnings),
            "seconds": round(time.perf_counter() - self.started, 3),
            **({"split": self.split} if getattr(self, "split", None) else {})})


def run_btf(tile: Tile, out_dir: str, image_format: str, image_size: int, settings: gonio.GonioSettings,
            per_pixel: int = 4, overwrite: bool = False, progress=None, cluster=None) -> dict:
    """:class:`BTFJob` at once (the command line); returns its report (a JSON-able dict)."""
    return BTFJob(tile, out_dir, image_format, image_size, settings, per_pixel, overwrite, progress,
                  cluster).run().report


# Marks a material VisiBake made from a fit (so that a later fit may replace it, never a user's).
FIT_MARK = "visibake_principled_fit"


def make_material(name: str, fit: dict):
    """A Principled BSDF material named ``name`` with the fitted parameters (report's
    ``principled_fit``). A material of that name that VisiBake did not make is left alone: the
    new one gets a free name. Returns the material."""
    from . import compat

    material = bpy.data.materials.get(name)
    if material is None or not material.get(FIT_MARK):
        material = bpy.data.materials.new(name)
        material[FIT_MARK] = True
        material.use_fake_user = True  # kept in the file until the artist assigns it
    compat.ensure_node_tree(material)
    tree = material.node_tree
    tree.nodes.clear()
    shader = tree.nodes.new("ShaderNodeBsdfPrincipled")
    output = tree.nodes.new("ShaderNodeOutputMaterial")
    output.location = (300, 0)
    translucent = fit.get("translucent_color")
    if translucent is not None and max(translucent) > 0:
        # The tile's diffuse transmission: a Translucent BSDF added to the fitted reflection.
        passing = tree.nodes.new("ShaderNodeBsdfTranslucent")
        passing.inputs["Color"].default_value = (*translucent, 1.0)
        passing.location = (0, -400)
        both = tree.nodes.new("ShaderNodeAddShader")
        both.location = (150, 0)
        tree.links.new(shader.outputs[0], both.inputs[0])
        tree.links.new(passing.outputs[0], both.inputs[1])
        surface = both
    else:
        surface = shader
    gaps = fit.get("transparency", 0.0)
    if gaps > 1e-3:
        # The straight-through share (the weave's gaps): a Transparent BSDF mixed in.
        through = tree.nodes.new("ShaderNodeBsdfTransparent")
        through.location = (150, -300)
        mix = tree.nodes.new("ShaderNodeMixShader")
        mix.location = (250, 0)
        mix.inputs["Fac"].default_value = gaps
        tree.links.new(surface.outputs[0], mix.inputs[1])
        tree.links.new(through.outputs[0], mix.inputs[2])
        surface = mix
    tree.links.new(surface.outputs[0], output.inputs["Surface"])
    inputs = shader.inputs
    inputs["Base Color"].default_value = (*fit["base_color"], 1.0)
    for socket, key in (("Roughness", "roughness"), ("Metallic", "metallic"), ("IOR", "ior"),
                        ("Specular IOR Level", "specular_ior_level"), ("Anisotropic", "anisotropic"),
                        ("Anisotropic Rotation", "anisotropic_rotation"), ("Sheen Weight", "sheen_weight"),
                        ("Sheen Roughness", "sheen_roughness"), ("Transmission Weight", "transmission_weight"),
                        ("Diffuse Roughness", "diffuse_roughness")):
        if socket in inputs and key in fit:
            inputs[socket].default_value = fit[key]
    if "Sheen Tint" in inputs:
        inputs["Sheen Tint"].default_value = (*fit["sheen_tint"], 1.0)
    if fit["anisotropic"] > 0:
        # The fit's rotation is measured from the tile's +x: the tangent runs along object X.
        axis = tree.nodes.new("ShaderNodeCombineXYZ")
        axis.inputs["X"].default_value = 1.0
        axis.location = (-500, -300)
        to_world = tree.nodes.new("ShaderNodeVectorTransform")
        to_world.vector_type, to_world.convert_from, to_world.convert_to = "VECTOR", "OBJECT", "WORLD"
        to_world.location = (-300, -300)
        tree.links.new(axis.outputs[0], to_world.inputs[0])
        tree.links.new(to_world.outputs[0], inputs["Tangent"])
    material["visibake_fit_rmse"] = fit["relative_rmse"]
    return material
