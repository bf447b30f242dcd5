"""Run VisiBake's command with the bpy module: ``python tools/visibake.py bake|demo ...``.

Same arguments and exit status as ``blender -c visibake ...``. The extension is
loaded from this source tree, and its packages (xatlas, embreex, OpenEXR) come
from the environment this Python runs in.
"""
import importlib.util
import os
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def load_extension(root: str = ROOT):
    """Import the repository at ``root`` (this one by default) as the package ``visibake`` and register it."""
    import bpy  # noqa: F401  (bpy must be imported before the extension)

    spec = importlib.util.spec_from_file_location("visibake", os.path.join(root, "__init__.py"),
                                                  submodule_search_locations=[root])
    module = importlib.util.module_from_spec(spec)
    sys.modules["visibake"] = module
    spec.loader.exec_module(module)
    module.register()
    return module


def loaded_extension(root: str = ROOT):
    """(the extension, ``module``): :func:`load_extension` of ``root``, and a function that
    imports one of its submodules by its name inside the extension (``module("core.kernels")``)."""
    extension = load_extension(root)

    def module(name: str):
        return importlib.import_module(f"{extension.__name__}.{name}")
    return extension, module


def main(argv=None) -> int:
    extension = load_extension()
    return extension.cli.main(sys.argv[1:] if argv is None else argv)


if __name__ == "__main__":
    status = main()
    sys.path.insert(0, ROOT)
    from tools.blender_compat import compat

    compat.end_module_process(status)
