"""The colours of the page's splats: a query's relevance margin on a perceptual ramp, and the
page's colour bar for it. (The splats themselves, their decimation and packing: ``query/splats.py``.)
"""

from __future__ import annotations

import numpy as np

# A perceptual ramp for relevance (low: dark blue, high: yellow), sampled at 5 stops.
RAMP = np.array(
    [[0.05, 0.03, 0.35], [0.23, 0.32, 0.55], [0.13, 0.57, 0.55], [0.37, 0.79, 0.38], [0.99, 0.91, 0.14]], np.float32
)
UNOBSERVED = np.array([0.35, 0.35, 0.35], np.float32)


def ramp(values: np.ndarray) -> np.ndarray:
    """[M] values in [0, 1] -> [M, 3] colours on ``RAMP`` (linear between stops)."""
    t = np.clip(np.asarray(values, np.float32), 0.0, 1.0) * (len(RAMP) - 1)
    low = np.minimum(t.astype(np.int64), len(RAMP) - 2)
    frac = (t - low)[:, None]
    return RAMP[low] * (1.0 - frac) + RAMP[low + 1] * frac


def relevance_colours(margin: np.ndarray, span: float = 0.2) -> np.ndarray:
    """[M, 3] colours of splats by their relevance margin [M] (the query's cosine minus the best
    negative's): -span and below at the bottom of the ramp, +span and above at the top, 0 (a tie
    with the best negative) in the middle. NaN (a Gaussian no view observed) is grey."""
    margin = np.asarray(margin, np.float32)
    colours = ramp((np.nan_to_num(margin) + span) / (2 * span))
    colours[np.isnan(margin)] = UNOBSERVED
    return colours.astype(np.float32)


def colour_bar_html(span: float = 0.2) -> str:
    """The page's colour bar for ``relevance_colours``, as HTML."""
    stops = ", ".join(f"rgb({int(r * 255)},{int(g * 255)},{int(b * 255)})" for r, g, b in RAMP)
    return (
        f'<div style="font-size:0.8em">relevance: query minus best negative (cosine)</div>'
        f'<div style="height:12px;background:linear-gradient(to right, {stops})"></div>'
        f'<div style="display:flex;justify-content:space-between;font-size:0.8em">'
        f"<span>-{span:g}</span><span>0 (tie)</span><span>+{span:g}</span></div>"
        f'<div style="font-size:0.8em">grey: never observed</div>'
    )
