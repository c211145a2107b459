"""Reading annotations: LabelMe polygon files (format in sim/README.md) into label maps.

Real scenes are annotated in the same format (with the LabelMe tool or by hand), so the reader
belongs to the core; the simulator only writes such files.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from ..errors import SceneFormatError


def read_annotation(doc: dict | str | Path, labels: list[str] | tuple[str, ...]) -> tuple[np.ndarray, np.ndarray]:
    """(label map [H, W] int16 index into ``labels`` or -1, instance map [H, W] int32 or -1).

    Shapes are grouped by (label, group_id); a group's region is its outer polygons minus the
    polygons flagged ``"hole": true``; groups are painted in file order. Points are continuous
    pixel coordinates (centre of the top-left pixel at (0.5, 0.5)). A label outside ``labels``
    raises SceneFormatError naming the file (or ValueError for an in-memory document).
    """
    where = None
    if isinstance(doc, dict):
        data: dict = doc
    else:
        where = Path(doc)
        try:
            data = json.loads(where.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise SceneFormatError(where, f"not a readable annotation ({type(exc).__name__}: {exc})") from None
    index = {name: i for i, name in enumerate(labels)}
    h, w = int(data["imageHeight"]), int(data["imageWidth"])
    groups: dict[tuple[str, int], list[list]] = {}
    for shape in data["shapes"]:
        if shape["label"] not in index:
            problem = f"unknown annotation label {shape['label']!r}; known: {', '.join(labels)}"
            raise SceneFormatError(where, problem) if where else ValueError(problem)
        key = (shape["label"], -1 if shape.get("group_id") is None else int(shape["group_id"]))
        groups.setdefault(key, [[], []])[bool(shape.get("flags", {}).get("hole"))].append(shape["points"])
    label_map = np.full((h, w), -1, np.int16)
    instances = np.full((h, w), -1, np.int32)
    for (label, instance), (outers, holes) in groups.items():
        mask = np.zeros((h, w), np.uint8)
        to_px = lambda pts: [np.round(np.asarray(p) - 0.5).astype(np.int32) for p in pts]  # noqa: E731
        cv2.fillPoly(mask, to_px(outers), 1)
        if holes:
            cv2.fillPoly(mask, to_px(holes), 0)
        label_map[mask > 0] = index[label]
        instances[mask > 0] = instance
    return label_map, instances
