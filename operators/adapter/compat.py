"""What differs between the Blenders VisiBake supports (4.2 LTS to the newest 5.x), in one place.

Every ``bpy.app.version`` test of the product is here; the rest of the code asks this
module. It needs nothing but bpy (and core's errors where it has them), so that the
reference tools and the tests can load it by its path as well (``tools.blender_compat``).
Measured with the bpy modules of 4.2.23, 4.5.15, 5.0.1 and 5.3.0:

- Materials and worlds made with ``bpy.data.*.new`` have no node tree before 5.0
  (``use_nodes`` is off); from 5.0 on they always render through their nodes and
  ``use_nodes`` is deprecated.
- Datablock names hold 63 bytes before 5.0, 255 from 5.0 on.
- The bundled ``openvdb`` module: none in 4.2; in 4.5 and 5.x it lives in the Python
  folder of Blender's resources, which 5.x exposes through
  ``bpy.utils.expose_bundled_modules``.
- ``bpy.utils.register_cli_command`` (``blender -c visibake``) exists from 4.2 on;
  ``gpu.compute`` in every supported version.
- Lamps: ``normalize`` (Blender 5's unnormalised lamps), ``exposure`` and
  ``use_temperature`` exist only in some versions; a missing one means its neutral value.
- The bpy *module* (not the Blender application) cannot end its process once a
  property with a Python callback (``update=``, dynamic enum items) was registered: at
  interpreter exit bpy 4.2 crashes (SIGSEGV) and bpy 4.5 hangs, even after the classes
  are unregistered; 5.0 and later exit normally. Scripts and tests that run on the
  module end their process with :func:`end_module_process` instead.
"""
from __future__ import annotations

import glob
import os
import sys

import bpy

VERSION = tuple(bpy.app.version)
# The oldest Blender VisiBake supports (blender_manifest.toml's blender_version_min).
MINIMUM = (4, 2, 0)
NODES_ALWAYS = VERSION >= (5, 0, 0)
MAX_NAME_BYTES = 255 if VERSION >= (5, 0, 0) else 63
MODULE_EXIT_IS_SAFE = VERSION >= (5, 0, 0)
# Lamps kept their own use_nodes switch longer than materials and worlds: Cycles 4.2 and
# 5.0 honour it, 5.3 renders a lamp's node tree whatever it says (Cycles bakes, 2026-12).
LAMP_NODES_ALWAYS = VERSION >= (5, 1, 0)
# The box, in texels, Cycles' bake averages each texel over (core.sampling.footprint): the
# texel's whole area from 5.2.1, half of it in 4.2 to 5.2.0 (measured against a closed form on
# 4.2.23, 4.5.15, 5.0.1, 5.1.0, 5.1.2, 5.2.0-5.2.4 and 5.3.0, docs/reliability.md;
# tests/blender/test_cycles_bake.py checks it on each Blender CI runs).
CYCLES_BAKE_FOOTPRINT_WIDTH = 1.0 if VERSION >= (5, 2, 1) else 0.5


try:
    from ...core.errors import BakeRefused
except ImportError:  # loaded by its path (tools.blender_compat), outside the extension's package
    BakeRefused = ValueError


class FeatureMissing(BakeRefused):
    """This Blender lacks something a feature needs; the message says which Blender has it.
    A refusal (exit status 2 on the command line), not a bug."""


def ensure_node_tree(datablock):
    """The node tree of a new material or world, made where this Blender does not make one."""
    if datablock.node_tree is None and not NODES_ALWAYS:
        datablock.use_nodes = True
    return datablock.node_tree


def uses_nodes(datablock) -> bool:
    """Whether a material or world renders through its node tree (5.x always does; 4.x
    honours ``use_nodes``)."""
    if datablock.node_tree is None:
        return False
    return NODES_ALWAYS or bool(datablock.use_nodes)


def lamp_uses_nodes(light) -> bool:
    """Whether Cycles renders a lamp (bpy.types.Light) through its node tree."""
    if getattr(light, "node_tree", None) is None:
        return False
    return LAMP_NODES_ALWAYS or bool(getattr(light, "use_nodes", False))


def lamp_setting(light, name: str, neutral):
    """A lamp setting that not every supported Blender has (``normalize``, ``exposure``,
    ``use_temperature``, ``temperature_color``): ``neutral`` where it is missing."""
    return getattr(light, name, neutral)


def set_equirectangular_panorama(camera) -> None:
    """Make ``camera`` (bpy.types.Camera) Cycles' equirectangular panorama. Every supported
    Blender has ``Camera.panorama_type``; before 4.0 it lived on ``camera.cycles``."""
    camera.type = "PANO"
    owner = camera if hasattr(camera, "panorama_type") else camera.cycles
    owner.panorama_type = "EQUIRECTANGULAR"


def fits_name(name: str) -> bool:
    """Whether Blender keeps ``name`` as it is (it cuts longer names at a UTF-8 boundary)."""
    return len(name.encode("utf-8")) <= MAX_NAME_BYTES


def openvdb():
    """Blender's bundled ``openvdb`` module; :class:`FeatureMissing` where this Blender has none."""
    if hasattr(bpy.utils, "expose_bundled_modules"):
        bpy.utils.expose_bundled_modules()
    try:
        import openvdb as module
        return module
    except ImportError:
        pass
    folder = bpy.utils.resource_path("LOCAL")
    for site in glob.glob(os.path.join(folder, "python", "lib", "python3*", "site-packages")):
        if site not in sys.path:
            sys.path.append(site)
    try:
        import openvdb as module
    except ImportError:
        raise FeatureMissing(f"Blender {bpy.app.version_string} ships no openvdb module; volumes need "
                             "Blender 4.5 or later") from None
    return module


def cli_commands_supported() -> bool:
    """Whether ``blender -c visibake`` can be registered."""
    return hasattr(bpy.utils, "register_cli_command")


def end_module_process(status: int) -> None:
    """End a process that runs Blender as the bpy module, with exit status ``status``.

    Where the module's own exit crashes or hangs (before 5.0, see above) the process
    ends without Python's finalisation, after flushing what it printed; elsewhere it
    is an ordinary ``sys.exit``. Only for the module: the Blender application exits
    through its own window manager.
    """
    if MODULE_EXIT_IS_SAFE:
        sys.exit(status)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(int(status))
