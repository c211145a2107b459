"""SegContrast pre-training: ground frame, segments, augmented views, pooling, loss, checkpoint."""

from __future__ import annotations

import numpy as np
import torch

from olsplat_nodes.structure.ground_frame import ground_frame
from olsplat_nodes.structure.minkunet import load_minkunet, minkunet_point_features
from olsplat_nodes.structure.points import StructuralPoints
from olsplat_nodes.structure.segcontrast import (
    PretrainConfig,
    TrainingMap,
    augmented_view,
    info_nce,
    pretrain,
    save_checkpoint,
    segment_max_pool,
    segments,
)

CENTRES = np.array([[30.0, 30.0, 80.0], [20.0, 40.0, 80.0]])
BOXES = [(5, 5, 12, 12, 6), (20, 8, 26, 16, 3), (40, 40, 52, 50, 9), (10, 35, 16, 41, 4), (45, 5, 55, 12, 5)]


def _town() -> StructuralPoints:
    """A 60 x 60 ground (z = 0, one point per unit voxel) with five boxes (walls and roofs)."""
    rng = np.random.default_rng(0)
    cells = [np.c_[np.mgrid[0:60, 0:60].reshape(2, -1).T, np.zeros(3600)]]
    for x0, y0, x1, y1, h in BOXES:
        xs, ys, zs = np.mgrid[x0:x1, y0:y1, 1 : h + 1].reshape(3, -1)
        surface = (xs == x0) | (xs == x1 - 1) | (ys == y0) | (ys == y1 - 1) | (zs == h)
        cells.append(np.c_[xs[surface], ys[surface], zs[surface]])
    positions = np.concatenate(cells) + 0.5
    return StructuralPoints(positions, rng.uniform(0.2, 1, len(positions)).astype(np.float32),
                            np.arange(len(positions)), 1.0)  # fmt: skip


def test_ground_frame_and_segments_find_the_boxes():
    points = _town()
    frame = ground_frame(points, CENTRES)
    ground = points.positions[:, 2] < 1
    assert np.abs(frame.height[ground]).max() < 0.5  # the ground is at height 0
    np.testing.assert_allclose(frame.height[~ground], points.positions[~ground, 2] - 0.5, atol=0.5)
    assert np.allclose(frame.inputs[:, 2], 1.0) and np.allclose(frame.inputs[:, 1], points.opacity)
    label = segments(frame, PretrainConfig(ground_voxels=0.5))
    assert (label[ground] == -1).all()
    assert label.max() + 1 == len(BOXES)
    for x0, y0, x1, y1, _ in BOXES:  # each box is one segment of its own
        inside = (~ground) & (points.positions[:, 0] >= x0) & (points.positions[:, 0] < x1)
        inside &= (points.positions[:, 1] >= y0) & (points.positions[:, 1] < y1)
        assert len(np.unique(label[inside])) == 1 and label[inside][0] >= 0


def test_an_augmented_view_keeps_a_window_and_moves_it_rigidly():
    points = _town()
    config = PretrainConfig(crop_voxels=40, jitter_voxels=0.0, scale=(1.5, 1.5), dropout=0.2)
    centre = np.array([30.0, 30.0, 0.0])
    keep, moved = augmented_view(points.positions, centre, config, np.random.default_rng(3))
    local = points.positions[keep, :2] - centre[:2]
    in_window = np.sum((np.abs(points.positions[:, :2] - 30) < 20).all(1))
    assert (np.abs(local) <= 20).all() and 0.4 < len(keep) / in_window < 0.7  # 0.85^2 x 0.8 of the window
    i, j = np.random.default_rng(0).integers(len(keep), size=(2, 200))
    before = np.linalg.norm(points.positions[keep[i]] - points.positions[keep[j]], axis=1)
    after = np.linalg.norm(moved[i] - moved[j], axis=1)
    np.testing.assert_allclose(after, 1.5 * before, atol=1e-9)  # rotation and mirror keep distances
    np.testing.assert_allclose(moved[:, 2], 1.5 * points.positions[keep, 2])  # "up" stays up


def test_segment_max_pool_and_info_nce_match_plain_definitions():
    g = torch.Generator().manual_seed(0)
    feats, seg = torch.randn((50, 4), generator=g), torch.randint(0, 5, (50,), generator=g)
    seg[:5] = torch.arange(5)
    pooled = segment_max_pool(feats, seg, 5)
    for s in range(5):
        torch.testing.assert_close(pooled[s], feats[seg == s].max(0).values)
    a = torch.nn.functional.normalize(torch.randn((6, 8), generator=g), dim=1)
    b = torch.nn.functional.normalize(torch.randn((6, 8), generator=g), dim=1)
    expected = 0.0
    for i in range(6):  # -log softmax of the matching pair, both directions
        expected -= 0.5 * (torch.log_softmax(a[i] @ b.T / 0.1, 0)[i] + torch.log_softmax(b[i] @ a.T / 0.1, 0)[i]) / 6
    torch.testing.assert_close(info_nce(a, b, 0.1), expected)


def test_pretraining_changes_the_network_and_its_checkpoint_loads(tmp_path):
    points = _town()
    frame = ground_frame(points, CENTRES)
    config = PretrainConfig(steps=6, crop_voxels=56, ground_voxels=0.5, seed=1)
    tmap = TrainingMap(frame, segments(frame, config), "town")
    torch.manual_seed(config.seed)
    from olsplat_nodes.structure.minkunet import MinkUNet

    untrained = minkunet_point_features(MinkUNet(3, config.cr).eval(), points, CENTRES)
    model = pretrain([tmap], config, log=lambda _: None)
    trained = minkunet_point_features(model, points, CENTRES)
    assert trained.shape == (len(points), 24) and not np.allclose(trained, untrained)
    path = save_checkpoint(model, tmp_path / "s.pt", config, "a test town")
    loaded = load_minkunet(path)
    assert loaded.inputs == "height-opacity"
    np.testing.assert_array_equal(minkunet_point_features(loaded, points, CENTRES), trained)
