"""Core -> Blender and disk: pass images as datablocks, EXR files, PNG previews; vertex-mode
colour attributes and PLY files."""
from __future__ import annotations

import os

import bpy

import numpy as np

from ...core.errors import OutputRefused
from ...core.outputs import names
from ...core.outputs.images import tonemap, write_exr
from ...core.outputs.ownership import StagedWrites, record_files, refuse_foreign, report_files, write_record
from ...core.outputs.vertex_files import element_geometry, write_ply
from . import compat
from .extract import read_values

OWNED_IMAGE_KEY = "visibake_image"
# On every image VisiBake writes: the (object, pass) it holds, so readers need not re-derive its name.
IMAGE_OBJECT_KEY, IMAGE_PASS_KEY = "visibake_object", "visibake_pass"
# What the command line itself writes into the output folder, beside the object or setup folders.
OUT_FOLDER_RESERVED = ("visibake_cache", "report.json", "preview_render.png", "visibake-bake.json")
# The folder record (core.outputs.ownership) of a bake's files in its output (or setup) folder.
RECORD, RECORD_FORMAT = "visibake-bake.json", "visibake-bake"


def image_name(object_name: str, pass_name: str) -> str:
    """``VB_<object>_<pass>``, or a hashed form of it where that is ambiguous or too long for Blender."""
    return names.image_name(object_name, pass_name, compat.MAX_NAME_BYTES)


def owned_image(name: str, object_name: str | None = None, pass_name: str | None = None):
    """The image VisiBake created under ``name``, None if there is none.

    Raises OutputRefused if an image of that name exists that VisiBake did not create, or
    that holds another object's or pass's result.
    """
    image = bpy.data.images.get(name)
    if image is None:
        return None
    if not image.get(OWNED_IMAGE_KEY):
        raise OutputRefused(f"image {name!r} exists and was not created by VisiBake; rename it to let VisiBake "
                            "write its pass")
    # Images of bakes before these keys existed hold no (object, pass): their name was the only record.
    held = image.get(IMAGE_OBJECT_KEY, object_name), image.get(IMAGE_PASS_KEY, pass_name)
    if object_name is not None and held != (object_name, pass_name):
        raise OutputRefused(f"image {name!r} holds VisiBake's pass {held[1]!r} of object {held[0]!r}; rename it to "
                            f"let VisiBake write pass {pass_name!r} of object {object_name!r}")
    return image


def find_image(object_name: str, pass_name: str):
    """VisiBake's image of ``object_name``'s pass ``pass_name``, None if there is none.

    Found by the (object, pass) stored on it, so a renamed image is found too.
    """
    pair = (object_name, pass_name)
    image = bpy.data.images.get(image_name(object_name, pass_name))
    if image is not None and image.get(OWNED_IMAGE_KEY) and \
            (image.get(IMAGE_OBJECT_KEY, object_name), image.get(IMAGE_PASS_KEY, pass_name)) == pair:
        return image
    return next((i for i in bpy.data.images if i.get(OWNED_IMAGE_KEY) and i.get(IMAGE_OBJECT_KEY) == object_name
                 and i.get(IMAGE_PASS_KEY) == pass_name), None)


def check_image_names(names) -> None:
    """Fail before a bake, not after it, if a result could not be written."""
    for name in names:
        owned_image(name)


def store_image(object_name: str, pass_name: str, pixels: np.ndarray) -> bpy.types.Image:
    """Create or update VisiBake's float image of ``object_name``'s ``pass_name`` with (H, W, 4) bottom-up pixels."""
    height, width = pixels.shape[:2]
    name = image_name(object_name, pass_name)
    image = owned_image(name, object_name, pass_name)
    if image is None:
        image = bpy.data.images.new(name, width, height, alpha=True, float_buffer=True)
        image[OWNED_IMAGE_KEY] = True
        image[IMAGE_OBJECT_KEY], image[IMAGE_PASS_KEY] = object_name, pass_name
        # Nothing uses a fresh result yet; without a fake user it would not be saved.
        image.use_fake_user = True
    # Non-Color before writing pixels, or saving would sRGB-encode the values. Only
    # when it differs, and before any resize: on a packed image a colour-space change
    # reloads the packed pixels, which would undo the resize.
    if image.colorspace_settings.name != "Non-Color":
        image.colorspace_settings.name = "Non-Color"
    if tuple(image.size) != (width, height):
        image.scale(width, height)
    image.pixels.foreach_set(np.ascontiguousarray(pixels, np.float32).ravel())
    image.update()
    image.pack()
    return image


def save_png(path: str, pixels: np.ndarray) -> None:
    """Save display-encoded (H, W, 4) bottom-up values in [0, 1] as an 8-bit PNG."""
    height, width = pixels.shape[:2]
    image = bpy.data.images.new("__visibake_preview__", width, height, alpha=True, float_buffer=True)
    try:
        image.colorspace_settings.name = "Non-Color"
        image.pixels.foreach_set(np.ascontiguousarray(pixels, np.float32).ravel())
        image.filepath_raw = path
        image.file_format = "PNG"
        image.save()
    finally:
        bpy.data.images.remove(image)


OWNED_ATTRIBUTES_KEY = "visibake_color_attributes"


def attribute_name(pass_name: str) -> str:
    return f"VB_{pass_name}"


def owned_attribute(mesh: bpy.types.Mesh, name: str):
    """VisiBake's colour attribute ``name`` on ``mesh``, None if there is none.

    Raises ValueError if an attribute of that name exists that VisiBake did not create.
    """
    attribute = mesh.attributes.get(name)
    if attribute is None:
        return None
    if name not in list(mesh.get(OWNED_ATTRIBUTES_KEY, [])):
        raise OutputRefused(f"mesh {mesh.name!r} has an attribute {name!r} that VisiBake did not create; rename it "
                         "to let VisiBake write its pass")
    return attribute


def check_attribute_names(objects, passes) -> None:
    """Fail before a bake, not after it, if a vertex-mode result could not be written."""
    for obj in objects:
        for pass_name in passes:
            owned_attribute(obj.data, attribute_name(pass_name))


def store_colors(obj: bpy.types.Object, pass_name: str, colors: np.ndarray, domain: str) -> None:
    """Create or update VisiBake's FLOAT_COLOR attribute ``VB_<pass>`` on the object's mesh."""
    mesh = obj.data
    name = attribute_name(pass_name)
    attribute = owned_attribute(mesh, name)
    if attribute is not None and (attribute.domain != domain or attribute.data_type != "FLOAT_COLOR"):
        mesh.attributes.remove(attribute)
        attribute = None
    if attribute is None:
        attribute = mesh.color_attributes.new(name, "FLOAT_COLOR", domain)
        mesh[OWNED_ATTRIBUTES_KEY] = sorted(set(mesh.get(OWNED_ATTRIBUTES_KEY, [])) | {name})
    attribute.data.foreach_set("color", np.ascontiguousarray(colors, np.float32).ravel())
    mesh.update()


def vertex_geometry(obj: bpy.types.Object, domain: str) -> tuple[np.ndarray, np.ndarray]:
    """The evaluated mesh of ``obj`` in world space as the PLY vertices and faces of a result on
    ``domain`` (core.outputs.vertex_files.element_geometry): (k, 3) float64, (m, 3) int32.

    Vertex mode keeps the base mesh's vertices and corners (extraction refuses modifiers that
    change them), so these elements are the attribute's, in its order.
    """
    evaluated = obj.evaluated_get(bpy.context.evaluated_depsgraph_get())
    mesh = evaluated.to_mesh()
    try:
        mesh.calc_loop_triangles()
        count = len(mesh.loop_triangles)
        positions = read_values(mesh.vertices, "co", len(mesh.vertices), 3, np.float64)
        triangles = read_values(mesh.loop_triangles, "vertices", count, 3, np.int32)
        loops = read_values(mesh.loop_triangles, "loops", count, 3, np.int64)
        loop_count = len(mesh.loops)
    finally:
        evaluated.to_mesh_clear()
    matrix = np.array(obj.matrix_world, np.float64)
    with np.errstate(invalid="ignore", over="ignore"):
        positions = positions @ matrix[:3, :3].T + matrix[:3, 3]
    if np.linalg.det(matrix[:3, :3]) < 0:
        # A mirroring transform turns the winding around; keep fronts counter-clockwise.
        triangles, loops = triangles[:, [0, 2, 1]], loops[:, [0, 2, 1]]
    return element_geometry(positions, triangles, loops, domain, loop_count)


def write_vertex_files(obj: bpy.types.Object, result, folder: str, previews: bool,
                       renamed: list | None = None, staged: StagedWrites | None = None) -> list[str]:
    """Write a vertex-mode result's passes as ``<pass>.ply`` in ``folder`` (with ``previews``, also
    tone-mapped ``<pass>.preview.ply``: a PNG cannot hold per-vertex data); returns the paths written.

    Format: core.outputs.vertex_files. File names as in :func:`write_outputs`; a preview's name
    never takes a pass's (a light group may be named ``x.preview``). ``staged``: writes each
    file through it (core.outputs.ownership), else a new StagedWrites.
    """
    staged = StagedWrites(folder) if staged is None else staged
    positions, faces = vertex_geometry(obj, result.domain)
    files = []
    for pass_name, (path, preview) in _vertex_paths(result, folder, previews).items():
        colors = result.images[pass_name]
        if os.path.basename(path) != pass_name + ".ply" and renamed is not None:
            renamed.append({"name": f"{result.name}: {pass_name}", "kind": "pass", "path": path})
        with staged.staged(path) as temporary:
            write_ply(temporary, positions, faces, colors, comment=f"VisiBake {pass_name} of {obj.name}: linear "
                      f"RGB in Cycles' units, {result.domain} domain")
        files.append(path)
        if preview is not None:
            with staged.staged(preview) as temporary:
                write_ply(temporary, positions, faces, tonemap(colors), display=True,
                          comment=f"VisiBake {pass_name} of {obj.name}: tone-mapped sRGB display colours")
            files.append(preview)
    return files


def _vertex_paths(result, folder: str, previews: bool) -> dict:
    """{pass: (its .ply, its preview .ply or None)} of a vertex-mode result in ``folder``."""
    stems = names.unique_components(result.images, suffix=".ply")
    preview_stems = names.unique_components([f"{p}.preview" for p in result.images] if previews else [],
                                            reserved=[stem + ".ply" for stem in stems.values()], suffix=".ply")
    return {pass_name: (names.inside_folder(folder, stems[pass_name] + ".ply"),
                        names.inside_folder(folder, preview_stems[f"{pass_name}.preview"] + ".ply")
                        if previews else None)
            for pass_name in result.images}


def _image_paths(result, folder: str, previews: bool) -> dict:
    """{pass: (its .exr, its .png preview or None)} of an atlas-mode result in ``folder``."""
    stems = names.unique_components(result.images)
    return {pass_name: (names.inside_folder(folder, stems[pass_name] + ".exr"),
                        names.inside_folder(folder, stems[pass_name] + ".png") if previews else None)
            for pass_name in result.images}


def output_paths(results, out_dir: str, previews: bool) -> list[str]:
    """Every file :func:`write_outputs` writes for ``results`` in ``out_dir``, its record first
    (absolute paths). ``results``: objects with ``name``, ``domain`` (None: atlas mode) and
    ``images`` (its keys, the pass names, are all that is read). OutputRefused if one would
    resolve outside ``out_dir``."""
    folders = names.unique_components([r.name for r in results], reserved=OUT_FOLDER_RESERVED)
    paths = [names.inside_folder(out_dir, RECORD)]
    for result in results:
        folder = names.inside_folder(out_dir, folders[result.name])
        pairs = _image_paths(result, folder, previews) if result.domain is None else \
            _vertex_paths(result, folder, previews)
        paths += [path for pair in pairs.values() for path in pair if path is not None]
    return paths


def refuse_foreign_outputs(results, out_dir: str, previews: bool) -> None:
    """The one rule (core.outputs.ownership): OutputRefused, naming them, if files the bake
    would write in ``out_dir`` exist and no VisiBake record lists them."""
    refuse_foreign(output_paths(results, out_dir, previews),
                   "remove or rename them, or choose another output folder; an earlier VisiBake's files count "
                   "as VisiBake's only where its visibake-bake.json or report.json lists them")


def check_output_paths(results, out_dir: str) -> None:
    """Refuse (OutputRefused) before anything is written if a result's folder or file under
    ``out_dir`` would resolve outside it (a link there pointing elsewhere)."""
    output_paths(results, out_dir, previews=True)


def write_outputs(results, out_dir: str | None, previews: bool, store_images: bool = True,
                  renamed: list | None = None, staged: StagedWrites | None = None) -> list[str]:
    """Store every pass as an image datablock (unless not ``store_images``) and, with ``out_dir``, as files
    ``out_dir/<object>/<pass>.exr`` (vertex mode: colour attributes, and ``<pass>.ply``).

    Object and pass names become distinct safe file names (core.outputs.names); every path is
    checked to be inside ``out_dir``, and to be new or VisiBake's (:func:`refuse_foreign_outputs`),
    before the first is written (OutputRefused otherwise). The files go through ``staged``
    (core.outputs.ownership.StagedWrites; a new one if None), after the folder's record
    ``visibake-bake.json``, which lists them and the files its earlier version listed that are
    still there. ``renamed``: extended with {"name", "kind", "path"} for every output whose file
    or image name is not its object's or pass's own name. Returns the paths of the files
    written, the record first.
    """
    files = []
    if out_dir:
        planned = output_paths(results, out_dir, previews)
        refuse_foreign_outputs(results, out_dir, previews)
        staged = StagedWrites(out_dir) if staged is None else staged
        staged.make_folder(out_dir)
        record = planned[0]
        # An earlier version's report.json lists its files too: they become the record's.
        earlier = {path for path in (record_files(out_dir, RECORD) or set()) | report_files(out_dir)
                   if os.path.isfile(path) and os.path.dirname(path) != out_dir} - {record}
        # The record first, listing every file: a run killed part way leaves files that stay VisiBake's.
        with staged.staged(record) as temporary:
            write_record(temporary, RECORD_FORMAT, sorted({os.path.relpath(path, out_dir)
                                                           for path in set(planned[1:]) | earlier}))
        files.append(record)
    folders = names.unique_components([r.name for r in results], reserved=OUT_FOLDER_RESERVED) if out_dir else {}
    for result in results:
        folder = names.inside_folder(out_dir, folders[result.name]) if out_dir else None
        if folder is not None and folders[result.name] != result.name and renamed is not None:
            renamed.append({"name": result.name, "kind": "object", "path": folder})
        if folder is not None:
            staged.make_folder(folder)
        if result.domain is not None:
            # Vertex mode: colour attributes on the mesh and, with out_dir, PLY files (else an
            # --out bake without --save would keep nothing of them).
            if store_images:
                for pass_name, colors in result.images.items():
                    store_colors(bpy.data.objects[result.name], pass_name, colors, result.domain)
            if folder is not None:
                files += write_vertex_files(bpy.data.objects[result.name], result, folder, previews, renamed,
                                            staged)
            continue
        paths = _image_paths(result, folder, previews) if folder is not None else {}
        for pass_name, pixels in result.images.items():
            if store_images:
                image = store_image(result.name, pass_name, pixels)
                if image.name != f"VB_{result.name}_{pass_name}" and renamed is not None:
                    renamed.append({"name": f"{result.name}: {pass_name}", "kind": "image", "path": image.name})
            if folder is None:
                continue
            path, png = paths[pass_name]
            if os.path.basename(path) != pass_name + ".exr" and renamed is not None:
                renamed.append({"name": f"{result.name}: {pass_name}", "kind": "pass", "path": path})
            with staged.staged(path) as temporary:
                write_exr(temporary, pixels)
            files.append(path)
            if png is not None:
                display = tonemap(pixels)
                display[..., 3] = 1.0
                with staged.staged(png) as temporary:
                    save_png(temporary, display)
                files.append(png)
    return files
