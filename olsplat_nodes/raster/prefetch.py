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


def _prefetch_row(typingctx, array, row):
    """Numba typing and code of ``prefetch_row(array, row)``."""
    if not isinstance(array, types.Array) or array.ndim != 2 or not isinstance(row, types.Integer):
        return None
    signature = types.void(array, row)

    def codegen(context, builder, sig, args):
        array_type, row_type = sig.args
        view = context.make_array(array_type)(context, builder, args[0])
        index = [context.cast(builder, args[1], row_type, types.intp), context.get_constant(types.intp, 0)]
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


# Called from numba code as prefetch_row(array, row): hint that array[row, 0] (a 2-D array,
# row >= 0) will be read soon; no effect on results. (Typed Any: the intrinsic's Python
# signature is numba's typing hook, not the call's.)
prefetch_row: Any = intrinsic(_prefetch_row)
