"""What the camera does to a rendered image: exposure, vignetting, noise, motion and focus blur.

Images are float RGB in 0..1 until ``to_uint8``. The exposure gain drifts from frame to frame
(auto-exposure hunting over bright roofs and dark lawns), the vignette darkens the corners,
and the noise is signal-dependent (shot noise) plus a read-noise floor. World v2's camera also
varies its sharpness from frame to frame (focus, vibration): a Gaussian blur of a per-frame sigma.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class SensorSpec:
    exposure_drift: float = 0.05  # std of the log-gain step between frames
    exposure_range: tuple[float, float] = (0.8, 1.25)  # gain clipped to this range
    vignette: float = 0.18  # darkening at the image corners
    shot_noise: float = 0.0009  # variance per unit intensity
    read_noise: float = 0.006  # std of the signal-independent noise
    blur_exposure_s: float = 0.0  # > 0: motion blur over this shutter time (renders several poses)
    blur_samples: int = 5
    focus_blur_px: tuple[float, float] = (0.0, 0.0)  # per-frame Gaussian blur sigma, uniform in this range (pixels)


def exposure_gains(n: int, spec: SensorSpec, rng: np.random.Generator) -> np.ndarray:
    """[n] gain per frame: a clipped random walk in log space starting at 1."""
    steps = rng.normal(0.0, spec.exposure_drift, n)
    steps[0] = 0.0
    lo, hi = np.log(spec.exposure_range[0]), np.log(spec.exposure_range[1])
    log_gain, out = 0.0, np.empty(n)
    for i, step in enumerate(steps):
        log_gain = float(np.clip(log_gain + step, lo, hi))
        out[i] = np.exp(log_gain)
    return out


def focus_blurs(n: int, spec: SensorSpec, rng: np.random.Generator) -> np.ndarray:
    """[n] Gaussian blur sigma per frame (pixels); no draw from ``rng`` when the range is (0, 0)."""
    lo, hi = spec.focus_blur_px
    if hi <= 0:
        return np.zeros(n)
    return rng.uniform(lo, hi, n)


def focus_blur(rgb: np.ndarray, sigma_px: float) -> np.ndarray:
    """[H, W, 3] float -> the same blurred by a Gaussian of ``sigma_px`` pixels (unchanged if <= 0.05)."""
    if sigma_px <= 0.05:
        return rgb
    import cv2

    return cv2.GaussianBlur(rgb.astype(np.float32), (0, 0), sigma_px, borderType=cv2.BORDER_REFLECT)


def apply_sensor(rgb: np.ndarray, gain: float, spec: SensorSpec, rng: np.random.Generator) -> np.ndarray:
    """[H, W, 3] float 0..1 -> [H, W, 3] float 0..1 as the camera would record it."""
    h, w = rgb.shape[:2]
    y, x = np.mgrid[0:h, 0:w]
    r2 = ((x + 0.5 - w / 2) ** 2 + (y + 0.5 - h / 2) ** 2) / ((w / 2) ** 2 + (h / 2) ** 2)
    image = rgb * (gain * (1.0 - spec.vignette * r2))[..., None]
    sigma = np.sqrt(spec.shot_noise * np.clip(image, 0, None) + spec.read_noise**2)
    return np.clip(image + rng.normal(size=image.shape) * sigma, 0.0, 1.0)


def to_uint8(rgb: np.ndarray) -> np.ndarray:
    """[H, W, 3] float RGB 0..1 -> uint8 RGB."""
    return (np.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
