"""MinkUNet: MinkowskiEngine key layout, checkpoint loading with clear errors, a forward pass."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from olsplat_nodes.errors import SceneFormatError
from olsplat_nodes.structure.minkunet import MinkUNet, load_minkunet, minkunet_point_features
from olsplat_nodes.structure.points import StructuralPoints

CENTRES = np.array([[10.0, 10.0, 60.0], [12.0, 8.0, 60.0]])  # cameras above the points: "up" is +z


def _points(seed=0) -> StructuralPoints:
    """A ground plane (z = 0) with a few boxes on it, one point per unit voxel."""
    rng = np.random.default_rng(seed)
    ground = np.c_[np.mgrid[0:20, 0:20].reshape(2, -1).T, np.zeros(400)]
    boxes = np.unique(np.floor(rng.uniform([2, 2, 1], [8, 8, 5], (300, 3))), axis=0)
    positions = np.r_[ground, boxes] + 0.5
    return StructuralPoints(positions, rng.uniform(0, 1, len(positions)).astype(np.float32),
                            np.arange(len(positions)), 1.0)  # fmt: skip


def test_key_layout_is_minkowski_engines():
    state = MinkUNet(4).state_dict()
    assert tuple(state["stem.0.kernel"].shape) == (27, 4, 32)
    assert "stem.1.bn.running_mean" in state and tuple(state["stem.3.kernel"].shape) == (27, 32, 32)
    assert tuple(state["stage1.0.net.0.kernel"].shape) == (8, 32, 32)
    assert tuple(state["stage2.1.downsample.0.kernel"].shape) == (1, 32, 64)
    assert tuple(state["up1.0.net.0.kernel"].shape) == (8, 256, 256)
    assert tuple(state["up1.1.0.net.0.kernel"].shape) == (27, 256 + 128, 256)
    assert tuple(state["up4.1.1.net.3.kernel"].shape) == (27, 96, 96)


def test_checkpoint_round_trip_and_errors(tmp_path):
    torch.manual_seed(0)
    original = MinkUNet(4)
    for module in original.modules():  # non-trivial running statistics, as a trained network has
        if isinstance(module, torch.nn.BatchNorm1d):
            module.running_mean.uniform_(-0.1, 0.1)
            module.running_var.uniform_(0.5, 1.5)
    checkpoint = {"model": {f"module.{k}": v for k, v in original.state_dict().items()}, "epoch": 3}
    torch.save(checkpoint, tmp_path / "segcontrast.pt")
    loaded = load_minkunet(tmp_path / "segcontrast.pt")
    assert loaded.inputs == "xyz-opacity"  # no olsplat record: SegContrast's own input recipe
    points = _points()
    a = minkunet_point_features(original.eval(), points, CENTRES)
    b = minkunet_point_features(loaded, points, CENTRES)
    assert a.shape == (len(points), 96) and np.isfinite(a).all() and a.std() > 0
    assert np.array_equal(a, b)

    bad = dict(original.state_dict())
    bad["stage1.0.net.0.kernel"] = torch.zeros(8, 32, 16)
    del bad["up4.1.1.net.4.bn.weight"]
    bad["head.weight"] = torch.zeros(1)
    torch.save(bad, tmp_path / "bad.pt")
    with pytest.raises(
        SceneFormatError,
        match=r"1 missing keys .*up4\.1\.1\.net\.4\.bn\.weight.*1 unexpected keys .*head\.weight.*"
        r"stage1\.0\.net\.0\.kernel \(8, 32, 16\) \(expected \(8, 32, 32\)\)",
    ):
        load_minkunet(tmp_path / "bad.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(SceneFormatError, match="not a PyTorch checkpoint"):
        load_minkunet(tmp_path / "junk.pt")


def test_a_smaller_network_with_an_olsplat_record_loads(tmp_path):
    torch.manual_seed(1)
    original = MinkUNet(3, cr=0.25)
    torch.save({"model": original.state_dict(), "olsplat": {"inputs": "height-opacity", "cr": 0.25}}, tmp_path / "s.pt")
    loaded = load_minkunet(tmp_path / "s.pt")
    assert loaded.inputs == "height-opacity" and loaded.out_channels == 24
    points = _points(1)
    a = minkunet_point_features(original.eval(), points, CENTRES)
    assert a.shape == (len(points), 24) and np.array_equal(a, minkunet_point_features(loaded, points, CENTRES))
    torch.save({"model": original.state_dict(), "olsplat": {"inputs": "xyz-opacity"}}, tmp_path / "wrong.pt")
    with pytest.raises(SceneFormatError, match="takes 3 input channels; its recipe 'xyz-opacity' gives 4"):
        load_minkunet(tmp_path / "wrong.pt")
