"""Loaded by every Dask worker of a VisiBake cluster (``dask worker ... --preload
<this file>``), before any task: it makes VisiBake's core importable under the name the
driver's tasks name it by.

Inside Blender, VisiBake is a package such as ``bl_ext.user_default.visibake``, whose own
``__init__`` needs bpy; a worker has no Blender. So that package and its parents are put in
``sys.modules`` as empty packages whose path is VisiBake's folder: importing its ``core``
then needs nothing but numpy and the other wheels. VISIBAKE_PACKAGE names the package (empty
where the driver imports ``core`` at the top level) and VISIBAKE_PACKAGE_DIR its folder.

This file is loaded by path, not as part of a package: it imports nothing of VisiBake.
"""
import os
import sys
import types


def expose(package: str, folder: str) -> None:
    """Make ``package`` (dotted) an importable package at ``folder``, without running any
    ``__init__`` of it or of its parents."""
    parts = [part for part in package.split(".") if part]
    for depth in range(1, len(parts) + 1):
        name = ".".join(parts[:depth])
        if name in sys.modules:
            continue
        module = types.ModuleType(name)
        module.__path__ = [folder] if depth == len(parts) else []
        sys.modules[name] = module
        if depth > 1:
            setattr(sys.modules[".".join(parts[:depth - 1])], parts[depth - 1], module)


expose(os.environ.get("VISIBAKE_PACKAGE", ""), os.environ.get("VISIBAKE_PACKAGE_DIR", ""))
