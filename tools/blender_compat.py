"""The extension's Blender compatibility module (``operators/adapter/compat.py``), loaded by
its path for the tools, benchmarks and tests that build scenes outside the extension:
one place knows what differs between Blender versions, for them too.

    from tools.blender_compat import compat
    compat.ensure_node_tree(bpy.data.materials.new("Red"))
"""
import importlib.util
import sys
from pathlib import Path

_NAME = "visibake_blender_compat"
_PATH = Path(__file__).resolve().parents[1] / "operators" / "adapter" / "compat.py"


def _load():
    if _NAME not in sys.modules:
        spec = importlib.util.spec_from_file_location(_NAME, _PATH)
        module = importlib.util.module_from_spec(spec)
        sys.modules[_NAME] = module
        spec.loader.exec_module(module)
    return sys.modules[_NAME]


compat = _load()
