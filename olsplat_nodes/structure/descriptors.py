"""Training-free 3D structural features: multi-scale geometric descriptors per point.

The paper's 3D branch uses a SegContrast-pretrained MinkUNet; with no weights to download,
the default is a descriptor that needs none and says what a sparse CNN learns to say about a
town: how high above the ground a point is, whether its surface is horizontal or vertical,
flat, linear or scattered (roofs vs walls vs crowns), and its local shape histogram (FPFH):

- height above ground, as a fraction of the flight altitude (scale-free): ground = the
  morphological opening of the lowest height per grid cell with a window wider than any
  building (the classic LiDAR ground filter), so roofs and crowns stand above it;
- verticality |n . up| of the local normal;
- linearity, planarity, scattering of the neighbourhood covariance at two scales (16 and 48
  neighbours);
- FPFH (33 bins, normalised) at two radii (3 and 6 voxels);
- opacity of the source Gaussian.

"Up" is the normal of the dominant plane (the ground), turned towards the cameras: a COLMAP
map has no gravity direction, but UAV cameras are above the scene. Every column is then
standardised over the map (zero mean, unit variance), so units never matter.
"""

from __future__ import annotations

import numpy as np

from .points import StructuralPoints

DESCRIPTOR_DIM = 1 + 1 + 3 + 3 + 33 + 33 + 1


def estimate_up(positions: np.ndarray, camera_centres: np.ndarray, voxel: float) -> np.ndarray:
    """[3] unit vector: the ground plane's normal (RANSAC), pointing to the cameras' side."""
    import open3d as o3d

    o3d.utility.random.seed(0)  # RANSAC: the same map gives the same "up" every run
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(positions))
    plane, _ = cloud.segment_plane(distance_threshold=2.0 * voxel, ransac_n=3, num_iterations=500, probability=1.0)
    normal = np.asarray(plane[:3], np.float64)
    normal /= np.linalg.norm(normal)
    return normal if np.mean(camera_centres @ normal + plane[3]) > 0 else -normal


def ground_axes(up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors that span the ground plane normal to ``up`` (with ``up``: right-handed)."""
    axis_a = np.cross(up, [1.0, 0.0, 0.0] if abs(up[0]) < 0.9 else [0.0, 1.0, 0.0])
    axis_a /= np.linalg.norm(axis_a)
    return axis_a, np.cross(up, axis_a)


def height_above_ground(positions: np.ndarray, up: np.ndarray, cell: float, window_cells: int) -> np.ndarray:
    """[P] height of each point above the local ground (map units).

    Heights are binned on a grid of side ``cell`` in the plane normal to ``up``; the ground is
    the grey-level opening (erode, then dilate) of the per-cell lowest height with a square
    window of 2 w + 1 cells: anything narrower than the window (a roof, a crown) is removed.
    """
    import cv2

    axis_a, axis_b = ground_axes(up)
    height = positions @ up
    cells = np.floor(np.c_[positions @ axis_a, positions @ axis_b] / cell).astype(np.int64)
    cells -= cells.min(0)
    shape = tuple(cells.max(0) + 1)
    lowest = np.full(shape, np.inf)
    np.minimum.at(lowest, (cells[:, 0], cells[:, 1]), height)
    filled = np.where(np.isfinite(lowest), lowest, height.max()).astype(np.float32)  # empty cells never are ground
    kernel = np.ones((2 * window_cells + 1, 2 * window_cells + 1), np.uint8)
    ground = cv2.dilate(
        cv2.erode(filled, kernel, borderType=cv2.BORDER_REPLICATE), kernel, borderType=cv2.BORDER_REPLICATE
    )
    return height - ground[cells[:, 0], cells[:, 1]]


def _eigen_features(cloud, k: int) -> np.ndarray:
    """[P, 3] linearity, planarity, scattering from the k-neighbour covariance eigenvalues."""
    import open3d as o3d

    cloud.estimate_covariances(o3d.geometry.KDTreeSearchParamKNN(k))
    eig = np.linalg.eigvalsh(np.asarray(cloud.covariances))[:, ::-1]  # l1 >= l2 >= l3
    l1 = np.maximum(eig[:, 0], 1e-18)
    return np.c_[(eig[:, 0] - eig[:, 1]) / l1, (eig[:, 1] - eig[:, 2]) / l1, eig[:, 2] / l1]


def geometric_descriptors(points: StructuralPoints, camera_centres: np.ndarray) -> np.ndarray:
    """[P, DESCRIPTOR_DIM] float32 standardised descriptors (see the module docstring)."""
    import open3d as o3d

    positions, voxel = points.positions, points.voxel
    up = estimate_up(positions, camera_centres, voxel)
    height = height_above_ground(positions, up, 4.0 * voxel, 25)
    altitude = np.median(camera_centres @ up) - np.median(positions @ up)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(positions))
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(16))
    verticality = np.abs(np.asarray(cloud.normals) @ up)
    columns = [
        height[:, None] / max(altitude, 1e-12),
        verticality[:, None],
        _eigen_features(cloud, 16),
        _eigen_features(cloud, 48),
    ]
    for radius in (3.0 * voxel, 6.0 * voxel):
        search = o3d.geometry.KDTreeSearchParamHybrid(radius, 64)
        # open3d's stub names only the overload with ``indices``; the two-argument one exists
        fpfh = o3d.pipelines.registration.compute_fpfh_feature(cloud, search)  # type: ignore[call-arg]
        columns.append(np.asarray(fpfh.data).T / 100.0)
    columns.append(points.opacity[:, None])
    features = np.concatenate(columns, axis=1)
    std = features.std(0)
    return ((features - features.mean(0)) / np.where(std > 0, std, 1.0)).astype(np.float32)
