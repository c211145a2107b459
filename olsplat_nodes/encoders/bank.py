"""Region features of one view: every region of every level through the encoder(s)."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..regions import RegionLevels
from .base import VisionLanguageEncoder
from .crops import CropConfig, region_crops
from .fusion import FusedEncoder


@dataclass
class FeatureBank:
    features: list[np.ndarray]  # per level l: [counts[l], D] float32, unit rows; row r = region r
    encoder: str  # the encoder (or fusion) that made them

    @property
    def dim(self) -> int:
        return self.features[0].shape[1]


def encode_regions(
    image_rgb: np.ndarray,  # [H, W, 3] uint8
    levels: RegionLevels,
    encoder: VisionLanguageEncoder | FusedEncoder,
    crop_config: CropConfig = CropConfig(),
    batch: int = 64,
) -> FeatureBank:
    """Crop every region of every level and embed it (see ``crops`` for how crops are made).

    An encoder with a ``crop_config`` of its own (shipped ones say how they were trained)
    gets crops made that way; others get ``crop_config``.
    """
    if image_rgb.ndim != 3 or image_rgb.shape[2] != 3 or image_rgb.dtype != np.uint8:
        raise ValueError(f"image must be [H, W, 3] uint8 RGB, got shape {image_rgb.shape} dtype {image_rgb.dtype}")
    members = encoder.encoders if isinstance(encoder, FusedEncoder) else [encoder]
    features = []
    for label_map in levels.label_maps:
        # each member gets crops its own way: its input size and, if it has one, its crop style
        crops = [
            region_crops(image_rgb, label_map, m.input_size, getattr(m, "crop_config", None) or crop_config)
            for m in members
        ]
        chunks = []
        for start in range(0, len(crops[0]), batch):
            part = [c[start : start + batch] for c in crops]
            chunks.append(
                encoder.encode_crops(part) if isinstance(encoder, FusedEncoder) else encoder.encode_images(part[0])
            )
        features.append(np.concatenate(chunks).astype(np.float32))
    return FeatureBank(features, encoder.name)


def encode_cache_file(scene_folder: Path, view_stem: str, encoder_name: str | None) -> Path:
    """Where a view's cached regions and features live: ``SCENE/cache/encode/<encoder>/<view>.npz``,
    one folder per encoder name (``regions`` for label maps without features), so that runs
    alternating encoders (Table 6's each-alone and fused, Table 7's weights) each keep their own
    instead of overwriting one file. The folder name is the encoder name with anything but
    letters, digits, ``.``, ``_``, ``-`` as ``_``, plus 8 hex digits of its sha1 (no collisions)."""
    import re

    if encoder_name is None:
        folder = "regions"
    else:
        slug = re.sub(r"[^A-Za-z0-9._-]", "_", encoder_name)[:60]
        folder = f"{slug}-{hashlib.sha1(encoder_name.encode()).hexdigest()[:8]}"
    return Path(scene_folder) / "cache" / "encode" / folder / f"{view_stem}.npz"


def view_key(image_path: Path, regions: str) -> str:
    """What a view's cache entry depends on: the region settings and the image's bytes (SHA-256),
    so that a new photo under an old name, or other settings, never reuses old regions. The
    encoder is checked apart (``load_bank``)."""
    digest = hashlib.sha256(Path(image_path).read_bytes()).hexdigest()
    return f"{regions}|image sha256 {digest}"


def save_bank(path: Path, label_maps: np.ndarray, bank: FeatureBank | None, regions: str) -> None:
    """One view's regions (and features) as the scene cache keeps them: ``label_maps`` [L, H, W]
    int32, ``features_<l>`` [R_l, D] float16, ``encoder``, ``regions`` (the region proposer's
    settings, e.g. ``repr(RegionConfig)``); written to a temp file, then renamed."""
    arrays: dict[str, Any] = {"label_maps": label_maps, "regions": np.array(regions)}
    if bank is not None:
        arrays.update({f"features_{i}": f.astype(np.float16) for i, f in enumerate(bank.features)})
        arrays["encoder"] = np.array(bank.encoder)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.stem + ".tmp.npz")
    np.savez_compressed(tmp, **arrays)
    tmp.replace(path)


def load_bank(path: Path, encoder_name: str, regions: str) -> tuple[np.ndarray, list[np.ndarray]] | None:
    """(label maps, float32 features per level) from a cache file made for ``encoder_name`` with
    the region settings ``regions``, else None (the caller computes them again)."""
    if not path.exists():
        return None
    data = np.load(path)
    if "encoder" not in data or str(data["encoder"]) != encoder_name:
        return None
    if "regions" not in data or str(data["regions"]) != regions:
        return None
    maps = data["label_maps"]
    return maps, [data[f"features_{i}"].astype(np.float32) for i in range(len(maps))]
