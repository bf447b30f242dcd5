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

    def draw(self, context):
        layout = self.layout
        layout.use_property_split = True
        layout.prop(self, "device")
        layout.prop(self, "gpu_memory_mib")


classes = (VisiBakePreferences,)
