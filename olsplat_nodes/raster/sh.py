"""Real spherical harmonics up to degree 3, the basis and sign conventions of INRIA 3DGS/gsplat.

colour = max(sum_k coeff_k * Y_k(dir) + 0.5, 0) with ``dir`` the unit vector from the camera
centre to the Gaussian's mean, in world coordinates.
"""

from __future__ import annotations

import numpy as np
from numba import njit

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


@njit(cache=True, inline="always")
def eval_sh(coeffs: np.ndarray, x: float, y: float, z: float) -> float:
    """sum_k coeffs[k] * Y_k(x, y, z) for one channel; coeffs [n] with n = 1, 4, 9 or 16."""
    n = coeffs.shape[0]
    out = C0 * coeffs[0]
    if n < 4:
        return out
    out += -C1 * y * coeffs[1] + C1 * z * coeffs[2] - C1 * x * coeffs[3]
    if n < 9:
        return out
    xx, yy, zz, xy, yz, xz = x * x, y * y, z * z, x * y, y * z, x * z
    out += (
        C2[0] * xy * coeffs[4]
        + C2[1] * yz * coeffs[5]
        + C2[2] * (2.0 * zz - xx - yy) * coeffs[6]
        + C2[3] * xz * coeffs[7]
        + C2[4] * (xx - yy) * coeffs[8]
    )
    if n < 16:
        return out
    out += (
        C3[0] * y * (3.0 * xx - yy) * coeffs[9]
        + C3[1] * xy * z * coeffs[10]
        + C3[2] * y * (4.0 * zz - xx - yy) * coeffs[11]
        + C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy) * coeffs[12]
        + C3[4] * x * (4.0 * zz - xx - yy) * coeffs[13]
        + C3[5] * z * (xx - yy) * coeffs[14]
        + C3[6] * x * (xx - 3.0 * yy) * coeffs[15]
    )
    return out
