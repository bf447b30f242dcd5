"""Unwraps kept between bakes of one session, for objects that get no UV map.

An object that only occludes and reflects is unwrapped in memory, since VisiBake never
writes a UV map onto a mesh it does not bake. Its unwrap would otherwise run again at
every bake: a benchmark room's unbaked shell (242 triangles) cost 0.2-0.25 s of a 0.4-0.6 s
bake, most of it starting the unwrap's child process. A baked object keeps its unwrap in
its ``VisiBake`` UV map; this memo gives the others the same.

An entry is found by a digest of exactly what the unwrap reads (world-space positions,
triangles, resolution), so a moved, edited or resized object is unwrapped anew.
"""
from __future__ import annotations

import hashlib
from collections import OrderedDict

import numpy as np

from .atlas import UnwrapResult

# Bytes of corner UVs kept (24 per triangle): a 64 MiB memo holds 2.8 M triangles' unwraps.
DEFAULT_MEMO_BYTES = 64 << 20


def unwrap_key(positions: np.ndarray, triangles: np.ndarray, resolution: int) -> str:
    """The memo's key of an unwrap of ``positions`` (n, 3) float and ``triangles`` (m, 3) int
    at ``resolution``: a BLAKE2b digest of their dtypes, shapes and bytes."""
    digest = hashlib.blake2b(digest_size=20)
    for array in (np.ascontiguousarray(positions), np.ascontiguousarray(triangles)):
        digest.update(f"{array.dtype.str}{array.shape};".encode())
        digest.update(array.reshape(-1).view(np.uint8))
    digest.update(f"resolution={int(resolution)}".encode())
    return digest.hexdigest()


class UnwrapMemo:
    """Least recently used unwraps (:class:`UnwrapResult`), at most ``max_bytes`` of corner
    UVs in all. The results handed out are shared and read-only."""

    def __init__(self, max_bytes: int = DEFAULT_MEMO_BYTES):
        self.max_bytes = int(max_bytes)
        self._results: OrderedDict[str, UnwrapResult] = OrderedDict()
        self._bytes = 0

    def __len__(self) -> int:
        return len(self._results)

    @property
    def nbytes(self) -> int:
        return self._bytes

    def get(self, key: str) -> UnwrapResult | None:
        result = self._results.get(key)
        if result is not None:
            self._results.move_to_end(key)
        return result

    def put(self, key: str, result: UnwrapResult) -> None:
        """Keep ``result`` under ``key``, dropping the least recently used beyond the cap; a
        result larger than the whole cap is not kept."""
        size = _size(result)
        if size > self.max_bytes:
            return
        if key in self._results:
            self._bytes -= _size(self._results.pop(key))
        for array in (result.corner_uv, result.degenerate):
            array.setflags(write=False)
        self._results[key] = result
        self._bytes += size
        while self._bytes > self.max_bytes:
            _, dropped = self._results.popitem(last=False)
            self._bytes -= _size(dropped)

    def clear(self) -> None:
        self._results.clear()
        self._bytes = 0


def _size(result: UnwrapResult) -> int:
    return int(result.corner_uv.nbytes + result.degenerate.nbytes)
