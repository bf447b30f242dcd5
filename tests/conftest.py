"""Shared test setup: paths, and a private Blender user profile for the whole session.

Kept free of bpy so that ``tests/core`` runs without Blender. The bpy fixtures live
in ``tests/blender_support.py`` and are re-exported by ``tests/blender/conftest.py``
(and ``tests/gpu/conftest.py``):

    from blender_support import visibake, clean_scene  # noqa: F401
"""

import atexit
import os
import shutil
import sys
import tempfile
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]
TESTS_DIR = Path(__file__).resolve().parent

# `import core`, `import tools.cycles_bake` (repo root), `import blender_support` (tests/)
# and the scene builders next to the tests (core_scenes, bpy_scenes).
for _p in (str(REPO_ROOT), str(TESTS_DIR), str(TESTS_DIR / "core"), str(TESTS_DIR / "blender")):
    if _p not in sys.path:
        sys.path.insert(0, _p)

# --skip-report=PATH: every skip of the run as JSON, for tools/check_skips.py (CI).
pytest_plugins = ("skip_report",)

# Blender reads BLENDER_USER_RESOURCES once, when bpy is first imported. This root
# conftest is imported before any other conftest or test module, so setting it here
# guarantees nothing is written to (or read from) the real user profile.
if "bpy" in sys.modules:  # pragma: no cover - only if a plugin imported bpy first
    raise RuntimeError("bpy was imported before tests/conftest.py could isolate the user profile")
_USER_RESOURCES = tempfile.mkdtemp(prefix="visibake-blender-user-")
os.environ["BLENDER_USER_RESOURCES"] = _USER_RESOURCES
# Registered before bpy is imported, so it runs after bpy's own exit handlers.
atexit.register(shutil.rmtree, _USER_RESOURCES, ignore_errors=True)
# Kernels compiled by tests/core (which runs the source tree, not the installed extension)
# are cached in the session's folder too, not in the user's cache.
os.environ.setdefault("NUMBA_CACHE_DIR", os.path.join(_USER_RESOURCES, "numba-cache"))

try:
    from hypothesis import settings as _hyp_settings

    # CI: reproducible examples, no wall-clock deadline on a slow 2-core machine.
    _hyp_settings.register_profile("ci", derandomize=True, deadline=None, print_blob=True)
    _hyp_settings.register_profile("dev", deadline=None)
    _hyp_settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci" if os.environ.get("CI") else "dev"))
except ImportError:  # pragma: no cover
    pass


# The bpy module's own exit is unreliable after a long session, on every version: 4.2
# crashes and 4.5 hangs once a property with a Python callback was registered
# (operators/adapter/compat.py); 5.0 and 5.3 either crash (tests/blender with tests/gpu,
# exit 139 after pytest's summary, already at commit 5355f5a) or end the full suite with
# "Error: Not freed memory blocks: 16" although no Python object then holds a gpu, bmesh,
# imbuf or idprop value (counted after gc.collect()). pytest has run and reported
# everything by then: end the test process with pytest's own exit status, without the
# module's teardown. The command (tools/visibake.py) still exits as compat says.
_session_status = []


def pytest_sessionfinish(session, exitstatus):
    _session_status.append(int(exitstatus))


@pytest.hookimpl(trylast=True)
def pytest_unconfigure(config):
    if "bpy" in sys.modules and _session_status:
        shutil.rmtree(_USER_RESOURCES, ignore_errors=True)  # atexit does not run after this
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(_session_status[-1])
