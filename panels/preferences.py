"""VisiBake's add-on preferences: machine settings that are not part of a scene."""
import bpy

from ..operators import device


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
    threads: bpy.props.IntProperty(
        name="Threads", default=0, min=0, soft_max=64,
        description="Worker threads for ray tracing and gathers (0: all cores)")

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.prop(self, "device")
        layout.prop(self, "gpu_memory_mib")
        layout.prop(self, "cache_dir")
        layout.prop(self, "threads")


classes = (VisiBakePreferences,)
