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
