"""Turn rasterizer outputs into pictures a person can read (8-bit BGR arrays for cv2.imwrite)."""

from __future__ import annotations

from pathlib import Path

import numpy as np


def _cv2():
    import cv2

    return cv2


def rgb_to_bgr8(rgb: np.ndarray) -> np.ndarray:
    """[H, W, 3] float RGB 0..1 -> [H, W, 3] uint8 BGR."""
    return (np.clip(rgb[..., ::-1], 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def colorize(values: np.ndarray, valid: np.ndarray | None = None, lo=None, hi=None) -> np.ndarray:
    """[H, W] scalars -> [H, W, 3] uint8 BGR (turbo colour map); invalid pixels black."""
    cv2 = _cv2()
    valid = np.isfinite(values) if valid is None else valid & np.isfinite(values)
    if not valid.any():
        return np.zeros((*values.shape, 3), np.uint8)
    lo = np.percentile(values[valid], 1) if lo is None else lo
    hi = np.percentile(values[valid], 99) if hi is None else hi
    scaled = np.clip((values - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    image = cv2.applyColorMap((scaled * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    image[~valid] = 0
    return image


def write_png(path, image: np.ndarray) -> None:
    """Write an 8-bit image, whole or not at all (a temporary file renamed into place); the
    format follows the extension (.png, .jpg). OSError naming the path when it cannot."""
    from .durable import write_atomic

    ok, encoded = _cv2().imencode(Path(path).suffix or ".png", image)
    if not ok:
        raise OSError(f"{path}: cannot encode the image for this extension")
    write_atomic(path, encoded.tobytes())


def query_pictures(
    image_rgb: np.ndarray,
    heatmap: np.ndarray,
    valid: np.ndarray,
    mask: np.ndarray,
    boxes,
    caption: str = "",
    scale: tuple[float, float] | None = None,
    unit: str = "cos",
) -> tuple[np.ndarray, np.ndarray]:
    """(heatmap picture, mask picture) as uint8 BGR, each the view [H, W] with a legend strip
    below it (so [H + LEGEND_H, W, 3]). Heatmap: the photo [H, W, 3] RGB blended with the cosine
    heatmap [H, W] in turbo (a perceptual map), stretched over the view's 1st..99th percentile
    (compact encoders give every text a high cosine, so a fixed -1..1 scale shows little); black
    where ``valid`` is False; the legend holds ``caption`` and a colour bar labelled with the
    cosines at its ends (``scale``: a fixed (lo, hi) instead of the percentiles; ``unit`` names
    the bar's values, e.g. "score" for a change heatmap). Mask: the photo with the mask [H, W] bool in yellow and each
    (x0, y0, x1, y1) box (exclusive end) in green; the legend holds ``caption`` and the area."""
    cv2 = _cv2()
    photo = image_rgb[..., ::-1].astype(np.float32)
    usable = valid & np.isfinite(heatmap)
    lo = float(np.percentile(heatmap[usable], 1)) if usable.any() else 0.0
    hi = float(np.percentile(heatmap[usable], 99)) if usable.any() else 1.0
    if scale is not None:
        lo, hi = scale
    heat = colorize(heatmap, valid, lo, hi).astype(np.float32)
    overlay = photo.copy()
    overlay[mask] = 0.4 * overlay[mask] + 0.6 * np.array([0, 220, 255])
    overlay = overlay.astype(np.uint8)
    for x0, y0, x1, y1 in boxes:
        cv2.rectangle(overlay, (int(x0), int(y0)), (int(x1) - 1, int(y1) - 1), (0, 255, 0), 1)
    width = photo.shape[1]
    share = 100.0 * mask.sum() / max(mask.size, 1)
    heat_legend = _legend(width, caption, colour_bar=(lo, hi), unit=unit)
    mask_legend = _legend(width, f"{caption}  |  mask: {int(mask.sum()):,} px ({share:.1f} %), {len(boxes)} regions")
    heat_picture = (0.45 * photo + 0.55 * heat).astype(np.uint8)
    return np.concatenate([heat_picture, heat_legend]), np.concatenate([overlay, mask_legend])


LEGEND_H = 58  # pixels of the strip under a query picture: two lines of caption, a colour bar


def _wrap(text: str, width: int, font, scale: float, lines: int) -> list[str]:
    """``text`` cut at spaces into at most ``lines`` lines that fit ``width`` pixels."""
    cv2 = _cv2()
    out, line = [], ""
    for word in text.split(" "):
        candidate = f"{line} {word}".strip()
        if cv2.getTextSize(candidate, font, scale, 1)[0][0] <= width or not line:
            line = candidate
        else:
            out.append(line)
            line = word
    out.append(line)
    if len(out) > lines:
        out = [*out[: lines - 1], " ".join(out[lines - 1 :])]
    return out


def _legend(width: int, caption: str, colour_bar: tuple[float, float] | None = None, unit: str = "cos") -> np.ndarray:
    """[LEGEND_H, width, 3] uint8 BGR: the caption (two lines at most) on top and, with
    ``colour_bar`` = (lo, hi), a turbo bar from lo to hi with the two cosines at its ends."""
    cv2 = _cv2()
    strip = np.full((LEGEND_H, width, 3), 24, np.uint8)
    font, scale = cv2.FONT_HERSHEY_SIMPLEX, 0.4
    for row, line in enumerate(_wrap(caption, width - 8, font, scale, 2)):
        cv2.putText(strip, line, (4, 13 + 14 * row), font, scale, (255, 255, 255), 1, cv2.LINE_AA)
    if colour_bar is not None:
        lo, hi = colour_bar
        left, right = 64, max(65, width - 48)
        ramp = np.linspace(0, 255, right - left).astype(np.uint8)[None, :]
        strip[38:52, left:right] = cv2.applyColorMap(np.repeat(ramp, 14, axis=0), cv2.COLORMAP_TURBO)
        cv2.putText(strip, f"{unit} {lo:.3f}", (2, 49), font, 0.35, (255, 255, 255), 1, cv2.LINE_AA)
        cv2.putText(strip, f"{hi:.3f}", (right + 4, 49), font, 0.35, (255, 255, 255), 1, cv2.LINE_AA)
    return strip


def safe_name(text: str, limit: int = 80) -> str:
    """``text`` as a plain file-name part: letters, digits, '.', '_' and '-' only (anything else,
    path separators and '..' included, becomes '_'), no leading or trailing '.' or '_', at most
    ``limit`` characters; "query" when nothing is left."""
    import re

    name = re.sub(r"[^A-Za-z0-9._-]+|\.{2,}", "_", text)
    name = re.sub(r"_+", "_", name).strip("._")[:limit]
    return name or "query"


def write_query_pictures(
    folder,
    view: str,
    text: str,
    image_rgb,
    heatmap,
    alpha,
    mask,
    regions,
    map_version: int | None = None,
    threshold: float | None = None,
    kind: str = "",
) -> list:
    """Write VIEW_TEXT_heatmap.png and VIEW_TEXT_mask.png into ``folder`` (with ``kind``, e.g.
    "preview": VIEW_TEXT_preview_heatmap.png ...); returns their paths.
    ``regions``: objects with a ``box`` or plain (x0, y0, x1, y1) tuples. The legend says the
    query text, the view, the map version (when known) and the mask's rule: the heatmap above
    ``threshold``, or (None / NaN) beating every negative text."""
    import math
    from pathlib import Path

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    boxes = [getattr(r, "box", r) for r in regions]
    rule = "beats every negative" if threshold is None or math.isnan(threshold) else f"cos > {threshold:g}"
    version = f", map v{map_version}" if map_version is not None else ""
    caption = f'"{text}" on {Path(view).name}{version}; mask: {rule}'
    heat, masked = query_pictures(image_rgb, heatmap, alpha > 0.5, mask.astype(bool), boxes, caption)
    stem = f"{safe_name(Path(view).stem)}_{safe_name(text)}"  # both come from the server's reply
    stem += f"_{kind}" if kind else ""
    paths = [folder / f"{stem}_heatmap.png", folder / f"{stem}_mask.png"]
    write_png(paths[0], heat)
    write_png(paths[1], masked)
    return paths
