"""Sparse 3D convolution in plain PyTorch (no MinkowskiEngine / spconv: they do not install here).

A sparse tensor holds integer voxel coordinates [N, 3] at a tensor stride s (coordinates are
multiples of s, MinkowskiEngine's convention) and features [N, C]. Neighbours are found by
hashing each coordinate triple into one int64 key (21 bits per axis) and looking keys up in
a sorted key table (binary search): no dense grid is ever allocated, so memory follows the
number of occupied voxels.

Kernels are stored as MinkowskiEngine stores them, [K, C_in, C_out], with its offset order
(odd kernels: x varies fastest; even kernels: z fastest; offsets -1..1 for size 3 and 0..1 for
size 2, times the input stride), so MinkowskiEngine checkpoints load unchanged.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field

import torch

_BITS = 21
_SHIFT = 1 << (_BITS - 1)  # coordinates in [-2^20, 2^20)


def kernel_offsets(size: int) -> torch.Tensor:
    """[size^3, 3] int64 offsets (in units of the input stride), in MinkowskiEngine's order."""
    axis = list(range(-((size - 1) // 2), size // 2 + 1)) if size % 2 else list(range(0, size))
    if size % 2:  # x fastest
        triples = [(x, y, z) for z in axis for y in axis for x in axis]
    else:  # z fastest
        triples = list(itertools.product(axis, axis, axis))
    return torch.tensor(triples, dtype=torch.int64)


def coordinate_keys(coords: torch.Tensor) -> torch.Tensor:
    """[N, 3] int64 -> [N] int64 keys, unique per coordinate triple in range."""
    c = coords + _SHIFT
    if bool(((c < 0) | (c >= (1 << _BITS))).any()):
        raise ValueError(f"voxel coordinates must lie in [-{_SHIFT}, {_SHIFT}); use a larger voxel")
    return (c[:, 0] << (2 * _BITS)) | (c[:, 1] << _BITS) | c[:, 2]


class CoordinateTable:
    """Row lookup for coordinate triples: the hash keys, sorted, searched with binary search."""

    def __init__(self, coords: torch.Tensor):
        keys = coordinate_keys(coords)
        self.sorted_keys, self.order = torch.sort(keys)

    def lookup(self, coords: torch.Tensor) -> torch.Tensor:
        """[M, 3] -> [M] int64 row of each coordinate, -1 where it is not occupied."""
        if len(self.sorted_keys) == 0:
            return torch.full((len(coords),), -1, dtype=torch.int64)
        keys = coordinate_keys(coords)
        position = torch.searchsorted(self.sorted_keys, keys).clamp(max=len(self.sorted_keys) - 1)
        found = self.sorted_keys[position] == keys
        return torch.where(found, self.order[position], torch.full_like(position, -1))


@dataclass
class SparseTensor:
    coords: torch.Tensor  # [N, 3] int64, multiples of stride
    feats: torch.Tensor  # [N, C] float32
    stride: int
    # the coordinates of every stride made so far in this forward pass (MinkowskiEngine's
    # coordinate manager): transposed convolutions return to them
    levels: dict[int, tuple[torch.Tensor, CoordinateTable]] = field(default_factory=dict)
    # neighbour tables already built in this forward pass, by (input stride, kernel size,
    # conv stride): every convolution of a level reuses its level's table (MinkowskiEngine's
    # kernel-map cache); the lookups otherwise dominate a forward pass
    kernel_maps: dict[tuple[int, int, int], torch.Tensor] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if self.stride not in self.levels:
            self.levels[self.stride] = (self.coords, CoordinateTable(self.coords))

    @property
    def table(self) -> CoordinateTable:
        return self.levels[self.stride][1]

    def with_feats(self, feats: torch.Tensor) -> SparseTensor:
        return SparseTensor(self.coords, feats, self.stride, self.levels, self.kernel_maps)


_CHUNK = 1 << 15  # output rows per gathered block: bounds the [rows, K, C_in] gather's memory


def _neighbours(x: SparseTensor, coords_out: torch.Tensor, size: int, stride: int) -> torch.Tensor:
    """[N_out, K] int64 input row of each output voxel's k-th kernel offset; ``len(x.feats)``
    (the index of an appended zero row) where that neighbour is not occupied."""
    key = (x.stride, size, stride)
    if key not in x.kernel_maps:
        offsets = kernel_offsets(size) * x.stride
        rows = torch.stack([x.table.lookup(coords_out + offsets[k]) for k in range(len(offsets))], dim=1)
        x.kernel_maps[key] = torch.where(rows >= 0, rows, torch.full_like(rows, len(x.coords)))
    return x.kernel_maps[key]


def conv(x: SparseTensor, kernel: torch.Tensor, size: int, stride: int) -> SparseTensor:
    """Convolution with a [size^3, C_in, C_out] kernel; stride 1 keeps the coordinates, stride 2
    halves the resolution (output voxels: the occupied parents at stride 2 s).

    Each output row gathers its K neighbours' features (a zero row where a neighbour is empty)
    into [rows, K * C_in] and multiplies once by the kernel flattened to [K * C_in, C_out]."""
    if stride == 1:
        coords_out, stride_out = x.coords, x.stride
    else:
        stride_out = x.stride * stride
        if stride_out in x.levels:
            coords_out = x.levels[stride_out][0]
        else:
            coords_out = torch.unique(torch.div(x.coords, stride_out, rounding_mode="floor") * stride_out, dim=0)
    neighbours = _neighbours(x, coords_out, size, stride)
    padded = torch.cat([x.feats, x.feats.new_zeros((1, x.feats.shape[1]))])
    weight = kernel.reshape(-1, kernel.shape[2])  # [K * C_in, C_out], k-major as the gather
    blocks = [
        padded[neighbours[i : i + _CHUNK]].reshape(-1, weight.shape[0]) @ weight
        for i in range(0, len(coords_out), _CHUNK)
    ]
    out = torch.cat(blocks) if blocks else x.feats.new_zeros((0, kernel.shape[2]))
    return SparseTensor(coords_out, out, stride_out, x.levels, x.kernel_maps)


def conv_transpose(x: SparseTensor, kernel: torch.Tensor, size: int, stride: int) -> SparseTensor:
    """Transposed convolution back to the finer stride s / stride, onto that stride's existing
    coordinates: output voxel c takes its parent p's feature through kernel entry (c - p) / s.

    Every parent is multiplied by all 8 kernel entries at once ([N_parent, 8, C_out]); each
    output row then picks its parent's row and its own entry."""
    if size != 2 or stride != 2:
        raise ValueError("only kernel size 2, stride 2 transposed convolutions are implemented (MinkUNet's)")
    stride_out = x.stride // stride
    if stride_out not in x.levels:
        raise ValueError(f"no coordinates at stride {stride_out} to return to")
    coords_out = x.levels[stride_out][0]
    parent = torch.div(coords_out, x.stride, rounding_mode="floor") * x.stride
    offset = torch.div(coords_out - parent, stride_out, rounding_mode="floor")
    entry = offset[:, 0] * 4 + offset[:, 1] * 2 + offset[:, 2]  # z fastest, as kernel_offsets(2)
    rows = x.table.lookup(parent)
    if bool((rows < 0).any()):  # cannot happen when x was made from these coordinates by conv
        raise ValueError("a voxel's parent is not in the coarser tensor")
    all_entries = (x.feats @ kernel.permute(1, 0, 2).reshape(kernel.shape[1], -1)).reshape(len(x.feats), 8, -1)
    return SparseTensor(coords_out, all_entries[rows, entry], stride_out, x.levels, x.kernel_maps)
