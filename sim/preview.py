"""Pictures that show a newcomer what a generated scene is: a contact sheet and an overview."""

from __future__ import annotations

import cv2
import numpy as np

from olsplat_nodes.raster import rasterize
from olsplat_nodes.scene import Camera, intrinsics, look_at

from .annotate import rasterize_annotation
from .labels import LABELS

# one BGR colour per annotation label (LABELS order)
LABEL_COLORS = np.array(
    [
        (40, 40, 230), (230, 120, 30), (245, 245, 245), (150, 150, 150), (190, 70, 110), (60, 200, 60),
        (20, 110, 20), (0, 220, 255), (200, 60, 200), (60, 130, 190), (200, 200, 120),
    ],
    np.uint8,
)  # fmt: skip


def overlay(image_rgb: np.ndarray, annotation: dict) -> np.ndarray:
    """[H, W, 3] BGR: the frame with its annotation regions tinted and outlined."""
    labels, _instances = rasterize_annotation(annotation)
    out = image_rgb[..., ::-1].astype(np.float32)
    tint = LABEL_COLORS[np.maximum(labels, 0)].astype(np.float32)
    has = labels >= 0
    out[has] = 0.6 * out[has] + 0.4 * tint[has]
    out = out.astype(np.uint8)
    for shape in annotation["shapes"]:
        pts = np.round(np.asarray(shape["points"]) - 0.5).astype(np.int32)
        color = tuple(int(c) for c in LABEL_COLORS[LABELS.index(shape["label"])])
        cv2.polylines(out, [pts], True, color, 1, cv2.LINE_AA)
    return out


def legend(width: int) -> np.ndarray:
    rows = (len(LABELS) + 3) // 4
    strip = np.full((rows * 22 + 6, width, 3), 30, np.uint8)
    for i, name in enumerate(LABELS):
        x, y = 8 + (i % 4) * (width // 4), 6 + (i // 4) * 22
        cv2.rectangle(strip, (x, y), (x + 14, y + 14), tuple(int(c) for c in LABEL_COLORS[i]), -1)
        cv2.putText(strip, name, (x + 20, y + 12), cv2.FONT_HERSHEY_SIMPLEX, 0.42, (235, 235, 235), 1, cv2.LINE_AA)
    return strip


def contact_sheet(
    tiles: list[tuple[str, np.ndarray, np.ndarray]], columns: int = 3, tile_width: int = 480
) -> np.ndarray:
    """tiles: (caption, frame BGR, overlay BGR) -> one BGR image, frames above their overlays."""
    cells = []
    for caption, frame, annotated in tiles:
        scale = tile_width / frame.shape[1]
        size = (tile_width, int(round(frame.shape[0] * scale)))
        pair = np.concatenate(
            [
                cv2.resize(frame, size, interpolation=cv2.INTER_AREA),
                cv2.resize(annotated, size, interpolation=cv2.INTER_AREA),
            ]
        )
        cv2.putText(pair, caption, (6, 18), cv2.FONT_HERSHEY_SIMPLEX, 0.5, (255, 255, 255), 2, cv2.LINE_AA)
        cells.append(np.pad(pair, ((2, 2), (2, 2), (0, 0))))
    while len(cells) % columns:
        cells.append(np.zeros_like(cells[0]))
    rows = [np.concatenate(cells[i : i + columns], axis=1) for i in range(0, len(cells), columns)]
    sheet = np.concatenate(rows, axis=0)
    return np.concatenate([sheet, legend(sheet.shape[1])], axis=0)


def overview(
    gaussians, size_m: float, cameras: list[tuple[str, Camera]], pixels: int = 1024, background=(0.45, 0.43, 0.38)
) -> np.ndarray:
    """Top-down BGR picture of the map with the flight's view centres on it.

    A view centre is where the camera's optical axis meets the ground (z = 0): for a nadir view
    it is below the drone, for an oblique one far ahead of it, so the dots show coverage.
    """
    fov = np.radians(30.0)
    altitude = 0.55 * size_m / np.tan(fov / 2) + 40.0
    focal = 0.5 * pixels / np.tan(fov / 2)
    top = Camera(
        "overview",
        pixels,
        pixels,
        intrinsics(focal, focal, pixels / 2, pixels / 2),
        look_at([0, 0, altitude], [0, 1e-6, 0], (0, 1, 0)),
    )
    image = rasterize(gaussians, top, want_topk=False, background=background).rgb
    out = np.ascontiguousarray((np.clip(image[..., ::-1], 0, 1) * 255).astype(np.uint8))
    colors = {"nadir": (0, 200, 255), "oblique": (255, 160, 0), "orbit": (255, 0, 200)}
    view = top.camera_from_world
    previous = None
    for kind, camera in cameras:
        centre, axis = camera.center, camera.world_from_camera[:3, 2]
        ground = centre - axis * centre[2] / axis[2] if axis[2] < -1e-6 else centre
        p = view[:3, :3] @ ground + view[:3, 3]
        uv = (int(focal * p[0] / p[2] + pixels / 2), int(focal * p[1] / p[2] + pixels / 2))
        if previous is not None and previous[0] == kind:
            cv2.line(out, previous[1], uv, (220, 220, 220), 1, cv2.LINE_AA)
        cv2.circle(out, uv, 4, colors.get(kind, (255, 255, 255)), -1, cv2.LINE_AA)
        previous = (kind, uv)
    _scale_and_north(out, view, focal, pixels)
    for i, (kind, color) in enumerate(colors.items()):
        cv2.circle(out, (16, 18 + 20 * i), 5, color, -1)
        cv2.putText(
            out,
            f"{kind} view centres",
            (28, 23 + 20 * i),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.5,
            (255, 255, 255),
            1,
            cv2.LINE_AA,
        )
    return out


def _scale_and_north(out: np.ndarray, view: np.ndarray, focal: float, pixels: int) -> None:
    """Draw a scale bar (a round number of metres on the ground, z = 0) and an arrow to north
    (world +y, the ENU convention of the scene) in the lower right corner, both measured by
    projecting ground points through the overview camera ``view`` (camera_from_world)."""

    def project(x: float, y: float) -> np.ndarray:
        p = view[:3, :3] @ np.array([x, y, 0.0]) + view[:3, 3]
        return np.array([focal * p[0] / p[2] + pixels / 2, focal * p[1] / p[2] + pixels / 2])

    per_metre = float(np.linalg.norm(project(1.0, 0.0) - project(0.0, 0.0)))
    metres = next(m for m in (1, 2, 5, 10, 20, 50, 100, 200, 500, 1000, 2000) if m * per_metre >= 0.12 * pixels)
    length = int(round(metres * per_metre))
    right, bottom = pixels - 20, pixels - 24
    white, font = (255, 255, 255), cv2.FONT_HERSHEY_SIMPLEX
    cv2.rectangle(out, (right - length, bottom - 6), (right, bottom), (0, 0, 0), -1)
    cv2.rectangle(out, (right - length, bottom - 6), (right - length // 2, bottom), white, -1)
    cv2.putText(out, f"{metres} m", (right - length, bottom - 12), font, 0.5, white, 1, cv2.LINE_AA)
    north = project(0.0, 1.0) - project(0.0, 0.0)
    north = north / max(float(np.linalg.norm(north)), 1e-9)
    base = np.array([right - 10.0, bottom - 60.0])
    tip = base + 36.0 * north
    cv2.arrowedLine(out, tuple(int(v) for v in base), tuple(int(v) for v in tip), white, 2, cv2.LINE_AA, tipLength=0.3)
    label = tip + 14.0 * north + np.array([-5.0, 5.0])
    cv2.putText(out, "N", tuple(int(v) for v in label), font, 0.55, white, 2, cv2.LINE_AA)
