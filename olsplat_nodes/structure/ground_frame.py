"""A point set in its ground frame, voxelised: what both the MinkUNet's inference
(``minkunet.py``) and its SegContrast pre-training (``segcontrast.py``) feed the network.

The frame: "up" is the ground-plane normal turned to the cameras (``descriptors.estimate_up``),
coordinates in voxel units, so a map's orientation and units never matter. Inputs
(``"height-opacity"``, 3 channels): the height above the ground as a fraction of the flight
altitude, the source Gaussian's opacity, and a constant 1 (occupancy).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .descriptors import estimate_up, ground_axes, height_above_ground
from .points import StructuralPoints


@dataclass
class GroundFrame:
    """A point set in its ground frame: what both pre-training and inference feed the network."""

    voxels: np.ndarray  # [P, 3] float64 positions in voxel units, axes (a, b, up)
    inputs: np.ndarray  # [P, 3] float32 network inputs (module docstring)
    height: np.ndarray  # [P] float64 height above the ground, voxel units


def ground_frame(points: StructuralPoints, camera_centres: np.ndarray) -> GroundFrame:
    """The point set rotated so that "up" is the third axis, in voxel units, with its inputs."""
    positions, voxel = points.positions, points.voxel
    up = estimate_up(positions, np.asarray(camera_centres, np.float64), voxel)
    rotation = np.stack([*ground_axes(up), up])  # rows: the frame's axes in world
    height = height_above_ground(positions, up, 4.0 * voxel, 25)
    # the filter's ground is each cell's lowest point, and a reconstruction has Gaussians below
    # the surface: the ground itself sits a few voxels higher. Most of a town is ground, so its
    # true level is the most common height (histogram of quarter voxels)
    counts, edges = np.histogram(height, bins=np.arange(height.min(), height.max() + 0.5 * voxel, 0.25 * voxel))
    height = height - edges[np.argmax(counts)]
    altitude = max(float(np.median(camera_centres @ up) - np.median(positions @ up)), 1e-12)
    inputs = np.c_[height / altitude, points.opacity, np.ones(len(positions))].astype(np.float32)
    return GroundFrame(positions @ rotation.T / voxel, inputs, height / voxel)


def voxelise(voxels: np.ndarray, inputs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(coords [N, 3] int64, voxel inputs [N, C] float32 = mean of their points', inverse [P]:
    each point's voxel row) of points at float voxel positions. numpy arrays: the network's
    callers wrap them as tensors (this module needs no torch, which is an extra)."""
    coords = np.floor(voxels).astype(np.int64)
    unique, inverse = np.unique(coords, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    sums = np.zeros((len(unique), inputs.shape[1]))
    np.add.at(sums, inverse, inputs)
    mean = sums / np.bincount(inverse, minlength=len(unique))[:, None]
    return unique, mean.astype(np.float32), inverse
