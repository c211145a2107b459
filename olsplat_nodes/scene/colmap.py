"""COLMAP sparse models (cameras + images), text and binary.

COLMAP stores, per image, the camera-from-world rotation (qw, qx, qy, qz) and translation;
we convert to ``Camera.world_from_camera``. Axes are OpenCV's in both. Supported camera
models: SIMPLE_PINHOLE, PINHOLE, SIMPLE_RADIAL, RADIAL, OPENCV, FULL_OPENCV. Fisheye and
other models raise a clear error. Points3D are not needed by olsplat; the writer emits an
empty points3D file so that COLMAP tools open the model.
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np

from ..errors import SceneFormatError
from .camera import Camera, intrinsics
from .rotations import quat_to_rotmat, rotmat_to_quat

# model name -> (COLMAP model id, parameter names)
MODELS: dict[str, tuple[int, tuple[str, ...]]] = {
    "SIMPLE_PINHOLE": (0, ("f", "cx", "cy")),
    "PINHOLE": (1, ("fx", "fy", "cx", "cy")),
    "SIMPLE_RADIAL": (2, ("f", "cx", "cy", "k1")),
    "RADIAL": (3, ("f", "cx", "cy", "k1", "k2")),
    "OPENCV": (4, ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2")),
    "FULL_OPENCV": (6, ("fx", "fy", "cx", "cy", "k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")),
}
_NAME_BY_ID = {model_id: name for name, (model_id, _) in MODELS.items()}
_UNSUPPORTED_IDS = {
    5: "OPENCV_FISHEYE",
    7: "FOV",
    8: "SIMPLE_RADIAL_FISHEYE",
    9: "RADIAL_FISHEYE",
    10: "THIN_PRISM_FISHEYE",
}
_DIST_ORDER = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")  # OpenCV's coefficient order
_N_DIST = {"SIMPLE_PINHOLE": 0, "PINHOLE": 0, "SIMPLE_RADIAL": 4, "RADIAL": 4, "OPENCV": 4, "FULL_OPENCV": 8}


def _intrinsics_from_params(model: str, params, where: Path) -> tuple[np.ndarray, np.ndarray]:
    names = MODELS[model][1]
    if len(params) != len(names):
        raise SceneFormatError(where, f"camera model {model} needs {len(names)} parameters, got {len(params)}")
    p = dict(zip(names, map(float, params), strict=True))
    fx, fy = (p["f"], p["f"]) if "f" in p else (p["fx"], p["fy"])
    # Missing coefficients of the OpenCV order are zero (radial-only models have p1 = p2 = 0).
    dist = np.array([p.get(name, 0.0) for name in _DIST_ORDER[: _N_DIST[model]]])
    return intrinsics(fx, fy, p["cx"], p["cy"]), dist


def _params_from_camera(camera: Camera) -> tuple[str, list[float]]:
    """The camera's own COLMAP model when it can hold K and dist exactly, else the simplest that can."""
    if len(camera.dist) > len(_DIST_ORDER):
        raise ValueError(
            f"camera {camera.name!r}: {len(camera.dist)} distortion coefficients do not fit a COLMAP model"
        )
    values = {"f": camera.fx, "fx": camera.fx, "fy": camera.fy, "cx": camera.cx, "cy": camera.cy}
    values.update({name: 0.0 for name in _DIST_ORDER})
    values.update(zip(_DIST_ORDER, map(float, camera.dist), strict=False))  # fewer coefficients: the rest stay 0

    def fits(model: str) -> bool:
        names = MODELS[model][1]
        if "f" in names and not np.isclose(camera.fx, camera.fy, rtol=1e-12):
            return False
        return all(name in names or values[name] == 0.0 for name in _DIST_ORDER)

    candidates = ([camera.model] if camera.model in MODELS else []) + ["PINHOLE", "OPENCV", "FULL_OPENCV"]
    model = next(m for m in candidates if fits(m))
    return model, [values[name] for name in MODELS[model][1]]


def _camera(name, width, height, model, params, qvec, tvec, where) -> Camera:
    K, dist = _intrinsics_from_params(model, params, where)
    camera_from_world = np.eye(4)
    camera_from_world[:3, :3] = quat_to_rotmat(qvec)
    camera_from_world[:3, 3] = tvec
    try:
        return Camera(name, width, height, K, np.linalg.inv(camera_from_world), dist, model)
    except ValueError as exc:
        raise SceneFormatError(where, str(exc)) from None


def _check_model(model: str, camera_id, where: Path) -> None:
    if model not in MODELS:
        raise SceneFormatError(
            where, f"camera {camera_id} uses the unsupported model {model}; supported: {', '.join(MODELS)}"
        )


# ---------------------------------------------------------------------------------------- text


def _data_lines(path: Path) -> list[str]:
    return [line.rstrip("\n") for line in path.read_text().splitlines() if not line.startswith("#")]


def _read_text(folder: Path) -> list[Camera]:
    cameras_path, images_path = folder / "cameras.txt", folder / "images.txt"
    cams = {}
    for line in _data_lines(cameras_path):
        if not line.strip():
            continue
        parts = line.split()
        try:
            camera_id, model, width, height = int(parts[0]), parts[1], int(parts[2]), int(parts[3])
            params = [float(v) for v in parts[4:]]
        except (IndexError, ValueError):
            raise SceneFormatError(cameras_path, f"malformed camera line: {line!r}") from None
        _check_model(model, camera_id, cameras_path)
        _intrinsics_from_params(model, params, cameras_path)  # fail here, on the camera's own file
        cams[camera_id] = (model, width, height, params)
    lines = _data_lines(images_path)
    out = []
    # Each image is two lines: the pose line, then its 2D points (possibly empty).
    for i in range(0, len(lines), 2):
        line = lines[i]
        if not line.strip():
            continue
        parts = line.split(maxsplit=9)
        try:
            qvec = [float(v) for v in parts[1:5]]
            tvec = [float(v) for v in parts[5:8]]
            camera_id, name = int(parts[8]), parts[9]
        except (IndexError, ValueError):
            raise SceneFormatError(images_path, f"malformed image line: {line!r}") from None
        if camera_id not in cams:
            raise SceneFormatError(images_path, f"image {name!r} refers to camera {camera_id}, which cameras.txt lacks")
        model, width, height, params = cams[camera_id]
        out.append(_camera(name, width, height, model, params, qvec, tvec, images_path))
    return out


def _write_text(folder: Path, cameras: list[Camera], ids: list[int], unique: list[tuple]) -> None:
    with open(folder / "cameras.txt", "w") as f:
        f.write("# Camera list with one line of data per camera:\n")
        f.write("#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n")
        for camera_id, (model, width, height, params) in enumerate(unique, start=1):
            f.write(f"{camera_id} {model} {width} {height} {' '.join(repr(float(p)) for p in params)}\n")
    with open(folder / "images.txt", "w") as f:
        f.write("# Image list with two lines of data per image:\n")
        f.write("#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n")
        f.write("#   POINTS2D[] as (X, Y, POINT3D_ID)\n")
        for image_id, (camera, camera_id) in enumerate(zip(cameras, ids, strict=True), start=1):
            qvec, tvec = _pose(camera)
            values = " ".join(repr(float(v)) for v in (*qvec, *tvec))
            f.write(f"{image_id} {values} {camera_id} {camera.name}\n\n")
    (folder / "points3D.txt").write_text("# 3D point list (olsplat writes none)\n")


# -------------------------------------------------------------------------------------- binary


class _Reader:
    def __init__(self, path: Path):
        self.path, self.data, self.pos = path, path.read_bytes(), 0

    def take(self, fmt: str):
        size = struct.calcsize(fmt)
        if self.pos + size > len(self.data):
            raise SceneFormatError(self.path, f"file is truncated at byte {self.pos} (needs {size} more)")
        values = struct.unpack_from(fmt, self.data, self.pos)
        self.pos += size
        return values

    def name(self) -> str:
        end = self.data.find(b"\x00", self.pos)
        if end < 0:
            raise SceneFormatError(self.path, f"file is truncated inside an image name at byte {self.pos}")
        value = self.data[self.pos : end].decode("utf-8", errors="replace")
        self.pos = end + 1
        return value


def _read_binary(folder: Path) -> list[Camera]:
    reader = _Reader(folder / "cameras.bin")
    cams = {}
    (count,) = reader.take("<Q")
    for _ in range(count):
        camera_id, model_id, width, height = reader.take("<iiQQ")
        if model_id not in _NAME_BY_ID:
            model = _UNSUPPORTED_IDS.get(model_id, f"id {model_id}")
            _check_model(model, camera_id, reader.path)
        model = _NAME_BY_ID[model_id]
        params = reader.take(f"<{len(MODELS[model][1])}d")
        cams[camera_id] = (model, width, height, list(params))
    reader = _Reader(folder / "images.bin")
    out = []
    (count,) = reader.take("<Q")
    for _ in range(count):
        _, qw, qx, qy, qz, tx, ty, tz, camera_id = reader.take("<i7di")
        name = reader.name()
        (n_points,) = reader.take("<Q")
        reader.take(f"<{24 * n_points}x")  # (x, y, point3D_id) per point: not needed
        if camera_id not in cams:
            raise SceneFormatError(reader.path, f"image {name!r} refers to camera {camera_id}, which cameras.bin lacks")
        model, width, height, params = cams[camera_id]
        out.append(_camera(name, width, height, model, params, (qw, qx, qy, qz), (tx, ty, tz), reader.path))
    return out


def _write_binary(folder: Path, cameras: list[Camera], ids: list[int], unique: list[tuple]) -> None:
    with open(folder / "cameras.bin", "wb") as f:
        f.write(struct.pack("<Q", len(unique)))
        for camera_id, (model, width, height, params) in enumerate(unique, start=1):
            f.write(struct.pack("<iiQQ", camera_id, MODELS[model][0], width, height))
            f.write(struct.pack(f"<{len(params)}d", *params))
    with open(folder / "images.bin", "wb") as f:
        f.write(struct.pack("<Q", len(cameras)))
        for image_id, (camera, camera_id) in enumerate(zip(cameras, ids, strict=True), start=1):
            qvec, tvec = _pose(camera)
            f.write(struct.pack("<i7di", image_id, *qvec, *tvec, camera_id))
            f.write(camera.name.encode("utf-8") + b"\x00")
            f.write(struct.pack("<Q", 0))
    (folder / "points3D.bin").write_bytes(struct.pack("<Q", 0))


# ---------------------------------------------------------------------------------- public API


def _pose(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    camera_from_world = camera.camera_from_world
    return rotmat_to_quat(camera_from_world[:3, :3]), camera_from_world[:3, 3]


def find_model_folder(path: str | Path) -> Path | None:
    """The folder holding cameras.{bin,txt}: ``path`` itself, or ``path/sparse/0``, ``path/sparse``."""
    path = Path(path)
    for candidate in (path, path / "sparse" / "0", path / "sparse"):
        if (candidate / "cameras.bin").is_file() or (candidate / "cameras.txt").is_file():
            return candidate
    return None


def read_colmap(path: str | Path) -> list[Camera]:
    """All images of a COLMAP model as cameras, sorted by image name. Binary wins over text."""
    folder = find_model_folder(path)
    if folder is None:
        raise SceneFormatError(path, "no COLMAP model here (no cameras.bin or cameras.txt, nor under sparse/0)")
    binary = (folder / "cameras.bin").is_file()
    images = folder / ("images.bin" if binary else "images.txt")
    if not images.is_file():
        raise SceneFormatError(folder, f"COLMAP model lacks {images.name}")
    cameras = _read_binary(folder) if binary else _read_text(folder)
    if not cameras:
        raise SceneFormatError(images, "the model holds no images")
    return sorted(cameras, key=lambda c: c.name)


def write_colmap(folder: str | Path, cameras: list[Camera], binary: bool = True) -> None:
    """Write cameras as a COLMAP model; identical intrinsics share one COLMAP camera."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    unique: list[tuple] = []
    ids = []
    for camera in cameras:
        model, params = _params_from_camera(camera)
        key = (model, camera.width, camera.height, params)
        if key not in unique:
            unique.append(key)
        ids.append(unique.index(key) + 1)
    (_write_binary if binary else _write_text)(folder, cameras, ids, unique)
