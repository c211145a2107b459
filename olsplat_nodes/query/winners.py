"""The relevance rule of docs/method.md ("Queries") as single passes over a map's rows.

A Gaussian picks the query when the dot product of its feature with the query's embedding is at
least its dot product with every negative's (the features and embeddings are unit rows, so these
are the cosines of eq. semantic_heatmap). That is numpy's ``(table @ embeddings.T).argmax(1) == 0``
(argmax takes the first maximum, so a tie goes to the query), the reference the tests hold these
kernels to. The numpy form makes an [N, Q] float32 product and reads it again for the argmax, and
reads the rows of never-observed Gaussians; here each row is read once, only when observed, and
the negatives are tried one at a time until one beats the query. On the small demo map (390k
Gaussians, D = 128, 3 negatives): 15-18 ms per query instead of 45-57 ms for one [N, Q] product.

A float16 table (a language map's stored form, which the query server keeps) goes to the C
kernel ``olsplat_nodes/native/winning_rows.c`` (numba has no float16), a float32 one to numba.
"""

from __future__ import annotations

import ctypes
from functools import cache

import numba
import numpy as np
from numba import njit, prange

from ..native import library

_P = ctypes.c_void_p
# winning_rows_half's parameters (native/winning_rows.c): table, n, dim, embeddings, count, observed, wins, threads
_HALF_ARGUMENTS: list = [_P, ctypes.c_int64, ctypes.c_int64, _P, ctypes.c_int64, _P, _P, ctypes.c_int]


@cache
def _half_kernel():
    """The C kernel ``winning_rows_half``, typed, or None without the C kernels."""
    loaded = library()
    if loaded is None:
        return None
    kernel = loaded.winning_rows_half
    kernel.argtypes, kernel.restype = _HALF_ARGUMENTS, None
    return kernel


def winning_rows(table: np.ndarray, embeddings: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """[N] bool: row g of ``table`` [N, D] (float32, or float16 where the C kernels are built)
    picks embeddings[0] over every other row of ``embeddings`` [Q, D] float32, and observed[g]
    ([N] bool; empty: every row counts)."""
    if table.dtype == np.float32:
        return _winning_rows_float32(table, embeddings, observed)
    kernel = _half_kernel()
    if table.dtype != np.float16 or kernel is None:
        raise TypeError(f"winning_rows: a float32 table, or float16 with the C kernels built; got {table.dtype}")
    table = np.ascontiguousarray(table)
    embeddings = np.ascontiguousarray(embeddings, np.float32)
    if embeddings.ndim != 2 or embeddings.shape[1] != table.shape[1] or not len(embeddings):
        raise ValueError(f"embeddings must be [Q >= 1, D={table.shape[1]}], got {embeddings.shape}")
    if len(observed) and len(observed) != len(table):
        raise ValueError(f"observed must be [{len(table)}] or empty, got {len(observed)}")
    seen = np.ascontiguousarray(observed, np.bool_)
    wins = np.empty(len(table), np.bool_)
    kernel(
        table.ctypes.data, len(table), table.shape[1], embeddings.ctypes.data, len(embeddings),
        seen.ctypes.data if len(seen) else None, wins.ctypes.data, numba.get_num_threads(),
    )  # fmt: skip
    return wins


@njit(parallel=True, cache=True, fastmath=True)
def _winning_rows_float32(table: np.ndarray, embeddings: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """``winning_rows`` of a float32 table, in numba."""
    n, dim = table.shape
    wins = np.zeros(n, np.bool_)
    every = observed.shape[0] == 0
    for g in prange(n):
        if not every and not observed[g]:
            continue
        query = np.float32(0.0)
        for d in range(dim):
            query += table[g, d] * embeddings[0, d]
        won = True
        for q in range(1, embeddings.shape[0]):
            other = np.float32(0.0)
            for d in range(dim):
                other += table[g, d] * embeddings[q, d]
            if other > query:
                won = False
                break
        wins[g] = won
    return wins


@njit(parallel=True, cache=True)
def gather_verdicts(verdicts: np.ndarray, rows: np.ndarray, observed: np.ndarray) -> np.ndarray:
    """[M] bool: verdicts[rows[i]] ([K] bool, e.g. a codebook's centres' ``winning_rows``) for
    ``rows`` [M] int32 (-1: no row, False), and observed[i] ([M] bool; empty: every row counts)."""
    out = np.zeros(rows.shape[0], np.bool_)
    every = observed.shape[0] == 0
    for i in prange(rows.shape[0]):
        row = rows[i]
        out[i] = row >= 0 and (every or observed[i]) and verdicts[row]
    return out
