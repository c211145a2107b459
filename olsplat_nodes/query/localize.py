"""Where the queried things are: regions in a view and instances in 3D.

In a view: connected components of the query's mask (8-connected, >= ``min_pixels``), with
box, centre and area. In 3D: the Gaussians that pick the query over the negatives (highest
cosine among query + negatives) and are observed, clustered with DBSCAN (open3d) on their
positions; each cluster is an instance with an axis-aligned box in world metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass
class Region2D:
    box: tuple[int, int, int, int]  # x0, y0, x1, y1 pixels (exclusive end)
    centre: tuple[float, float]  # pixel coordinates, centre of the top-left pixel at (0.5, 0.5)
    pixels: int


@dataclass
class Instance3D:
    box_min: tuple[float, float, float]  # world metres
    box_max: tuple[float, float, float]
    centre: tuple[float, float, float]
    gaussians: int


def regions_in_view(mask: np.ndarray, min_pixels: int = 50) -> list[Region2D]:
    count, labels, stats, centroids = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    out = []
    for i in range(1, count):
        x, y, w, h, area = stats[i]
        if area >= min_pixels:
            out.append(Region2D((int(x), int(y), int(x + w), int(y + h)), (float(centroids[i][0] + 0.5), float(centroids[i][1] + 0.5)), int(area)))
    return sorted(out, key=lambda r: -r.pixels)


def instances_in_3d(means: np.ndarray, selected: np.ndarray, eps: float = 1.5, min_points: int = 20) -> list[Instance3D]:
    """Clusters of the selected Gaussians' centres [N, 3] (DBSCAN radius ``eps`` metres)."""
    import open3d as o3d

    points = means[selected].astype(np.float64)
    if len(points) < min_points:
        return []
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    labels = np.asarray(cloud.cluster_dbscan(eps=eps, min_points=min_points, print_progress=False))
    out = []
    for cluster in range(labels.max() + 1):
        member = points[labels == cluster]
        out.append(Instance3D(tuple(member.min(0)), tuple(member.max(0)), tuple(member.mean(0)), len(member)))
    return sorted(out, key=lambda i: -i.gaussians)
