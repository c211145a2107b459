"""The language map: one feature per Gaussian plus what it takes to embed text the same way;
and the run's map folder of versioned snapshots (``write_snapshot``, ``latest_map``).

Saved as one ``.npz`` (written to a temp file, then renamed: readers never see half a map),
in one of two forms:
- ``float16``: ``features`` [N, D] float16 unit rows (zero rows for never-observed Gaussians);
- ``codebook``: ``codes`` [N] uint16 (65535 = never observed) and ``centres`` [K, D] float16
  unit rows (``aggregate.codebook``): ~2.7 instead of 256 bytes per Gaussian for D = 128,
  K = 1024. Measured on the small preset (seed 0): mIoU 65.9 / Loc@50 60.2 against 65.9 /
  60.3 for float16 (``olsplat bench compression``). Loading decodes it to dense rows.
Both carry ``observed`` [N] bool, ``encoder`` (the encoder or fusion spec text), ``version``.
Version 1 files (float16 only, no ``form``) still load. A map of one flight (``flights.py``)
also carries its evidence per Gaussian, which change scores need (``EVIDENCE``); maps without
it load with None there.
"""

from __future__ import annotations

import json
import time
import zipfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numba import njit

from ..aggregate.codebook import compress, decompress, fit_codebook
from ..durable import append_line, write_atomic
from ..errors import SceneFormatError

FORMAT_VERSION = 2
READABLE_VERSIONS = (1, 2)
# Optional per-Gaussian evidence arrays of a map (name -> stored type); all or none are present.
EVIDENCE = {
    "strength_sum": np.float32,
    "view_count": np.int32,
    "effective_views": np.float32,
    "view_spread": np.float32,
}


@njit(cache=True)
def normalise_rows(rows: np.ndarray) -> None:
    """Scale the rows of ``rows`` [M, D] float32 to length 1 in place (rows of 0 stay 0): what
    ``unit_rows`` returns, without its three [M, D] temporaries (on this VM the first touch of
    fresh memory cost a live refiner 0.5 s per 262k x 128 range, a fifth of a pass)."""
    for i in range(rows.shape[0]):
        square = np.float32(0.0)
        for d in range(rows.shape[1]):
            square += rows[i, d] * rows[i, d]
        norm = np.float32(np.sqrt(square))
        scale = np.float32(1.0) / max(norm, np.float32(1e-12)) if norm > 0 else np.float32(0.0)
        for d in range(rows.shape[1]):
            rows[i, d] *= scale


def unit_rows(features: np.ndarray) -> np.ndarray:
    """[M, D] rows scaled to length 1, float32 (rows of 0 stay 0): what a map stores. The same
    kernel as ``normalise_rows`` on a copy, so that a live refiner (in place) and an offline run
    (through this) store bit-identical float16 maps; numpy's pairwise sums round differently."""
    rows = np.array(features, np.float32, order="C", ndmin=2)
    normalise_rows(rows)
    return rows


@dataclass
class LanguageMap:
    features: np.ndarray  # [N, D] float16 or float32, unit rows (0 for unobserved); [0, D] when not decoded
    observed: np.ndarray  # [N] bool
    encoder: str  # e.g. "shipped:0.6,0.4" or "enc/remoteclip,enc/georsclip:0.6,0.4"
    form: str = "float16"  # how it was (or will be) stored: "float16" or "codebook"
    codes: np.ndarray | None = None  # codebook form, as loaded: [N] uint16 (65535: never observed)
    centres: np.ndarray | None = None  # codebook form, as loaded: [K, D] float16 unit rows
    # Evidence (a flight's map; None when the map does not carry it), per Gaussian over the views it was made of:
    strength_sum: np.ndarray | None = None  # [N] float32 sum of d_iv (pixel weight x quality; 0: unobserved)
    view_count: np.ndarray | None = None  # [N] int32 views that kept an observation of it (d_iv > tau_d)
    effective_views: np.ndarray | None = None  # [N] float32 Kish's (sum d)^2 / sum d^2 (0: unobserved)
    view_spread: np.ndarray | None = None  # [N] float32 d-weighted mean of 1 - cos(f_iv, F_i) (NaN: unobserved)

    def __len__(self) -> int:
        """The number of Gaussians (also when the features are kept as codes)."""
        return len(self.observed)

    @staticmethod
    def from_features(features: np.ndarray, observed: np.ndarray, encoder: str) -> LanguageMap:
        return LanguageMap(unit_rows(features).astype(np.float16), observed.astype(bool), encoder)

    def save(self, path: str | Path, codebook: int | None = None) -> None:
        """Write atomically and durably (``durable.write_atomic``); with ``codebook`` = K, in the
        codebook form with K centres fitted now; without it, a map that holds ``codes`` and
        ``centres`` (a live refiner's ``LiveCodebook``) in the codebook form they make."""
        path = Path(path)
        common: dict[str, Any] = {
            "observed": self.observed,
            "encoder": np.array(self.encoder),
            "version": FORMAT_VERSION,
        }
        arrays: dict[str, Any]
        if not codebook and self.codes is not None and self.centres is not None:
            arrays = {"form": "codebook", "codes": self.codes, "centres": np.asarray(self.centres, np.float16)}
        elif codebook:  # from the rows as they are (float16): their float32 copy would double the peak
            centres = fit_codebook(self.features, codebook)
            codes = compress(self.features, centres)
            arrays = {"form": "codebook", "codes": codes, "centres": centres.astype(np.float16)}
        else:
            arrays = {"form": "float16", "features": np.asarray(self.features, np.float16)}  # no copy if float16
        content: dict[str, Any] = {**arrays, **common, **self._evidence()}
        write_atomic(path, lambda f: np.savez(f, **content))

    def has_evidence(self) -> bool:
        return all(getattr(self, key) is not None for key in EVIDENCE)

    def _evidence(self) -> dict[str, np.ndarray]:
        """The evidence arrays to store (none, or all of them with one row per Gaussian)."""
        arrays = {key: getattr(self, key) for key in EVIDENCE}
        if all(value is None for value in arrays.values()):
            return {}
        if any(value is None or len(value) != len(self) for value in arrays.values()):
            shapes = {key: None if value is None else np.shape(value) for key, value in arrays.items()}
            raise ValueError(f"evidence needs all of {sorted(EVIDENCE)} with {len(self)} rows, got {shapes}")
        return {key: np.asarray(value, EVIDENCE[key]) for key, value in arrays.items()}

    @staticmethod
    def load(path: str | Path, decode: bool = True) -> LanguageMap:
        """Read a snapshot. A codebook map also keeps ``codes`` and ``centres``; with ``decode``
        False its ``features`` are left empty ([0, D]): a large map's N x D rows are never made
        (the query server scores and renders the centres through the codes)."""
        path = Path(path)
        if path.is_dir():
            raise SceneFormatError(path, "is a folder; expected a language map (language_map.npz)")
        try:
            with open(path, "rb") as file:  # closed also when numpy fails half way through the archive
                data = np.load(file, allow_pickle=False)
                if not isinstance(data, np.lib.npyio.NpzFile):
                    raise SceneFormatError(path, "not a language map (a single array, not an .npz archive)")
                with data:
                    return LanguageMap._from_archive(path, data, decode)
        except SceneFormatError:
            raise
        except FileNotFoundError:
            raise SceneFormatError(path, "does not exist") from None
        except KeyError as exc:
            raise SceneFormatError(path, f"not a language map: no {exc} array in it") from None
        except (ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:
            # numpy's own text (e.g. its advice to allow pickles) would mislead: say what it is
            raise SceneFormatError(path, "not a language map: truncated, damaged or not an .npz archive") from exc

    @staticmethod
    def _from_archive(path: Path, data, decode: bool) -> LanguageMap:
        version = int(data["version"])
        if version not in READABLE_VERSIONS:
            raise SceneFormatError(path, f"language map version {version}, this olsplat reads {READABLE_VERSIONS}")
        form = str(data["form"]) if "form" in data else "float16"
        observed = data["observed"]
        codes = centres = None
        if form == "codebook":
            codes, centres = data["codes"], data["centres"]
            if len(codes) != len(observed) or centres.ndim != 2 or len(centres) >= 65_535:
                raise SceneFormatError(
                    path, f"{len(codes)} codes, {len(observed)} observed flags, centres {centres.shape}"
                )
            if len(codes) and int(codes[codes != 65_535].max(initial=0)) >= max(len(centres), 1):
                raise SceneFormatError(path, f"codes beyond the {len(centres)} centres")
            features = (
                decompress(codes, centres).astype(np.float16) if decode else np.zeros((0, centres.shape[1]), np.float16)
            )
        elif form == "float16":
            features = data["features"]
            if len(features) != len(observed):
                raise SceneFormatError(path, f"{len(features)} features but {len(observed)} observed flags")
        else:
            raise SceneFormatError(path, f"unknown language map form {form!r}")
        evidence = {key: data[key] for key in EVIDENCE if key in data}
        if evidence and (len(evidence) < len(EVIDENCE) or any(len(a) != len(observed) for a in evidence.values())):
            shapes = {key: value.shape for key, value in evidence.items()}
            raise SceneFormatError(path, f"evidence arrays {shapes} for {len(observed)} Gaussians")
        return LanguageMap(features, observed, str(data["encoder"]), form, codes, centres, **evidence)


# The run's map folder: versioned snapshots and latest.json, the late joiner's way in, and
# versions.jsonl, every version's record in order (a reader polling latest.json can miss a
# version written moments after another: the bench's per-pass figures read the history)
KEEP_VERSIONS = 3  # older snapshots are deleted; a reader that still holds one has it in memory
HISTORY = "versions.jsonl"


def latest_map(map_dir: str | Path) -> dict | None:
    """The record of the newest snapshot in ``map_dir`` ({version, path, file, views,
    observed_gaussians, encoder, final, bytes, write_s; the refiner adds refine_s, its pass's
    seconds before the write, and exact, false for a fold of the new views}) or None when
    there is none yet. ``path`` is the snapshot in *this* folder (from ``file``, its name), so
    a run folder that was copied or moved reads its own snapshots."""
    try:
        record = json.loads((Path(map_dir) / "latest.json").read_text())
    except FileNotFoundError:
        return None
    if isinstance(record, dict) and isinstance(record.get("file"), str):
        record["path"] = str(Path(map_dir).resolve() / Path(record["file"]).name)
    return record


def map_history(map_dir: str | Path) -> list[dict]:
    """Every version's record the refiner wrote to ``map_dir`` (``versions.jsonl``), oldest
    first, as ``latest_map`` gives them but without ``path`` (a version's snapshot may be
    deleted: only the newest ``KEEP_VERSIONS`` are kept). A line a power cut tore is skipped
    (with the next, appended to it); [] when there is no history."""
    try:
        lines = (Path(map_dir) / HISTORY).read_text().splitlines()
    except FileNotFoundError:
        return []
    records = []
    for line in lines:
        try:
            record = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(record, dict) and isinstance(record.get("version"), int):
            records.append(record)
    return records


def write_snapshot(map_dir: Path, version: int, language_map: LanguageMap, record: dict, codebook: int | None) -> dict:
    """Write ``MAP_DIR/language_map_NNNNNN.npz`` for ``version`` and point ``latest.json`` at it
    (both atomic), append its record to ``versions.jsonl``; delete all but the newest
    ``KEEP_VERSIONS``. Returns the new record, which
    adds to ``record`` the version, file, path, ``bytes`` (the snapshot's size) and ``write_s``
    (seconds to write it)."""
    map_dir.mkdir(parents=True, exist_ok=True)
    path = map_dir / f"language_map_{version:06d}.npz"
    start = time.perf_counter()
    language_map.save(path, codebook)
    record = {
        **record,
        "version": version,
        "file": path.name,
        "path": str(path.resolve()),
        "bytes": path.stat().st_size,
        "write_s": round(time.perf_counter() - start, 3),
    }
    write_atomic(map_dir / "latest.json", json.dumps(record).encode())  # after the snapshot it names
    try:  # the history is a record of the run, not the map: a full disk costs a line, never the version
        append_line(map_dir / HISTORY, json.dumps({k: v for k, v in record.items() if k != "path"}))
    except OSError:
        pass
    for old in sorted(map_dir.glob("language_map_*.npz"))[:-KEEP_VERSIONS]:
        old.unlink(missing_ok=True)
    return record
