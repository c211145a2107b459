"""``olsplat bench diagnose`` as a user runs it: on a simulated flight every statistic the
issue names is in the JSON and in range; on real photos the label-free ones; bad input is one line."""

from __future__ import annotations

import json

from olsplat_nodes.cli import main

KEYS = [
    "encoders.olsplat-cnn64.region_accuracy",
    "encoders.olsplat-cnn64.accuracy_by_obliqueness",
    "encoders.olsplat-vit48.region_accuracy",
    "pair.phi",
    "pair.both_wrong",
    "pair.both_wrong_if_independent",
    "pair.same_wrong_label",
    "surfaces.error_icc",
    "surfaces.wrong_every_view",
    "surfaces.wrong_some_views",
    "patches.label_flip_rate",
    "patches.colour_change",
    "patches.sharpness_change",
]


def _get(report: dict, path: str):
    value = report
    for key in path.split("."):
        value = value[key]
    return value


def test_diagnose_a_simulated_flight(tiny, tmp_path, capsys):
    scene, _ = tiny
    out = tmp_path / "diag.json"
    assert main(["bench", "diagnose", "--scene", str(scene), "--json", str(out), "--md", str(tmp_path / "d.md")]) == 0
    report = json.loads(out.read_text())
    for key in KEYS:
        value = _get(report, key)
        assert value is not None, key
    assert 0.3 < report["encoders"]["olsplat-cnn64"]["region_accuracy"] <= 1.0  # a trained encoder, not chance
    pair = report["pair"]
    assert pair["both_wrong"] <= min(1 - _get(report, f"encoders.{n}.region_accuracy") for n in pair["encoders"])
    assert -1.0 <= pair["phi"] <= 1.0 and 0.0 <= pair["same_wrong_label"] <= 1.0
    surfaces = report["surfaces"]
    assert surfaces["surfaces"] > 20 and surfaces["wrong_every_view"] + surfaces["wrong_some_views"] <= 1.0
    bins = report["encoders"]["olsplat-cnn64"]["accuracy_by_obliqueness"]
    assert sum(b["regions"] for b in bins.values()) == report["encoders"]["olsplat-cnn64"]["regions"]
    assert report["patches"]["pairs"] > 0  # the tiny flight's two overlapping frame pairs
    assert report["sources"][scene.name]["flight"]["views"] == 12
    assert "| pair.phi |" in capsys.readouterr().out and "| pair.phi |" in (tmp_path / "d.md").read_text()


def test_diagnose_real_photos(shared_data, tmp_path):
    out = tmp_path / "diag.json"
    assert main(["bench", "diagnose", "--photos", str(shared_data / "caliterra"), "--json", str(out)]) == 0
    source = json.loads(out.read_text())["sources"]["caliterra"]
    assert source["patches"]["pairs"] > 500 and source["patches"]["frame_pairs"] == 23
    assert 40 < source["flight"]["height_range_m"] < 60  # the drone climbs ~49 m over the 24 photos
    assert "encoders" not in source  # no labels on real photos: no accuracy
    assert 0.8 < source["flight"]["relative_tilt_deg"] < 2.5  # 1.59 degrees between frames (EXIF focal length)
    assert 0.2 < source["patches"]["colour_change_global"] < 0.35  # 0.28 (docs/world.md)
    # the first gate (docs/world.md, "The colour floor"): NCC >= 0.6 alone keeps more pairs; on
    # the first eight photos (seven frame pairs) against the default gate on the same eight
    photos = tmp_path / "eight"
    photos.mkdir()
    for path in sorted(p for p in (shared_data / "caliterra").iterdir() if p.suffix.lower() in (".jpg", ".jpeg"))[:8]:
        (photos / path.name).symlink_to(path)
    figures = {}
    for name, gate in (("default", []), ("loose", ["--min-ncc", "0.6", "--max-shift", "0"])):
        assert (
            main(["bench", "diagnose", "--photos", str(photos), *gate, "--json", str(tmp_path / f"{name}.json")]) == 0
        )
        figures[name] = json.loads((tmp_path / f"{name}.json").read_text())
    assert figures["loose"]["patch_gate"] == {"min_ncc": 0.6, "max_shift_px": 0}
    default, looser = (figures[n]["sources"]["eight"]["patches"] for n in ("default", "loose"))
    assert default["frame_pairs"] == looser["frame_pairs"] == 7
    assert looser["pairs"] > default["pairs"] > 0 and 0.2 < looser["colour_change_global"] < 0.35


def test_diagnose_refuses_bad_input_in_one_line(tmp_path, capsys):
    assert main(["bench", "diagnose"]) == 1
    assert main(["bench", "diagnose", "--photos", str(tmp_path), "--encoders", "olsplat-cnn64"]) == 1
    assert main(["bench", "diagnose", "--photos", str(tmp_path)]) == 1
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 3 and all(line.startswith("olsplat bench: error: ") for line in lines), lines
    assert "--scene or --photos" in lines[0] and "two encoders" in lines[1] and str(tmp_path) in lines[2]
