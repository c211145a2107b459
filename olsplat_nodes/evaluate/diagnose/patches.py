"""Label-free statistics of how one piece of ground changes between two overlapping frames of a flight.

For consecutive frames (i, i + step) the ground plane's homography is estimated from SIFT matches,
frame i + step is warped onto frame i's pixels, and a grid of square patches inside the overlap is
cut from both. The patches whose grey levels still agree after the warp (normalised
cross-correlation >= ``min_ncc``, 0.9) are "ground patches": flat, textured and static, so what
differs between the two copies is what the camera did (exposure, white balance, blur, JPEG,
viewing angle), not misalignment; a patch must also align best at no shift (``locally_aligned``,
within 2 px). Why so strict: on simulated flights, patches holding a tree crown or a roof edge
that moved with parallax still reach NCC 0.6-0.9 (smooth, high-contrast renders), or even 0.9
with a shift of a pixel or two when flat colour fills most of the patch, and their "colour
change" is another object in the patch: with NCC >= 0.6 alone they made up most of the median
on world v1 (docs/world.md, "The colour floor"). On the real photos (caliterra) the statistics
hardly depend on the rule (colour_change_global 0.31 with NCC >= 0.6 alone, 0.28 with both
tests), so the strict rule measures the camera and not the geometry in both.
``patch_statistics`` then says how much their colour, their sharpness and (given an encoder) their label change.

Conventions: images are [H, W, 3] uint8 RGB; pixel coordinates are OpenCV's (x right, y down,
the centre of pixel (0, 0) at (0, 0)), which is what SIFT keypoints, ``cv2.findHomography`` and
``cv2.warpPerspective`` all use, so no half-pixel shift appears anywhere.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from ...errors import OlsplatInputError

log = logging.getLogger(__name__)

IMAGE_SUFFIXES = (".jpg", ".jpeg", ".png")
# the default patch side as a fraction of the image width: a patch then covers the same share of
# the field of view at 320 px (27 px) and at 1000 px (83 px), hence a comparable piece of ground
# for comparable altitude and lens
PATCH_FRACTION = 1 / 12


@dataclass(frozen=True, eq=False)
class PatchPair:
    """One ground patch seen in two frames, aligned pixel for pixel.

    frame_a, frame_b: indices into the image sequence (frame_b > frame_a).
    box: (x0, y0, x1, y1) in frame a's pixels, x1/y1 exclusive (x1 - x0 = y1 - y0 = S).
    patch_a: [S, S, 3] uint8 RGB, cut from frame a.
    patch_b: [S, S, 3] uint8 RGB, frame b warped onto frame a's pixels (Lanczos), same box.
    ncc: normalised cross-correlation of the two grey patches, in [-1, 1].
    homography: [3, 3] float64, frame b's pixel from frame a's pixel (homogeneous, H[2, 2] = 1),
    the frame pair's ground-plane estimate (shared by all patches of the pair).
    flight: 0 from ``ground_patch_pairs``; set it (``dataclasses.replace``) to tell flights apart
    when their pairs are pooled: a frame pair is (flight, frame_a, frame_b).
    """

    frame_a: int
    frame_b: int
    box: tuple[int, int, int, int]
    patch_a: np.ndarray = field(repr=False)
    patch_b: np.ndarray = field(repr=False)
    ncc: float
    homography: np.ndarray = field(repr=False)
    flight: int = 0  # which flight the frames belong to, when pairs of several flights are pooled


def read_flight_images(folder: str | Path) -> list[np.ndarray]:
    """[H, W, 3] uint8 RGB images of a photo folder (``*.jpg``, ``*.jpeg``, ``*.png``, sorted by
    name) or of a simulated flight (its ``images/`` subfolder, sorted by name: the flight order).

    The EXIF orientation is not applied (as in ``sources.exif``: the sensor's layout). Raises
    ``OlsplatInputError`` naming the folder when it holds fewer than 2 images or one that does
    not decode."""
    folder = Path(folder)
    where = folder / "images" if (folder / "images").is_dir() else folder
    files = sorted(p for p in where.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES) if where.is_dir() else []
    if len(files) < 2:
        raise OlsplatInputError(
            f"{folder}: {len(files)} images (*.jpg/*.png, or a simulated flight's images/ folder); the diagnostics "
            "need at least 2 overlapping frames"
        )
    images = []
    for path in files:
        bgr = cv2.imdecode(np.fromfile(path, np.uint8), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)
        if bgr is None:
            raise OlsplatInputError(f"{path}: does not decode as an image")
        images.append(np.ascontiguousarray(bgr[..., ::-1]))
    return images


def _grey(image: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)


def _features(image: np.ndarray, sift) -> tuple[np.ndarray, np.ndarray | None]:
    keypoints, descriptors = sift.detectAndCompute(_grey(image), None)
    return np.array([k.pt for k in keypoints], np.float32).reshape(-1, 2), descriptors


def _plausible(H: np.ndarray, width: int, height: int, max_scale: float) -> bool:
    """A homography a nadir camera between two nearby shots can produce: frame a's corners map to
    a convex, same-orientation quadrilateral whose area changes by at most a factor ``max_scale``
    (4: twice the ground distance; the simulator's oblique views reach 1.6 between neighbours)."""
    if not np.isfinite(H).all():
        return False
    corners = np.array([[0, 0], [width, 0], [width, height], [0, height]], np.float64)
    mapped = cv2.perspectiveTransform(corners[None], H)[0]
    w = (H[2, :2] @ corners.T) + H[2, 2]
    if (w <= 0).any():  # a corner crosses the horizon
        return False
    edges = np.roll(mapped, -1, axis=0) - mapped
    turns = edges[:, 0] * np.roll(edges, -1, axis=0)[:, 1] - edges[:, 1] * np.roll(edges, -1, axis=0)[:, 0]
    if not ((turns > 0).all()):  # y down: a clockwise-on-screen, convex quadrilateral has all turns > 0
        return False
    area = 0.5 * abs(np.sum(mapped[:, 0] * np.roll(mapped[:, 1], -1) - np.roll(mapped[:, 0], -1) * mapped[:, 1]))
    ratio = area / (width * height)
    return 1.0 / max_scale <= ratio <= max_scale


def estimate_homography(
    features_a: tuple[np.ndarray, np.ndarray | None],
    features_b: tuple[np.ndarray, np.ndarray | None],
    size_a: tuple[int, int],
    *,
    ratio: float = 0.75,
    ransac_px: float = 3.0,
    min_inliers: int = 30,
    max_scale: float = 4.0,
) -> tuple[np.ndarray, int] | None:
    """(H [3, 3] b-from-a pixels, RANSAC inliers) from SIFT features ``(points [N, 2], descriptors
    [N, 128])`` of two frames; None when there are fewer than ``min_inliers`` inliers or the
    homography is implausible (see ``_plausible``; ``size_a`` = (width, height) of frame a).

    Matches pass Lowe's ratio test (best distance < ``ratio`` x second best); RANSAC's
    reprojection threshold is ``ransac_px`` pixels in frame b."""
    (points_a, desc_a), (points_b, desc_b) = features_a, features_b
    if desc_a is None or desc_b is None or len(desc_a) < 2 or len(desc_b) < 2:
        return None
    knn = cv2.BFMatcher(cv2.NORM_L2).knnMatch(desc_a, desc_b, k=2)
    good = [m[0] for m in knn if len(m) == 2 and m[0].distance < ratio * m[1].distance]
    if len(good) < min_inliers:
        return None
    src = points_a[[m.queryIdx for m in good]]
    dst = points_b[[m.trainIdx for m in good]]
    H, mask = cv2.findHomography(src, dst, cv2.RANSAC, ransac_px, maxIters=5000, confidence=0.999)
    if H is None or mask is None or int(mask.sum()) < min_inliers:
        return None
    H = H / H[2, 2]
    if not _plausible(H, *size_a, max_scale):
        return None
    return H, int(mask.sum())


def ncc(grey_a: np.ndarray, grey_b: np.ndarray, min_std: float = 2.0) -> float:
    """Zero-mean normalised cross-correlation of two same-shape grey patches (0..255), in [-1, 1];
    0 when either patch's standard deviation is below ``min_std`` grey levels (texture-less:
    its correlation would measure JPEG noise, not alignment)."""
    a = grey_a.astype(np.float64) - grey_a.mean()
    b = grey_b.astype(np.float64) - grey_b.mean()
    sa, sb = np.sqrt((a * a).mean()), np.sqrt((b * b).mean())
    if sa < min_std or sb < min_std:
        return 0.0
    return float((a * b).mean() / (sa * sb))


def locally_aligned(grey_a: np.ndarray, grey_b: np.ndarray, box: tuple[int, int, int], radius: int) -> bool:
    """Whether frame b (already warped onto frame a, same shape) aligns best with frame a at no
    shift: the inner square of the patch (x0, y0, side S), its border of ``radius`` px dropped,
    correlates with b at shift (0, 0) at least as well as at every integer shift (dx, dy) with
    |dx|, |dy| <= ``radius`` (``ncc``). A shift that reads outside frame b counts as not better."""
    x0, y0, side = box
    inner = slice(y0 + radius, y0 + side - radius), slice(x0 + radius, x0 + side - radius)
    height, width = grey_b.shape
    centred = ncc(grey_a[inner], grey_b[inner])
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            top, left = y0 + radius + dy, x0 + radius + dx
            bottom, right = top + side - 2 * radius, left + side - 2 * radius
            if (dx or dy) and top >= 0 and left >= 0 and bottom <= height and right <= width:
                if ncc(grey_a[inner], grey_b[top:bottom, left:right]) > centred:
                    return False
    return True


def ground_patch_pairs(
    images: Sequence[np.ndarray],
    patch_px: int | None = None,
    *,
    steps: Sequence[int] = (1,),
    min_ncc: float = 0.9,
    max_shift_px: int = 2,
    min_inliers: int = 30,
    ratio: float = 0.75,
    ransac_px: float = 3.0,
    max_features: int = 8000,
) -> list[PatchPair]:
    """The ground patches of every overlapping frame pair (i, i + step) for step in ``steps``.

    images: [H, W, 3] uint8 RGB, in flight order. The default compares consecutive frames only
    (``steps=(1,)``): the question is how the ground changes between two neighbouring shots,
    and a longer baseline adds parallax and loses overlap; ``steps=(1, 2)`` adds a second pair.
    patch_px: the patch side S in pixels; default round(W / 12) of the first image (``PATCH_FRACTION``).
    The patches tile frame a on a grid of stride S from (0, 0); a patch is cut only where all of
    its pixels, plus one pixel of margin for the interpolation, lie inside the warped frame b.
    Frame b is warped with Lanczos interpolation, which blurs less than bilinear does (see
    ``patch_statistics`` for how the sharpness statistic keeps clear of the rest).
    Kept: patches whose grey NCC >= ``min_ncc`` (see ``ncc``) and, with ``max_shift_px`` = R > 0,
    that the warp aligns best (``locally_aligned``: no integer shift of up to R px correlates
    better; a roof edge or a crown that moved by a pixel or two with parallax can still reach 0.9
    when flat colour fills most of the patch). A frame pair is skipped (logged
    at debug level) when its homography fails (``estimate_homography``: too few inliers, e.g.
    across a turn of a lawnmower flight, or implausible)."""
    if len(images) < 2:
        return []
    for i, image in enumerate(images):
        if image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
            raise ValueError(f"image {i}: expected [H, W, 3] uint8 RGB, got shape {image.shape} dtype {image.dtype}")
    size = int(patch_px) if patch_px is not None else max(8, round(images[0].shape[1] * PATCH_FRACTION))
    if size < 4:
        raise ValueError(f"patch_px must be at least 4, got {patch_px}")
    if any(int(s) < 1 for s in steps):
        raise ValueError(f"steps must be positive, got {tuple(steps)}")
    sift = cv2.SIFT_create(nfeatures=max_features)  # type: ignore[attr-defined]  # OpenCV >= 4.4, not in its stubs
    features = [_features(image, sift) for image in images]
    pairs: list[PatchPair] = []
    for step in sorted({int(s) for s in steps}):
        for i in range(len(images) - step):
            j = i + step
            a, b = images[i], images[j]
            height, width = a.shape[:2]
            found = estimate_homography(
                features[i], features[j], (width, height), ratio=ratio, ransac_px=ransac_px, min_inliers=min_inliers
            )
            if found is None:
                log.debug("frames %d-%d: no plausible ground homography, skipped", i, j)
                continue
            H, _ = found
            flags = cv2.INTER_LANCZOS4 | cv2.WARP_INVERSE_MAP  # dst(x) = b(H x)
            warped = cv2.warpPerspective(b, H, (width, height), flags=flags, borderMode=cv2.BORDER_CONSTANT)
            inside = cv2.warpPerspective(
                np.ones(b.shape[:2], np.uint8), H, (width, height), flags=cv2.INTER_NEAREST | cv2.WARP_INVERSE_MAP
            )
            # Lanczos reads 4 pixels either side: keep clear of frame b's border
            inside = cv2.erode(inside, np.ones((9, 9), np.uint8), borderType=cv2.BORDER_CONSTANT, borderValue=0)
            grey_a, grey_w = _grey(a), _grey(warped)
            for y0 in range(0, height - size + 1, size):
                for x0 in range(0, width - size + 1, size):
                    if not inside[y0 : y0 + size, x0 : x0 + size].all():
                        continue
                    score = ncc(grey_a[y0 : y0 + size, x0 : x0 + size], grey_w[y0 : y0 + size, x0 : x0 + size])
                    if score < min_ncc:
                        continue
                    if max_shift_px > 0 and not locally_aligned(grey_a, grey_w, (x0, y0, size), max_shift_px):
                        continue
                    pairs.append(
                        PatchPair(
                            i,
                            j,
                            (x0, y0, x0 + size, y0 + size),
                            a[y0 : y0 + size, x0 : x0 + size].copy(),
                            warped[y0 : y0 + size, x0 : x0 + size].copy(),
                            score,
                            H,
                        )
                    )
    return pairs


def relative_tilts_deg(pairs: Sequence[PatchPair], focal_px: float, centre: tuple[float, float]) -> np.ndarray:
    """[F] the tilt between the two views of each frame pair (degrees; the frame pairs of
    ``pairs``, in order of first appearance), read from its ground-plane homography.

    For cameras K (focal ``focal_px``, principal point ``centre`` = (cx, cy) in OpenCV pixels) and
    the ground plane at distance d along its normal n in frame a's camera axes, the homography is
    H ~ K (R + t n^T / d) K^-1 (R, t: frame b's camera from frame a's). With n the optical axis (a
    nadir frame a), t n^T only touches the last column, so the normalised H_n = K^-1 H K has as
    the first two entries of its last row R's (r31, r32), and as its (3, 3) entry r33 + t_z / d; the
    angle is atan(|(r31, r32)| / (r33 + t_z / d)). A translation alone reads 0; a camera tilted by
    a degrees against a nadir one at the same height reads a exactly (|(r31, r32)| = sin a, r33 =
    cos a); a climb t_z between the frames reads atan(sin a / (cos a + t_z / d)), slightly off."""
    seen: dict[tuple[int, int, int], np.ndarray] = {}
    for p in pairs:
        seen.setdefault((p.flight, p.frame_a, p.frame_b), p.homography)
    K = np.array([[focal_px, 0.0, centre[0]], [0.0, focal_px, centre[1]], [0.0, 0.0, 1.0]])
    out = []
    for H in seen.values():
        Hn = np.linalg.inv(K) @ H @ K
        out.append(np.degrees(np.arctan2(float(np.hypot(Hn[2, 0], Hn[2, 1])), abs(float(Hn[2, 2])))))
    return np.array(out, np.float64)


def _srgb_to_linear(c: np.ndarray) -> np.ndarray:
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def _linear_to_srgb(c: np.ndarray) -> np.ndarray:
    c = np.clip(c, 0.0, 1.0)
    return np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)


def _mean_lab(patch_srgb: np.ndarray) -> np.ndarray:
    """[3] mean CIELAB (L 0..100) of a [S, S, 3] float sRGB patch in [0, 1] (D65, cv2's conversion)."""
    return cv2.cvtColor(patch_srgb.astype(np.float32), cv2.COLOR_RGB2Lab).reshape(-1, 3).mean(0)


def laplacian_variance(patch: np.ndarray, sigma: float = 1.0) -> float:
    """Variance of the 3x3 Laplacian of a [S, S, 3] uint8 RGB patch's grey levels after a Gaussian
    blur of ``sigma`` px (0: none), in grey levels squared. A border of ceil(3 sigma) + 1 pixels is
    dropped so that no padding enters."""
    grey: np.ndarray = _grey(patch).astype(np.float32)
    if sigma > 0:
        grey = cv2.GaussianBlur(grey, (0, 0), sigma)
    lap = cv2.Laplacian(grey, cv2.CV_32F, ksize=1)
    m = int(np.ceil(3 * sigma)) + 1 if sigma > 0 else 1
    return float(lap[m:-m, m:-m].var())


def patch_statistics(
    pairs: Sequence[PatchPair],
    label_of: Callable[[np.ndarray], np.ndarray] | None = None,
    *,
    sharpness_sigma: float = 1.0,
    sharpness_floor: float = 0.01,
) -> dict:
    """How much the ground patches change between their two frames.

    - ``colour_change`` / ``colour_change_p90``: median / 90th percentile over patch pairs of the
      CIE76 Delta E between the mean CIELAB colours of patch_a and patch_b (1 ~ just noticeable,
      L in 0..100).
    - ``colour_change_global``: the same median after removing each frame pair's global
      exposure and white-balance drift: patch_b's linear RGB divided, per channel, by the frame
      pair's median (over its patches) ratio of mean linear RGB b / a, re-encoded to sRGB
      (clipped to [0, 1]). What remains is local, view-dependent change.
    - ``sharpness_change`` / ``sharpness_change_p90``: median / p90 of |log2(v(a) / v(b))|, v =
      ``laplacian_variance`` (a Laplacian of Gaussian of ``sharpness_sigma`` px); 1 = one patch
      has twice the other's variance. The Gaussian is there because patch_b is resampled: with
      the plain 3x3 Laplacian the warp's own blur dominates (a half-pixel shift alone reads 0.38
      after Lanczos, 1.77 after bilinear; the real photos read 0.36), with sigma = 1 it reads 0.04
      (measured on the tests' synthetic frames) while a real blur of 1.5 px still reads > 2.
      It measures contrast too: a gain g in linear light scales the variance by about g^(2/2.2)
      (1.3 -> 0.35 in log2). Variances are floored at ``sharpness_floor`` grey levels squared (far below the 0.2 of a
      flat patch with 2 grey levels of noise) so that a flat patch gives a finite ratio.
    - ``label_flip_rate`` (only with ``label_of``): share of pairs whose labels differ;
      ``label_of`` maps [B, S, S, 3] uint8 RGB to [B] integer labels.
    - ``pairs``, ``frame_pairs`` (frame pairs with at least one patch), ``patch_px`` (S; None
      without pairs). The figures are NaN without pairs.
    """
    n = len(pairs)
    out: dict = {
        "pairs": n,
        "frame_pairs": len({(p.flight, p.frame_a, p.frame_b) for p in pairs}),
        "patch_px": int(pairs[0].patch_a.shape[0]) if n else None,
    }
    if n == 0:
        keys = ["colour_change", "colour_change_p90", "colour_change_global", "sharpness_change"]
        out.update({k: float("nan") for k in [*keys, "sharpness_change_p90"]})
        if label_of is not None:
            out["label_flip_rate"] = float("nan")
        return out
    srgb_a = [p.patch_a.astype(np.float32) / 255.0 for p in pairs]
    srgb_b = [p.patch_b.astype(np.float32) / 255.0 for p in pairs]
    lab_a = np.array([_mean_lab(x) for x in srgb_a])  # [N, 3]
    lab_b = np.array([_mean_lab(x) for x in srgb_b])
    delta = np.linalg.norm(lab_a - lab_b, axis=1)

    # per frame pair gain b / a per channel, from the patches' mean linear RGB
    lin_a = np.array([_srgb_to_linear(x).reshape(-1, 3).mean(0) for x in srgb_a])  # [N, 3]
    lin_b = np.array([_srgb_to_linear(x).reshape(-1, 3).mean(0) for x in srgb_b])
    ratios = lin_b / np.maximum(lin_a, 1e-6)
    _, group = np.unique([(p.flight, p.frame_a, p.frame_b) for p in pairs], axis=0, return_inverse=True)
    group = group.ravel()  # [N] frame pair index of each patch pair
    gains = np.array([np.median(ratios[group == g], axis=0) for g in range(group.max() + 1)])  # [G, 3]
    lin_b_fixed = [_srgb_to_linear(x) / np.maximum(gains[g], 1e-6) for x, g in zip(srgb_b, group, strict=True)]
    lab_b_fixed = np.array([_mean_lab(_linear_to_srgb(x)) for x in lin_b_fixed])
    delta_global = np.linalg.norm(lab_a - lab_b_fixed, axis=1)

    var_a = np.maximum([laplacian_variance(p.patch_a, sharpness_sigma) for p in pairs], sharpness_floor)
    var_b = np.maximum([laplacian_variance(p.patch_b, sharpness_sigma) for p in pairs], sharpness_floor)
    sharp = np.abs(np.log2(var_a / var_b))

    out.update(
        colour_change=float(np.median(delta)),
        colour_change_p90=float(np.percentile(delta, 90)),
        colour_change_global=float(np.median(delta_global)),
        sharpness_change=float(np.median(sharp)),
        sharpness_change_p90=float(np.percentile(sharp, 90)),
    )
    if label_of is not None:
        labels_a = np.asarray(label_of(np.stack([p.patch_a for p in pairs])))
        labels_b = np.asarray(label_of(np.stack([p.patch_b for p in pairs])))
        if labels_a.shape != (n,) or labels_b.shape != (n,):
            raise ValueError(f"label_of must return [B] labels for a batch of {n}, got shape {labels_a.shape}")
        out["label_flip_rate"] = float(np.mean(labels_a != labels_b))
    return out


def label_of_encoder(encoder, texts: Sequence[str], batch: int = 256) -> Callable[[np.ndarray], np.ndarray]:
    """A ``label_of`` for ``patch_statistics``: [B, S, S, 3] uint8 RGB patches -> [B] int64 index
    of the text (of ``texts``) most similar to each patch.

    Each square patch is resized to the encoder's ``input_size`` (cv2.INTER_AREA), embedded by
    ``encoder.encode_images`` ([B, dim] unit rows) and compared by cosine similarity with
    ``encoder.encode_text(texts)`` (embedded once, here), ``batch`` patches at a time."""
    text_embeddings = np.asarray(encoder.encode_text(list(texts)), np.float32)  # [T, dim]
    side = int(encoder.input_size)

    def label_of(patches: np.ndarray) -> np.ndarray:
        patches = np.asarray(patches)
        out = np.empty(len(patches), np.int64)
        for start in range(0, len(patches), batch):
            chunk = patches[start : start + batch]
            crops = np.stack([cv2.resize(p, (side, side), interpolation=cv2.INTER_AREA) for p in chunk])
            out[start : start + len(chunk)] = (encoder.encode_images(crops) @ text_embeddings.T).argmax(1)
        return out

    return label_of
