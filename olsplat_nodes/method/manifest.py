"""The observation store's manifest, ``STORE/manifest.json``: the method (with every resolved
parameter), the encoder and the feature width the store's observations were made with, and the
3D branch's settings when its features were fused with it (``structure``; None: 2D only).

The accumulator writes it, the refiner reads it: the two can never refine with settings other
than those the observations were made with. A store made with other settings is refused rather
than mixed. Written to a temp file, fsynced and renamed, so it is whole or absent.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

from ..errors import OlsplatInputError
from .table import Method

MANIFEST = "manifest.json"


@dataclass(frozen=True)
class StoreManifest:
    method: Method
    encoder: str | None  # the encoder spec of the features; None until the first view
    feature_dim: int | None = None  # D, the width of the features; None until the first view
    structure: dict | None = None  # the 3D branch's settings (``structure_record``); None: 2D features only


def read_manifest(store: str | Path) -> StoreManifest | None:
    """The manifest of the store folder ``store``, or None when it has none yet."""
    path = Path(store) / MANIFEST
    try:
        record = json.loads(path.read_text())
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as exc:
        raise OlsplatInputError(f"{path}: unreadable store manifest ({exc})") from exc
    if not isinstance(record, dict) or "method" not in record:
        raise OlsplatInputError(f"{path}: not a store manifest (no 'method')")
    dim = record.get("feature_dim")
    structure = record.get("structure")
    if structure is not None and not isinstance(structure, dict):
        raise OlsplatInputError(f"{path}: 'structure' must be an object or null")
    return StoreManifest(Method.from_record(record["method"], str(path)), record.get("encoder"), dim, structure)


def write_manifest(store: str | Path, manifest: StoreManifest) -> None:
    folder = Path(store)
    folder.mkdir(parents=True, exist_ok=True)
    tmp = folder / (MANIFEST + ".tmp")
    with open(tmp, "w") as f:
        record = {
            "method": manifest.method.record(),
            "encoder": manifest.encoder,
            "feature_dim": manifest.feature_dim,
            "structure": manifest.structure,
        }
        json.dump(record, f, indent=1)
        f.flush()
        os.fsync(f.fileno())
    tmp.replace(folder / MANIFEST)
    fd = os.open(folder, os.O_RDONLY)
    try:
        os.fsync(fd)  # the rename itself survives a power cut
    finally:
        os.close(fd)


def check_store(store: str | Path, method: Method, structure: dict | None = None) -> StoreManifest | None:
    """The store's manifest (None when it has none yet); OlsplatInputError naming the differing
    settings when the store was made with another method, other parameters or other 3D-branch
    settings (``structure``, None = 2D only)."""
    existing = read_manifest(store)
    if existing is not None and (existing.method != method or existing.structure != structure):
        old = {**_flat(existing.method), **_prefixed(existing.structure)}
        new = {**_flat(method), **_prefixed(structure)}
        changed = [
            f"{k}: {old.get(k)!r} in the store, {new.get(k)!r} now"
            for k in sorted(set(old) | set(new))
            if old.get(k) != new.get(k)
        ]
        raise OlsplatInputError(
            f"{Path(store) / MANIFEST}: this store was made with other method settings ({'; '.join(changed)}); "
            "use a new run folder or the store's own settings"
        )
    return existing


def claim_store(store: str | Path, method: Method, structure: dict | None = None) -> StoreManifest:
    """The store's manifest for a run with ``method`` (and the 3D branch's ``structure``
    settings): written when the store has none, returned when it has the same settings;
    OlsplatInputError naming the differing settings otherwise."""
    existing = check_store(store, method, structure)
    if existing is None:
        existing = StoreManifest(method, None, None, structure)
        write_manifest(store, existing)
    return existing


def _prefixed(structure: dict | None) -> dict[str, object]:
    return (
        {"features": "2d"}
        if structure is None
        else {"features": "2d3d", **{f"3d.{k}": v for k, v in structure.items()}}
    )


def _flat(method: Method) -> dict[str, object]:
    record = method.record()
    return {"method": record["name"], **record["aggregation"], **record["raster"]}
