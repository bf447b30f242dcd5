"""Arguments, scene properties and preferences turned into core settings, in one place.

Each value is the argument where one is given (the command line's options, the job's
parameters), else the scene's property (``scene.visibake``), else VisiBake's
preference, else core's default (core.settings); :func:`resolve` validates the
complete set once. (The command line writes its scene options onto ``scene.visibake``
first, so that a saved file keeps them.)
"""
from __future__ import annotations

import os
from dataclasses import dataclass, fields

import bpy

from ...core.errors import BakeRefused
from ...core.settings import PASSES, PREFERENCE_SETTINGS, SETTINGS, BakeSettings, LayoutSettings
from . import EXTENSION_PACKAGE
from .compat import CYCLES_BAKE_FOOTPRINT_WIDTH
from .device import preferences

CACHE_FOLDER_NAME = "visibake_cache"

# The BakeSettings fields the scene's settings hold; the others keep core's defaults.
_SCENE_BAKE_FIELDS = tuple(f.name for f in fields(BakeSettings) if SETTINGS[f.name].on_scene)


@dataclass
class Resolved:
    """The settings of one bake."""

    bake: BakeSettings
    layout: LayoutSettings
    device: str  # one of core.settings.DEVICES, as asked for ('auto' is decided when the bake starts)
    refine: bool  # bake refined copies of coarse vertex-mode objects (operators.adapter.refine)
    resident_bytes: int = 0  # the preparation kept in memory between bakes may hold this much (the preference)


def bake_settings(props, threads: int = SETTINGS["threads"].default) -> BakeSettings:
    """The BakeSettings of ``props`` (scene.visibake), not validated yet."""
    values = {name: getattr(props, name) for name in _SCENE_BAKE_FIELDS}
    values["passes"] = tuple(p for p in PASSES if p in values["passes"])
    # Texels average what this Blender's Cycles bake averages, so that they compare with it.
    return BakeSettings(**values, threads=threads, footprint_width=CYCLES_BAKE_FOOTPRINT_WIDTH)


def layout_settings(props) -> LayoutSettings:
    """The LayoutSettings of ``props`` (scene.visibake), not validated yet."""
    return LayoutSettings(**{f.name: getattr(props, f.name) for f in fields(LayoutSettings)})


def _preference(context, name: str):
    prefs = preferences(context)
    return getattr(prefs, name) if prefs is not None else PREFERENCE_SETTINGS[name].default


def resolve(context, threads: int | None = None, device: str | None = None,
            refine: bool | None = None) -> Resolved:
    """The settings of a bake of ``context.scene``; an argument given (not None) wins.

    threads : worker threads (0: all cores); None: the preference
    device : 'auto', 'gpu' or 'cpu'; None: the preference
    refine : None: the scene's Refine Coarse Vertex Objects

    Raises core.errors.BakeRefused (a ValueError) for values that cannot work.
    """
    props = context.scene.visibake
    resolved = Resolved(
        bake=bake_settings(props, _preference(context, "threads") if threads is None else threads),
        layout=layout_settings(props),
        device=device or _preference(context, "device"),
        refine=props.refine_vertex_objects if refine is None else refine,
        resident_bytes=int(_preference(context, "resident_memory_mib")) * 2**20)
    resolved.bake.validate()
    resolved.layout.validate()
    reason = PREFERENCE_SETTINGS["device"].check(resolved.device)
    if reason is not None:
        raise BakeRefused(reason)
    return resolved


def kernel_cache_folder() -> str | None:
    """Where compiled CPU kernels are cached: the extension's user folder, which Blender lets
    it write and keeps across updates (the install folder is replaced); None where it is not
    installed as an extension (the core's default folder then)."""
    try:
        return bpy.utils.extension_path_user(EXTENSION_PACKAGE, path="kernels", create=True)
    except ValueError:
        return None


def cache_limit_bytes(context=None) -> int:
    """The most bytes a cache folder may hold (the preference; 0: no limit)."""
    return int(_preference(context or bpy.context, "cache_limit_mib")) * 2**20


def cache_folder(scene) -> str:
    """The cache folder: the scene's setting, the preference, beside the saved .blend, the user folder."""
    props = scene.visibake
    if props.cache_dir:
        return bpy.path.abspath(props.cache_dir)
    prefs = preferences()
    if prefs is not None and prefs.cache_dir:
        return bpy.path.abspath(prefs.cache_dir)
    if bpy.data.filepath:
        return os.path.join(os.path.dirname(bpy.data.filepath), CACHE_FOLDER_NAME)
    try:
        return bpy.utils.extension_path_user(EXTENSION_PACKAGE, path="cache", create=True)
    except ValueError:
        # Not installed as an extension (run from a source checkout by tools/visibake.py).
        return os.path.join(bpy.utils.user_resource("CONFIG"), "visibake", "cache")
