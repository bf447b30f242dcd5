"""Memory: what this machine has, what a bake may take, and the refusal before
anything is allocated."""
from __future__ import annotations

import os
import sys

from ..errors import BakeRefused
from ..visibility.table import table_bytes


def physical_memory_bytes() -> int:
    """Installed memory, or 0 where it cannot be read."""
    try:
        return int(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))
    except (ValueError, OSError, AttributeError):
        return 0


def peak_memory_bytes() -> int:
    """Peak resident memory of this process so far, or 0 where it cannot be read."""
    try:
        import resource
    except ImportError:
        return 0
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return int(peak if sys.platform == "darwin" else peak * 1024)


_LIBC = None
# The heap's free bytes above which release_free_heap hands them back: below it, the pages are
# worth more kept for the next pass (each page given back is a fault when it is used again).
TRIM_FREE_BYTES = 128 << 20


def _libc():
    """glibc with malloc_trim and mallinfo2 typed, or None (another C library or system)."""
    global _LIBC
    if _LIBC is None:
        _LIBC = False
        if sys.platform.startswith("linux"):
            try:
                import ctypes

                class Mallinfo2(ctypes.Structure):
                    _fields_ = [(name, ctypes.c_size_t) for name in (
                        "arena", "ordblks", "smblks", "hblks", "hblkhd", "usmblks", "fsmblks", "uordblks",
                        "fordblks", "keepcost")]

                libc = ctypes.CDLL("libc.so.6")
                libc.malloc_trim.argtypes = [ctypes.c_size_t]
                libc.mallinfo2.restype = Mallinfo2
                _LIBC = libc
            except (OSError, AttributeError):  # not glibc, or older than 2.33 (no mallinfo2)
                pass
    return _LIBC or None


def release_free_heap(above: int = TRIM_FREE_BYTES) -> None:
    """Hand the allocator's free memory back to the system where it holds more than
    ``above`` bytes (glibc's ``malloc_trim``; nothing elsewhere). Numpy's arrays under glibc's
    mmap threshold, which rises to 32 MiB once larger arrays are freed, come from the heap,
    whose free pages glibc keeps: between the passes of a Production bake that is a few hundred
    megabytes of resident memory holding nothing. A call takes milliseconds; a fixed threshold
    instead cost 20% of a Production bake's time in page faults (docs/benchmarks.md, speed
    part 10)."""
    libc = _libc()
    if libc is not None and libc.mallinfo2().fordblks > above:
        libc.malloc_trim(0)


def memory_budget_bytes() -> int:
    """How much the table may take: half the installed memory (the rest is Blender's)."""
    physical = physical_memory_bytes()
    return physical // 2 if physical else 8 << 30


def human_bytes(count: float) -> str:
    for unit in ("B", "KiB", "MiB", "GiB", "TiB"):
        if count < 1024 or unit == "TiB":
            return f"{count:.1f} {unit}"
        count /= 1024
    return f"{count:.1f} TiB"


def check_budget(sizes, directions: int, budget: int | None = None) -> None:
    """Refuse, before anything is allocated, atlases or a table that cannot fit in memory.

    Parameters
    ----------
    sizes : iterable of (width, height), the atlas of every object
    directions : size of the direction set

    The bound counts every texel of every atlas (covered ones are fewer), so a bake
    that passes here cannot run out of memory in the table.
    """
    budget = memory_budget_bytes() if budget is None else budget
    sizes = [(int(w), int(h)) for w, h in sizes]
    for width, height in sizes:
        if width < 1 or height < 1:
            raise BakeRefused(f"atlas resolution must be at least 1x1, got {width}x{height}")
    texels = sum(w * h for w, h in sizes)
    # Per texel: coverage, per-sample geometry and colours, radiance atlases and outputs.
    per_texel = 200
    need_atlas = texels * per_texel
    if need_atlas > budget:
        raise BakeRefused(f"the atlases ({texels} texels) would need about {human_bytes(need_atlas)}, "
                          f"more than the {human_bytes(budget)} available; lower the resolution")
    need_table = table_bytes(directions, texels)
    if need_table + need_atlas > budget:
        raise BakeRefused(f"the visibility table ({directions} directions x up to {texels} texels) "
                          f"could need {human_bytes(need_table)}, more than the {human_bytes(budget - need_atlas)} "
                          f"available; lower the directions or the resolution")
