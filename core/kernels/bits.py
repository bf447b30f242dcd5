"""Bit operations the table kernels share: finding a stored entry of the visibility table from
its (direction, sample) (core.visibility.table.TableEntries) by counting the set bits below it.

The counts are LLVM's own intrinsics (one POPCNT / TZCNT instruction where the CPU has it),
which numba does not expose; so is the reading of a float32's bits as an int32 and back (a
register move, where numba would need an array and two views of it).
"""
from __future__ import annotations

import numba as nb
import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic


@intrinsic
def popcount(typingctx, word):
    """The number of set bits of a uint64."""
    if word != types.uint64:
        return None

    def codegen(context, builder, signature, args):
        return builder.ctpop(args[0])

    return types.uint64(types.uint64), codegen


@intrinsic
def trailing_zeros(typingctx, word):
    """The index of the lowest set bit of a non-zero uint64."""
    if word != types.uint64:
        return None

    def codegen(context, builder, signature, args):
        return builder.cttz(args[0], context.get_constant(types.boolean, True))

    return types.uint64(types.uint64), codegen


@intrinsic
def float32_bits(typingctx, value):
    """The bits of a float32, as an int32 (a bit cast, like numpy's ``view(np.int32)``)."""
    if value != types.float32:
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(32))

    return types.int32(types.float32), codegen


@intrinsic
def bits_float32(typingctx, value):
    """:func:`float32_bits` undone: the float32 whose bits are the int32 ``value``."""
    if value != types.int32:
        return None

    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.FloatType())

    return types.float32(types.int32), codegen


@nb.njit(inline="always")
def entry_of(above_words, word_base, direction, sample):
    """The index among the stored entries of (direction, sample), or -1 where that entry is
    not stored (below the sample's horizon): the word's first entry plus the set bits below
    the sample's bit."""
    word = above_words[direction, sample >> 6]
    bit = np.uint64(sample & 63)
    if (word >> bit) & np.uint64(1) == np.uint64(0):
        return np.int64(-1)
    below = word & ((np.uint64(1) << bit) - np.uint64(1))
    return word_base[direction, sample >> 6] + np.int64(popcount(below))
