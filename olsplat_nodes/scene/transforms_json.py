"""nerfstudio / instant-ngp ``transforms.json``.

``transform_matrix`` in these files is world-from-camera in the OpenGL/Blender camera
convention (+x right, +y up, +z backwards); we flip y and z to reach OpenCV axes.
Intrinsics may be global or per frame (per-frame values win), as ``fl_x``/``fl_y`` or as
instant-ngp's ``camera_angle_x``/``camera_angle_y``; ``cx``/``cy`` default to the image
centre; ``w``/``h`` are required (or read from the image file when it exists).
Distortion ``k1 k2 p1 p2 k3`` follows nerfstudio's OPENCV model; fisheye is refused.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import SceneFormatError
from .camera import Camera, intrinsics

_GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])  # flips y and z; its own inverse
_DIST_KEYS = ("k1", "k2", "p1", "p2", "k3")


def _image_size(folder: Path, file_path: str) -> tuple[int, int] | None:
    candidate = folder / file_path
    if not candidate.is_file():
        return None
    import cv2  # only needed for files without w/h

    image = cv2.imread(str(candidate), cv2.IMREAD_UNCHANGED)
    return None if image is None else (image.shape[1], image.shape[0])


def read_transforms_json(path: str | Path) -> list[Camera]:
    """All frames of a transforms.json as cameras, in file order."""
    path = Path(path)
    try:
        meta = json.loads(path.read_text())
    except FileNotFoundError:
        raise SceneFormatError(path, "file does not exist") from None
    except IsADirectoryError:
        raise SceneFormatError(path, "is a folder; expected a transforms.json file") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise SceneFormatError(path, f"not valid JSON ({exc})") from None
    if not isinstance(meta, dict) or not isinstance(meta.get("frames"), list) or not meta["frames"]:
        raise SceneFormatError(path, "no 'frames' list (or it is empty)")
    if str(meta.get("camera_model", "OPENCV")).upper() not in ("OPENCV", "PINHOLE"):
        raise SceneFormatError(path, f"unsupported camera_model {meta['camera_model']!r}; supported: OPENCV, PINHOLE")
    cameras = []
    for index, frame in enumerate(meta["frames"]):
        where = f"frame {index}"
        if not isinstance(frame, dict) or "transform_matrix" not in frame or "file_path" not in frame:
            raise SceneFormatError(path, f"{where} lacks 'file_path' or 'transform_matrix'")
        value: Callable[..., Any] = {**meta, **frame}.get
        size = (value("w"), value("h"))
        if None in size:
            read = _image_size(path.parent, frame["file_path"])
            if read is None:
                raise SceneFormatError(path, f"{where}: no image size ('w'/'h') and the image cannot be read")
            size = read
        width, height = int(size[0]), int(size[1])
        fx, fy = value("fl_x"), value("fl_y")
        if fx is None and value("camera_angle_x") is not None:
            fx = 0.5 * width / math.tan(0.5 * float(value("camera_angle_x")))
        if fy is None and value("camera_angle_y") is not None:
            fy = 0.5 * height / math.tan(0.5 * float(value("camera_angle_y")))
        if fx is None and fy is None:
            raise SceneFormatError(path, f"{where}: no intrinsics (fl_x/fl_y or camera_angle_x)")
        fx, fy = float(fx if fx is not None else fy), float(fy if fy is not None else fx)
        cx, cy = float(value("cx", width / 2.0)), float(value("cy", height / 2.0))
        dist = np.array([float(value(key, 0.0)) for key in _DIST_KEYS])
        dist = dist if dist[4] else dist[:4]  # (k1, k2, p1, p2) as COLMAP's OPENCV when k3 = 0
        dist = dist if dist.any() else np.zeros(0)
        try:
            pose_gl = np.asarray(frame["transform_matrix"], dtype=np.float64)
            if pose_gl.shape == (3, 4):
                pose_gl = np.vstack([pose_gl, [0.0, 0.0, 0.0, 1.0]])
            if pose_gl.shape != (4, 4):
                raise ValueError(f"transform_matrix is {list(pose_gl.shape)}, expected 4x4 (or 3x4)")
            camera = Camera(
                name=str(frame["file_path"]),
                width=width,
                height=height,
                K=intrinsics(fx, fy, cx, cy),
                world_from_camera=pose_gl @ _GL_FROM_CV,
                dist=dist,
                model="OPENCV" if dist.size else "PINHOLE",
            )
        except (ValueError, TypeError) as exc:
            raise SceneFormatError(path, f"{where}: {exc}") from None
        cameras.append(camera)
    return cameras


def write_transforms_json(path: str | Path, cameras: list[Camera]) -> None:
    """Write cameras as a nerfstudio transforms.json with per-frame intrinsics."""
    frames = []
    for camera in cameras:
        frame = {
            "file_path": camera.name,
            "w": camera.width,
            "h": camera.height,
            "fl_x": camera.fx,
            "fl_y": camera.fy,
            "cx": camera.cx,
            "cy": camera.cy,
            "transform_matrix": (camera.world_from_camera @ _GL_FROM_CV).tolist(),
        }
        frame.update({key: float(v) for key, v in zip(_DIST_KEYS, camera.dist, strict=False)})  # fewer: the rest are 0
        frames.append(frame)
    Path(path).write_text(json.dumps({"camera_model": "OPENCV", "frames": frames}, indent=2))
