"""What a relight of a kept preparation can take from the last one: light that does not
depend on what changed.

Direct light is linear in each lamp's power and colour, so a lamp whose shape, place,
shadowing and linking are unchanged (:func:`core.lights.lamps.lamp_shape_key`) needs no
new shadow ray: its unit light, kept here, times the new power and colour is bitwise what
the pass would give again. The directly sampled emitters and the gather of emitted and world
light depend only on the preparation (geometry, materials), the groups' emitters and the
world, so they are kept under a key of those. An artist turning a lamp's power or colour,
the most common relight, then pays for the bounce gathers alone.

Kept per :class:`core.pipeline.prepare.Prepared`, so it lives as long as the preparation
(the Relight button's resident one) and never outlives a change of geometry or materials.
At most DEFAULT_LIMIT_BYTES; a kept preparation's memo gets what the preference Resident
Memory leaves beside the preparation, if less.
"""
from __future__ import annotations

import threading
from collections import OrderedDict

import numpy as np

DEFAULT_LIMIT_BYTES = 256 << 20


class LightMemo:
    """Results kept by key, least recently used dropped past ``limit_bytes``.

    Values are arrays (or tuples holding arrays and plain numbers); they are handed out
    as they are, so callers never write into them.
    """

    def __init__(self, limit_bytes: int = DEFAULT_LIMIT_BYTES):
        self.limit_bytes = int(limit_bytes)
        self._entries: OrderedDict = OrderedDict()
        self._lock = threading.Lock()

    @staticmethod
    def _size(value) -> int:
        parts = value if isinstance(value, tuple) else (value,)
        return sum(part.nbytes for part in parts if isinstance(part, np.ndarray))

    def get(self, key):
        """The value kept under ``key``, or None."""
        with self._lock:
            value = self._entries.get(key)
            if value is not None:
                self._entries.move_to_end(key)
            return value

    def put(self, key, value) -> None:
        """Keep ``value`` under ``key`` unless it alone exceeds the limit; drop the least
        recently used entries until everything fits."""
        if self._size(value) > self.limit_bytes:
            return
        with self._lock:
            self._entries[key] = value
            self._entries.move_to_end(key)
            while sum(self._size(v) for v in self._entries.values()) > self.limit_bytes:
                self._entries.popitem(last=False)

    def clear(self) -> None:
        """Drop everything kept (a preparation that will not be relit again needs none of it)."""
        with self._lock:
            self._entries.clear()

    def nbytes(self) -> int:
        with self._lock:
            return sum(self._size(v) for v in self._entries.values())

    def __len__(self) -> int:
        return len(self._entries)
