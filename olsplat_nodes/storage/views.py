"""The run's view folder: every accepted view's photo and camera, kept so that nothing a user
gave us is lost and so that the query server can render a heatmap over any view it has seen.

Layout: ``VIEWS/NNNNNN.jpg`` (the photo, JPEG quality 95) and ``VIEWS/NNNNNN.json``
(name, width, height, K [3x3 row-major], dist, world_from_camera [4x4 row-major, OpenCV camera
axes: x right, y down, z forward]), where NNNNNN is the view's index in the observation store.
Both are written atomically and fsynced (``durable.py``), the JSON last: a view without its
JSON does not exist, and one with it has its photo, also after a power cut.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ..durable import write_atomic
from ..errors import OlsplatInputError
from ..scene import Camera


def save_view(folder: str | Path, index: int, camera: Camera, image_rgb: np.ndarray) -> int:
    """Write view ``index``: photo [H, W, 3] uint8 RGB and camera; returns the bytes written."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    stem = folder / f"{index:06d}"
    ok, jpeg = cv2.imencode(".jpg", np.ascontiguousarray(image_rgb[..., ::-1]), [cv2.IMWRITE_JPEG_QUALITY, 95])
    if not ok:
        raise OSError(f"{stem}.jpg: cannot encode the view's photo")
    write_atomic(str(stem) + ".jpg", jpeg.tobytes())
    record = {
        "name": camera.name,
        "width": camera.width,
        "height": camera.height,
        "K": camera.K.reshape(-1).tolist(),
        "dist": camera.dist.tolist(),
        "world_from_camera": camera.world_from_camera.reshape(-1).tolist(),
    }
    data = json.dumps(record).encode()
    write_atomic(str(stem) + ".json", data)  # last: the view exists once it does
    return len(jpeg) + len(data)


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
