"""The independent pair's budget rule by validation mIoU (``sim.train_pair``'s docstring states it).

Pure parts: ``next_to_score`` (the lazy scan) and ``choose_rungs`` over per-rung scores (``None``
where a rung was not scored). The rest runs ``olsplat eval`` on the validation scenes for one
exported rung and keeps the scores in a JSON file so that an interrupted run continues.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
from collections.abc import Sequence
from pathlib import Path

import numpy as np

VALIDATION_SEEDS = (2000, 2001, 2002)
TARGET_MIOU = 55.0  # the middle of the 50-65 range real aerial CLIPs reach on UAV scenes
MAX_GAP_MIOU = 3.0
METHOD = "outlangsplat"

Scores = Sequence[float | None]


def next_to_score(scores: Scores, target: float = TARGET_MIOU) -> int | None:
    """The rung the lazy scan scores next (lowest first), or None when the scan is over: a scored
    rung reaches ``target`` with every rung below it scored, or every rung is scored."""
    for i, score in enumerate(scores):
        if score is None:
            return i
        if score >= target:
            return None
    return None


def chosen_rung(scores: Scores, target: float = TARGET_MIOU) -> int:
    """The smallest rung whose score reaches ``target``; if none does, the best-scoring (earliest on a tie)."""
    if not len(scores):
        raise ValueError("choose_rungs needs a score per rung for both encoders, got an empty ladder")
    pending = next_to_score(scores, target)
    if pending is not None:
        raise ValueError(f"rung {pending} is not scored yet: the scan from the lowest rung is not over")
    first = next((i for i, s in enumerate(scores) if s is not None and s >= target), None)
    if first is not None:
        return first
    return max(range(len(scores)), key=lambda i: (scores[i], -i))


def choose_rungs(scores_a: Scores, scores_b: Scores, target: float = TARGET_MIOU,
                 max_gap: float = MAX_GAP_MIOU) -> tuple[int, int]:  # fmt: skip
    """(rung index of A, of B) by the budget rule: each its ``chosen_rung``; if the two scores differ
    by more than ``max_gap``, the stronger steps down to its rung at or below its chosen one whose
    score is nearest the weaker's (the earlier on a tie). Every rung it may step to is scored
    when the lazy scan is over, so lazy and full scoring choose the same rungs."""
    chosen = [chosen_rung(scores_a, target), chosen_rung(scores_b, target)]
    scores = (scores_a, scores_b)
    picked = [float(scores[k][chosen[k]]) for k in (0, 1)]  # type: ignore[arg-type]
    if abs(picked[0] - picked[1]) > max_gap:
        strong = 0 if picked[0] > picked[1] else 1
        weak = picked[1 - strong]
        mine = scores[strong]
        chosen[strong] = min(range(chosen[strong] + 1), key=lambda i: (abs(float(mine[i]) - weak), i))  # type: ignore[arg-type]
    return chosen[0], chosen[1]


class ScoreCache:
    """Rung scores ({encoder: {epochs: {"miou": {seed: mIoU}, "seconds": s}}}) in a JSON file,
    written after every rung."""

    def __init__(self, path: Path):
        self.path = path
        self.data: dict[str, dict[str, dict]] = json.loads(path.read_text()) if path.is_file() else {}

    def get(self, encoder: str, epochs: float) -> dict[str, float] | None:
        entry = self.data.get(encoder, {}).get(f"{epochs:g}")
        return None if entry is None else entry["miou"]

    def seconds(self, encoder: str) -> float:
        return sum(entry["seconds"] for entry in self.data.get(encoder, {}).values())

    def mean(self, encoder: str, epochs: float) -> float | None:
        per_seed = self.get(encoder, epochs)
        return None if per_seed is None else sum(per_seed.values()) / len(per_seed)

    def put(self, encoder: str, epochs: float, per_seed: dict[str, float], seconds: float) -> None:
        if self.path.is_file():  # keep what another writer added since
            for name, entries in json.loads(self.path.read_text()).items():
                self.data.setdefault(name, {}).update({k: v for k, v in entries.items() if k not in self.data[name]})
        self.data.setdefault(encoder, {})[f"{epochs:g}"] = {"miou": per_seed, "seconds": seconds}
        self.path.parent.mkdir(parents=True, exist_ok=True)
        tmp = self.path.with_suffix(".tmp")
        tmp.write_text(json.dumps(self.data, indent=1, sort_keys=True))
        os.replace(tmp, self.path)


def _olsplat() -> list[str]:
    found = Path(sys.executable).parent / "olsplat"
    return [str(found)] if found.is_file() else [shutil.which("olsplat") or "olsplat"]


def validation_scenes(folder: Path, seeds: Sequence[int] = VALIDATION_SEEDS, log=print) -> list[Path]:
    """``folder``/valS for each validation seed: small preset, world v1, default flight (made when missing)."""
    if not seeds or not set(seeds) <= set(VALIDATION_SEEDS):
        raise ValueError(f"validation seeds must be some of {VALIDATION_SEEDS}, got {seeds!r}")
    scenes = []
    for seed in seeds:
        scene = folder / f"val{seed}"
        if not (scene / "scene.json").is_file():
            log(f"making {scene}")
            cmd = ["sim", "make", "--preset", "small", "--seed", str(seed), "--world", "v1", "--out", str(scene)]
            subprocess.run(_olsplat() + cmd, check=True, stdout=subprocess.DEVNULL)
        meta = json.loads((scene / "scene.json").read_text())
        world = meta.get("options", {}).get("world", {}).get("name")
        if meta.get("seed") != seed or meta.get("preset", {}).get("name") != "small" or world != "v1":
            raise ValueError(f"{scene} is not seed {seed}, small preset, world v1: {meta.get('seed')}, {world}")
        scenes.append(scene)
    return scenes


def _region_key() -> str:
    from olsplat_nodes.regions import RegionConfig

    return repr(RegionConfig())  # the region settings ``olsplat eval`` uses (``view_features``' default)


def prepare_crops(scenes: Sequence[Path], encoder, folder: Path, log=print) -> None:
    """Per view of each scene, ``folder``/valS/STEM.npz: its regions (label maps, read from the
    scene's own cache when its region settings and image bytes match, else proposed) and the crops
    ``encoder`` takes of them (its input size and crop style): what every rung of one design shares."""
    from olsplat_nodes.encoders.bank import view_key
    from olsplat_nodes.encoders.crops import CropConfig, region_crops
    from olsplat_nodes.pipeline.scene_folder import Scene
    from olsplat_nodes.regions import RegionConfig, propose_regions

    crop_config = getattr(encoder, "crop_config", None) or CropConfig()
    for scene_path in scenes:
        scene = Scene.open(scene_path)
        todo = [c for c in scene.cameras if not (folder / scene_path.name / f"{Path(c.name).stem}.npz").is_file()]
        if todo:
            log(f"{scene_path.name}: regions and {encoder.name} crops of {len(todo)} views -> {folder}")
        for camera in todo:
            stem = Path(camera.name).stem
            key = view_key(scene_path / "images" / camera.name, _region_key())
            image = scene.image(camera)
            label_maps = None
            cached = scene_path / "cache" / "encode" / f"{stem}.npz"
            if cached.is_file():
                with np.load(cached) as data:
                    if "regions" in data and str(data["regions"]) == key:
                        label_maps = data["label_maps"]
            if label_maps is None:
                label_maps = propose_regions(image, RegionConfig()).label_maps
            crops = {
                f"crops_{i}": region_crops(image, m, encoder.input_size, crop_config) for i, m in enumerate(label_maps)
            }
            target = folder / scene_path.name / f"{stem}.npz"
            target.parent.mkdir(parents=True, exist_ok=True)
            tmp = target.with_name(f"{stem}.{os.getpid()}-{threading.get_ident()}.tmp.npz")  # rungs at once
            np.savez(tmp, label_maps=label_maps, key=np.array(key), **crops)  # type: ignore[arg-type]
            os.replace(tmp, target)


def score_encoder(encoder: Path, scenes: Sequence[Path], log=print, crops: Path | None = None) -> dict[str, float]:
    """``olsplat eval --methods outlangsplat --encoders ENCODER`` on ``scenes``: {seed: mIoU}.

    It runs on copies of the scenes (links to their files) whose feature cache is filled first from
    ``crops`` (``prepare_crops``, kept across rungs) with this encoder, by the package's own
    ``encode_images`` and ``save_bank`` in ``encode_regions``' batches: what ``olsplat eval`` would
    compute and cache itself, without proposing and cropping every view again for every rung. The
    scene folders' own caches are never read for features nor written (every rung has its design's name)."""
    from olsplat_nodes.encoders.bank import FeatureBank, save_bank
    from olsplat_nodes.encoders.onnx_encoder import OnnxEncoder

    model = OnnxEncoder(encoder, 1)
    crops = crops if crops is not None else encoder.parent / "crops"
    prepare_crops(scenes, model, crops, log)
    with tempfile.TemporaryDirectory(prefix="pair-eval-", dir=encoder.parent) as tmp:
        copies = []
        for scene in scenes:
            copy = Path(tmp) / scene.name
            copy.mkdir()
            for entry in scene.iterdir():
                if entry.name not in ("cache", "eval"):
                    (copy / entry.name).symlink_to(entry.resolve())
            for view in sorted((crops / scene.name).glob("*.npz")):
                with np.load(view) as data:
                    label_maps = data["label_maps"]
                    features = []
                    for i in range(len(label_maps)):
                        rows = data[f"crops_{i}"]
                        parts = [model.encode_images(rows[s : s + 64]) for s in range(0, len(rows), 64)]
                        features.append(np.concatenate(parts).astype(np.float32))
                    save_bank(copy / "cache" / "encode" / view.name, label_maps, FeatureBank(features, model.name),
                              str(data["key"]))  # fmt: skip
            copies.append(copy)
        out = Path(tmp) / "eval.json"
        scene_args = [a for s in copies for a in ("--scene", str(s))]
        cmd = [*_olsplat(), "eval", *scene_args, "--methods", METHOD, "--encoders", str(encoder),
               "--work", str(Path(tmp) / "work"), "--json", str(out)]  # fmt: skip
        log(" ".join(cmd))
        done = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        if done.returncode != 0:
            raise RuntimeError(f"olsplat eval failed ({done.returncode}): {done.stderr[-2000:]}")
        result = json.loads(out.read_text())
    per_seed = {}
    for scene in scenes:
        seed = json.loads((scene / "scene.json").read_text())["seed"]
        per_seed[str(seed)] = float(result["scenes"][scene.name]["methods"][METHOD]["mIoU"])
    return per_seed
