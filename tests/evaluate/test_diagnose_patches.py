"""The label-free ground-patch statistics (issue 43 part 1) on frame pairs made with a known
perspective homography: the homography is recovered, and each statistic moves with exactly the
change made to the second frame (a gain, a blur, a moved object) and not with the others."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from olsplat_nodes.errors import OlsplatInputError
from olsplat_nodes.evaluate.diagnose import (
    PatchPair,
    ground_patch_pairs,
    label_of_encoder,
    patch_statistics,
    read_flight_images,
    relative_tilts_deg,
)
from olsplat_nodes.evaluate.diagnose.patches import locally_aligned

SS = 4  # supersampling of the canvas: both frames are area-averaged from it, as a camera would
WIDTH, HEIGHT = 320, 240
# b-from-a: a 3 degree turn, 3 % closer, a shift and a little perspective
ANGLE = math.radians(3.0)
TRUE_H = np.array(
    [
        [1.03 * math.cos(ANGLE), -1.03 * math.sin(ANGLE), -30.0],
        [1.03 * math.sin(ANGLE), 1.03 * math.cos(ANGLE), -20.0],
        [2e-5, -3e-5, 1.0],
    ]
)


def town_canvas(width: int, height: int, seed: int = 0) -> np.ndarray:
    """[H, W, 3] uint8 RGB: overlapping anti-aliased rectangles and discs of random colours (a
    procedural "town" with corners for SIFT), values in 30..190 so that a gain of 1.3 in linear
    light does not clip."""
    rng = np.random.default_rng(seed)
    canvas = np.full((height, width, 3), 90, np.uint8)
    for _ in range(width * height // (60 * SS * SS)):
        colour = tuple(int(v) for v in rng.integers(30, 190, 3))
        x, y, r = int(rng.integers(0, width)), int(rng.integers(0, height)), int(rng.integers(2 * SS, 14 * SS))
        if rng.random() < 0.5:
            cv2.circle(canvas, (x, y), r, colour, -1, cv2.LINE_AA)
        else:
            cv2.rectangle(canvas, (x, y), (x + r, y + int(rng.integers(2 * SS, 14 * SS))), colour, -1, cv2.LINE_AA)
    return canvas


def frame_pair(canvas: np.ndarray, H: np.ndarray, width: int, height: int, ss: int) -> tuple[np.ndarray, np.ndarray]:
    """Frames a and b (each [height, width, 3]) of a canvas ``ss`` times finer, b seeing what a sees
    at b-pixel H @ a-pixel: each is rendered at the canvas resolution and area-averaged down."""
    # a pixel x of the small frame covers canvas pixels ss x .. ss x + ss - 1: centre ss x + (ss - 1) / 2
    S = np.array([[ss, 0.0, (ss - 1) / 2], [0.0, ss, (ss - 1) / 2], [0.0, 0.0, 1.0]])
    fine_H = S @ H @ np.linalg.inv(S)
    a = cv2.resize(canvas[: height * ss, : width * ss], (width, height), interpolation=cv2.INTER_AREA)
    b_fine = cv2.warpPerspective(canvas, fine_H, (width * ss, height * ss), flags=cv2.INTER_LINEAR)
    return a, cv2.resize(b_fine, (width, height), interpolation=cv2.INTER_AREA)


@pytest.fixture(scope="module")
def procedural() -> tuple[np.ndarray, np.ndarray]:
    return frame_pair(town_canvas(WIDTH * SS + 200, HEIGHT * SS + 200), TRUE_H, WIDTH, HEIGHT, SS)


@pytest.fixture(params=["procedural", "caliterra"])
def textured(request, procedural) -> tuple[np.ndarray, np.ndarray]:
    """The procedural pair, and the same warp of a real photo (skipped without the shared data)."""
    if request.param == "procedural":
        return procedural
    photo = request.getfixturevalue("shared_data") / "caliterra" / "IMG_9360.jpg"
    canvas = cv2.imread(str(photo), cv2.IMREAD_COLOR | cv2.IMREAD_IGNORE_ORIENTATION)[..., ::-1]
    return frame_pair(np.ascontiguousarray(canvas), TRUE_H, 440, 330, 2)


def linear_gain(image: np.ndarray, gain: float) -> np.ndarray:
    """The image with its linear-light RGB multiplied by ``gain`` (an exposure change)."""
    c = image / 255.0
    linear = np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4) * gain
    srgb = np.where(linear <= 0.0031308, 12.92 * linear, 1.055 * np.clip(linear, 0, 1) ** (1 / 2.4) - 0.055)
    return np.clip(np.round(srgb * 255), 0, 255).astype(np.uint8)


def brightness_label(patches: np.ndarray) -> np.ndarray:
    """[B] labels: the mean grey level of each patch in bins of 16."""
    return (patches.reshape(len(patches), -1).mean(1) // 16).astype(np.int64)


def test_known_homography_is_recovered_and_nothing_changes(textured):
    a, b = textured
    pairs = ground_patch_pairs([a, b])
    assert len(pairs) >= 20
    assert {(p.frame_a, p.frame_b) for p in pairs} == {(0, 1)}
    side = round(a.shape[1] / 12)
    centres = np.array([[(p.box[0] + p.box[2] - 1) / 2, (p.box[1] + p.box[3] - 1) / 2] for p in pairs])
    estimated = cv2.perspectiveTransform(centres[None], pairs[0].homography)[0]
    true = cv2.perspectiveTransform(centres[None], TRUE_H)[0]
    assert np.abs(estimated - true).max() < 1.0  # px
    for p in pairs:
        x0, y0, x1, y1 = p.box
        assert x1 - x0 == y1 - y0 == side and p.patch_a.shape == p.patch_b.shape == (side, side, 3)
        assert np.array_equal(p.patch_a, a[y0:y1, x0:x1]) and p.ncc >= 0.9
        # the whole patch lies where frame b sees: its corners map inside frame b
        corners = cv2.perspectiveTransform(np.array([[[x0, y0], [x1 - 1, y1 - 1]]], np.float64), TRUE_H)[0]
        assert (corners >= 0).all() and (corners[:, 0] < b.shape[1]).all() and (corners[:, 1] < b.shape[0]).all()
    stats = patch_statistics(pairs)
    assert stats["pairs"] == len(pairs) and stats["frame_pairs"] == 1 and stats["patch_px"] == side
    assert stats["colour_change"] < 0.3 and stats["colour_change_global"] < 0.3  # Delta E
    assert stats["sharpness_change"] < 0.15  # log2; the warp's own blur stays below this
    assert "label_flip_rate" not in stats


def test_an_exposure_gain_is_colour_change_that_the_global_correction_removes(procedural):
    a, b = procedural
    stats = patch_statistics(ground_patch_pairs([a, linear_gain(b, 1.3)]))
    assert stats["colour_change"] > 3.0 and stats["colour_change_p90"] >= stats["colour_change"]
    assert stats["colour_change_global"] < 0.3


def test_pooled_flights_keep_their_own_exposure_gains(procedural):
    """Frame pair (0, 1) of two flights: one brightened by 1.3, the other darkened by 0.75. Pooled
    with their flight set, each pair's own gain is divided out; lumped as one flight, one median
    gain serves both and the "local" change is the gains' difference."""
    import dataclasses

    a, b = procedural
    first = ground_patch_pairs([a, linear_gain(b, 1.3)])
    second = ground_patch_pairs([a, linear_gain(b, 0.75)])
    pooled = first + [dataclasses.replace(p, flight=1) for p in second]
    stats = patch_statistics(pooled)
    assert stats["frame_pairs"] == 2 and stats["colour_change_global"] < 0.3
    assert patch_statistics(first + second)["colour_change_global"] > 3.0


def test_a_blur_is_sharpness_change_not_colour_change(procedural):
    a, b = procedural
    stats = patch_statistics(ground_patch_pairs([a, cv2.GaussianBlur(b, (0, 0), 1.5)]))
    assert stats["sharpness_change"] > 1.5 and stats["sharpness_change_p90"] >= stats["sharpness_change"]
    assert stats["colour_change"] < 1.5


def test_label_flips_follow_the_labels(procedural):
    a, _ = procedural
    same = patch_statistics(ground_patch_pairs([a, a.copy()]), brightness_label)
    assert same["pairs"] > 0 and same["label_flip_rate"] == 0.0
    brighter = patch_statistics(ground_patch_pairs([a, linear_gain(a, 1.3)]), brightness_label)
    assert brighter["label_flip_rate"] > 0.5


def test_a_moved_object_drops_its_patches_only(procedural):
    """Content that does not follow the ground's homography (a car that drove off, a roof with
    parallax) fails the NCC test; the rest of the overlap is kept."""
    a, b = procedural
    baseline = {p.box for p in ground_patch_pairs([a, b])}
    moved = b.copy()
    moved[60:140, 80:160] = np.ascontiguousarray(np.rot90(b[60:140, 80:160], 2))  # turned by 180 degrees
    kept = {p.box for p in ground_patch_pairs([a, moved])}
    # the boxes of frame a that see the turned square in frame b
    inverse = np.linalg.inv(TRUE_H)
    square = cv2.perspectiveTransform(np.array([[[80.0, 60.0], [159.0, 139.0]]]), inverse)[0]
    (sx0, sy0), (sx1, sy1) = square.min(0), square.max(0)
    inside = {box for box in baseline if box[0] >= sx0 and box[2] <= sx1 and box[1] >= sy0 and box[3] <= sy1}
    assert inside and not (inside & kept)
    assert len(kept) >= len(baseline) - 16


@pytest.mark.parametrize("shift", [1, 3])
def test_parallax_of_a_few_pixels_is_not_a_ground_patch(procedural, shift):
    """A block of frame b shifted by 1 or 3 px against the ground's homography (a roof or a tree
    crown seen with parallax) still correlates with frame a (0.92-0.96 at 1 px, 0.6-0.85 at 3 px);
    the defaults (NCC >= 0.9 and the best alignment at no shift) drop its patches, where a loose
    NCC >= 0.6 alone keeps them and would count the shift as colour change."""
    a, b = procedural
    shifted = b.copy()
    shifted[60:140, 80:160] = b[60:140, 80 + shift : 160 + shift]
    inverse = np.linalg.inv(TRUE_H)
    square = cv2.perspectiveTransform(np.array([[[80.0, 60.0], [159.0, 139.0]]]), inverse)[0]
    (sx0, sy0), (sx1, sy1) = square.min(0), square.max(0)

    def inside(pairs):
        return [p for p in pairs if p.box[0] >= sx0 and p.box[2] <= sx1 and p.box[1] >= sy0 and p.box[3] <= sy1]

    loose = inside(ground_patch_pairs([a, shifted], min_ncc=0.6, max_shift_px=0))
    assert len(loose) >= 2
    assert inside(ground_patch_pairs([a, shifted])) == []
    assert len(inside(ground_patch_pairs([a, b]))) == len(loose)  # unshifted, the same boxes pass the defaults
    if shift == 1:  # the correlation alone does not see it: the shift test does
        assert len(inside(ground_patch_pairs([a, shifted], max_shift_px=0))) == len(loose)


def test_locally_aligned_finds_the_better_shift(procedural):
    a, _ = procedural
    grey = cv2.cvtColor(a, cv2.COLOR_RGB2GRAY)
    assert locally_aligned(grey, grey, (80, 60, 27), 2)
    for dx, dy in [(1, 0), (0, -2), (-1, 1)]:
        moved = np.roll(grey, (dy, dx), axis=(0, 1))
        assert not locally_aligned(grey, moved, (80, 60, 27), 2)
    assert (
        locally_aligned(grey, np.roll(grey, 1, axis=1), (0, 0, 27), 2) is False
    )  # shifts that read outside are skipped


def rotation(axis: str, degrees: float) -> np.ndarray:
    c, s = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    return {"x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]), "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])}[axis]


@pytest.mark.parametrize("tilt", [0.0, 1.0, 4.0, 10.0])
def test_relative_tilt_is_read_from_the_ground_homography(tilt):
    """A nadir frame a and a frame b turned by ``tilt`` degrees about a tilted axis, moved along the
    ground and down by 5 %: the plane-induced homography K (R + t n^T / d) K^-1 gives the tilt
    back exactly, and with a climb the documented atan(sin a / (cos a + t_z / d))."""
    f, centre = 400.0, (159.5, 119.5)
    K = np.array([[f, 0, centre[0]], [0, f, centre[1]], [0, 0, 1.0]])
    R = rotation("x", tilt * 0.6) @ rotation("y", tilt * 0.8)
    n, d = np.array([0.0, 0.0, 1.0]), 50.0
    level = K @ (R + np.outer([3.0, -2.0, 0.0], n) / d) @ np.linalg.inv(K)
    climbed = K @ (R + np.outer([3.0, -2.0, 2.5], n) / d) @ np.linalg.inv(K)
    axis_angle = math.degrees(math.asin(math.hypot(R[2, 0], R[2, 1])))
    assert axis_angle == pytest.approx(tilt, abs=0.02)

    def pair(H, a, b):
        return PatchPair(a, b, (0, 0, 4, 4), np.zeros((4, 4, 3), np.uint8), np.zeros((4, 4, 3), np.uint8), 1.0, H)

    pairs = [pair(level, 0, 1), pair(level * 3.0, 0, 1), pair(climbed, 1, 2)]  # a homography's scale is free
    tilts = relative_tilts_deg(pairs, f, centre)
    assert tilts.shape == (2,)  # one per frame pair
    assert tilts[0] == pytest.approx(axis_angle, abs=1e-6)
    expected = math.degrees(math.atan(math.sin(math.radians(axis_angle)) / (R[2, 2] + 2.5 / d)))
    assert tilts[1] == pytest.approx(expected, abs=1e-6)
    assert relative_tilts_deg([], f, centre).shape == (0,)


def test_relative_tilt_of_a_real_warp_is_near_zero(procedural):
    """The procedural pair's homography has a perspective row of 2e-5 and 3e-5 per pixel: at a
    focal length of 400 px that is a tilt of atan(400 * 3.6e-5) = 0.83 degrees."""
    a, b = procedural
    tilts = relative_tilts_deg(ground_patch_pairs([a, b]), 400.0, (159.5, 119.5))
    assert tilts.shape == (1,) and tilts[0] == pytest.approx(0.83, abs=0.1)


def test_two_steps_add_the_longer_baseline():
    canvas = town_canvas(WIDTH * SS + 400, HEIGHT * SS + 200, seed=1)
    shift = np.array([[1.0, 0.0, -20.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    frames = [frame_pair(canvas, np.linalg.matrix_power(shift, k), WIDTH, HEIGHT, SS)[1] for k in range(3)]
    assert {(p.frame_a, p.frame_b) for p in ground_patch_pairs(frames)} == {(0, 1), (1, 2)}
    pairs = ground_patch_pairs(frames, 40, steps=(1, 2))
    assert {(p.frame_a, p.frame_b) for p in pairs} == {(0, 1), (1, 2), (0, 2)}
    assert all(p.patch_a.shape == (40, 40, 3) for p in pairs)


def test_textureless_frames_give_no_pairs_and_nan_figures():
    flat = np.full((HEIGHT, WIDTH, 3), (120, 130, 90), np.uint8)
    assert ground_patch_pairs([flat, flat.copy()]) == []
    assert ground_patch_pairs([flat]) == []
    stats = patch_statistics([], brightness_label)
    assert stats["pairs"] == stats["frame_pairs"] == 0 and stats["patch_px"] is None
    assert math.isnan(stats["colour_change"]) and math.isnan(stats["label_flip_rate"])


def test_misuse_names_the_bad_value(procedural):
    a, b = procedural
    with pytest.raises(ValueError, match="float32"):
        ground_patch_pairs([a, b.astype(np.float32)])
    with pytest.raises(ValueError, match="got 2"):
        ground_patch_pairs([a, b], patch_px=2)


def test_label_of_encoder_labels_with_the_shipped_encoder(procedural):
    from olsplat_nodes.encoders.spec import encoder_from_spec
    from olsplat_sim.zeroshot import label_queries

    texts = label_queries()
    encoder = encoder_from_spec(threads=1)
    patches = np.stack([p.patch_a for p in ground_patch_pairs(list(procedural))][:10])  # [10, 27, 27, 3]
    labels = label_of_encoder(encoder, texts)(patches)
    assert labels.shape == (10,) and labels.dtype == np.int64
    assert ((labels >= 0) & (labels < len(texts))).all()
    assert np.array_equal(label_of_encoder(encoder, texts, batch=3)(patches), labels)  # batching changes nothing
    assert np.array_equal(label_of_encoder(encoder, texts)(patches[::-1]), labels[::-1])


def test_read_flight_images(tmp_path):
    rgb = np.zeros((6, 8, 3), np.uint8)
    rgb[..., 0] = 200  # red
    photos = tmp_path / "photos"
    photos.mkdir()
    for name in ("b.png", "a.png"):
        cv2.imwrite(str(photos / name), rgb[..., ::-1])
    (photos / "notes.txt").write_text("not an image")
    images = read_flight_images(photos)
    assert len(images) == 2 and images[0].shape == (6, 8, 3) and images[0][0, 0].tolist() == [200, 0, 0]
    flight = tmp_path / "flight"
    (flight / "images").mkdir(parents=True)
    for i in range(3):
        cv2.imwrite(str(flight / "images" / f"frame_{i:04d}.png"), np.full((4, 4, 3), 10 * i, np.uint8))
    assert [int(im[0, 0, 0]) for im in read_flight_images(flight)] == [0, 10, 20]


@pytest.mark.parametrize("count", [0, 1])
def test_fewer_than_two_images_is_one_clear_error(tmp_path, count):
    for i in range(count):
        cv2.imwrite(str(tmp_path / f"{i}.jpg"), np.zeros((4, 4, 3), np.uint8))
    with pytest.raises(OlsplatInputError) as error:
        read_flight_images(tmp_path)
    message = str(error.value)
    assert str(tmp_path) in message and f"{count} images" in message and "\n" not in message
    with pytest.raises(OlsplatInputError, match="missing"):
        read_flight_images(tmp_path / "missing")


def test_patch_pair_is_frozen(procedural):
    pair = ground_patch_pairs(list(procedural))[0]
    assert isinstance(pair, PatchPair)
    with pytest.raises(AttributeError):
        pair.ncc = 1.0
