"""MinkUNet: MinkowskiEngine key layout, checkpoint loading with clear errors, a forward pass."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from olsplat_nodes.errors import SceneFormatError
from olsplat_nodes.structure.minkunet import MinkUNet, load_minkunet, minkunet_point_features


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
    rng = np.random.default_rng(0)
    positions = np.unique(np.floor(rng.uniform(0, 20, (600, 3))), axis=0) + 0.5
    opacity = rng.uniform(0, 1, len(positions))
    a = minkunet_point_features(original.eval(), positions, opacity, voxel=1.0)
    b = minkunet_point_features(loaded, positions, opacity, voxel=1.0)
    assert a.shape == (len(positions), 96) and np.isfinite(a).all() and a.std() > 0
    assert np.array_equal(a, b)

    bad = dict(original.state_dict())
    bad["stem.0.kernel"] = torch.zeros(27, 3, 32)
    del bad["up4.1.1.net.4.bn.weight"]
    bad["head.weight"] = torch.zeros(1)
    torch.save(bad, tmp_path / "bad.pt")
    with pytest.raises(
        SceneFormatError,
        match=r"1 missing keys .*up4\.1\.1\.net\.4\.bn\.weight.*1 unexpected keys .*head\.weight.*"
        r"stem\.0\.kernel \(27, 3, 32\) \(expected \(27, 4, 32\)\)",
    ):
        load_minkunet(tmp_path / "bad.pt")
    (tmp_path / "junk.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(SceneFormatError, match="not a PyTorch checkpoint"):
        load_minkunet(tmp_path / "junk.pt")
