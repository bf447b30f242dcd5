"""The skip report (tests/skip_report.py, pytest --skip-report) and its check against
tests/expected_skips.toml (tools/check_skips.py): CI fails on a skip nobody allowed."""
import json
import os
import re
import subprocess
import sys
import textwrap

import pytest

from tools import check_skips

TESTS_DIR = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))

SKIPPING_TESTS = textwrap.dedent('''
    import pytest

    def test_runs():
        assert True

    @pytest.mark.skipif(True, reason="marked off here")
    def test_marked():
        pass

    @pytest.mark.parametrize("kind", ["A", "B"])
    def test_in_the_body(kind):
        if kind == "B":
            pytest.skip(f"no {kind} here")

    @pytest.mark.xfail(reason="known bug", strict=True)
    def test_expected_to_fail():
        assert False
''')


def _run_pytest(folder, report):
    """pytest in ``folder`` (its own empty config) with the plugin, as make does."""
    (folder / "pytest.ini").write_text("[pytest]\n")
    env = dict(os.environ, PYTHONPATH=TESTS_DIR)
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "skip_report", f"--skip-report={report}",
                           "-p", "no:cacheprovider", str(folder)],
                          cwd=folder, env=env, capture_output=True, text=True, timeout=120)


def test_the_report_lists_each_skip_with_its_reason_and_no_xfail(tmp_path):
    (tmp_path / "test_some.py").write_text(SKIPPING_TESTS)
    (tmp_path / "test_module_skip.py").write_text(
        'import pytest\npytest.importorskip("no_such_module_visibake")\n')
    report = tmp_path / "out" / "bpy5.0.1.json"
    proc = _run_pytest(tmp_path, report)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    written = json.loads(report.read_text())
    skips = {s["nodeid"]: s for s in written["skips"]}
    assert set(skips) == {"test_some.py::test_marked", "test_some.py::test_in_the_body[B]", "test_module_skip.py"}
    assert skips["test_some.py::test_marked"]["reason"] == "marked off here"
    assert skips["test_some.py::test_in_the_body[B]"]["reason"] == "no B here"
    assert skips["test_some.py::test_in_the_body[B]"]["location"].endswith("test_some.py:14")
    assert "no_such_module_visibake" in skips["test_module_skip.py"]["reason"]
    assert skips["test_module_skip.py"]["when"] == "collect"
    assert written["bpy"] is None and written["exitstatus"] == 0


def _report(folder, version, skips, ci=True, bpy=None):
    path = folder / f"bpy{version}.json"
    path.write_text(json.dumps({"bpy": bpy, "python": "3.11", "ci": ci, "exitstatus": 0,
                                "skips": [{"nodeid": n, "reason": r, "location": "x.py:1", "when": "call"}
                                          for n, r in skips]}))
    return path


EXPECTED = '''
[[skip]]
blender = ["4.2.*"]
test = "tests/blender/test_volume_*.py::*"
reason = "needs openvdb"
why = "4.2 has none"

[[skip]]
blender = "*"
test = "tests/gpu/test_x.py::test_y[A]"
reason = "no GPU context"
why = "a machine without EGL"
outside_ci_only = true
'''


@pytest.fixture
def expected(tmp_path):
    path = tmp_path / "expected_skips.toml"
    path.write_text(EXPECTED)
    return path


def test_a_skip_the_list_allows_passes(tmp_path, expected, capsys):
    report = _report(tmp_path, "4.2.23", [("tests/blender/test_volume_bake.py::test_a", "volumes needs openvdb: no")])
    assert check_skips.main([str(report), "--expected", str(expected)]) == 0
    assert "1 skip(s) in bpy4.2.23.json, each allowed" in capsys.readouterr().out


@pytest.mark.parametrize("version, nodeid, reason, ci", [
    ("4.5.15", "tests/blender/test_volume_bake.py::test_a", "needs openvdb", True),     # another Blender
    ("4.2.23", "tests/blender/test_cli.py::test_a", "needs openvdb", True),            # another test
    ("4.2.23", "tests/blender/test_volume_bake.py::test_a", "needs mount", True),      # another reason
    ("5.0.1", "tests/gpu/test_x.py::test_y[A]", "no GPU context here", True),          # under CI
    ("5.0.1", "tests/gpu/test_x.py::test_yA", "no GPU context here", False),           # [A] is literal
])
def test_a_skip_outside_the_list_fails_and_is_named(tmp_path, expected, capsys, version, nodeid, reason, ci):
    report = _report(tmp_path, version, [(nodeid, reason)], ci=ci)
    assert check_skips.main([str(report), "--expected", str(expected)]) == 1
    err = capsys.readouterr().err
    assert f"bpy {version}: {nodeid}" in err and f"reason: {reason}" in err and "from:   x.py:1" in err


def test_an_outside_ci_skip_passes_on_a_developer_s_machine(tmp_path, expected):
    report = _report(tmp_path, "5.0.1", [("tests/gpu/test_x.py::test_y[A]", "no GPU context here")], ci=False)
    assert check_skips.main([str(report), "--expected", str(expected)]) == 0


@pytest.mark.parametrize("make, message", [
    (lambda folder: folder / "bpy5.0.1.json", "no readable skip report"),
    (lambda folder: _report(folder, "5.0.1", [], bpy="4.5.15"), "ran under bpy 4.5.15"),
    (lambda folder: (folder / "skips.json").write_text("{}") or folder / "skips.json", "named bpy<version>.json"),
])
def test_a_missing_or_misnamed_report_is_an_error(tmp_path, expected, capsys, make, message):
    assert check_skips.main([str(make(tmp_path)), "--expected", str(expected)]) == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize("entry, message", [
    ('blender = "*"\ntest = "t"\nreason = "r"\n', "'why' is required"),
    ('blender = "*"\ntest = "t"\nreason = "r"\nwhy = "w"\nreasons = "typo"\n', "unknown field(s) ['reasons']"),
])
def test_an_entry_without_its_why_or_with_an_unknown_field_is_refused(tmp_path, entry, message):
    path = tmp_path / "expected_skips.toml"
    path.write_text("[[skip]]\n" + entry)
    with pytest.raises(check_skips.ListError, match=re.escape(message)):
        check_skips.load_expected(path)


def test_the_project_s_list_reads_and_says_why_for_each_entry():
    allowed = check_skips.load_expected()
    assert allowed and all(len(entry.why) > 20 for entry in allowed)
    # What CI must never skip: the GPU twins and the compiled kernels, on any Blender.
    for version in ("4.2.23", "4.5.15", "5.0.1", "5.3.0"):
        for nodeid, reason in (("tests/gpu/test_raster.py::test_a", "no GPU context on this machine: EGL"),
                               ("tests/core/test_kernels.py::test_a", "numba kernels unavailable here: x")):
            assert not any(a.allows(version, nodeid, reason, ci=True) for a in allowed)
            assert any(a.allows(version, nodeid, reason, ci=False) for a in allowed)
