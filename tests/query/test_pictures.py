"""Picture file names on the ground side come from the server's reply: they stay plain names
inside the output folder whatever the reply says."""

from __future__ import annotations

import numpy as np

from olsplat_nodes.viz import safe_name, write_query_pictures


def test_names_from_a_reply_cannot_leave_the_folder(tmp_path):
    assert safe_name("red roof buildings") == "red_roof_buildings"
    assert safe_name("../../etc/passwd") == "etc_passwd" and safe_name("a..b") == "a_b"
    assert safe_name("..") == "query" and safe_name("") == "query"
    assert len(safe_name("x" * 1000)) == 80
    image = np.zeros((8, 10, 3), np.uint8)
    heat, alpha, mask = np.zeros((8, 10), np.float32), np.ones((8, 10), np.float32), np.zeros((8, 10), np.uint8)
    out = tmp_path / "out"
    paths = write_query_pictures(out, "../../v/frame.jpg", "../../../evil /x", image, heat, alpha, mask, [])
    assert all(p.parent == out and p.exists() for p in paths), paths
    assert sorted(p.name for p in out.iterdir()) == ["frame_evil_x_heatmap.png", "frame_evil_x_mask.png"]
    assert list(tmp_path.iterdir()) == [out]


def test_query_pictures_carry_a_legend_with_a_colour_bar(tmp_path):
    import cv2

    from olsplat_nodes.viz import LEGEND_H

    rng = np.random.default_rng(0)
    image = rng.integers(0, 255, (60, 200, 3), dtype=np.uint8)
    heat = np.linspace(-0.2, 0.3, 60 * 200, dtype=np.float32).reshape(60, 200)
    mask = heat > 0.2
    paths = write_query_pictures(
        tmp_path, "frame.jpg", "road", image, heat, np.ones_like(heat), mask, [(0, 0, 10, 10)], map_version=7,
        threshold=0.2,
    )  # fmt: skip
    heat_png, mask_png = (cv2.imread(str(p)) for p in paths)
    assert heat_png.shape == mask_png.shape == (60 + LEGEND_H, 200, 3)
    bar = heat_png[60 + 40 : 60 + 50, 70:140].astype(int)  # the turbo bar: blue to red, left to right
    assert bar[:, :5, 0].mean() > bar[:, :5, 2].mean() and bar[:, -5:, 2].mean() > bar[:, -5:, 0].mean()
    assert (heat_png[60:, :, :] > 200).any() and (mask_png[60:, :, :] > 200).any()  # captions written
