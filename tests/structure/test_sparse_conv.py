"""The hash-based sparse convolutions against torch's dense 3D convolutions on a small grid."""

from __future__ import annotations

import torch

from olsplat_nodes.structure.sparse_conv import SparseTensor, conv, conv_transpose, kernel_offsets


def _occupied(seed=0, side=8, share=0.3, channels=3):
    g = torch.Generator().manual_seed(seed)
    mask = torch.rand((side, side, side), generator=g) < share
    coords = torch.nonzero(mask).to(torch.int64)
    feats = torch.randn((len(coords), channels), generator=g)
    return coords, feats


def _dense(coords, feats, side):
    grid = torch.zeros((1, feats.shape[1], side, side, side))
    grid[0, :, coords[:, 0], coords[:, 1], coords[:, 2]] = feats.T
    return grid


def _dense_weight(kernel, size):
    """[K, C_in, C_out] in MinkowskiEngine order -> torch conv3d weight [C_out, C_in, x, y, z]."""
    offsets = kernel_offsets(size) - kernel_offsets(size).min(0).values
    weight = torch.zeros((kernel.shape[2], kernel.shape[1], size, size, size))
    for k, (ox, oy, oz) in enumerate(offsets.tolist()):
        weight[:, :, ox, oy, oz] = kernel[k].T
    return weight


def test_offset_orders():
    assert kernel_offsets(3)[:3].tolist() == [[-1, -1, -1], [0, -1, -1], [1, -1, -1]]  # x fastest
    assert kernel_offsets(2)[:3].tolist() == [[0, 0, 0], [0, 0, 1], [0, 1, 0]]  # z fastest


def test_submanifold_conv_equals_dense_conv_at_occupied_voxels():
    coords, feats = _occupied()
    kernel = torch.randn((27, 3, 5))
    out = conv(SparseTensor(coords, feats, 1), kernel, 3, 1)
    dense = torch.nn.functional.conv3d(_dense(coords, feats, 8), _dense_weight(kernel, 3), padding=1)
    assert torch.equal(out.coords, coords)
    torch.testing.assert_close(out.feats, dense[0, :, coords[:, 0], coords[:, 1], coords[:, 2]].T, atol=1e-5, rtol=1e-5)


def test_strided_conv_and_transpose_equal_dense():
    coords, feats = _occupied(seed=1)
    down_kernel, up_kernel = torch.randn((8, 3, 4)), torch.randn((8, 4, 2))
    x = SparseTensor(coords, feats, 1)
    down = conv(x, down_kernel, 2, 2)
    dense_down = torch.nn.functional.conv3d(_dense(coords, feats, 8), _dense_weight(down_kernel, 2), stride=2)
    assert down.stride == 2 and (down.coords % 2 == 0).all()
    half = down.coords // 2
    torch.testing.assert_close(down.feats, dense_down[0, :, half[:, 0], half[:, 1], half[:, 2]].T, atol=1e-5, rtol=1e-5)
    occupied_parents = dense_down.abs().sum(1)[0] > 0
    assert occupied_parents.sum() <= len(down.coords)  # every occupied parent is an output voxel
    up = conv_transpose(down, up_kernel, 2, 2)
    transpose_weight = _dense_weight(up_kernel, 2).transpose(0, 1)  # conv_transpose3d wants [C_in, C_out, ...]
    dense_up = torch.nn.functional.conv_transpose3d(_dense(half, down.feats, 4), transpose_weight, stride=2)
    assert torch.equal(up.coords, coords) and up.stride == 1  # back onto the input's coordinates
    torch.testing.assert_close(
        up.feats, dense_up[0, :, coords[:, 0], coords[:, 1], coords[:, 2]].T, atol=1e-5, rtol=1e-5
    )


def test_gradients_equal_dense():
    """Training needs the backward pass: input and kernel gradients match conv3d's."""
    coords, feats = _occupied(seed=2)
    feats.requires_grad_(True)
    kernel = torch.randn((27, 3, 4), requires_grad=True)
    probe = torch.randn((len(coords), 4))
    (conv(SparseTensor(coords, feats, 1), kernel, 3, 1).feats * probe).sum().backward()
    dense_feats = feats.detach().clone().requires_grad_(True)
    weight = kernel.detach().clone().requires_grad_(True)
    dense = torch.nn.functional.conv3d(_dense(coords, dense_feats, 8), _dense_weight(weight, 3), padding=1)
    (dense[0, :, coords[:, 0], coords[:, 1], coords[:, 2]].T * probe).sum().backward()
    torch.testing.assert_close(feats.grad, dense_feats.grad, atol=1e-4, rtol=1e-4)
    torch.testing.assert_close(kernel.grad, weight.grad, atol=1e-4, rtol=1e-4)
