"""`olsplat encode` on a simulator scene: regions, features from exported encoders, overlays."""

from __future__ import annotations

import gzip
import shutil

import numpy as np
import torch

from olsplat_nodes.cli import main
from olsplat_nodes.encoders.bank import encode_cache_file
from olsplat_nodes.encoders.clip_model import ClipModel
from olsplat_nodes.encoders.export import export_model

from .encoders.test_clip_export import MERGES, small_config


def test_encode_scene(tiny, tmp_path, capsys):
    scene = tmp_path / "scene"  # a copy: the shared tiny scene stays as `sim make` wrote it
    shutil.copytree(tiny[0], scene)
    vocab = tmp_path / "merges.txt.gz"
    with gzip.open(vocab, "wt", encoding="utf-8") as f:
        f.write("#version: 0.2\n" + "\n".join(MERGES) + "\n")
    torch.manual_seed(0)
    folders = [export_model(ClipModel(small_config()), vocab, tmp_path / f"e{i}", f"e{i}") for i in range(2)]
    args = ["encode", "--scene", str(scene), "--limit", "2", "--levels", "2", "--png", "--force",
            "--encoders", ",".join(map(str, folders)), "--weights", "0.6,0.4"]  # fmt: skip
    assert main(args) == 0
    data = np.load(encode_cache_file(scene, "frame_0000", "e0:0.60+e1:0.40"))
    maps = data["label_maps"]
    assert maps.shape == (2, 240, 320) and maps.dtype == np.int32
    for level in range(2):
        features = data[f"features_{level}"]
        assert features.shape == (maps[level].max() + 1, 32) and features.dtype == np.float16
    assert str(data["encoder"]) == "e0:0.60+e1:0.40"
    assert (scene / "cache" / "encode" / "frame_0001_regions.png").stat().st_size > 0
    assert not encode_cache_file(scene, "frame_0002", "e0:0.60+e1:0.40").exists()
    assert main(["encode", "--scene", str(scene), "--limit", "1", "--force", "--encoders", "olsplat-vit48"]) == 0
    data = np.load(encode_cache_file(scene, "frame_0000", "olsplat-vit48"))
    assert str(data["encoder"]) == "olsplat-vit48" and data["features_2"].shape[1] == 64
    assert main(["encode", "--scene", str(scene), "--limit", "1", "--force"]) == 0  # default: olsplat-cnn64
    assert str(np.load(encode_cache_file(scene, "frame_0000", "olsplat-cnn64"))["encoder"]) == "olsplat-cnn64"
    assert main(["encode", "--scene", str(scene), "--limit", "1", "--force", "--encoders", "shipped"]) == 0
    assert (
        str(np.load(encode_cache_file(scene, "frame_0000", "olsplat-cnn64:0.60+olsplat-vit48:0.40"))["encoder"])
        == "olsplat-cnn64:0.60+olsplat-vit48:0.40"
    )
    assert main(["encode", "--scene", str(tmp_path), "--levels", "2"]) == 1
    assert "no images/ folder" in capsys.readouterr().err
    assert main(["encode", "--scene", str(scene), "--levels", "9"]) == 1
    assert "--levels must be 1..6" in capsys.readouterr().err


def test_the_feature_cache_is_keyed_by_the_region_settings(tiny, tmp_path):
    """A cache made with other region settings (here `olsplat encode --levels 2`) is not
    reused by the offline runs: they compute their own regions and replace it."""
    from olsplat_nodes.encoders.spec import encoder_from_spec
    from olsplat_nodes.pipeline import Scene
    from olsplat_nodes.pipeline.scene_folder import view_features
    from olsplat_nodes.regions import RegionConfig

    scene_dir = tmp_path / "scene"
    shutil.copytree(tiny[0], scene_dir)
    assert main(["encode", "--scene", str(scene_dir), "--limit", "1", "--levels", "2"]) == 0
    cache = encode_cache_file(scene_dir, "frame_0000", "olsplat-cnn64")
    assert np.load(cache)["label_maps"].shape[0] == 2
    scene = Scene.open(scene_dir)
    maps, bank = view_features(scene, scene.cameras[0], encoder_from_spec())
    assert maps.shape[0] == len(RegionConfig().level_counts) == len(bank)
    assert str(np.load(cache)["regions"]).startswith(repr(RegionConfig()) + "|image sha256 ")  # and the photo's hash
    again, _ = view_features(scene, scene.cameras[0], encoder_from_spec())  # now from the cache
    np.testing.assert_array_equal(again, maps)


def test_each_encoder_keeps_its_own_cache(tiny, tmp_path):
    """Runs that alternate encoders (an evaluation's each-alone and fused runs) reuse each one's
    features: the second encoder's do not overwrite the first's."""
    from olsplat_nodes.encoders.spec import encoder_from_spec
    from olsplat_nodes.pipeline import Scene
    from olsplat_nodes.pipeline.scene_folder import view_features

    scene_dir = tmp_path / "scene"
    shutil.copytree(tiny[0], scene_dir, ignore=shutil.ignore_patterns("cache"))
    scene = Scene.open(scene_dir)
    camera = scene.cameras[0]
    first, second = encoder_from_spec("olsplat-cnn64"), encoder_from_spec("olsplat-vit48")
    maps, bank = view_features(scene, camera, first)
    view_features(scene, camera, second)
    files = {e.name: encode_cache_file(scene_dir, "frame_0000", e.name) for e in (first, second)}
    assert files["olsplat-cnn64"] != files["olsplat-vit48"] and all(f.is_file() for f in files.values())
    assert str(np.load(files["olsplat-cnn64"])["encoder"]) == "olsplat-cnn64"
    stamp = files["olsplat-cnn64"].stat().st_mtime_ns
    again_maps, again_bank = view_features(scene, camera, first)  # from its own file, not recomputed
    assert files["olsplat-cnn64"].stat().st_mtime_ns == stamp
    np.testing.assert_array_equal(again_maps, maps)
    for a, b in zip(again_bank, bank, strict=True):
        np.testing.assert_array_equal(a, b)
    assert encode_cache_file(scene_dir, "v", "a/b:0.60") != encode_cache_file(scene_dir, "v", "a_b:0.60")
    # a file of the earlier layout (cache/encode/<view>.npz) is still read when it is this encoder's
    legacy = scene_dir / "cache" / "encode" / "frame_0000.npz"
    files["olsplat-cnn64"].replace(legacy)
    np.testing.assert_array_equal(view_features(scene, camera, first)[0], maps)
    assert not files["olsplat-cnn64"].exists()  # read from the old file, not computed again
