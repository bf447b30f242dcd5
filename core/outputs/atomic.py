"""Files written whole or not at all: a reader (or a crash) never sees half a file."""
from __future__ import annotations

import contextlib
import os
import tempfile

from .ownership import space_checked


@contextlib.contextmanager
def atomic_file(path: str, mode: str = "wb", encoding: str | None = None):
    """Yield a stream to a temporary file beside ``path``; when the block ends normally it is
    flushed to disk and renamed over ``path``, otherwise removed (and ``path`` left as it was). A full disk raises
    core.errors.OutputRefused ("not enough space in FOLDER")."""
    folder = os.path.dirname(os.path.abspath(path))
    with space_checked(folder):
        handle, temporary = tempfile.mkstemp(prefix=f".{os.path.basename(path)}.", suffix=".tmp", dir=folder)
    try:
        with space_checked(folder):
            with os.fdopen(handle, mode, encoding=encoding) as stream:
                yield stream
                stream.flush()
                os.fsync(stream.fileno())
        os.replace(temporary, path)
    except BaseException:
        if os.path.exists(temporary):
            os.remove(temporary)
        raise


def remove_written(files, folders) -> None:
    """Take back what a failed or cancelled run wrote: each of ``files`` (paths) that exists,
    then each of ``folders`` (paths, in the order they were made: parents before children)
    that is left empty, the last made first. A folder that holds anything else stays."""
    for path in files:
        if os.path.isfile(path):
            os.remove(path)
    for folder in reversed(list(folders)):
        if os.path.isdir(folder) and not os.listdir(folder):
            os.rmdir(folder)
