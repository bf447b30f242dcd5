"""The session's memo of in-memory unwraps: found by exactly what the unwrap reads, bounded."""
import numpy as np
import pytest

from core.sampling.atlas import UnwrapResult
from core.sampling.unwrap_memo import UnwrapMemo, unwrap_key


def _result(triangles: int) -> UnwrapResult:
    return UnwrapResult(corner_uv=np.zeros((triangles, 3, 2), np.float32), width=16, height=16,
                        degenerate=np.zeros(triangles, bool), texels_per_unit=1.0, chart_count=1)


def _quad():
    positions = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], np.float64)
    return positions, np.array([[0, 1, 2], [0, 2, 3]], np.int64)


def test_the_key_changes_with_anything_the_unwrap_reads():
    positions, triangles = _quad()
    key = unwrap_key(positions, triangles, 16)
    assert unwrap_key(positions.copy(), triangles.copy(), 16) == key
    moved = positions.copy()
    moved[2, 0] = np.nextafter(1.0, 2.0)  # one ulp
    assert unwrap_key(moved, triangles, 16) != key
    assert unwrap_key(positions, triangles[:, [0, 2, 1]], 16) != key
    assert unwrap_key(positions, triangles, 32) != key
    # The same numbers in another dtype are another input to xatlas's caller.
    assert unwrap_key(positions.astype(np.float32), triangles, 16) != key


def test_the_memo_drops_the_least_recently_used_beyond_its_cap():
    size = _result(100).corner_uv.nbytes + 100
    memo = UnwrapMemo(max_bytes=2 * size)
    memo.put("a", _result(100))
    memo.put("b", _result(100))
    assert memo.get("a") is not None  # now the most recently used
    memo.put("c", _result(100))
    assert memo.get("b") is None and memo.get("a") is not None and memo.get("c") is not None
    assert memo.nbytes == 2 * size and len(memo) == 2
    memo.put("huge", _result(1000))  # larger than the whole cap: not kept, nothing dropped
    assert memo.get("huge") is None and len(memo) == 2
    memo.put("a", _result(100))  # replacing an entry does not count it twice
    assert memo.nbytes == 2 * size
    memo.clear()
    assert len(memo) == 0 and memo.nbytes == 0


def test_a_kept_result_cannot_be_changed_by_whoever_reads_it():
    memo = UnwrapMemo()
    memo.put("a", _result(4))
    with pytest.raises(ValueError):
        memo.get("a").corner_uv[0, 0, 0] = 1.0
