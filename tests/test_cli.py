"""The ``olsplat`` command: render end to end, and one clear line for every user mistake."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from olsplat_nodes.cli import main
from olsplat_nodes.raster import rasterize
from olsplat_nodes.scene import read_colmap, write_colmap, write_ply, write_transforms_json

from .conftest import camera_for, random_gaussians


@pytest.fixture
def scene(tmp_path) -> Path:
    gaussians = random_gaussians(200, 3, seed=1)
    write_ply(tmp_path / "map.ply", gaussians)
    cameras = [camera_for("PINHOLE_SKEWED", 48, 40), camera_for("OPENCV_WIDE", 40, 30)]
    cameras[0].name, cameras[1].name = "a.png", "b.png"
    write_colmap(tmp_path / "sparse" / "0", cameras)
    write_transforms_json(tmp_path / "transforms.json", cameras)
    return tmp_path


@pytest.mark.parametrize("cameras", ["sparse/0", "transforms.json"])
def test_render_writes_the_documented_npz(scene, cameras, capsys):
    code = main(
        ["render", "--ply", str(scene / "map.ply"), "--cameras", str(scene / cameras), "--view", "b.png",
         "--out", str(scene / "out" / "b.npz"), "--png", str(scene / "b.png")]
    )  # fmt: skip
    assert code == 0
    data = np.load(scene / "out" / "b.npz")
    assert data["rgb"].shape == (30, 40, 3) and data["rgb"].dtype == np.float32
    assert data["alpha"].shape == (30, 40) and data["depth"].shape == (30, 40)
    assert data["topk_ids"].shape == (30, 40, 32) and data["topk_ids"].dtype == np.int32
    assert data["topk_weights"].shape == (30, 40, 32) and data["topk_weights"].dtype == np.float32
    expected = rasterize(random_gaussians(200, 3, seed=1), read_colmap(scene)[1])
    np.testing.assert_allclose(data["rgb"], expected.rgb, atol=1e-6)
    assert (scene / "b.png").stat().st_size > 0
    assert "rendered b.png" in capsys.readouterr().out


def _render_args(scene, ply="map.ply", cameras="sparse/0", view="0"):
    return [
        "render",
        "--ply",
        str(scene / ply),
        "--cameras",
        str(scene / cameras),
        "--view",
        view,
        "--out",
        str(scene / "o.npz"),
    ]


def test_bad_inputs_give_one_line_and_exit_1(scene, capsys):
    data = (scene / "map.ply").read_bytes()
    (scene / "cut.ply").write_bytes(data[: len(data) // 3])
    (scene / "model").mkdir()
    (scene / "model" / "cameras.txt").write_text("1 OPENCV_FISHEYE 10 10 1 1 5 5 0 0 0 0\n")
    (scene / "model" / "images.txt").write_text("")
    (scene / "noK.json").write_text(
        '{"w": 4, "h": 4, "frames": [{"file_path": "x", '
        '"transform_matrix": [[1,0,0,0],[0,1,0,0],[0,0,1,0],[0,0,0,1]]}]}'
    )
    cases = [
        (_render_args(scene, ply="cut.ply"), "cut.ply: not a readable PLY file"),
        (_render_args(scene, ply="nothing.ply"), "nothing.ply: file does not exist"),
        (_render_args(scene, view="zebra.png"), "no view 'zebra.png'"),
        (_render_args(scene, cameras="model"), "unsupported model OPENCV_FISHEYE"),
        (_render_args(scene, cameras="noK.json"), "noK.json: frame 0: no intrinsics"),
    ]
    for args, message in cases:
        assert main(args) == 1, message
        err = capsys.readouterr().err
        assert message in err
        assert err.count("\n") == 1 and "Traceback" not in err


def test_nonfinite_map_needs_the_flag(scene, capsys):
    gaussians = random_gaussians(200, 3, seed=1)
    gaussians.means[5] = np.nan
    write_ply(scene / "nan.ply", gaussians)
    assert main(_render_args(scene, ply="nan.ply")) == 1
    assert "--allow-nonfinite" in capsys.readouterr().err
    assert main([*_render_args(scene, ply="nan.ply"), "--allow-nonfinite"]) == 0
    ids = np.load(scene / "o.npz")["topk_ids"]
    assert ids.max() > 5 and not (ids == 5).any()  # ids still index the file; the NaN one is absent


def test_console_script_runs_as_a_process(scene):
    """The installed entry point, in a real process: a user mistake exits 1 without a traceback."""
    exe = Path(sys.executable).with_name("olsplat")
    done = subprocess.run([str(exe), *_render_args(scene, view="99")], capture_output=True, text=True, timeout=300)
    assert done.returncode == 1
    assert "no view '99'" in done.stderr and "Traceback" not in done.stderr
    help_text = subprocess.run([str(exe), "--help"], capture_output=True, text=True, timeout=60).stdout
    for command in ("render", "demo", "bench"):
        assert command in help_text


def test_the_parsers_method_names_are_the_method_table():
    from olsplat_nodes.method import METHODS
    from olsplat_nodes.tools.method_names import METHOD_NAMES

    assert list(METHOD_NAMES) == list(METHODS)


def test_the_parsers_default_encoder_is_the_encoders_default():
    from olsplat_nodes.encoders.spec import DEFAULT_SPEC, encoder_from_spec
    from olsplat_nodes.tools.method_names import DEFAULT_ENCODER

    assert DEFAULT_ENCODER == DEFAULT_SPEC == encoder_from_spec().name


def test_help_does_not_import_the_heavy_packages():
    """`olsplat --help` stays fast: building the parser imports neither numba nor OpenCV nor torch."""
    import subprocess
    import sys

    code = (
        "import sys; from olsplat_nodes.cli import build_parser; build_parser(); "
        "print(sorted(m for m in ('numba', 'cv2', 'torch', 'onnxruntime') if m in sys.modules))"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "[]"


def test_every_command_has_examples_and_every_option_a_help_text():
    import argparse

    from olsplat_nodes.cli import build_parser

    leaves = []

    def walk(parser, path):
        subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
        for action in subs:
            for name, sub in action.choices.items():
                walk(sub, [*path, name])
        if not subs:
            leaves.append((" ".join(path), parser))

    walk(build_parser(), [])
    assert len(leaves) >= 20
    for name, parser in leaves:
        assert parser.epilog and "examples:" in parser.epilog, name
        for action in parser._actions:
            assert action.help, (name, action.option_strings or action.dest)
        text = parser.format_help()
        if any(a.option_strings and a.default not in (None, False, []) for a in parser._actions[1:]):
            assert "default" in text, name
