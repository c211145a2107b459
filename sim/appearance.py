"""View-dependent appearance of the true scene (world v2): lobes projected onto spherical harmonics.

A material's lobe is a function of the viewing direction d (unit, camera to Gaussian, world
coordinates: the rasterizer's SH convention, olsplat_nodes/raster/sh.py) symmetric about an axis
a: f(d . a). Its projection onto the real SH of degree l is, by the addition theorem,
c_lm = Y_lm(a) * 2 pi * integral_{-1}^{1} f(mu) P_l(mu) dmu, so one 1D integral per degree and
lobe shape and the basis at each Gaussian's axis give its coefficients. The rasterizer's per-view
SH evaluation then brightens each Gaussian as the camera moves into its lobe.

- Specular (roofs, car paint, glass): white sunlight added around the sun's mirror direction in
  the Gaussian's surface, m = s - 2 (s . n) n (s towards the sun, n the normal): a camera whose
  ray to the Gaussian runs along m sees the sun reflected. Only surfaces facing the sun shine.
- Hot spot (trees, lawn): the Gaussian's own colour brightened around a = -s, i.e. for a camera
  with the sun behind it (backscatter, shadow hiding).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from olsplat_nodes.raster.sh import C0, C1, C2, C3
from olsplat_nodes.scene import Gaussians
from olsplat_nodes.scene.rotations import quat_to_rotmat

from .labels import CATEGORY
from .scene import TruthScene
from .world import AppearanceWorld


def sun_vector(spec: AppearanceWorld) -> np.ndarray:
    """[3] unit vector from the ground towards the sun."""
    az, el = np.radians(spec.sun_azimuth_deg), np.radians(spec.sun_elevation_deg)
    return np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])


def sh_basis(dirs: np.ndarray, degree: int) -> np.ndarray:
    """[M, 3] unit directions -> [M, (degree + 1)^2] real SH values, the order and signs of
    ``olsplat_nodes.raster.sh.eval_sh`` (so that sum(coeffs * basis) is what it evaluates)."""
    x, y, z = dirs[:, 0], dirs[:, 1], dirs[:, 2]
    out = [np.full(len(dirs), C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [C2[0] * x * y, C2[1] * y * z, C2[2] * (2 * zz - xx - yy), C2[3] * x * z, C2[4] * (xx - yy)]
    if degree >= 3:
        out += [
            C3[0] * y * (3 * xx - yy),
            C3[1] * x * y * z,
            C3[2] * y * (4 * zz - xx - yy),
            C3[3] * z * (2 * zz - 3 * xx - 3 * yy),
            C3[4] * x * (4 * zz - xx - yy),
            C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3 * yy),
        ]
    return np.stack(out, axis=1)


def zonal_coefficients(exponent: float, degree: int) -> np.ndarray:
    """[degree + 1] g_l = 2 pi * integral of ((1 + mu) / 2)^exponent * P_l(mu) over [-1, 1]."""
    mu, weights = np.polynomial.legendre.leggauss(64)  # exact for the polynomial lobes, accurate otherwise
    lobe = ((1.0 + mu) / 2.0) ** exponent
    legendre = [np.polynomial.legendre.Legendre.basis(level)(mu) for level in range(degree + 1)]
    return np.array([2.0 * np.pi * np.sum(weights * lobe * p) for p in legendre])


def lobe_coefficients(axes: np.ndarray, exponent: float, degree: int) -> np.ndarray:
    """[M, 3] unit lobe axes -> [M, (degree + 1)^2] SH coefficients of the unit-peak lobe
    ((1 + d . a) / 2)^exponent, band-limited to ``degree``."""
    g = zonal_coefficients(exponent, degree)
    per_coeff = np.concatenate([np.full(2 * level + 1, g[level]) for level in range(degree + 1)])
    return sh_basis(axes, degree) * per_coeff


def with_view_dependence(truth: TruthScene, spec: AppearanceWorld, rng: np.random.Generator) -> TruthScene:
    """The truth with SH of ``spec.sh_degree`` carrying the specular and hot-spot lobes (the
    same object when the degree is 0). ``rng`` draws one roof strength per building, in order
    of the building instances."""
    if spec.sh_degree == 0:
        return truth
    g = truth.gaussians
    n, k = len(g), (spec.sh_degree + 1) ** 2
    sun = sun_vector(spec)
    sh = np.zeros((n, k, 3))
    sh[:, 0] = g.sh[:, 0]
    normals = quat_to_rotmat(g.quats.astype(np.float64))[:, :, 2]  # a flat Gaussian's thin axis
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    glass = truth.glass if truth.glass is not None else np.zeros(n, bool)

    # specular strengths (linear rgb at the lobe's peak), per Gaussian
    strength = np.zeros(n)
    roofs = truth.category == CATEGORY["roof"]
    buildings = np.unique(truth.instance[roofs])
    per_building = rng.uniform(*spec.roof_specular, len(buildings))
    strength[roofs] = per_building[np.searchsorted(buildings, truth.instance[roofs])]
    cars = truth.category == CATEGORY["car"]
    strength[cars & ~glass] = spec.car_specular
    strength[glass] = spec.glass_specular
    facing = (normals @ sun) > 0  # no sun glint off a surface in its own shadow
    shiny = np.flatnonzero((strength > 0) & facing)
    if len(shiny):
        mirror = sun[None] - 2.0 * (normals[shiny] @ sun)[:, None] * normals[shiny]
        coeffs = lobe_coefficients(mirror, spec.specular_exponent, spec.sh_degree) * strength[shiny, None]
        sh[shiny] += coeffs[:, :, None]  # white light: the same in each channel

    vegetation = np.flatnonzero(np.isin(truth.category, [CATEGORY["tree"], CATEGORY["lawn"]]))
    if spec.hotspot > 0 and len(vegetation):
        colour = g.sh[vegetation, 0].astype(np.float64) * C0 + 0.5  # [V, 3] the base colour
        unit = lobe_coefficients(np.tile(-sun, (1, 1)), spec.hotspot_exponent, spec.sh_degree)[0]  # [K]
        sh[vegetation] += spec.hotspot * unit[None, :, None] * colour[:, None, :]
    gaussians = Gaussians(g.means, g.quats, g.log_scales, g.opacity_logits, sh, dict(g.extras))
    return dataclasses.replace(truth, gaussians=gaussians)
