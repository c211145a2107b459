"""A scene folder on disk (``olsplat sim make`` writes them; so can COLMAP): the prior map,
the SfM cameras, the frames, and the cache of each view's regions and features.

Layout: ``map/point_cloud.ply``, ``sparse/0/`` (COLMAP model), ``images/`` (the frames),
``cache/encode/<encoder>/<frame stem>.npz`` (written by ``olsplat encode`` or on first use;
``encoders.bank.encode_cache_file``).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..encoders import encode_regions
from ..encoders.bank import encode_cache_file, load_bank, save_bank, view_key
from ..errors import OlsplatInputError
from ..regions import RegionConfig, propose_regions
from ..scene import Camera, read_colmap


@dataclass
class Scene:
    folder: Path
    ply: Path
    cameras: list[Camera]

    @staticmethod
    def open(folder: str | Path) -> Scene:
        folder = Path(folder)
        ply = folder / "map" / "point_cloud.ply"
        missing = [str(p) for p in (ply, folder / "sparse" / "0", folder / "images") if not p.exists()]
        if missing:
            raise OlsplatInputError(f"{folder}: not a scene folder (missing {', '.join(missing)})")
        return Scene(folder, ply, read_colmap(folder / "sparse" / "0"))

    def image(self, camera: Camera) -> np.ndarray:
        """The view's frame [H, W, 3] uint8 RGB; OlsplatInputError when missing or mis-sized."""
        path = self.folder / "images" / camera.name
        bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
        if bgr is None:
            raise OlsplatInputError(f"{path}: missing or not an image")
        if bgr.shape[:2] != (camera.height, camera.width):
            raise OlsplatInputError(
                f"{path}: {bgr.shape[1]}x{bgr.shape[0]}, but its camera says {camera.width}x{camera.height}"
            )
        return np.ascontiguousarray(bgr[..., ::-1])


def view_features(
    scene: Scene, camera: Camera, encoder, region_config: RegionConfig | None = None
) -> tuple[np.ndarray, list[np.ndarray]]:
    """(label maps [L, H, W], bank per level) of one view, from the scene's cache when it holds
    this encoder's features for these region settings (``olsplat encode``), else computed and
    cached."""
    cache = encode_cache_file(scene.folder, Path(camera.name).stem, encoder.name)
    region_config = region_config or RegionConfig()
    photo = scene.folder / "images" / camera.name
    key = view_key(photo, repr(region_config)) if photo.is_file() else repr(region_config)
    cached = load_bank(cache, encoder.name, key)
    if cached is None:  # a cache file of the layout before per-encoder folders, when it is this encoder's
        cached = load_bank(cache.parent.parent / cache.name, encoder.name, key)
    if cached is not None:
        return cached
    image = scene.image(camera)
    levels = propose_regions(image, region_config)
    bank = encode_regions(image, levels, encoder)
    save_bank(cache, levels.label_maps, bank, key)
    # through float16 as the cache stores them: computed and cached runs give the same numbers
    return levels.label_maps, [f.astype(np.float16).astype(np.float32) for f in bank.features]
