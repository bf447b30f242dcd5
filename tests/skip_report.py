"""pytest plugin: ``--skip-report=PATH`` writes every skip of the run to PATH as JSON.

CI must not go green because whole areas skipped: ``make test`` writes this report and
tools/check_skips.py compares it with tests/expected_skips.toml. Registered by
tests/conftest.py (``pytest_plugins``). The report::

    {"bpy": "5.0.1" | null (bpy never imported, e.g. tests/core alone),
     "python": "3.11.13", "ci": true, "exitstatus": 0,
     "skips": [{"nodeid": "tests/gpu/test_x.py::test_y[a]", "reason": "no GPU context ...",
                "location": "tests/gpu/conftest.py:20", "when": "setup" | "call" | "collect"}]}
"""
import json
import os
import platform
import sys

import pytest


def pytest_addoption(parser):
    parser.addoption("--skip-report", metavar="PATH", default=None,
                     help="write every skip of the run (test id, reason) to PATH as JSON "
                          "(tools/check_skips.py compares it with tests/expected_skips.toml)")


def pytest_configure(config):
    path = config.getoption("--skip-report")
    if path:
        config.pluginmanager.register(SkipRecorder(path), "visibake-skip-report")


def _reason(longrepr) -> tuple[str, str]:
    """(reason, "path:line") of a skipped report's longrepr: pytest gives skips as a
    (path, lineno, "Skipped: reason") tuple, anything else is kept as its text."""
    if isinstance(longrepr, tuple) and len(longrepr) == 3:
        path, lineno, message = longrepr
        return message.removeprefix("Skipped: "), f"{path}:{lineno}"
    return str(longrepr), ""


class SkipRecorder:
    """Collects the skips of one session and writes them to ``path`` at its end."""

    def __init__(self, path: str):
        self.path = path
        self.skips: list[dict] = []

    def _record(self, nodeid, longrepr, when):
        reason, location = _reason(longrepr)
        self.skips.append({"nodeid": nodeid, "reason": reason, "location": location, "when": when})

    @pytest.hookimpl(trylast=True)
    def pytest_runtest_logreport(self, report):
        # xfail also reports as skipped (with report.wasxfail): that is not a skip.
        if report.skipped and not hasattr(report, "wasxfail"):
            self._record(report.nodeid, report.longrepr, report.when)

    @pytest.hookimpl(trylast=True)
    def pytest_collectreport(self, report):
        # A module-level skip (pytest.skip(allow_module_level=True), importorskip at import).
        if report.skipped:
            self._record(report.nodeid, report.longrepr, "collect")

    def pytest_sessionfinish(self, session, exitstatus):
        # Written here, not at unconfigure: tests/conftest.py ends a bpy session with
        # os._exit in its last pytest_unconfigure.
        bpy = sys.modules.get("bpy")
        # The version as numbers: version_string adds " LTS" on the long-term releases (4.2.23 LTS).
        version = getattr(getattr(bpy, "app", None), "version", None)
        report = {
            "bpy": ".".join(map(str, version)) if version else None,
            "python": platform.python_version(),
            "ci": bool(os.environ.get("CI")),
            "exitstatus": int(exitstatus),
            "skips": self.skips,
        }
        os.makedirs(os.path.dirname(os.path.abspath(self.path)), exist_ok=True)
        with open(self.path, "w", encoding="utf-8") as stream:
            json.dump(report, stream, indent=1)
