"""bpy fixtures and helpers shared by ``tests/blender`` and ``tests/gpu``.

Use from a conftest.py (pytest finds fixtures in the conftest's namespace)::

    from blender_support import visibake, clean_scene  # noqa: F401

bpy is imported lazily (inside fixtures/helpers), never at import time, so that
``tests/conftest.py`` has already pointed BLENDER_USER_RESOURCES at a temp folder.

Facts this relies on (checked with bpy 5.0.1 in module mode):

- ``extensions.package_install_files`` returns {'CANCELLED'} (no exception) on failure.
- The installed wheels go to ``<user>/extensions/.local/lib/python3.X/site-packages``,
  which Blender *appends* to sys.path: a copy in the venv wins for in-process imports.
- ``wm.read_factory_settings`` calls the extension's ``unregister()`` and removes it from
  the enabled add-ons; the module stays in sys.modules. ``addon_utils.enable`` registers
  the same module object again (no reload while the installed files are unchanged).
- ``hasattr(bpy.ops.visibake, "bake")`` is True even for unregistered operators; use
  :func:`operator_exists`.
"""

from __future__ import annotations

import importlib
import os
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
MANIFEST_PATH = REPO_ROOT / "blender_manifest.toml"
EXTENSION_REPO = "user_default"
# What goes into the package; a zip older than any of these is rebuilt.
PACKAGE_SOURCES = ("__init__.py", "blender_manifest.toml", "core", "operators", "panels", "gpu_shaders")


def load_manifest() -> dict:
    with open(MANIFEST_PATH, "rb") as fh:
        return tomllib.load(fh)


def extension_module_name() -> str:
    """``bl_ext.user_default.visibake``: how Blender names the installed extension."""
    return f"bl_ext.{EXTENSION_REPO}.{load_manifest()['id']}"


def built_zip_path() -> Path:
    """``$VISIBAKE_ZIP`` if set, else ``dist/<id>-<version>.zip`` (what ``make build`` writes)."""
    if env := os.environ.get("VISIBAKE_ZIP"):
        return Path(env).resolve()
    manifest = load_manifest()
    return REPO_ROOT / "dist" / f"{manifest['id']}-{manifest['version']}.zip"


def _newest_source_mtime() -> float:
    newest = 0.0
    for name in PACKAGE_SOURCES:
        path = REPO_ROOT / name
        files = path.rglob("*") if path.is_dir() else [path]
        for f in files:
            if f.is_file() and "__pycache__" not in f.parts:
                newest = max(newest, f.stat().st_mtime)
    return newest


def ensure_built_zip() -> Path:
    """The extension zip, running ``make build`` if it is missing or older than the sources."""
    zip_path = built_zip_path()
    if os.environ.get("VISIBAKE_ZIP"):
        assert zip_path.is_file(), f"VISIBAKE_ZIP={zip_path} does not exist"
        return zip_path
    if not zip_path.is_file() or zip_path.stat().st_mtime < _newest_source_mtime():
        subprocess.run(["make", "build"], cwd=REPO_ROOT, check=True, stdin=subprocess.DEVNULL)
    assert zip_path.is_file(), f"`make build` did not produce {zip_path}"
    return zip_path


def operator_exists(idname: str) -> bool:
    """True if ``bpy.ops.<idname>`` (e.g. ``"visibake.bake"``) is a registered operator."""
    import bpy

    category, name = idname.split(".")
    try:
        getattr(getattr(bpy.ops, category), name).get_rna_type()
    except (AttributeError, KeyError):
        return False
    return True


def extension_site_packages() -> Path:
    """Where Blender installs the wheels of extensions (appended to sys.path by Blender)."""
    import bpy

    python = f"python{sys.version_info.major}.{sys.version_info.minor}"
    return Path(bpy.utils.user_resource("EXTENSIONS")) / ".local" / "lib" / python / "site-packages"


def gpu_runtime_or_skip(visibake):
    """The installed extension's gpu_shaders.runtime with a GPU context, and its device info.
    Without a context the test skips and says why, except under CI (CI set), where
    llvmpipe gives one: there a missing context fails, so the GPU tests cannot go green
    by skipping."""
    runtime = importlib.import_module(f"{visibake.__name__}.gpu_shaders.runtime")
    try:
        return runtime, runtime.device_info()
    except runtime.GPUUnavailable as error:
        if os.environ.get("CI"):
            pytest.fail(f"no GPU context under CI (llvmpipe's EGL should give one): {error}")
        pytest.skip(f"no GPU context on this machine: {error}")


def _raise(ex: BaseException) -> None:
    raise ex


def is_enabled(module_name: str | None = None) -> bool:
    import bpy  # noqa: F401  (puts Blender's script modules, e.g. addon_utils, on sys.path)

    import addon_utils

    return addon_utils.check(module_name or extension_module_name())[1]


def enable_extension():
    """Enable the installed extension if it is not (e.g. after read_factory_settings)."""
    import bpy  # noqa: F401

    import addon_utils

    name = extension_module_name()
    if not is_enabled(name):
        # handle_error=_raise: register() errors surface as test errors, not console noise.
        addon_utils.enable(name, default_set=True, handle_error=_raise)
    assert is_enabled(name), f"{name} could not be enabled"
    return sys.modules[name]


def _keep_wheels_between_tests() -> None:
    """Let the extension's wheels stay extracted for the whole session.

    ``read_factory_settings`` (every :func:`clean_scene`) disables the extension, and
    Blender then deletes the wheels that only disabled extensions use, and extracts them
    again when the next test enables it: numba's LLVM alone is 170 MB, seconds per test.
    The wheels do not change within a session, so the first extraction (the install, through
    Blender's own wheel manager) is kept and later syncs of the same or fewer wheels are
    skipped. Where Blender has no such function, nothing changes (only slower).
    """
    import addon_utils

    original = getattr(addon_utils, "_extension_sync_wheels", None)
    if original is None or getattr(original, "keeps_wheels", False):
        return
    extracted: set = set()

    def sync(*, wheel_list, **keywords):
        wanted = {(name, tuple(paths)) for name, paths in wheel_list}
        if wanted <= extracted:
            return None
        extracted.update(wanted)
        return original(wheel_list=wheel_list, **keywords)

    sync.keeps_wheels = True
    addon_utils._extension_sync_wheels = sync


def _check_user_profile_isolated() -> None:
    import bpy

    user = os.environ.get("BLENDER_USER_RESOURCES")
    assert user, "tests/conftest.py must set BLENDER_USER_RESOURCES before bpy is imported"
    assert Path(bpy.utils.resource_path("USER")).resolve() == Path(user).resolve(), (
        "bpy was imported before BLENDER_USER_RESOURCES was set; the real user profile is in use"
    )


@pytest.fixture(scope="session")
def visibake():
    """The extension, built, installed and enabled the way Blender does it.

    Returns the imported module ``bl_ext.user_default.visibake``.
    """
    zip_path = ensure_built_zip()
    import bpy

    import addon_utils  # importable only once bpy is

    _check_user_profile_isolated()
    _keep_wheels_between_tests()
    name = extension_module_name()
    result = bpy.ops.extensions.package_install_files(
        filepath=str(zip_path), repo=EXTENSION_REPO, enable_on_install=True
    )
    assert result == {"FINISHED"}, f"installing {zip_path} returned {result} (see the log above)"
    if not is_enabled(name):
        # enable_on_install swallowed a register() error: enable again to raise it here.
        addon_utils.enable(name, default_set=True, handle_error=_raise)
    module = importlib.import_module(name)
    yield module
    # Exercise unregister(): a failure shows up as an error in the last test's teardown.
    if is_enabled(name):
        addon_utils.disable(name, default_set=True, handle_error=_raise)


@pytest.fixture
def clean_scene(visibake):
    """An empty factory scene with the extension (re-)enabled; returns the scene.

    read_factory_settings unregisters and disables every non-factory add-on, so the
    extension is enabled again (same module object, register() runs again).
    """
    import bpy

    bpy.ops.wm.read_factory_settings(use_empty=True)
    module = enable_extension()
    assert module is visibake
    return bpy.context.scene
