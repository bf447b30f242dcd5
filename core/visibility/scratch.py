"""Large arrays kept in a scratch file's mapping, whose pages the process can hand back.

A table at Production settings is 1.7 GB: held in anonymous memory it sits in the process's
resident set from the trace to the last gather, though each pass reads it once, in order.
Held in a shared mapping of a file, the pages a pass has finished with are handed back
(``madvise(MADV_DONTNEED)``): their contents stay in the file (the system's page cache holds
them as long as it has room, and writes them to disk when it needs the memory), and reading
them again maps them back. Resident memory then holds only the part of the table a pass is
working on.

The file is made with ``tempfile.TemporaryFile``: on POSIX it has no name from the start, so
nothing is left behind however the process ends; on Windows the system deletes it when the
last handle (the mapping's) closes. Its space is reserved up front (``posix_fallocate``), so a
full disk is found before the trace, not as a fault in the middle of it (where the system has
no ``posix_fallocate``, twice the file's size must be free on the disk).

Where the system cannot hand pages back (Windows: ``mmap.madvise`` does not exist), the
mapping still works and :meth:`ScratchArrays.release` does nothing.
"""
from __future__ import annotations

import mmap
import os
import shutil
import tempfile

import numpy as np

# Arrays start at page boundaries, so that handing back one array's pages never touches another's.
_ALIGN = mmap.PAGESIZE
# Tables smaller than this stay in memory: mapping them saves little, and costs a file.
MIN_MAPPED_BYTES = 64 << 20
_CAN_RELEASE = hasattr(mmap.mmap, "madvise") and hasattr(mmap, "MADV_DONTNEED")


class ScratchArrays:
    """Arrays of given dtypes and shapes in one mapped, nameless scratch file in ``folder``.

    ``layout``: name -> (dtype, shape). Raises OSError where the file cannot be made or its
    space cannot be reserved (no room on the disk): the caller keeps the arrays in memory then.
    """

    def __init__(self, folder: str | None, layout: dict):
        offsets, size = {}, 0
        for name, (dtype, shape) in layout.items():
            offsets[name] = size
            nbytes = int(np.dtype(dtype).itemsize * np.prod(shape, dtype=np.int64))
            size += -(-nbytes // _ALIGN) * _ALIGN
        self.nbytes = max(size, _ALIGN)
        if not hasattr(os, "posix_fallocate"):
            # Without a reservation the file is sparse, and a write into a full disk through the
            # mapping is a fault (SIGBUS), not an error: ask for twice the room, or stay in memory.
            free = shutil.disk_usage(folder or tempfile.gettempdir()).free
            if free < 2 * self.nbytes:
                raise OSError(f"{free / 2**20:.0f} MiB free in {folder}, {2 * self.nbytes / 2**20:.0f} MiB wanted")
        with tempfile.TemporaryFile(prefix="visibake-table-", dir=folder) as stream:
            if hasattr(os, "posix_fallocate"):
                os.posix_fallocate(stream.fileno(), 0, self.nbytes)
            else:
                stream.truncate(self.nbytes)
            # The mapping keeps its own handle: the file lives as long as the mapping does.
            self._map = mmap.mmap(stream.fileno(), self.nbytes, access=mmap.ACCESS_WRITE)
        self.arrays = {name: np.frombuffer(self._map, np.dtype(dtype), int(np.prod(shape, dtype=np.int64)),
                                           offsets[name]).reshape(shape)
                       for name, (dtype, shape) in layout.items()}

    def release(self) -> None:
        """Hand back every page of the mapping that is resident (the contents stay: see the
        module docstring). Cheap where few are: the system skips the unmapped ranges."""
        if _CAN_RELEASE:
            self._map.madvise(mmap.MADV_DONTNEED, 0, self.nbytes)


def mapped_layout(arrays: dict) -> bool:
    """Whether arrays of ``arrays`` (name -> (dtype, shape)) are large enough to map."""
    return sum(int(np.dtype(d).itemsize * np.prod(s, dtype=np.int64)) for d, s in arrays.values()) >= MIN_MAPPED_BYTES


class MappedFile:
    """A file mapped copy-on-write (``mmap.ACCESS_COPY``: writable arrays, so the compiled
    kernels take them as they take any table, while the file itself is never written), whose
    resident pages can be handed back like a scratch file's: untouched pages are read again
    from the file. Used for a cached table read in place (core.visibility.cache). POSIX only:
    on Windows a mapped file could not be replaced by the next bake's table.

    Raises OSError where the file cannot be opened or mapped."""

    def __init__(self, path: str):
        with open(path, "rb") as stream:
            self.nbytes = os.fstat(stream.fileno()).st_size
            self._map = mmap.mmap(stream.fileno(), 0, access=mmap.ACCESS_COPY)

    def array(self, offset: int, dtype, shape: tuple) -> np.ndarray:
        """The (shape) ``dtype`` array whose bytes start at ``offset`` of the file."""
        return np.frombuffer(self._map, np.dtype(dtype), int(np.prod(shape, dtype=np.int64)), offset).reshape(shape)

    def release(self) -> None:
        """Hand back every resident page (see :meth:`ScratchArrays.release`)."""
        if _CAN_RELEASE:
            self._map.madvise(mmap.MADV_DONTNEED, 0, self.nbytes)


CAN_MAP_FILES = os.name == "posix"
