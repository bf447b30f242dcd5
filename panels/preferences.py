"""VisiBake's add-on preferences: machine settings that are not part of a scene."""
import bpy

from ..core.settings import PREFERENCE_SETTINGS
from ..operators.adapter import device
from . import properties
from .properties import setting_property


class VisiBakePreferences(bpy.types.AddonPreferences):
    bl_idname = device.ADDON_PACKAGE

    device: setting_property(PREFERENCE_SETTINGS["device"])
    gpu_memory_mib: setting_property(PREFERENCE_SETTINGS["gpu_memory_mib"])
    resident_memory_mib: setting_property(PREFERENCE_SETTINGS["resident_memory_mib"])

    cache_dir: setting_property(PREFERENCE_SETTINGS["cache_dir"], subtype="DIR_PATH")
    cache_limit_mib: setting_property(PREFERENCE_SETTINGS["cache_limit_mib"])
    default_preset: setting_property(PREFERENCE_SETTINGS["default_preset"])
    threads: setting_property(PREFERENCE_SETTINGS["threads"])
    cluster_workers: setting_property(PREFERENCE_SETTINGS["cluster_workers"])

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.prop(self, "device")
        layout.prop(self, "gpu_memory_mib")
        layout.prop(self, "resident_memory_mib")
        layout.prop(self, "cache_dir")
        layout.prop(self, "cache_limit_mib")
        layout.prop(self, "default_preset")
        layout.prop(self, "threads")
        layout.prop(self, "cluster_workers")


classes = (VisiBakePreferences,)


def apply_default_preset_to_new_scenes(*_ignored) -> None:
    """Give every scene that has no VisiBake settings yet the preferred preset.

    Runs after a file is loaded (File > New too), when the extension is enabled, and
    (from a timer) when the panel is drawn for a scene added since. Returns None, so a
    timer runs it once.
    """
    prefs = device.preferences()
    if prefs is None or prefs.default_preset == "NONE":
        return
    for scene in bpy.data.scenes:
        properties.apply_default_preset(scene, prefs.default_preset)


@bpy.app.handlers.persistent
def _on_load_post(*_ignored) -> None:
    apply_default_preset_to_new_scenes()


def register_handlers() -> None:
    bpy.app.handlers.load_post.append(_on_load_post)
    # From a timer: while the extension registers, bpy.data may not be reachable.
    bpy.app.timers.register(apply_default_preset_to_new_scenes, first_interval=0.0)


def unregister_handlers() -> None:
    if _on_load_post in bpy.app.handlers.load_post:
        bpy.app.handlers.load_post.remove(_on_load_post)
    if bpy.app.timers.is_registered(apply_default_preset_to_new_scenes):
        bpy.app.timers.unregister(apply_default_preset_to_new_scenes)
