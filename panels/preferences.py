"""VisiBake's add-on preferences: machine settings that are not part of a scene."""
import bpy

from ..operators.adapter import device
from . import properties


class VisiBakePreferences(bpy.types.AddonPreferences):
    bl_idname = device.ADDON_PACKAGE

    device: bpy.props.EnumProperty(
        name="Device", default="auto",
        items=[("auto", "Auto", "The GPU passes on a real GPU; numpy on a software renderer or without a GPU"),
               ("gpu", "GPU", "Always run the transport passes on the GPU (Blender's gpu module)"),
               ("cpu", "CPU", "Always run the transport passes in numpy")],
        description="Where the transport passes (the gathers) run")
    gpu_memory_mib: bpy.props.IntProperty(
        name="GPU Memory (MiB)", default=device.DEFAULT_GPU_MEMORY_MIB, min=64, soft_max=16384,
        description="GPU memory the transport passes may use; the table is streamed in batches of directions "
                    "that fit")

    cache_dir: bpy.props.StringProperty(
        name="Cache Folder", subtype="DIR_PATH", default="",
        description="Where visibility caches go when a scene sets no folder of its own (e.g. a fast disk); "
                    "empty: beside the saved .blend, else VisiBake's user folder")
    default_preset: bpy.props.EnumProperty(
        name="Default Preset", default="NONE",
        items=[("NONE", "None", "New scenes start with VisiBake's built-in settings (128 directions, 2 bounces, "
                                "256 texels)"),
               ("DRAFT", "Draft", "New scenes start with the Draft preset"),
               ("PRODUCTION", "Production", "New scenes start with the Production preset")],
        description="The preset a scene gets when VisiBake first sees it with no settings of its own (a new "
                    "file or scene, or a file saved without VisiBake); scenes with settings are never changed")
    threads: bpy.props.IntProperty(
        name="Threads", default=0, min=0, soft_max=64,
        description="Worker threads for ray tracing and gathers (0: all cores)")

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.prop(self, "device")
        layout.prop(self, "gpu_memory_mib")
        layout.prop(self, "cache_dir")
        layout.prop(self, "default_preset")
        layout.prop(self, "threads")


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
