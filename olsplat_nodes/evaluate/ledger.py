"""A ledger of finished evaluation runs: the scores of one aggregation of one scene, kept so
that a long evaluation (``olsplat bench paper``: about 19 h on two cores) can be done in pieces,
on other machines, and its results kept with the code that made them.

Each finished run is one small JSON file in the ledger's folder, named by the sha256 of what
made it (``run_key``): the scene's content (every file ``olsplat sim make`` wrote, not its
name or path: a scene made again by the same command matches, one made by other simulator code
does not), the method with every parameter as resolved, the encoder spec and the sha256 of its
model files, the fusion weights and the 3D branch's settings (its MinkUNet by the checkpoint's
sha256). A run whose key is in the ledger is not run again; anything else that changed is a new
key. What the key cannot see is a change of olsplat's own code that changes a result: a ledger
therefore recomputes the first run it would reuse (once per tuning, once per evaluation) and
refuses to go on
(one error naming the entry and both scores) when the fresh score differs by more than
``CHECK_TOLERANCE`` mIoU, so stale entries are found at the cost of one run.

**A scene made again on another machine.** ``olsplat sim make`` is deterministic on one machine,
but two machines' numeric libraries (OpenBLAS's kernels for each CPU, numpy's SIMD paths) can
round the same command's float64 camera poses in their last bit, so its files, and its digest,
differ while its images and scores do not (measured: docs/evaluation-protocol.md, "Changes after
the first held-out run"). The ledger therefore knows a scene by a second name, an alias
(``ALIASES_FILE``): when a run of a scene that has no alias is computed and not found, the
entries with the same key but for the scene, and the same label (the scene's folder name and
the run), are its candidates; if exactly one candidate scores within ``CHECK_TOLERANCE`` of the
run just computed, its scene is this scene's alias and that scene's entries are reused for this
one from then on (``saved``). No candidate, or more than one within the tolerance: no alias,
and the scene's runs are computed as a new scene's. Every alias is written with the run and
both scores that made it, and the first reuse through it is checked like any other.
"""

from __future__ import annotations

import dataclasses
import datetime
import hashlib
import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any

from ..errors import OlsplatInputError

# mIoU and Loc@50 (percent) within which a recomputed run must match its ledger entry: the
# aggregation is deterministic up to the order of floating-point sums across threads
CHECK_TOLERANCE = 0.05
# what runs write into a scene folder: ``olsplat eval``'s default --work and the encodings cache
SKIPPED_IN_SCENES = {"eval", "cache"}
# in the ledger's folder: {scene digest here: {"scene": digest of the ledger's entries, "run":
# the label that matched, "scores": [computed, saved] mIoU, "made": time}} (the module docstring)
ALIASES_FILE = "scene-aliases.json"


def scene_digest(folder: Path) -> str:
    """sha256 (hex) over every file under ``folder`` (relative path and bytes, in path order),
    leaving out the top-level folders runs write (``SKIPPED_IN_SCENES``): a scene's content,
    wherever it lies."""
    digest = hashlib.sha256()
    folder = Path(folder)
    for path in sorted(p for p in folder.rglob("*") if p.is_file()):
        relative = path.relative_to(folder)
        if relative.parts[0] in SKIPPED_IN_SCENES:
            continue
        digest.update(f"{relative.as_posix()}\0".encode())
        with open(path, "rb") as handle:
            for block in iter(lambda: handle.read(1 << 20), b""):
                digest.update(block)
        digest.update(b"\0")
    return digest.hexdigest()


def file_digest(path: Path | None) -> str | None:
    """sha256 (hex) of a file's bytes, None for None."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest() if path is not None else None


def run_key(scene: str, method, encoders: str, weights, encoder_files: str, structure) -> dict[str, Any]:
    """What a run's scores depend on, as a JSON-able mapping: ``scene`` (``scene_digest``),
    ``method`` (a resolved ``Method``: its repr names every parameter, but
    ``raster.topk_scale``, added as ``topk_scale`` when not 1), ``encoders`` (the spec)
    with ``weights`` (the lambda_2D fusion weights or None) and ``encoder_files``
    (``encoder_fingerprint``), ``structure`` (a ``StructureConfig`` or None: 2D features)."""
    branch = None
    if structure is not None:
        branch = {
            "settings": repr(dataclasses.replace(structure, minkunet=None)),
            "minkunet": file_digest(structure.minkunet),
        }
    key: dict[str, Any] = {
        "scene": scene,
        "method": repr(method),
        "encoders": encoders,
        "weights": list(weights) if weights is not None else None,
        "encoder_files": encoder_files,
        "structure": branch,
    }
    scale = getattr(getattr(method, "raster", None), "topk_scale", 1.0)
    if scale != 1.0:  # left out of the method's repr, so that the keys of runs at 1 stay as they were
        key["topk_scale"] = scale
    return key


class LedgerMismatch(OlsplatInputError):
    """A recomputed run differs from its ledger entry: the code changed what the key cannot see
    (an input error: the ledger folder is the user's; the CLI prints it as one line)."""


class RunLedger:
    """Finished runs under ``folder`` (created on the first entry); ``folder`` None keeps
    nothing (every run is computed). ``check`` False skips the recomputation of the first reused
    run (for tests of the ledger itself)."""

    def __init__(self, folder: Path | None, check: bool = True):
        self.folder = Path(folder) if folder is not None else None
        self.to_check = check
        self.reused = self.computed = 0

    def path(self, key: dict[str, Any]) -> Path:
        assert self.folder is not None
        name = hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()
        return self.folder / f"{name[:24]}.json"

    def saved(self, key: dict[str, Any]) -> dict | None:
        """The scores saved for ``key``, None when there are none (or the entry is unreadable or
        made for another key: a name collision is not a match); failing that, those saved for
        the same key on the scene's alias (the module docstring), if it has one."""
        scores = self._entry_scores(key)
        alias = self.aliases().get(key["scene"]) if scores is None and isinstance(key.get("scene"), str) else None
        if alias is not None:
            scores = self._entry_scores({**key, "scene": alias["scene"]})
        return scores

    def _entry_scores(self, key: dict[str, Any]) -> dict | None:
        if self.folder is None:
            return None
        try:
            entry = json.loads(self.path(key).read_text())
        except (OSError, ValueError):
            return None
        if not isinstance(entry, dict) or entry.get("key") != key or not isinstance(entry.get("scores"), dict):
            return None
        return entry["scores"]

    def aliases(self) -> dict[str, dict]:
        """{scene digest: its alias record} (``ALIASES_FILE``; {} without one)."""
        if self.folder is None:
            return {}
        try:
            aliases = json.loads((self.folder / ALIASES_FILE).read_text())
        except (OSError, ValueError):
            return {}
        return aliases if isinstance(aliases, dict) else {}

    def _entries(self):
        """Every readable entry of the folder: (key, label, scores)."""
        for path in sorted(self.folder.glob("*.json")) if self.folder is not None else []:
            try:
                entry = json.loads(path.read_text())
                key, label, scores = entry["key"], entry.get("label", ""), entry["scores"]
            except (OSError, ValueError, KeyError, TypeError):
                continue
            if isinstance(key, dict) and isinstance(scores, dict):
                yield key, label, scores

    def _find_alias(self, key: dict[str, Any], label: str, scores: dict) -> None:
        """Give ``key``'s scene an alias when exactly one entry of another scene has the same key
        but for the scene and the same ``label`` and scores within ``CHECK_TOLERANCE`` of
        ``scores`` (this run, just computed); print what was found."""
        scene = key.get("scene")
        if self.folder is None or not label or not isinstance(scene, str) or scene in self.aliases():
            return
        near, far = [], 0
        for other, other_label, saved in self._entries():
            if other_label != label or other.get("scene") == scene or {**other, "scene": scene} != key:
                continue
            if not _same_annotations(saved, scores):
                far += 1
                continue
            worst = max(abs(float(scores[m]) - float(saved[m])) for m in ("mIoU", "loc50"))
            if worst <= CHECK_TOLERANCE:
                near.append((other["scene"], saved))
            else:
                far += 1
        if len(near) != 1:
            if near or far:
                print(f"ledger: {label}: no alias for this scene ({len(near)} entries of other scenes within "
                      f"{CHECK_TOLERANCE} mIoU, {far} further): its runs are computed")  # fmt: skip
            return
        alias, saved = near[0]
        aliases = self.aliases()
        aliases[scene] = {
            "scene": alias,
            "run": label,
            "scores": {m: [float(scores[m]), float(saved[m])] for m in ("mIoU", "loc50")},
            "made": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        }
        path = self.folder / ALIASES_FILE
        partial = path.with_name(path.name + ".partial")
        partial.write_text(json.dumps(aliases, indent=1, sort_keys=True) + "\n")
        os.replace(partial, path)
        print(f"ledger: {label} computed here scores mIoU {scores['mIoU']:.2f} / Loc@50 {scores['loc50']:.2f}, its "
              f"entry on scene {alias[:12]} {saved['mIoU']:.2f} / {saved['loc50']:.2f}: the same scene made on "
              f"another machine; its entries are reused for this one")  # fmt: skip

    def scene_counts(self) -> dict[str, int]:
        """How many runs the ledger holds per scene (``scene_digest``): a long evaluation's progress.
        A scene with an alias counts its alias's runs that it has not made itself too."""
        made: dict[str, set[str]] = {}
        for key, _, _ in self._entries():
            if isinstance(key.get("scene"), str):
                made.setdefault(key["scene"], set()).add(json.dumps({**key, "scene": ""}, sort_keys=True))
        for scene, alias in self.aliases().items():
            made[scene] = made.get(scene, set()) | made.get(str(alias.get("scene")), set())
        return {scene: len(runs) for scene, runs in made.items()}

    def run(self, key: dict[str, Any], compute: Callable[[], dict], label: str = "") -> tuple[dict, bool]:
        """(scores, reused): the saved scores of ``key``, or ``compute()``'s (a dict with at
        least mIoU and loc50), saved before they are returned. The first run this ledger would
        reuse is computed anyway and compared (``CHECK_TOLERANCE``): LedgerMismatch when it
        differs."""
        saved = self.saved(key)
        if saved is not None and not self.to_check:
            self.reused += 1
            return saved, True
        scores = compute()
        self.computed += 1
        if saved is None:
            self._find_alias(key, label, scores)
        if saved is not None:
            self.to_check = False
            worst = max(abs(float(scores[m]) - float(saved[m])) for m in ("mIoU", "loc50"))
            if worst > CHECK_TOLERANCE:
                raise LedgerMismatch(
                    f"{self.path(key)}: {label or 'a run'} saved mIoU {saved['mIoU']:.2f} / Loc@50 "
                    f"{saved['loc50']:.2f}, computed again {scores['mIoU']:.2f} / {scores['loc50']:.2f}: olsplat's "
                    "code changed a result since the ledger was written; remove the ledger folder (or give another) "
                    "to run everything again"
                )
            print(f"ledger: {label or 'a run'} computed again matches its entry {self.path(key).name} (within "
                  f"{CHECK_TOLERANCE} mIoU): the other entries are reused")  # fmt: skip
            return saved, True
        self._write(key, scores, label)
        return scores, False

    def _write(self, key: dict[str, Any], scores: dict, label: str) -> None:
        if self.folder is None:
            return
        self.folder.mkdir(parents=True, exist_ok=True)
        entry = {
            "key": key,
            "label": label,
            "scores": scores,
            "made": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        }
        path = self.path(key)
        partial = path.with_name(path.name + ".partial")
        partial.write_text(json.dumps(entry, indent=1, sort_keys=True, default=_plain) + "\n")
        os.replace(partial, path)  # whole or not at all


def _same_annotations(saved: dict, scores: dict) -> bool:
    """Whether two runs' scores were counted over the same annotations: the same number of
    annotated instances and the same queries scored (what a scene made again keeps exactly)."""
    queries = set(saved.get("per_query") or {}) == set(scores.get("per_query") or {})
    return queries and saved.get("instances") == scores.get("instances")


def _plain(value: Any) -> Any:
    """numpy scalars and arrays as JSON numbers and lists."""
    return value.tolist() if hasattr(value, "tolist") else str(value)
