"""Quaternion <-> rotation matrix, quaternions as (w, x, y, z) (COLMAP and INRIA order)."""

from __future__ import annotations

import numpy as np


def quat_to_rotmat(quat) -> np.ndarray:
    """[..., 4] wxyz (any norm) -> [..., 3, 3] rotation matrices."""
    q = np.asarray(quat, dtype=np.float64)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    w, x, y, z = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
            np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
        ],
        -2,
    )


def rotmat_to_quat(rotation) -> np.ndarray:
    """[3, 3] rotation -> [4] unit quaternion wxyz with w >= 0."""
    m = np.asarray(rotation, dtype=np.float64)
    # The top eigenvector of this symmetric 4x4 matrix (lower triangle given; eigh reads only
    # that) is the quaternion, robust for every rotation angle (Bar-Itzhack).
    k = (
        np.array(
            [
                [m[0, 0] - m[1, 1] - m[2, 2], 0, 0, 0],
                [m[1, 0] + m[0, 1], m[1, 1] - m[0, 0] - m[2, 2], 0, 0],
                [m[2, 0] + m[0, 2], m[2, 1] + m[1, 2], m[2, 2] - m[0, 0] - m[1, 1], 0],
                [m[2, 1] - m[1, 2], m[0, 2] - m[2, 0], m[1, 0] - m[0, 1], m[0, 0] + m[1, 1] + m[2, 2]],
            ]
        )
        / 3.0
    )
    values, vectors = np.linalg.eigh(k)
    x, y, z, w = vectors[:, np.argmax(values)]
    quat = np.array([w, x, y, z])
    return quat if w >= 0 else -quat
