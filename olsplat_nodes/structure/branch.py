"""The 3D branch as one object the aggregation calls per view: built once per map (points and
their structural features), then, per view, region pooling with visibility, an online h_theta
update and the lambda_f fusion of the view's region bank.

Streaming: view t is fused with h_theta as trained on views 1..t. Until h has seen
``DistillConfig.warmup_regions`` regions, views keep their 2D bank (an untrained h would only
add noise); they are not revisited, so a map built from a stream is a little more 2D than one
built with a trained h. Fusion applies to every region level.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..scene import Camera, Gaussians
from .descriptors import geometric_descriptors
from .distill import DistillConfig, OnlineDistiller, fuse_regions
from .points import StructuralPoints, structural_points
from .pooling import Visibility, pool_regions, visible_pixels

# the MinkUNet pre-trained here with SegContrast's objective (``olsplat sim train-structure``)
SHIPPED_MINKUNET = Path(__file__).resolve().parent / "assets" / "segcontrast-olsplat.pt"


def minkunet_path(value: str | Path | None) -> Path | None:
    """A user's choice of MinkUNet checkpoint: "shipped" = SHIPPED_MINKUNET, "" or None = none
    (geometric descriptors), anything else a file path."""
    if value is None or str(value) == "":
        return None
    return SHIPPED_MINKUNET if str(value) == "shipped" else Path(value)


@dataclass(frozen=True)
class StructureConfig:
    tau_o: float = 0.1  # opacity threshold of the point set (paper's tau_o; value not given there)
    voxel: float | None = None  # voxel side in map units; None = auto (about 150k points on the ground footprint)
    lambda_f: float = 0.7  # weight of the 2D feature in the fusion (paper)
    lambda_f_points: int = 0  # > 0: the 3D share scales with a region's visible points up to this many (not the paper)
    visibility: Visibility = Visibility()
    distill: DistillConfig = field(default_factory=DistillConfig)
    minkunet: Path | None = None  # a MinkUNet checkpoint for the point features; None = geometric descriptors


def structure_record(config: StructureConfig) -> dict:
    """The settings that decide a fused map's numbers, JSON-ready (the store's manifest)."""
    record = {
        "lambda_f": config.lambda_f,
        "tau_o": config.tau_o,
        "voxel": config.voxel,
        "minkunet": str(config.minkunet) if config.minkunet is not None else None,
    }
    if config.lambda_f_points:  # only when set: stores made before the option existed still match
        record["lambda_f_points"] = config.lambda_f_points
    return record


class StructuralBranch:
    def __init__(
        self,
        points: StructuralPoints,
        features: np.ndarray,
        config: StructureConfig = StructureConfig(),
        camera_centres: np.ndarray | None = None,
    ):
        """``features`` [P, D3]: one structural feature per point of ``points``, made with the
        ``camera_centres`` [V, 3] (world) that ``build`` was given."""
        self.config, self.points, self.features = config, points, features
        self.camera_centres = None if camera_centres is None else np.asarray(camera_centres, np.float64)
        self.distiller: OnlineDistiller | None = None
        self.losses: list[float] = []  # mean distillation loss per view

    @staticmethod
    def build(
        gaussians: Gaussians, camera_centres: np.ndarray, config: StructureConfig = StructureConfig()
    ) -> StructuralBranch:
        """Point set and point features of a map (once per map); camera centres [V, 3] give "up"."""
        points = structural_points(gaussians, config.tau_o, config.voxel)
        if config.minkunet is not None:
            from .minkunet import load_minkunet, minkunet_point_features  # torch: ~1 s to import, only for this

            features = minkunet_point_features(load_minkunet(config.minkunet), points, camera_centres)
        else:
            features = geometric_descriptors(points, np.asarray(camera_centres, np.float64))
        return StructuralBranch(points, features, config, camera_centres)

    def state(self) -> dict[str, np.ndarray]:
        """What a restarted stream needs to go on exactly as this one would: the camera centres
        the point features were made with, h_theta's full training state and the losses so far."""
        if self.camera_centres is None:
            raise ValueError("a branch made without build() has no camera centres to save")
        arrays = {"camera_centres": self.camera_centres, "losses": np.asarray(self.losses, np.float64)}
        if self.distiller is not None:
            arrays.update({f"h.{k}": v for k, v in self.distiller.state().items()})
        return arrays

    @staticmethod
    def restore(gaussians: Gaussians, state: dict[str, np.ndarray], config: StructureConfig) -> StructuralBranch:
        """The branch of ``state()`` over the same map (its point features made again, the same
        way); KeyError/ValueError when the state does not fit."""
        branch = StructuralBranch.build(gaussians, np.asarray(state["camera_centres"], np.float64), config)
        distiller = {k[2:]: v for k, v in state.items() if k.startswith("h.")}
        if distiller:
            branch.distiller = OnlineDistiller.from_state(distiller)
            if branch.distiller.in_dim != branch.features.shape[1]:
                raise ValueError(
                    f"h_theta takes {branch.distiller.in_dim}-d point features, "
                    f"the map gives {branch.features.shape[1]}"
                )
        branch.losses = [float(x) for x in state["losses"]]
        return branch

    def fuse_view(
        self, camera: Camera, depth: np.ndarray, label_maps: np.ndarray, bank: list[np.ndarray]
    ) -> list[np.ndarray]:
        """The view's fused region bank (one [R_l, D] array per level), training h on the way."""
        visible = visible_pixels(self.points.positions, camera, depth, self.points.voxel, self.config.visibility)
        pooled, counts = pool_regions(self.features, visible, label_maps, [len(b) for b in bank])
        if self.distiller is None:
            self.distiller = OnlineDistiller(self.features.shape[1], bank[0].shape[1], self.config.distill)
        f3d = np.concatenate([p[c > 0] for p, c in zip(pooled, counts, strict=True)])
        f2d = np.concatenate([b[c > 0] for b, c in zip(bank, counts, strict=True)])
        self.losses.append(self.distiller.update(f3d, f2d))
        if not self.distiller.ready:
            return bank
        return [
            fuse_regions(b, self.distiller.project(p), c, self.config.lambda_f, self.config.lambda_f_points)
            for b, p, c in zip(bank, pooled, counts, strict=True)
        ]
