"""The check of an output destination before a bake (core.outputs.destinations)."""
import os
import stat

import pytest

from core.errors import OutputRefused
from core.outputs.destinations import FILE, FOLDER, check_destinations, destination_problem


def read_only_folder(tmp_path) -> str:
    """A folder no file can be created in, for this user: chmod 555, or (root ignores modes)
    a folder of a file system that refuses writes."""
    folder = tmp_path / "read-only"
    folder.mkdir()
    folder.chmod(stat.S_IRUSR | stat.S_IXUSR | stat.S_IRGRP | stat.S_IXGRP)
    try:
        (folder / "probe").write_bytes(b"")
    except OSError:
        return str(folder)
    (folder / "probe").unlink()
    for candidate in ("/sys", "/proc/sys"):
        try:
            open(os.path.join(candidate, "visibake-probe"), "wb").close()
        except OSError:
            return candidate
    pytest.skip("no folder here refuses writes to this user")


def _tree(path) -> list:
    return sorted(os.path.relpath(os.path.join(root, name), path)
                  for root, folders, files in os.walk(path) for name in folders + files)


def test_a_writable_destination_passes_and_nothing_is_created(tmp_path):
    (tmp_path / "old.blend").write_bytes(b"x")
    before = _tree(tmp_path)
    assert destination_problem(str(tmp_path / "a" / "b" / "out"), FOLDER, "--out") is None
    assert destination_problem(str(tmp_path), FOLDER, "--out") is None
    assert destination_problem(str(tmp_path / "new" / "saved.blend"), FILE, "--save") is None
    assert destination_problem(str(tmp_path / "old.blend"), FILE, "--save") is None
    assert _tree(tmp_path) == before  # no folder made, no probe left


@pytest.mark.parametrize("layout, path, kind, expected", [
    ({"out": "file"}, "out", FOLDER, "is a file, not a folder"),
    ({"out": "file"}, "out/sub/deeper", FOLDER, "out is a file, not a folder"),
    ({"report.json": "folder"}, "report.json", FILE, "is a folder; give a file name"),
    ({"a": "file"}, "a/report.json", FILE, "a is a file, not a folder"),
])
def test_a_destination_of_the_wrong_kind_is_named(tmp_path, layout, path, kind, expected):
    for name, what in layout.items():
        (tmp_path / name).mkdir() if what == "folder" else (tmp_path / name).write_text("x")
    reason = destination_problem(str(tmp_path / path), kind, "--opt")
    assert reason is not None and reason.startswith("--opt ") and reason.endswith(expected)
    assert "\n" not in reason


def test_a_read_only_folder_is_refused_for_folders_and_files_in_it(tmp_path):
    folder = read_only_folder(tmp_path)
    for path, kind in ((folder, FOLDER), (os.path.join(folder, "out"), FOLDER),
                       (os.path.join(folder, "saved.blend"), FILE)):
        reason = destination_problem(path, kind, "--save")
        assert reason is not None and "not writable" in reason


def test_a_device_is_no_file_to_replace():
    assert destination_problem("/dev/null", FILE, "--report").endswith("is not a regular file")


def test_check_destinations_raises_for_the_first_bad_one_and_skips_none(tmp_path):
    (tmp_path / "f").write_text("x")
    check_destinations([(None, FOLDER, "--out"), (str(tmp_path / "ok"), FOLDER, "--out")])
    with pytest.raises(OutputRefused, match="^--report .* is a folder"):
        check_destinations([(str(tmp_path / "ok"), FOLDER, "--out"), (str(tmp_path), FILE, "--report"),
                            (str(tmp_path / "f"), FOLDER, "--setups")])
    with pytest.raises(ValueError, match="kind"):
        destination_problem(str(tmp_path), "pipe", "--out")
