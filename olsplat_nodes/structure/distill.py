"""h_theta: the 2-layer MLP that maps pooled 3D structural features into the language space
(paper eq. distillation), trained online as views stream, and the lambda_f fusion.

Training: the cosine loss 1 - cos(h(f3D), f2D) over a view's regions that hold visible points
(the 2D feature is the teacher, never updated), a few Adam steps per view on the new regions
mixed with a reservoir of earlier ones, so later views do not make it forget earlier ones.
Weights are saved as plain ``.npz`` arrays (no pickle): a loaded h gives identical outputs.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import SceneFormatError


@dataclass(frozen=True)
class DistillConfig:
    hidden: int = 256
    learning_rate: float = 3e-3
    steps_per_view: int = 30
    batch: int = 512
    reservoir: int = 20_000  # earlier (f3D, f2D) pairs kept for replay
    warmup_regions: int = 500  # fuse only once h has been trained on this many regions (2-6 views)
    seed: int = 0


class OnlineDistiller:
    def __init__(self, in_dim: int, out_dim: int, config: DistillConfig = DistillConfig()):
        import torch

        self.config, self.in_dim, self.out_dim = config, in_dim, out_dim
        generator = torch.Generator().manual_seed(config.seed)
        self.model = torch.nn.Sequential(
            torch.nn.Linear(in_dim, config.hidden), torch.nn.ReLU(), torch.nn.Linear(config.hidden, out_dim)
        )
        with torch.no_grad():
            for p in self.model.parameters():  # seeded initialisation, independent of torch's global state
                p.copy_(torch.empty(p.shape).uniform_(-1, 1, generator=generator) / np.sqrt(p.shape[-1]))
        self.optimizer = torch.optim.Adam(self.model.parameters(), lr=config.learning_rate)
        self.rng = np.random.default_rng(config.seed)
        self.seen = 0  # regions trained on so far
        self.memory_3d = np.zeros((0, in_dim), np.float32)
        self.memory_2d = np.zeros((0, out_dim), np.float32)

    @property
    def ready(self) -> bool:
        return self.seen >= self.config.warmup_regions

    def _remember(self, f3d: np.ndarray, f2d: np.ndarray) -> None:
        """Reservoir sampling: every pair seen so far is in memory with equal probability."""
        room = max(self.config.reservoir - len(self.memory_3d), 0)
        self.memory_3d = np.vstack([self.memory_3d, f3d[:room]])
        self.memory_2d = np.vstack([self.memory_2d, f2d[:room]])
        rest = np.arange(room, len(f3d))
        slots = self.rng.integers(0, self.seen + rest + 1)  # item i is the (seen + i + 1)-th pair
        keep = slots < self.config.reservoir
        self.memory_3d[slots[keep]] = f3d[rest[keep]]
        self.memory_2d[slots[keep]] = f2d[rest[keep]]
        self.seen += len(f3d)

    def update(self, f3d: np.ndarray, f2d: np.ndarray) -> float:
        """A few training steps on this view's pairs ([R, in], [R, out]) plus replay; mean loss."""
        import torch

        if len(f3d) == 0:
            return float("nan")
        f3d, f2d = f3d.astype(np.float32), f2d.astype(np.float32)
        losses = []
        for _ in range(self.config.steps_per_view):
            old = (
                self.rng.integers(0, len(self.memory_3d), min(self.config.batch, len(self.memory_3d)))
                if len(self.memory_3d)
                else np.zeros(0, int)
            )
            x = torch.from_numpy(np.vstack([f3d, self.memory_3d[old]]))
            y = torch.from_numpy(np.vstack([f2d, self.memory_2d[old]]))
            loss = (1.0 - torch.nn.functional.cosine_similarity(self.model(x), y, dim=1)).mean()
            self.optimizer.zero_grad()
            loss.backward()
            self.optimizer.step()
            losses.append(float(loss.detach()))
        self._remember(f3d, f2d)
        return float(np.mean(losses))

    def project(self, f3d: np.ndarray) -> np.ndarray:
        """[R, in] -> [R, out] float32 unit rows h(f3D) / |h(f3D)|."""
        import torch

        with torch.no_grad():
            out = self.model(torch.from_numpy(f3d.astype(np.float32))).numpy()
        return out / np.maximum(np.linalg.norm(out, axis=1, keepdims=True), 1e-12)

    def save(self, path: str | Path) -> None:
        arrays: dict[str, Any] = {f"param_{i}": p.detach().numpy() for i, p in enumerate(self.model.parameters())}
        np.savez(
            path,
            in_dim=self.in_dim,
            out_dim=self.out_dim,
            seen=self.seen,
            **arrays,
            **{f"config_{k}": v for k, v in asdict(self.config).items()},
        )

    def state(self) -> dict[str, np.ndarray]:
        """Everything the next update depends on, as plain arrays: the weights, Adam's moments
        and step counts, the replay reservoir, the random generator and the count of regions
        seen. ``from_state`` continues training exactly where this one stopped."""
        arrays = {f"param_{i}": p.detach().numpy().copy() for i, p in enumerate(self.model.parameters())}
        for i, p in enumerate(self.model.parameters()):
            moments = self.optimizer.state.get(p, {})
            for key in ("exp_avg", "exp_avg_sq", "step"):
                if key in moments:
                    arrays[f"adam_{key}_{i}"] = np.asarray(moments[key].detach().numpy()).copy()
        rng = json.dumps(self.rng.bit_generator.state)
        config = json.dumps(asdict(self.config))
        return {
            **arrays,
            "memory_3d": self.memory_3d,
            "memory_2d": self.memory_2d,
            "dims": np.array([self.in_dim, self.out_dim, self.seen], np.int64),
            "rng": np.array(rng),
            "config": np.array(config),
        }

    @staticmethod
    def from_state(state: dict[str, np.ndarray]) -> OnlineDistiller:
        """The distiller that ``state()`` described; KeyError/ValueError when it does not fit."""
        import torch

        in_dim, out_dim, seen = (int(x) for x in state["dims"])
        distiller = OnlineDistiller(in_dim, out_dim, DistillConfig(**json.loads(str(state["config"]))))
        with torch.no_grad():
            for i, p in enumerate(distiller.model.parameters()):
                value = np.asarray(state[f"param_{i}"], np.float32)
                if value.shape != tuple(p.shape):
                    raise ValueError(f"parameter {i} has shape {value.shape}, expected {tuple(p.shape)}")
                p.copy_(torch.from_numpy(value))
                if f"adam_step_{i}" in state:
                    distiller.optimizer.state[p] = {
                        "step": torch.tensor(float(state[f"adam_step_{i}"])),
                        "exp_avg": torch.from_numpy(np.array(state[f"adam_exp_avg_{i}"], np.float32)),
                        "exp_avg_sq": torch.from_numpy(np.array(state[f"adam_exp_avg_sq_{i}"], np.float32)),
                    }
        distiller.memory_3d = np.array(state["memory_3d"], np.float32)
        distiller.memory_2d = np.array(state["memory_2d"], np.float32)
        distiller.rng.bit_generator.state = json.loads(str(state["rng"]))
        distiller.seen = seen
        return distiller

    @staticmethod
    def load(path: str | Path) -> OnlineDistiller:
        import torch

        path = Path(path)
        try:
            data = np.load(path)
            config = DistillConfig(
                **{k[len("config_") :]: data[k].item() for k in data.files if k.startswith("config_")}
            )
            distiller = OnlineDistiller(int(data["in_dim"]), int(data["out_dim"]), config)
            params = list(distiller.model.parameters())
            with torch.no_grad():
                for i, p in enumerate(params):
                    value = data[f"param_{i}"]
                    if value.shape != tuple(p.shape):
                        raise SceneFormatError(
                            path, f"parameter {i} has shape {value.shape}, expected {tuple(p.shape)}"
                        )
                    p.copy_(torch.from_numpy(value))
            distiller.seen = int(data["seen"])
            return distiller
        except FileNotFoundError:
            raise SceneFormatError(path, "does not exist") from None
        except (KeyError, ValueError, TypeError, OSError) as exc:
            raise SceneFormatError(path, f"not an h_theta file ({type(exc).__name__}: {exc})") from None


def fuse_regions(
    f2d: np.ndarray, projected_3d: np.ndarray, counts: np.ndarray, lambda_f: float, full_points: int = 0
) -> np.ndarray:
    """[R, D] fused region features: lambda_f f2D + (1 - lambda_f) |f2D| h^(f3D) where the
    region has visible points (counts > 0), else f2D unchanged (paper eq. 2d3d fusion).

    ``full_points`` > 0 (not in the paper): a region with n visible points gets the 3D share
    (1 - lambda_f) min(1, n / full_points), so a region that pooled a handful of points leans
    on its 2D feature."""
    has = counts > 0
    out = f2d.astype(np.float32).copy()
    share = np.full((int(has.sum()), 1), 1.0 - lambda_f)
    if full_points > 0:
        share *= np.minimum(1.0, counts[has, None] / full_points)
    scale = np.linalg.norm(f2d[has], axis=1, keepdims=True)
    out[has] = (1.0 - share) * f2d[has] + share * scale * projected_3d[has]
    return out
