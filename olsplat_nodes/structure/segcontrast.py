"""Self-supervised pre-training of the MinkUNet with SegContrast's segment-contrastive objective.

SegContrast (Nunes et al., RA-L 2022) needs no labels: remove the ground, cut the rest of the
point cloud into segments by clustering, make two randomly augmented views of the same cloud,
pool the network's point features per segment and pull each segment's two views together while
pushing it away from the other segments. What we do, per training step:

1. a square window (``crop_voxels`` wide, in the ground frame) of one map's point set;
2. two views of it, each: a random sub-window (``keep_window`` of the side), random point
   dropout, rotation about "up", a mirror, scaling and jitter (in voxel units), then voxelised;
3. the MinkUNet's voxel features, back to points, max-pooled per segment (ground excluded),
   a projection head (MLP), L2-normalised;
4. InfoNCE over the segments seen in both views (temperature ``temperature``): the other
   segments of the window are the negatives (SegContrast keeps a MoCo queue of negatives from
   a momentum encoder; with one window per step on a CPU we use the window's own segments).

Ground: points lower than ``ground_voxels`` above the ground level (the descriptors' ground
filter, ``height_above_ground``, moved up to the most common height); segments: DBSCAN
(open3d) on the rest, eps ``dbscan_eps_voxels``, clusters under ``min_segment_points`` dropped.

Network inputs (``INPUTS = "height-opacity"``, 3 channels): the point's height above the
ground as a fraction of the flight altitude, the source Gaussian's opacity, and a constant 1
(occupancy). Coordinates are voxel indices in the ground frame ("up" = the ground-plane
normal turned to the cameras), so a map's orientation and units never matter.
Everything here is a pure function of its inputs and the seed (no sockets, no files except
``save_checkpoint``).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from torch import nn

from ..errors import OlsplatInputError
from .ground_frame import GroundFrame, voxelise
from .minkunet import MinkUNet
from .sparse_conv import SparseTensor

INPUTS = "height-opacity"  # the input recipe of checkpoints made here (see minkunet.INPUT_RECIPES)


@dataclass(frozen=True)
class PretrainConfig:
    cr: float = 0.25  # channel ratio of the MinkUNet (1.0 = SegContrast's size; 0.25 sized for a CPU)
    steps: int = 1200  # training windows
    crop_voxels: int = 96  # side of a training window, voxels
    keep_window: float = 0.85  # each view keeps a random sub-window of this share of the side
    dropout: float = 0.1  # share of points each view drops
    scale: tuple[float, float] = (0.9, 1.1)
    jitter_voxels: float = 0.1
    ground_voxels: float = 1.5  # points less high than this above the ground are ground
    dbscan_eps_voxels: float = 1.5
    min_segment_points: int = 20
    head_dim: int = 64
    temperature: float = 0.1
    lr: float = 1e-3  # Adam
    seed: int = 0


def segments(frame: GroundFrame, config: PretrainConfig = PretrainConfig()) -> np.ndarray:
    """[P] int64 segment id per point, -1 for ground and DBSCAN noise."""
    import open3d as o3d

    above = np.flatnonzero(frame.height >= config.ground_voxels)
    labels = np.full(len(frame.voxels), -1, np.int64)
    if len(above) == 0:
        return labels
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(frame.voxels[above]))
    # a surface point has ~8 neighbours within 1.5 voxels: 4 makes a core point, small clusters go after
    found = np.asarray(cloud.cluster_dbscan(config.dbscan_eps_voxels, 4, False))
    sizes = np.bincount(found[found >= 0], minlength=1)
    big = np.flatnonzero(sizes >= config.min_segment_points)
    rank = np.full(len(sizes) + 1, -1, np.int64)  # last entry: DBSCAN's noise (-1)
    rank[big] = np.arange(len(big))
    labels[above] = rank[found]
    return labels


def augmented_view(
    voxels: np.ndarray, centre: np.ndarray, config: PretrainConfig, rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray]:
    """(kept point indices [M], their augmented positions [M, 3] in voxel units) of one view of
    the window of side ``config.crop_voxels`` around ``centre`` (ground-frame voxels)."""
    half = config.crop_voxels / 2
    side = config.keep_window * config.crop_voxels
    low = centre[:2] - half + rng.uniform(0, config.crop_voxels - side, 2)
    inside = np.all((voxels[:, :2] >= low) & (voxels[:, :2] < low + side), axis=1)
    keep = np.flatnonzero(inside & (rng.random(len(voxels)) >= config.dropout))
    local = voxels[keep] - np.r_[centre[:2], 0.0]
    angle = rng.uniform(0, 2 * np.pi)
    c, s = np.cos(angle), np.sin(angle)
    rotation = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    if rng.random() < 0.5:
        rotation = rotation @ np.diag([-1.0, 1.0, 1.0])
    moved = local @ rotation.T * rng.uniform(*config.scale) + rng.normal(0, config.jitter_voxels, local.shape)
    return keep, moved


def segment_max_pool(point_feats: torch.Tensor, segment: torch.Tensor, n_segments: int) -> torch.Tensor:
    """[S, C] the max over each segment's points of [P, C] features (segment ids 0..S-1, every
    segment non-empty)."""
    out = point_feats.new_full((n_segments, point_feats.shape[1]), -torch.inf)
    index = segment[:, None].expand(-1, point_feats.shape[1])
    return out.scatter_reduce(0, index, point_feats, reduce="amax", include_self=True)


def info_nce(a: torch.Tensor, b: torch.Tensor, temperature: float) -> torch.Tensor:
    """Symmetric InfoNCE of [S, D] L2-normalised embeddings where row i of ``a`` and of ``b``
    are the same segment; every other row is a negative."""
    logits = a @ b.T / temperature
    target = torch.arange(len(a))
    return 0.5 * (nn.functional.cross_entropy(logits, target) + nn.functional.cross_entropy(logits.T, target))


class ProjectionHead(nn.Module):
    def __init__(self, c_in: int, dim: int):
        super().__init__()
        self.net = nn.Sequential(nn.Linear(c_in, c_in), nn.ReLU(), nn.Linear(c_in, dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return nn.functional.normalize(self.net(x), dim=1)


@dataclass
class TrainingMap:
    frame: GroundFrame
    segment: np.ndarray  # [P] int64, -1 = ground / noise
    name: str


def _view_segment_features(model, head, tmap: TrainingMap, keep, moved, common):
    """[len(common), head_dim] projected, normalised features of the segments ``common`` in one
    augmented view (points ``keep`` of the map at positions ``moved``), row i = common[i]."""
    coords, inputs, inverse = voxelise(moved, tmap.frame.inputs[keep])
    voxel_feats = model(SparseTensor(torch.from_numpy(coords), torch.from_numpy(inputs), 1)).feats
    seg = tmap.segment[keep]
    rank = np.full(tmap.segment.max() + 2, -1, np.int64)
    rank[common] = np.arange(len(common))
    point_rank = rank[seg]  # -1 for ground and for segments not in both views
    use = np.flatnonzero(point_rank >= 0)
    feats = voxel_feats[torch.from_numpy(inverse[use])]
    return head(segment_max_pool(feats, torch.from_numpy(point_rank[use]), len(common)))


def pretrain(maps: list[TrainingMap], config: PretrainConfig = PretrainConfig(), log=print) -> MinkUNet:
    """A MinkUNet (3 inputs, channel ratio ``config.cr``) trained with the segment-contrastive
    objective on windows of ``maps`` (see the module docstring), returned in eval mode."""
    if not maps:
        raise ValueError("pre-training needs at least one map")
    bare = [m.name for m in maps if not (m.segment >= 0).any()]
    if bare:  # a window must hold segments to contrast
        raise OlsplatInputError(
            f"map {', '.join(bare)}: no segment above the ground (points at least {config.ground_voxels:g} voxels "
            f"high in clusters of >= {config.min_segment_points} points): nothing to contrast; a larger preset "
            "(small) has buildings and trees that do"
        )
    torch.manual_seed(config.seed)
    rng = np.random.default_rng(config.seed)
    model = MinkUNet(in_channels=3, cr=config.cr)
    head = ProjectionHead(model.out_channels, config.head_dim)
    optimiser = torch.optim.Adam([*model.parameters(), *head.parameters()], lr=config.lr)
    model.train()
    start, losses, skipped = time.perf_counter(), [], 0
    for step in range(config.steps):
        tmap = maps[step % len(maps)]
        anchors = np.flatnonzero(tmap.segment >= 0)
        centre = tmap.frame.voxels[anchors[rng.integers(len(anchors))]]
        views = [augmented_view(tmap.frame.voxels, centre, config, rng) for _ in range(2)]
        in_both = np.intersect1d(tmap.segment[views[0][0]], tmap.segment[views[1][0]])
        common = in_both[in_both >= 0]
        if len(common) < 2:  # nothing to contrast in this window
            skipped += 1
            continue
        a, b = (_view_segment_features(model, head, tmap, keep, moved, common) for keep, moved in views)
        loss = info_nce(a, b, config.temperature)
        optimiser.zero_grad()
        loss.backward()
        optimiser.step()
        losses.append(float(loss.detach()))
        if (step + 1) % 50 == 0 or step + 1 == config.steps:
            recent = losses[-50:]
            log(f"step {step + 1}/{config.steps}: InfoNCE {np.mean(recent):.3f} over the last {len(recent)} windows "
                f"(chance {np.log(len(common)):.2f} for this one, {len(common)} segments), "
                f"{time.perf_counter() - start:.0f} s")  # fmt: skip
    if skipped:
        log(f"{skipped} windows had fewer than two segments in both views and were skipped")
    return model.eval()


def save_checkpoint(model: MinkUNet, path: Path, config: PretrainConfig, trained_on: str, half: bool = False) -> Path:
    """The backbone in SegContrast's checkpoint layout ({"model": state dict} with
    MinkowskiEngine's key names), plus an "olsplat" record of how it was made and which input
    recipe it expects; written atomically. ``half``: floating tensors stored as float16 (half
    the file; ``load_minkunet`` computes in float32 either way)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    record = {"inputs": INPUTS, "cr": config.cr, "trained_on": trained_on, "config": repr(asdict(config))}
    tmp = path.with_name(path.name + ".tmp")
    state = {k: v.half() if half and v.is_floating_point() else v for k, v in model.state_dict().items()}
    torch.save({"model": state, "olsplat": {**record, "stored_as": "float16" if half else "float32"}}, tmp)
    tmp.replace(path)
    return path
