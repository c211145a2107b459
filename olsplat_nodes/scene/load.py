"""Pick the right camera reader for a path, and one view out of a list by name or index."""

from __future__ import annotations

from pathlib import Path

from ..errors import OlsplatInputError, SceneFormatError
from .camera import Camera
from .colmap import find_model_folder, read_colmap
from .transforms_json import read_transforms_json


def read_cameras(path: str | Path) -> list[Camera]:
    """Cameras from a COLMAP model folder or a transforms.json file."""
    path = Path(path)
    if path.is_dir():
        if find_model_folder(path) is None and (path / "transforms.json").is_file():
            return read_transforms_json(path / "transforms.json")
        return read_colmap(path)
    if path.suffix.lower() == ".json":
        return read_transforms_json(path)
    if not path.exists():
        raise SceneFormatError(path, "does not exist")
    raise SceneFormatError(path, "is neither a COLMAP model folder nor a transforms.json file")


def select_view(cameras: list[Camera], view: str | int) -> Camera:
    """The camera called ``view`` (exact name, then file name, then stem), or at that index."""
    key = str(view)
    for match in (
        lambda c: c.name == key,
        lambda c: Path(c.name).name == key,
        lambda c: Path(c.name).stem == key,
    ):
        found = [c for c in cameras if match(c)]
        if len(found) == 1:
            return found[0]
        if len(found) > 1:
            raise OlsplatInputError(f"view {key!r} is ambiguous: matches {[c.name for c in found[:5]]}")
    try:
        index = int(key)
    except ValueError:
        index = None
    if index is not None and -len(cameras) <= index < len(cameras):
        return cameras[index]
    sample = ", ".join(c.name for c in cameras[:5]) + (", ..." if len(cameras) > 5 else "")
    raise OlsplatInputError(f"no view {key!r}: give a name or an index in 0..{len(cameras) - 1} (views: {sample})")
