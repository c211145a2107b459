"""A cache prefetch hint for numba kernels (LLVM's ``llvm.prefetch``), which numba does not expose.

A rasterizer tile reads its Gaussians' records and feature rows from scattered places in the
map's arrays: one cache miss each. Asking for the lines of the next rows ahead of the copy lets
the core wait for many misses at once instead of one after another.
"""

from __future__ import annotations

from typing import Any

from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic


def _prefetch(typingctx, array, row, column):
    """Numba typing and code of ``prefetch(array, row, column)``."""
    integers = isinstance(row, types.Integer) and isinstance(column, types.Integer)
    if not isinstance(array, types.Array) or array.ndim != 2 or not integers:
        return None
    signature = types.void(array, row, column)

    def codegen(context, builder, sig, args):
        array_type, row_type, column_type = sig.args
        view = context.make_array(array_type)(context, builder, args[0])
        index = [
            context.cast(builder, args[1], row_type, types.intp),
            context.cast(builder, args[2], column_type, types.intp),
        ]
        pointer = cgutils.get_item_pointer(context, builder, array_type, view, index, wraparound=False)
        byte_pointer = ir.IntType(8).as_pointer()
        i32 = ir.IntType(32)
        hint = cgutils.get_or_insert_function(
            builder.module, ir.FunctionType(ir.VoidType(), [byte_pointer, i32, i32, i32]), "llvm.prefetch.p0i8"
        )
        # read (0), keep in all cache levels (3), data cache (1)
        builder.call(hint, [builder.bitcast(pointer, byte_pointer), i32(0), i32(3), i32(1)])
        return context.get_dummy_value()

    return signature, codegen


# Called from numba code as prefetch(array, row, column): hint that the cache line holding
# array[row, column] (a 2-D array, indices >= 0) will be read soon; no effect on results.
# (Typed Any: the intrinsic's Python signature is numba's typing hook, not the call's.)
prefetch: Any = intrinsic(_prefetch)
