"""core.outputs.ownership: which files are VisiBake's, staged writes taken back on failure, and a
full disk (a file size limit here, EFBIG, which needs no privileges) refused as the user's problem."""
import errno
import json
import os
import resource
import signal
import subprocess
import sys
import textwrap

import pytest

from core.errors import OutputRefused
from core.outputs.ownership import (
    StagedWrites,
    foreign_files,
    is_leftover,
    is_space_error,
    is_visibakes,
    refuse_foreign,
    remove_leftovers,
    report_files,
    temporary_name,
)

USERS = b"the user's own bytes"


def test_only_files_a_visibake_record_lists_are_visibakes(tmp_path):
    (tmp_path / "mine.exr").write_bytes(USERS)
    (tmp_path / "view.png").write_bytes(b"png")
    (tmp_path / "lightfield.json").write_text(json.dumps({"format": "visibake-lightfield", "files": ["view.png"]}))
    (tmp_path / "tv000_pv000").mkdir()
    (tmp_path / "tv000_pv000" / "a.png").write_bytes(b"png")
    (tmp_path / "btf.json").write_text(json.dumps({"format": "visibake-btf", "files": ["tv000_pv000/a.png"]}))
    (tmp_path / "cloth.binary").write_bytes(b"merl")
    (tmp_path / "cloth.binary.visibake.json").write_text(json.dumps({"command": "brdf"}))
    (tmp_path / "fake.binary").write_bytes(USERS)
    (tmp_path / "fake.binary.visibake.json").write_bytes(USERS)  # not a VisiBake report: proves nothing
    assert is_visibakes(tmp_path / "view.png") and is_visibakes(tmp_path / "lightfield.json")
    assert is_visibakes(tmp_path / "tv000_pv000" / "a.png")
    assert is_visibakes(tmp_path / "cloth.binary") and is_visibakes(tmp_path / "cloth.binary.visibake.json")
    assert foreign_files([str(tmp_path / n) for n in ("mine.exr", "view.png", "fake.binary", "absent.exr")]) == [
        str(tmp_path / "mine.exr"), str(tmp_path / "fake.binary")]
    with pytest.raises(OutputRefused, match="mine.exr exists and VisiBake did not write it"):
        refuse_foreign([str(tmp_path / "mine.exr"), str(tmp_path / "view.png")])
    # A record of another format, or damaged, lists nothing.
    (tmp_path / "lightfield.json").write_text(json.dumps({"format": "someone-else", "files": ["view.png"]}))
    assert not is_visibakes(tmp_path / "view.png")


def test_a_rollback_removes_what_the_run_made_and_nothing_that_was_there(tmp_path):
    earlier = tmp_path / "out" / "earlier.exr"
    earlier.parent.mkdir()
    earlier.write_bytes(b"an earlier run's")
    staged = StagedWrites(str(tmp_path / "out"))
    staged.make_folder(str(tmp_path / "out" / "a" / "b"))
    with staged.staged(str(tmp_path / "out" / "a" / "b" / "new.exr")) as temporary:
        open(temporary, "wb").write(b"new")
    with staged.staged(str(earlier)) as temporary:
        open(temporary, "wb").write(b"replaced")
    with pytest.raises(KeyboardInterrupt), staged.staged(str(tmp_path / "out" / "half.exr")) as temporary:
        open(temporary, "wb").write(b"ha")
        raise KeyboardInterrupt
    assert sorted(os.listdir(tmp_path / "out")) == ["a", "earlier.exr"]
    staged.rollback()
    assert os.listdir(tmp_path / "out") == ["earlier.exr"] and earlier.read_bytes() == b"replaced"


def test_a_file_that_comes_out_empty_or_fails_its_check_is_a_full_disk(tmp_path):
    staged = StagedWrites(str(tmp_path))
    with pytest.raises(OutputRefused, match=f"not enough space in {tmp_path}"):
        with staged.staged(str(tmp_path / "empty.vdb")) as temporary:
            open(temporary, "wb").close()

    def unreadable(path):
        raise RuntimeError("Stream failure reading the size of a blosc chunk")

    with pytest.raises(OutputRefused, match="cut.vdb came out incomplete"):
        with staged.staged(str(tmp_path / "cut.vdb"), unreadable) as temporary:
            open(temporary, "wb").write(b"VDB")
    staged.rollback()
    assert os.listdir(tmp_path) == []


def test_space_errors_are_told_from_others():
    assert is_space_error(OSError(errno.ENOSPC, os.strerror(errno.ENOSPC)))
    assert is_space_error(OSError(errno.EFBIG, os.strerror(errno.EFBIG)))
    assert is_space_error(RuntimeError(f'Failed to write pixel data to "x.exr". {os.strerror(errno.ENOSPC)}.'))
    assert not is_space_error(OSError(errno.EACCES, os.strerror(errno.EACCES)))
    assert not is_space_error(ValueError("a bug"))


def test_a_file_size_limit_gives_not_enough_space_and_leaves_nothing(tmp_path):
    """Unprivileged stand-in for a full disk: RLIMIT_FSIZE with SIGXFSZ ignored (writes fail with EFBIG)."""
    script = textwrap.dedent(f"""
        import sys
        sys.path.insert(0, {os.getcwd()!r})
        from core.errors import OutputRefused
        from core.outputs.atomic import atomic_file
        from core.outputs.ownership import StagedWrites
        staged = StagedWrites({str(tmp_path)!r})
        try:
            with staged.staged({str(tmp_path / "big.bin")!r}) as temporary:
                open(temporary, "wb").write(b"x" * 100_000)
        except OutputRefused as error:
            print("refused:", error)
        try:
            with atomic_file({str(tmp_path / "report.json")!r}) as stream:
                stream.write(b"y" * 100_000)
        except OutputRefused as error:
            print("refused:", error)
        staged.rollback()
    """)

    def limit():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
        resource.setrlimit(resource.RLIMIT_FSIZE, (40 * 1024, 40 * 1024))

    done = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, preexec_fn=limit,
                          timeout=120)
    assert done.returncode == 0, done.stderr
    lines = done.stdout.strip().splitlines()
    assert len(lines) == 2 and all(f"not enough space in {tmp_path}" in line for line in lines), lines
    assert os.listdir(tmp_path) == []


def test_a_bake_record_and_an_earlier_version_s_report_list_files_as_visibakes(tmp_path):
    (tmp_path / "Ground").mkdir()
    (tmp_path / "Ground" / "lighting.exr").write_bytes(b"exr")
    (tmp_path / "Ground" / "mine.exr").write_bytes(USERS)
    (tmp_path / "visibake-bake.json").write_text(json.dumps({"format": "visibake-bake",
                                                             "files": ["Ground/lighting.exr"]}))
    assert is_visibakes(tmp_path / "Ground" / "lighting.exr") and not is_visibakes(tmp_path / "Ground" / "mine.exr")
    # Before the records: the demo's report.json (absolute paths) is the only list of a bake's files.
    (tmp_path / "visibake-bake.json").unlink()
    (tmp_path / "preview_render.png").write_bytes(b"png")
    listed = [str(tmp_path / "Ground" / "lighting.exr"), str(tmp_path / "preview_render.png")]
    (tmp_path / "report.json").write_text(json.dumps({"files": listed, "objects": [], "stage_seconds": {}}))
    assert report_files(str(tmp_path)) == {*listed, str(tmp_path / "report.json")}
    assert foreign_files(listed + [str(tmp_path / "report.json"), str(tmp_path / "Ground" / "mine.exr")]) == [
        str(tmp_path / "Ground" / "mine.exr")]
    # A user's report.json (not a bake's report) lists nothing, and is itself the user's.
    (tmp_path / "report.json").write_text(json.dumps({"files": listed}))
    assert foreign_files(listed + [str(tmp_path / "report.json")]) == listed + [str(tmp_path / "report.json")]


def test_only_temporary_name_s_exact_pattern_is_a_leftover(tmp_path):
    (tmp_path / "Ground").mkdir()
    left = [temporary_name(str(tmp_path / "Ground" / "lighting.exr")), temporary_name(str(tmp_path / "record"))]
    for path in left:
        open(path, "wb").write(b"half")
    users = [".lighting.0123abcd.partial.exr.bak", ".lighting.0123ABCD.partial.exr", "lighting.0123abcd.partial.exr",
             ".lighting.0123abc.partial.exr", ".lighting.partial.exr"]
    for name in users:
        (tmp_path / "Ground" / name).write_bytes(USERS)
    assert all(is_leftover(path) for path in left)
    assert sorted(remove_leftovers(str(tmp_path))) == sorted(left)
    assert sorted(os.listdir(tmp_path / "Ground")) == sorted(users) and os.listdir(tmp_path) == ["Ground"]


def test_keep_replaced_puts_an_earlier_file_back_on_rollback_and_keep_drops_the_link(tmp_path):
    earlier = tmp_path / "lighting.exr"
    earlier.write_bytes(b"an earlier bake's")
    for finish in ("rollback", "keep"):
        staged = StagedWrites(str(tmp_path), keep_replaced=True)
        with staged.staged(str(earlier)) as temporary:
            open(temporary, "wb").write(b"this bake's")
        with staged.staged(str(tmp_path / "new.exr")) as temporary:
            open(temporary, "wb").write(b"new")
        assert earlier.read_bytes() == b"this bake's" and len(os.listdir(tmp_path)) == 3  # and the hidden link
        getattr(staged, finish)()
        if finish == "rollback":
            assert os.listdir(tmp_path) == ["lighting.exr"] and earlier.read_bytes() == b"an earlier bake's"
        else:
            assert sorted(os.listdir(tmp_path)) == ["lighting.exr", "new.exr"]
            assert earlier.read_bytes() == b"this bake's"
