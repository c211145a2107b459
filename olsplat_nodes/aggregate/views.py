"""The run's view folder: every accepted view's photo and camera, kept so that nothing a user
gave us is lost and so that the query server can render a heatmap over any view it has seen.

Layout: ``VIEWS/NNNNNN.jpg`` (the photo, JPEG quality 95) and ``VIEWS/NNNNNN.json``
(name, width, height, K [3x3 row-major], dist, world_from_camera [4x4 row-major, OpenCV camera
axes: x right, y down, z forward]), where NNNNNN is the view's index in the observation store.
The JSON is written last and atomically (temp + rename): a view without its JSON does not exist.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..errors import OlsplatInputError
from ..scene import Camera


def save_view(folder: str | Path, index: int, camera: Camera, image_rgb: np.ndarray) -> None:
    """Write view ``index``: photo [H, W, 3] uint8 RGB and camera."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    stem = folder / f"{index:06d}"
    if not cv2.imwrite(str(stem) + ".jpg", np.ascontiguousarray(image_rgb[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, 95]):
        raise OSError(f"{stem}.jpg: cannot write the view's photo")
    record = {
        "name": camera.name,
        "width": camera.width,
        "height": camera.height,
        "K": camera.K.reshape(-1).tolist(),
        "dist": camera.dist.tolist(),
        "world_from_camera": camera.world_from_camera.reshape(-1).tolist(),
    }
    tmp = Path(str(stem) + ".json.tmp")
    tmp.write_text(json.dumps(record))
    tmp.replace(str(stem) + ".json")


@dataclass
class SavedView:
    camera: Camera
    photo: Path  # JPEG

    def image(self) -> np.ndarray:
        """The photo [H, W, 3] uint8 RGB."""
        bgr = cv2.imread(str(self.photo), cv2.IMREAD_COLOR)
        if bgr is None:
            raise OlsplatInputError(f"{self.photo}: the view's photo is missing or unreadable")
        return np.ascontiguousarray(bgr[..., ::-1])


def load_views(folder: str | Path) -> list[SavedView]:
    """Every saved view, in index order (none when the folder does not exist yet)."""
    views = []
    for path in sorted(Path(folder).glob("*.json")):
        try:
            r = json.loads(path.read_text())
            camera = Camera(r["name"], r["width"], r["height"], r["K"], r["world_from_camera"], r["dist"])
        except (ValueError, KeyError, TypeError) as exc:
            raise OlsplatInputError(f"{path}: not a view record ({exc})") from None
        views.append(SavedView(camera, path.with_suffix(".jpg")))
    return views
