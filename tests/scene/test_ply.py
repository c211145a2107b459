"""INRIA PLY: round trips, real files from other trainers, and clear errors on bad files."""

from __future__ import annotations

import numpy as np
import pytest
from plyfile import PlyData, PlyElement

from olsplat_nodes.errors import SceneFormatError
from olsplat_nodes.scene import Gaussians, read_ply, write_ply

from ..conftest import random_gaussians


@pytest.mark.parametrize("sh_degree", [0, 1, 2, 3])
def test_round_trip_every_sh_degree(tmp_path, sh_degree):
    gaussians = random_gaussians(57, sh_degree, seed=sh_degree)
    gaussians.extras["nx"] = np.zeros(57, np.float32)
    gaussians.extras["confidence"] = np.linspace(0, 1, 57).astype(np.float64)
    write_ply(tmp_path / "map.ply", gaussians)
    back = read_ply(tmp_path / "map.ply")
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        np.testing.assert_array_equal(getattr(back, name), getattr(gaussians, name), err_msg=name)
    assert back.sh_degree == sh_degree
    assert set(back.extras) == {"nx", "confidence"}
    np.testing.assert_array_equal(back.extras["confidence"], gaussians.extras["confidence"])
    assert back.extras["confidence"].dtype == np.float64


def test_inria_field_layout(tmp_path):
    """f_rest is channel-major (f_rest_{c*15+j}), rot is wxyz, as the INRIA trainer writes it."""
    gaussians = random_gaussians(3, 3)
    write_ply(tmp_path / "map.ply", gaussians)
    vertex = PlyData.read(str(tmp_path / "map.ply"))["vertex"].data
    names = vertex.dtype.names
    assert names[:3] == ("x", "y", "z") and names[3:6] == ("f_dc_0", "f_dc_1", "f_dc_2")
    assert vertex["f_rest_16"][1] == gaussians.sh[1, 2, 1]  # channel 1, coefficient 1 + 1
    assert vertex["rot_0"][2] == gaussians.quats[2, 0]


def test_real_file_from_another_trainer(shared_data):
    """donut_fused.ply: no normals, no f_rest (SH degree 0)."""
    gaussians = read_ply(shared_data / "donut_fused.ply")
    assert len(gaussians) == 45_624
    assert gaussians.sh_degree == 0
    assert np.isfinite(gaussians.means).all()


def _write_raw(path, fields: dict[str, np.ndarray]):
    table = np.empty(len(next(iter(fields.values()))), dtype=[(k, "<f4") for k in fields])
    for k, v in fields.items():
        table[k] = v
    PlyData([PlyElement.describe(table, "vertex")]).write(str(path))


def test_missing_positions_is_named(tmp_path):
    _write_raw(tmp_path / "a.ply", {"opacity": np.zeros(3), "red": np.zeros(3)})
    with pytest.raises(SceneFormatError, match=r"a\.ply: missing positions: no field\(s\) x, y, z"):
        read_ply(tmp_path / "a.ply")


def test_plain_point_cloud_is_refused_with_the_missing_fields(tmp_path):
    _write_raw(tmp_path / "cloud.ply", {"x": np.zeros(3), "y": np.zeros(3), "z": np.zeros(3)})
    with pytest.raises(SceneFormatError, match=r"missing Gaussian parameters: no field.*opacity"):
        read_ply(tmp_path / "cloud.ply")


def test_truncated_file(tmp_path):
    write_ply(tmp_path / "full.ply", random_gaussians(100, 3))
    data = (tmp_path / "full.ply").read_bytes()
    (tmp_path / "cut.ply").write_bytes(data[: len(data) // 2])
    with pytest.raises(SceneFormatError, match=r"cut\.ply: not a readable PLY file"):
        read_ply(tmp_path / "cut.ply")


@pytest.mark.parametrize("content", [b"", b"hello world\n", b"ply\nformat binary_little_endian 1.0\nelement"])
def test_garbage_file(tmp_path, content):
    (tmp_path / "bad.ply").write_bytes(content)
    with pytest.raises(SceneFormatError, match=r"bad.ply"):
        read_ply(tmp_path / "bad.ply")


def test_missing_file(tmp_path):
    with pytest.raises(SceneFormatError, match="does not exist"):
        read_ply(tmp_path / "nope.ply")


def test_nonfinite_policies(tmp_path):
    gaussians = random_gaussians(10, 1)
    gaussians.means[3, 1] = np.nan
    gaussians.sh[7, 2, 0] = np.inf
    write_ply(tmp_path / "nan.ply", gaussians)
    with pytest.raises(SceneFormatError, match="2 of 10 Gaussians have NaN/inf parameters \\(first at index 3\\)"):
        read_ply(tmp_path / "nan.ply")
    assert len(read_ply(tmp_path / "nan.ply", on_nonfinite="drop")) == 8
    assert len(read_ply(tmp_path / "nan.ply", on_nonfinite="keep")) == 10


def test_bad_sh_count(tmp_path):
    fields = {k: np.zeros(2) for k in ["x", "y", "z", "opacity", "f_dc_0", "f_dc_1", "f_dc_2"]}
    fields.update({f"scale_{i}": np.zeros(2) for i in range(3)})
    fields.update({f"rot_{i}": np.ones(2) for i in range(4)})
    fields.update({f"f_rest_{i}": np.zeros(2) for i in range(6)})  # 2 per channel: no degree
    _write_raw(tmp_path / "sh.ply", fields)
    with pytest.raises(SceneFormatError, match="6 f_rest_\\* fields match no SH degree"):
        read_ply(tmp_path / "sh.ply")


def test_gaussians_validate_shapes():
    with pytest.raises(ValueError, match="quats must have shape"):
        Gaussians(np.zeros((2, 3)), np.zeros((3, 4)), np.zeros((2, 3)), np.zeros(2), np.zeros((2, 1, 3)))
