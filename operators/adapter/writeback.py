"""Core -> Blender and disk: pass images as datablocks, EXR files, PNG previews."""
from __future__ import annotations

import os
import re

import bpy

import numpy as np

from ...core.errors import OutputRefused
from ...core.outputs.images import tonemap, write_exr

OWNED_IMAGE_KEY = "visibake_image"


def image_name(object_name: str, pass_name: str) -> str:
    return f"VB_{object_name}_{pass_name}"


def safe_file_name(name: str) -> str:
    """An object name usable as one path component on every platform."""
    cleaned = re.sub(r'[<>:"/\\|?*\x00-\x1f]', "_", name).strip(" .")
    return cleaned or "_"


def owned_image(name: str):
    """The image VisiBake created under ``name``, None if there is none.

    Raises ValueError if an image of that name exists that VisiBake did not create.
    """
    image = bpy.data.images.get(name)
    if image is None:
        return None
    if not image.get(OWNED_IMAGE_KEY):
        raise OutputRefused(f"image {name!r} exists and was not created by VisiBake; rename it to let VisiBake "
                            "write its pass")
    return image


def check_image_names(names) -> None:
    """Fail before a bake, not after it, if a result could not be written."""
    for name in names:
        owned_image(name)


def store_image(name: str, pixels: np.ndarray) -> bpy.types.Image:
    """Create or update VisiBake's float image ``name`` with (H, W, 4) bottom-up pixels."""
    height, width = pixels.shape[:2]
    image = owned_image(name)
    if image is None:
        image = bpy.data.images.new(name, width, height, alpha=True, float_buffer=True)
        image[OWNED_IMAGE_KEY] = True
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


def write_outputs(results, out_dir: str | None, previews: bool, store_images: bool = True) -> list[str]:
    """Store every pass as an image datablock (unless not ``store_images``) and, with ``out_dir``, as files.

    Returns the paths of the files written.
    """
    files = []
    for result in results:
        if result.domain is not None:
            # Vertex mode: colour attributes on the mesh; no image files.
            if store_images:
                for pass_name, colors in result.images.items():
                    store_colors(bpy.data.objects[result.name], pass_name, colors, result.domain)
            continue
        for pass_name, pixels in result.images.items():
            if store_images:
                store_image(image_name(result.name, pass_name), pixels)
            if not out_dir:
                continue
            folder = os.path.join(out_dir, safe_file_name(result.name))
            os.makedirs(folder, exist_ok=True)
            path = os.path.join(folder, f"{pass_name}.exr")
            write_exr(path, pixels)
            files.append(path)
            if previews:
                display = tonemap(pixels)
                display[..., 3] = 1.0
                png = os.path.join(folder, f"{pass_name}.png")
                save_png(png, display)
                files.append(png)
    return files
