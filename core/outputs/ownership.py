"""Which files are VisiBake's, and writing them so that a failure leaves the folder as it was.

The one rule every command follows (volume, brdf, btf, lightfield):

- A path that exists is VisiBake's only if a VisiBake record lists it: the sidecar
  ``FILE.visibake.json`` beside it (brdf), or a folder record in its folder or the folder
  above (``btf.json``, ``lightfield.json``, ``visibake-volume.json``, ``visibake-bake.json``),
  or, for outputs of versions before the records, a bake's ``report.json`` there whose
  ``files`` name it (the demo's report, a ``--report`` into the output folder). Any other existing
  file is the user's: :func:`refuse_foreign` names it and nothing is written
  (:class:`core.errors.OutputRefused`, exit 2). ``--overwrite`` never changes this for a
  file of the same name; it only lets a run write *beside* the user's files.
- :class:`StagedWrites` writes each output under a temporary name in its final folder
  (recorded before it is written), checks it (not empty; a caller's check too, such as
  reading a VDB's header back, since OpenVDB's writer does not report a full disk), and
  only then renames it into place. :meth:`StagedWrites.rollback` removes the temporaries
  and the files and folders this run created, never a file that existed before the run.
- A leftover temporary (:func:`temporary_name`'s pattern exactly: a run killed before its
  rename) is VisiBake's: :func:`remove_leftovers` removes those of a folder a run claims.
- A full disk or quota (ENOSPC, EDQUOT, EFBIG) is the user's problem, not a bug:
  "not enough space in DIR" (OutputRefused).
"""
from __future__ import annotations

import contextlib
import errno
import json
import os
import re
import secrets

from ..errors import OutputRefused

SIDECAR_SUFFIX = ".visibake.json"
# Folder records: file name -> the "format" that marks it VisiBake's. Each lists "files",
# relative to its folder ("/"-separated).
FOLDER_RECORDS = {"btf.json": "visibake-btf", "lightfield.json": "visibake-lightfield",
                  "visibake-volume.json": "visibake-volume", "visibake-bake.json": "visibake-bake"}
# A bake's report (operators.cli: the demo's, or --report): before the folder records it was the
# only list of a bake's files; its "files" are absolute paths.
REPORT_RECORD = "report.json"
_REPORT_KEYS = frozenset({"files", "objects", "stage_seconds"})
# temporary_name's pattern, and nothing looser: a user's file is never taken for one.
_TEMPORARY = re.compile(r"\.(?P<stem>.+)\.[0-9a-f]{8}\.partial(?P<ext>\.[^.]*)?")
# How many folders above a file its record may lie (btf: tvXXX_pvXXX/image).
RECORD_DEPTH = 2
SPACE_ERRNOS = frozenset(code for code in (errno.ENOSPC, getattr(errno, "EDQUOT", None), errno.EFBIG) if code)
_SPACE_TEXTS = tuple(os.strerror(code) for code in SPACE_ERRNOS)


def _is_file_list(files) -> bool:
    return isinstance(files, list) and all(isinstance(f, str) for f in files)


def read_record(path: str, format_name: str | None = None) -> dict | None:
    """The JSON object in the regular file ``path`` (a link is never a record); with
    ``format_name``, only a record of that ``"format"`` whose ``"files"`` is a list of
    strings. None for anything else (missing, unreadable, not JSON, another format)."""
    if not os.path.isfile(path) or os.path.islink(path):
        return None
    try:
        with open(path, encoding="utf-8") as handle:
            content = json.load(handle)
    except (OSError, ValueError):
        return None
    if not isinstance(content, dict):
        return None
    if format_name is not None and (content.get("format") != format_name or not _is_file_list(content.get("files"))):
        return None
    return content


def record_files(folder: str, record: str) -> set[str] | None:
    """The absolute paths the VisiBake record ``record`` (a FOLDER_RECORDS name) in ``folder``
    lists, the record itself included; None if there is none or it is not VisiBake's."""
    path = os.path.join(folder, record)
    content = read_record(path, FOLDER_RECORDS[record])
    if content is None:
        return None
    listed = {os.path.normpath(os.path.join(folder, *f.split("/"))) for f in content["files"]}
    return listed | {os.path.normpath(path)}


def report_files(folder: str) -> set[str]:
    """The absolute paths a bake's ``report.json`` in ``folder`` lists, itself included; empty
    if there is none or it is not a VisiBake bake's report."""
    path = os.path.join(folder, REPORT_RECORD)
    content = read_record(path)
    if content is None or not _REPORT_KEYS <= content.keys() or not _is_file_list(content["files"]):
        return set()
    return {os.path.normpath(os.path.join(folder, f)) for f in content["files"]} | {os.path.normpath(path)}


def _is_sidecar(path: str) -> bool:
    """A brdf report beside its file: JSON naming the command that wrote it."""
    if not path.endswith(SIDECAR_SUFFIX):
        return False
    content = read_record(path)
    return content is not None and "command" in content


def is_visibakes(path: str, _records: dict | None = None) -> bool:
    """Whether the existing ``path`` is a file a VisiBake record lists (module docstring).
    ``_records``: {(folder, record): its files}, shared across calls to read each record once."""
    records = {} if _records is None else _records
    path = os.path.normpath(os.path.abspath(path))
    if os.path.islink(path) or os.path.isdir(path):
        return False  # a link or folder is never an output VisiBake wrote
    if _is_sidecar(path + SIDECAR_SUFFIX) or _is_sidecar(path):
        return True
    folder = os.path.dirname(path)
    for _ in range(RECORD_DEPTH):
        for record in FOLDER_RECORDS:
            if (folder, record) not in records:
                records[folder, record] = record_files(folder, record) or set()
            if path in records[folder, record]:
                return True
        if (folder, REPORT_RECORD) not in records:
            records[folder, REPORT_RECORD] = report_files(folder)
        if path in records[folder, REPORT_RECORD]:
            return True
        folder = os.path.dirname(folder)
    return False


def foreign_files(paths) -> list[str]:
    """Those of ``paths`` that exist (as anything) and are not VisiBake's, in order."""
    records: dict = {}
    return [path for path in paths if os.path.lexists(path) and not is_visibakes(path, records)]


def refuse_foreign(paths, hint: str = "remove or rename them, or choose another folder") -> None:
    """Raise :class:`OutputRefused` naming the existing files among ``paths`` (the files a run
    would write) that VisiBake did not write; nothing has been written then."""
    foreign = foreign_files(paths)
    if foreign:
        shown = ", ".join(foreign[:5]) + (f" and {len(foreign) - 5} more" if len(foreign) > 5 else "")
        raise OutputRefused(f"{shown} exist{'s' if len(foreign) == 1 else ''} and VisiBake did not write "
                            f"{'it' if len(foreign) == 1 else 'them'}; VisiBake never replaces a file of yours "
                            f"({hint}); nothing was written")


def write_record(path: str, format_name: str, files, extra: dict | None = None) -> None:
    """Write a folder record of ``format_name`` (a FOLDER_RECORDS value) listing ``files``
    (paths relative to its folder) to ``path``: a :meth:`StagedWrites.staged` temporary, so
    that it is checked and renamed into place as every output is."""
    content = {"format": format_name, "version": 1, **(extra or {}),
               "files": sorted(str(f).replace(os.sep, "/") for f in files)}
    with open(path, "w", encoding="utf-8") as handle:
        json.dump(content, handle, indent=1)
        handle.write("\n")


def is_space_error(error: BaseException) -> bool:
    """Whether ``error`` says the disk or quota is full (or a file too large for its limit):
    an OSError with that errno, or a library's error carrying its text."""
    if isinstance(error, OSError) and error.errno in SPACE_ERRNOS:
        return True
    text = str(error)
    return any(message in text for message in _SPACE_TEXTS)


def space_refusal(folder: str, detail: str = "") -> OutputRefused:
    return OutputRefused(f"not enough space in {folder}{': ' + detail if detail else ''}; free some space or "
                         "choose another folder; nothing was written")


@contextlib.contextmanager
def space_checked(folder: str):
    """Turn a full disk's error inside the block into :func:`space_refusal` for ``folder``."""
    try:
        yield
    except OutputRefused:
        raise
    except Exception as error:
        if is_space_error(error):
            raise space_refusal(folder, str(getattr(error, "strerror", None) or error)) from error
        raise


def _not_empty(path: str) -> None:
    if os.path.getsize(path) == 0:
        raise OSError(errno.ENOSPC, "the file came out empty", path)


def temporary_name(path: str) -> str:
    """A hidden name beside ``path`` that keeps its extension (writers that pick the format by
    it, or add one that is missing, still write the right file)."""
    folder, base = os.path.split(path)
    stem, ext = os.path.splitext(base)
    return os.path.join(folder, f".{stem}.{secrets.token_hex(4)}.partial{ext}")


def is_leftover(path: str) -> bool:
    """Whether ``path`` is a regular file named as :func:`temporary_name` names one."""
    return bool(_TEMPORARY.fullmatch(os.path.basename(path))) and os.path.isfile(path) \
        and not os.path.islink(path)


def remove_leftovers(folder: str, depth: int = RECORD_DEPTH) -> list[str]:
    """Remove the temporaries a killed run left in ``folder`` and its subfolders ``depth`` - 1
    deep (the files its records may list); returns their paths. Only for a folder a run is
    claiming: a run writing there at the same moment would lose its temporaries."""
    removed = []
    if not os.path.isdir(folder) or os.path.islink(folder):
        return removed
    with os.scandir(folder) as entries:
        for entry in entries:
            if entry.is_dir(follow_symlinks=False):
                if depth > 1:
                    removed += remove_leftovers(entry.path, depth - 1)
            elif is_leftover(entry.path):
                _remove(entry.path)
                removed.append(entry.path)
    return removed


class StagedWrites:
    """A run's outputs, written whole or not at all, and taken back on failure.

    created : final paths this run made (they did not exist before it), in order
    folders : folders this run made, parents before children
    temporaries : temporary files not yet renamed into place
    """

    def __init__(self, root: str | None = None, keep_replaced: bool = False):
        """root : the output folder a full disk's message names (default: each file's folder).
        keep_replaced : keep each file a staged write replaces (a hard link under a hidden
        temporary name: no copy of its bytes) until :meth:`keep`, so that :meth:`rollback` puts
        it back; where the file system has no hard links it is replaced as without."""
        self.root = root
        self.keep_replaced = keep_replaced
        self.created: list[str] = []
        self.folders: list[str] = []
        self.temporaries: list[str] = []
        self.replaced: list[tuple[str, str]] = []  # (path, the hidden link to its earlier content)

    def make_folder(self, folder: str) -> None:
        """Create ``folder`` and its missing parents, recording each one made."""
        missing = []
        current = os.path.abspath(folder)
        while not os.path.lexists(current):
            missing.append(current)
            current = os.path.dirname(current)
        with space_checked(self.root or (os.path.dirname(missing[-1]) if missing else folder)):
            for made in reversed(missing):
                os.mkdir(made)
                self.folders.append(made)

    def claim(self, path: str) -> None:
        """Record ``path`` before a writer that is itself atomic (core.outputs.atomic) writes it:
        a file that did not exist is this run's to take back."""
        path = os.path.abspath(path)
        if not os.path.lexists(path) and path not in self.created:
            self.created.append(path)

    @contextlib.contextmanager
    def staged(self, path: str, check=None):
        """Yield a temporary path to write ``path``'s content to; when the block ends it is
        checked (not empty, then ``check(temporary)``, which raises if the file is not whole)
        and renamed to ``path``. On any error the temporary goes. A full disk raises
        :func:`space_refusal`; a file that comes out empty or fails ``check`` is taken for one
        (writers such as OpenVDB's do not report it)."""
        path = os.path.abspath(path)
        folder = os.path.dirname(path)
        temporary = temporary_name(path)
        self.temporaries.append(temporary)
        self.claim(path)  # recorded before it is written: a cancel finds it
        try:
            with space_checked(self.root or folder):
                yield temporary
                _not_empty(temporary)
                if check is not None:
                    try:
                        check(temporary)
                    except Exception as error:  # noqa: BLE001 - any reader's complaint: the file is not whole
                        reason = str(error)[:200]  # a reader may quote the garbage it found
                        raise OSError(errno.ENOSPC, f"{os.path.basename(path)} came out incomplete ({reason})",
                                      path) from error
                _sync(temporary)
            if self.keep_replaced and os.path.isfile(path) and not os.path.islink(path):
                self._keep_earlier(path)
            os.replace(temporary, path)
        except BaseException:
            _remove(temporary)
            raise
        finally:
            self.temporaries.remove(temporary)

    def _keep_earlier(self, path: str) -> None:
        earlier = temporary_name(path)
        try:
            os.link(path, earlier)
        except OSError:
            return  # no hard links here: the earlier file is replaced, not kept
        self.replaced.append((path, earlier))

    def keep(self) -> None:
        """The run is done: drop the earlier files :meth:`rollback` would have put back."""
        for _, earlier in self.replaced:
            _remove(earlier)
        self.replaced.clear()

    def rollback(self) -> None:
        """Remove the temporaries, the files this run created and the folders it made (if
        left empty); a file that existed before the run stays (with ``keep_replaced``, as it was)."""
        for path, earlier in reversed(self.replaced):
            with contextlib.suppress(OSError):
                os.replace(earlier, path)
        self.replaced.clear()
        for temporary in self.temporaries:
            _remove(temporary)
        for path in self.created:
            if os.path.isfile(path) or os.path.islink(path):
                _remove(path)
        for folder in reversed(self.folders):
            with contextlib.suppress(OSError):
                if os.path.isdir(folder) and not os.listdir(folder):
                    os.rmdir(folder)
        self.temporaries.clear()
        self.created.clear()
        self.folders.clear()


def _sync(path: str) -> None:
    """Flush ``path`` to disk: a file system that allocates late reports a full disk here."""
    handle = os.open(path, os.O_RDONLY)
    try:
        os.fsync(handle)
    finally:
        os.close(handle)


def _remove(path: str) -> None:
    with contextlib.suppress(FileNotFoundError):
        os.remove(path)
