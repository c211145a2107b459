"""Scene presets: from unit-test size to the size of the paper's scenes."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Preset:
    name: str
    n_gaussians: int  # ground-truth Gaussians (the reconstructed map has about as many)
    n_views: int
    width: int
    height: int
    size_m: float  # side of the square town, metres
    altitude_m: float


PRESETS = {
    p.name: p
    for p in (
        Preset("tiny", 20_000, 12, 320, 240, 100.0, 60.0),  # 10,000 m^2, for unit tests
        Preset("small", 300_000, 60, 640, 480, 130.0, 70.0),  # 16,900 m^2
        Preset("medium", 1_000_000, 150, 960, 720, 170.0, 90.0),  # 28,900 m^2
        Preset("large", 4_000_000, 300, 1280, 960, 230.0, 110.0),  # 52,900 m^2, like the paper's scenes
    )
}
