"""VisiBake: light baking from precomputed visibility (Daubert et al. 2002) for Blender.

Registration in order, unregistration in reverse. The module name is never
hard-coded: extensions load as ``bl_ext.<repository>.visibake``.
"""
import bpy

from . import operators, panels
from .core import kernels
from .core.pipeline import resident
from .core.visibility import rays
from .operators import cli
from .operators.adapter import cache_status, compat
from .operators.adapter.settings import kernel_cache_folder
from .panels import preferences, properties

_classes = operators.classes + panels.classes
_cli_handle = None


def _cli_command(argv):
    return cli.main(argv)


def register():
    global _cli_handle
    for cls in _classes:
        bpy.utils.register_class(cls)
    properties.register_properties()
    # Only where compiled kernels will be cached: nothing is compiled or imported until a bake needs it.
    kernels.configure(kernel_cache_folder())
    preferences.register_handlers()
    cache_status.register_handlers()
    if compat.cli_commands_supported():
        _cli_handle = bpy.utils.register_cli_command("visibake", _cli_command)


def unregister():
    global _cli_handle
    if _cli_handle is not None:
        bpy.utils.unregister_cli_command(_cli_handle)
        _cli_handle = None
    cache_status.unregister_handlers()
    preferences.unregister_handlers()
    # A kept preparation (core.pipeline.resident) is let go with the extension.
    resident.forget()
    # And the helper threads the ray queries keep (core.visibility.rays.run_together).
    rays.stop_helpers()
    properties.unregister_properties()
    for cls in reversed(_classes):
        bpy.utils.unregister_class(cls)
