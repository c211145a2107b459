"""A newcomer's first hour (issue 16): every mistake of the list gets one line naming the file or
option and the problem, exit 1, and nothing half written; no silent wrong result."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from olsplat_nodes.cli import main
from olsplat_nodes.scene import read_ply, write_ply


def run(capsys, *args) -> tuple[int, str, str]:
    code = main([str(a) for a in args])
    out, err = capsys.readouterr()
    return code, out, err


def one_line_error(code: int, err: str, command: str, *words: str) -> None:
    assert code == 1, err
    assert err.count("\n") == 1 and err.startswith(f"olsplat {command}: error: "), err
    assert "Traceback" not in err and "internal error" not in err
    for word in words:
        assert word in err, (word, err)


@pytest.fixture
def scene(tiny, tmp_path) -> Path:
    """A private copy of the tiny scene (tests below write into it)."""
    copy = tmp_path / "scene"
    shutil.copytree(tiny[0], copy, ignore=shutil.ignore_patterns("cache"))
    return copy


# --- silent wrong results -------------------------------------------------------------------


def test_sim_make_refuses_a_folder_that_holds_files_and_force_empties_it(tmp_path, capsys):
    out = tmp_path / "old"
    out.mkdir()
    (out / "keep.txt").write_text("a user's file")
    code, _, err = run(capsys, "sim", "make", "--preset", "tiny", "--views", "2", "--out", out)
    one_line_error(code, err, "sim", str(out), "not empty", "--force")
    assert [p.name for p in out.iterdir()] == ["keep.txt"]  # untouched
    code, _, err = run(capsys, "sim", "make", "--preset", "tiny", "--views", "2", "--out", out, "--force")
    assert code == 0, err
    assert not (out / "keep.txt").exists() and (out / "replay.mcap").exists()


def test_the_encode_cache_follows_the_image_and_the_encoder_not_the_file_name(scene, capsys):
    code, out, _ = run(capsys, "encode", "--scene", scene, "--encoders", "none", "--limit", "2")
    assert code == 0 and "2 encoded" in out
    code, out, _ = run(capsys, "encode", "--scene", scene, "--encoders", "none", "--limit", "2")
    assert "0 encoded, 2 from the cache" in out
    first = sorted((scene / "images").iterdir())[0]
    second = sorted((scene / "images").iterdir())[1]
    shutil.copy(second, first)  # another photo under the first one's name
    code, out, _ = run(capsys, "encode", "--scene", scene, "--encoders", "none", "--limit", "2")
    assert "1 encoded, 1 from the cache" in out
    # pictures asked for after a plain run are written, from the cache
    code, out, _ = run(capsys, "encode", "--scene", scene, "--encoders", "none", "--limit", "2", "--png")
    assert code == 0 and "0 encoded" in out
    assert len(list((scene / "cache" / "encode").glob("*_regions.png"))) == 2


def test_rendering_a_map_with_another_scenes_cameras_is_an_error(scene, tmp_path, capsys):
    far = tmp_path / "far.ply"
    gaussians = read_ply(scene / "map" / "point_cloud.ply")
    gaussians.means = gaussians.means + np.float32(1e5)  # the same map, elsewhere
    write_ply(far, gaussians)
    code, _, err = run(
        capsys, "render", "--ply", far, "--cameras", scene / "sparse" / "0", "--view", "0", "--out", tmp_path / "r"
    )
    one_line_error(code, err, "render", "no Gaussian", "same scene")
    assert not (tmp_path / "r.npz").exists()


# --- tracebacks that became one line --------------------------------------------------------


@pytest.mark.parametrize("command", ["render", "sim", "aggregate", "query", "keys", "record"])
def test_an_output_under_a_file_is_one_line_before_any_work(command, scene, tmp_path, capsys):
    (tmp_path / "afile").write_text("x")
    out = tmp_path / "afile" / "out"
    ply, model = scene / "map" / "point_cloud.ply", scene / "sparse" / "0"
    args = {
        "render": ["render", "--ply", ply, "--cameras", model, "--view", "0", "--out", out],
        "sim": ["sim", "make", "--preset", "tiny", "--out", out],
        "aggregate": ["aggregate", "--scene", scene, "--out", out],
        "query": ["query", "--map", tmp_path / "none.npz", "--scene", scene, "road", "--out", out],
        "keys": ["keys", "generate", "--out", out, "--name", "k"],
        "record": ["record", "--source", scene / "replay.mcap", "--out", out],
    }[command]
    code, _, err = run(capsys, *args)
    one_line_error(code, err, command, str(tmp_path / "afile"), "is a file, not a folder")


def test_render_checks_the_picture_path_before_writing_the_npz(scene, tmp_path, capsys):
    (tmp_path / "afile").write_text("x")
    code, _, err = run(
        capsys, "render", "--ply", scene / "map" / "point_cloud.ply", "--cameras", scene / "sparse" / "0",
        "--view", "0", "--out", tmp_path / "r.npz", "--png", tmp_path / "afile" / "r.png",
    )  # fmt: skip
    one_line_error(code, err, "render", "--png", "is a file")
    assert not (tmp_path / "r.npz").exists()


def test_the_printed_output_is_the_written_one(scene, tmp_path, capsys):
    code, out, _ = run(
        capsys, "render", "--ply", scene / "map" / "point_cloud.ply", "--cameras", scene / "sparse" / "0",
        "--view", "0", "--out", tmp_path / "x",
    )  # fmt: skip
    assert code == 0 and out.rstrip().endswith(f"-> {tmp_path / 'x.npz'}") and (tmp_path / "x.npz").exists()


@pytest.mark.parametrize("damage", ["random bytes", "truncated"])
def test_a_damaged_language_map_is_one_line_without_numpys_advice(damage, scene, tmp_path, capsys):
    bad = tmp_path / "map.npz"
    if damage == "random bytes":
        bad.write_bytes(np.random.default_rng(0).bytes(1000))
    else:
        np.savez(bad, version=2, features=np.zeros((5, 4), np.float16), observed=np.ones(5, bool), encoder="e")
        bad.write_bytes(bad.read_bytes()[:200])
    code, _, err = run(capsys, "query", "--map", bad, "--scene", scene, "road")
    one_line_error(code, err, "query", str(bad), "not a language map")
    assert "pickle" not in err


def test_bad_values_of_options_are_one_line(scene, tmp_path, capsys):
    code, _, err = run(capsys, "encode", "--scene", scene, "--weights", "a,b")
    one_line_error(code, err, "encode", "weights")
    with pytest.raises(SystemExit) as exit_info:  # a usage error: argparse's exit 2, with the reason
        main(["ground", "status", "--timeout", "-1"])
    assert exit_info.value.code == 2 and "positive number of seconds" in capsys.readouterr().err


def test_a_text_file_named_jpg_in_a_photo_folder_is_one_line(tmp_path, capsys):
    photos = tmp_path / "photos"
    photos.mkdir()
    (photos / "IMG_0001.jpg").write_text("not a photo")
    code, _, err = run(
        capsys, "record", "--source-kind", "exif_folder", "--source", photos, "--out", tmp_path / "o.mcap"
    )
    assert code == 1 and err.count("\n") == 1 and "IMG_0001.jpg" in err and "Traceback" not in err


def test_a_transforms_json_with_a_3x3_matrix_is_one_line(scene, tmp_path, capsys):
    doc = {"fl_x": 100, "w": 64, "h": 48, "frames": [{"file_path": "a.png", "transform_matrix": np.eye(3).tolist()}]}
    (tmp_path / "transforms.json").write_text(json.dumps(doc))
    code, _, err = run(
        capsys, "render", "--ply", scene / "map" / "point_cloud.ply", "--cameras", tmp_path / "transforms.json",
        "--view", "0", "--out", tmp_path / "r",
    )  # fmt: skip
    one_line_error(code, err, "render", "transforms.json", "4x4")


# --- misleading messages --------------------------------------------------------------------


def test_a_nan_map_does_not_suggest_an_option_aggregate_lacks(scene, capsys):
    gaussians = read_ply(scene / "map" / "point_cloud.ply")
    gaussians.means[3] = np.nan
    write_ply(scene / "map" / "point_cloud.ply", gaussians)
    code, _, err = run(capsys, "aggregate", "--scene", scene, "--out", scene / "agg")
    one_line_error(code, err, "aggregate", "NaN", "aggregation needs every Gaussian finite")


def test_a_folder_given_as_the_ply_says_so(scene, tmp_path, capsys):
    code, _, err = run(
        capsys, "render", "--ply", scene / "map", "--cameras", scene / "sparse" / "0", "--view", "0",
        "--out", tmp_path / "r",
    )  # fmt: skip
    one_line_error(code, err, "render", "is a folder")


def test_a_corrupt_checkpoint_never_relays_torchs_unsafe_advice(tmp_path, capsys):
    bad = tmp_path / "model.pt"
    bad.write_bytes(np.random.default_rng(1).bytes(500))
    code, _, err = run(capsys, "export-clip", "--checkpoint", bad, "--vocab", bad, "--out", tmp_path / "enc")
    one_line_error(code, err, "export-clip", str(bad), "never pickled code")
    assert "weights_only" not in err


def test_record_needs_its_source_and_writes_what_it_prints(scene, tmp_path, capsys):
    code, _, err = run(capsys, "record", "--out", tmp_path / "a.mcap")
    one_line_error(code, err, "record", "--source")
    out = tmp_path / "missing" / "session"
    code, printed, err = run(capsys, "record", "--source", scene / "replay.mcap", "--out", out, "--frames", "2")
    assert code == 0, err
    assert printed.rstrip().endswith(f"-> {out}.mcap") and Path(f"{out}.mcap").exists()
    assert [p.name for p in out.parent.iterdir()] == ["session.mcap"]  # no temporary file left


def test_encode_of_a_missing_scene_creates_nothing(tmp_path, capsys):
    missing = tmp_path / "nope" / "scene"
    code, _, err = run(capsys, "encode", "--scene", missing)
    one_line_error(code, err, "encode", str(missing))
    assert not (tmp_path / "nope").exists()


# --- query feedback --------------------------------------------------------------------------


def test_unknown_words_and_empty_negatives_are_said(scene, tiny_map, capsys):
    code, out, _ = run(capsys, "query", "--map", tiny_map, "--scene", scene, "swimming pool")
    assert code == 0 and 'does not know "swimming", "pool"' in out
    code, out, _ = run(capsys, "query", "--map", tiny_map, "--scene", scene, "red roof buildings")
    assert code == 0 and "does not know" not in out
    code, _, err = run(capsys, "query", "--map", tiny_map, "--scene", scene, "road", "--negatives", " , road,")
    one_line_error(code, err, "query", "no negatives left")


def test_an_empty_ground_query_is_refused_without_the_network(capsys):
    code, _, err = run(capsys, "ground", "query", "   ", "--connect", "tcp://127.0.0.1:9", "--timeout", "30")
    one_line_error(code, err, "ground", "empty")


# --- the command line itself -------------------------------------------------------------------


def test_version_and_exit_codes_are_in_the_help(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--version"])
    assert exit_info.value.code == 0 and capsys.readouterr().out.startswith("olsplat ")
    with pytest.raises(SystemExit):
        main(["--help"])
    text = capsys.readouterr().out
    assert "exit codes" in text and "130 interrupted" in text and "examples:" in text


def test_a_bug_keeps_its_traceback_and_says_it_is_a_bug(monkeypatch, capsys):
    from olsplat_nodes.tools import keys

    def broken(args):
        raise RuntimeError("an impossible state")

    monkeypatch.setattr(keys, "run", broken)
    code = main(["keys", "generate", "--out", "x", "--name", "k"])
    err = capsys.readouterr().err
    assert code == 1 and "Traceback" in err and "an impossible state" in err and "a bug in olsplat" in err


def test_the_3d_clustering_can_be_set_and_follows_the_maps_density(scene, tiny_map, capsys):
    def instances(*extra) -> int:
        code, out, err = run(capsys, "query", "--map", tiny_map, "--scene", scene, "road", *extra)
        assert code == 0, err
        return int(out.split("negatives; ")[1].split(" instances")[0])

    # the tiny map is sparse (26k Gaussians over the town): a fixed 1.5 m finds no road at all,
    # the default radius from the map's density finds it
    assert instances("--cluster-radius", "1.5") == 0 and instances() > 0
    assert instances("--cluster-radius", "3") > instances("--cluster-radius", "8") > 0  # small splits, large joins
    code, _, err = run(capsys, "query", "--map", tiny_map, "--scene", scene, "road", "--min-points", "0")
    one_line_error(code, err, "query", "--min-points")
