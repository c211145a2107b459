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


def rotmats_to_quats(rotations) -> np.ndarray:
    """[M, 3, 3] rotations -> [M, 4] unit quaternions wxyz with w >= 0, vectorised (Shepperd's
    method: the largest of the four squared components is taken from the diagonal, the others
    from the off-diagonal sums, so no division is by a small number). ``rotmat_to_quat`` is
    the one-matrix version."""
    m = np.asarray(rotations, dtype=np.float64).reshape(-1, 3, 3)
    trace = m[:, 0, 0] + m[:, 1, 1] + m[:, 2, 2]
    # 4 w^2 - 1 = trace, 4 x^2 - 1 = m00 - m11 - m22 + ..., and so on: pick the largest per matrix
    squares = np.stack(
        [
            trace,
            m[:, 0, 0] - m[:, 1, 1] - m[:, 2, 2],
            m[:, 1, 1] - m[:, 0, 0] - m[:, 2, 2],
            m[:, 2, 2] - m[:, 0, 0] - m[:, 1, 1],
        ],
        1,
    )
    pick = np.argmax(squares, 1)
    q = np.empty((len(m), 4))
    s = 2.0 * np.sqrt(np.maximum(1.0 + np.take_along_axis(squares, pick[:, None], 1)[:, 0], 1e-300))  # 4 |component|
    d21, d02, d10 = m[:, 2, 1] - m[:, 1, 2], m[:, 0, 2] - m[:, 2, 0], m[:, 1, 0] - m[:, 0, 1]
    a01, a02, a12 = m[:, 0, 1] + m[:, 1, 0], m[:, 0, 2] + m[:, 2, 0], m[:, 1, 2] + m[:, 2, 1]
    for k, (w, x, y, z) in enumerate(
        [(s / 4, d21 / s, d02 / s, d10 / s), (d21 / s, s / 4, a01 / s, a02 / s),
         (d02 / s, a01 / s, s / 4, a12 / s), (d10 / s, a02 / s, a12 / s, s / 4)]
    ):  # fmt: skip
        rows = pick == k
        q[rows] = np.stack([np.broadcast_to(c, len(m))[rows] for c in (w, x, y, z)], 1)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return np.where(q[:, :1] < 0, -q, q)
