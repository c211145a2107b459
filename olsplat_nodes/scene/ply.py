"""Read and write the INRIA 3DGS binary PLY layout.

The reader is lenient about what real trainers write and strict about what we need:
- required: ``x y z``, ``opacity``, ``scale_0..2``, ``rot_0..3`` (w, x, y, z), ``f_dc_0..2``;
- optional: ``f_rest_*`` (absent means SH degree 0), normals and any other per-vertex field,
  which are kept in ``Gaussians.extras`` and written back, so a round trip loses nothing.

``f_rest_*`` is stored channel-major as INRIA writes it: ``f_rest_{c * M + j}`` is coefficient
``j + 1`` of colour channel ``c``, with ``M = (deg + 1)^2 - 1``.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np
from numba import njit, prange
from plyfile import PlyData, PlyElement

from ..errors import SceneFormatError
from .gaussians import Gaussians, sh_degree_from_count

_REQUIRED = (
    ["x", "y", "z", "opacity"]
    + [f"scale_{i}" for i in range(3)]
    + [f"rot_{i}" for i in range(4)]
    + [f"f_dc_{i}" for i in range(3)]
)
_NORMALS = ("nx", "ny", "nz")

NonFinitePolicy = Literal["error", "drop", "keep"]


def read_ply(path: str | Path, on_nonfinite: NonFinitePolicy = "error") -> Gaussians:
    """Load a Gaussian map from an INRIA-layout PLY file.

    on_nonfinite: what to do with Gaussians holding NaN/inf parameters — ``"error"`` raises
    (naming how many and the first index), ``"drop"`` removes them, ``"keep"`` keeps them (the
    rasterizer skips them).
    """
    path = Path(path)
    if path.is_dir():
        raise SceneFormatError(path, "is a folder; expected a Gaussian PLY file (e.g. point_cloud.ply)")
    if not path.is_file():
        raise SceneFormatError(path, "file does not exist")
    try:
        ply = PlyData.read(str(path))
    except Exception as exc:  # plyfile raises several types for truncated/garbled files
        raise SceneFormatError(path, f"not a readable PLY file ({type(exc).__name__}: {exc})") from None
    if "vertex" not in ply:
        names = [el.name for el in ply.elements]
        raise SceneFormatError(path, f"no 'vertex' element (elements present: {names})")
    vertex = ply["vertex"].data
    fields = list(vertex.dtype.names or ())
    missing = [name for name in _REQUIRED if name not in fields]
    if missing:
        what = "positions" if {"x", "y", "z"} & set(missing) else "Gaussian parameters"
        raise SceneFormatError(path, f"missing {what}: no field(s) {', '.join(missing)}")
    n = len(vertex)
    if n == 0:
        raise SceneFormatError(path, "the PLY holds no Gaussians (0 vertices)")

    # INRIA files hold float32 fields only: the body is then one [N, fields] float32 matrix (the
    # memory-mapped file), and a column block is taken in one parallel row-major pass
    # (``_columns``: one pass over the file's pages, where stacking the strided field views one by
    # one, or numpy's fancy indexing of the mapped matrix, reads every page many times)
    matrix = None
    if all(vertex.dtype[name] == np.dtype("<f4") for name in fields) and vertex.dtype.itemsize == 4 * len(fields):
        matrix = np.asarray(vertex).view("<f4").reshape(len(vertex), len(fields))

    def stack(names: list[str]) -> np.ndarray:
        if matrix is not None:
            return _columns(matrix, np.array([fields.index(name) for name in names], np.int64))
        return np.stack([np.asarray(vertex[name], dtype=np.float32) for name in names], axis=1)

    rest_names = sorted((f for f in fields if f.startswith("f_rest_")), key=lambda f: int(f[7:]))
    if [int(f[7:]) for f in rest_names] != list(range(len(rest_names))):
        raise SceneFormatError(path, "f_rest_* fields are not numbered 0..M-1 without gaps")
    if len(rest_names) % 3:
        raise SceneFormatError(path, f"{len(rest_names)} f_rest_* fields is not a multiple of 3 channels")
    per_channel = len(rest_names) // 3
    try:
        sh_degree_from_count(per_channel + 1)
    except ValueError:
        raise SceneFormatError(path, f"{len(rest_names)} f_rest_* fields match no SH degree 0..4") from None
    # sh [N, coefficients, channel]: coefficient 0 is f_dc_c, coefficient j >= 1 is f_rest_{c * M + j - 1}
    sh_names = [
        f"f_dc_{c}" if j == 0 else rest_names[c * per_channel + j - 1] for j in range(per_channel + 1) for c in range(3)
    ]
    sh = stack(sh_names).reshape(n, per_channel + 1, 3)

    used = set(_REQUIRED) | set(rest_names)
    extras = {
        name: stack([name])[:, 0] if matrix is not None else np.asarray(vertex[name]).copy()
        for name in fields
        if name not in used
    }
    gaussians = Gaussians(
        means=stack(["x", "y", "z"]),
        quats=stack([f"rot_{i}" for i in range(4)]),
        log_scales=stack([f"scale_{i}" for i in range(3)]),
        opacity_logits=stack(["opacity"])[:, 0],
        sh=sh,
        extras=extras,
    )
    if matrix is not None:  # the same test over the fields the map uses, in one pass over the body
        bad = _nonfinite_rows(matrix, np.array([fields.index(name) for name in used], np.int64))
    else:
        bad = gaussians.nonfinite_mask()
    if bad.any() and on_nonfinite == "error":
        first = int(np.flatnonzero(bad)[0])
        raise SceneFormatError(
            path,
            f"{int(bad.sum())} of {n} Gaussians have NaN/inf parameters (first at index {first}); "
            "repair or drop them (olsplat render --allow-nonfinite renders the others; aggregation needs "
            "every Gaussian finite)",
        )
    if bad.any() and on_nonfinite == "drop":
        gaussians = gaussians.subset(~bad)
    return gaussians


@njit(cache=True, parallel=True)
def _columns(matrix, columns):
    """[N, C] float32 C-contiguous copy of matrix[:, columns] (matrix [N, F] float32, row-major,
    e.g. a memory-mapped PLY body)."""
    out = np.empty((matrix.shape[0], columns.shape[0]), np.float32)
    for i in prange(matrix.shape[0]):
        for c in range(columns.shape[0]):
            out[i, c] = matrix[i, columns[c]]
    return out


@njit(cache=True, parallel=True)
def _nonfinite_rows(matrix, columns):
    """[N] bool: True where any of matrix[i, columns] is NaN or infinite."""
    bad = np.zeros(matrix.shape[0], np.bool_)
    for i in prange(matrix.shape[0]):
        for c in range(columns.shape[0]):
            if not np.isfinite(matrix[i, columns[c]]):
                bad[i] = True
    return bad


_SIZES = {  # bytes of a PLY scalar type
    **dict.fromkeys(("char", "uchar", "int8", "uint8"), 1),
    **dict.fromkeys(("short", "ushort", "int16", "uint16"), 2),
    **dict.fromkeys(("int", "uint", "int32", "uint32", "float", "float32"), 4),
    **dict.fromkeys(("double", "float64"), 8),
}


def ply_header(path: str | Path) -> tuple[int, int] | None:
    """(vertices, bytes per vertex) that a PLY file's header declares, without reading its body
    (what a node or a check that needs only the map's size reads); None when the header cannot
    be read. List properties count as 0 bytes (a Gaussian map has none)."""
    count = row = 0
    in_vertex = False
    try:
        with open(path, "rb") as f:
            for _ in range(1000):
                words = f.readline().decode("ascii", "replace").split()
                if not words:
                    return None
                if words[0] == "element":
                    in_vertex = words[1] == "vertex"
                    count = int(words[2]) if in_vertex else count
                elif words[0] == "property" and in_vertex and words[1] != "list":
                    row += _SIZES.get(words[1], 4)
                elif words[0] == "end_header":
                    return (count, row) if count else None
    except (OSError, ValueError, IndexError):
        return None
    return None


def ply_vertex_count(path: str | Path) -> int:
    """The number of Gaussians a PLY file's header declares (0 when unreadable)."""
    header = ply_header(path)
    return header[0] if header else 0


def write_ply(path: str | Path, gaussians: Gaussians) -> None:
    """Write ``gaussians`` as a binary little-endian INRIA-layout PLY (atomically)."""
    path = Path(path)
    n = len(gaussians)
    per_channel = gaussians.sh.shape[1] - 1
    columns: list[tuple[str, np.ndarray]] = [
        ("x", gaussians.means[:, 0]),
        ("y", gaussians.means[:, 1]),
        ("z", gaussians.means[:, 2]),
    ]
    columns += [(name, gaussians.extras[name]) for name in _NORMALS if name in gaussians.extras]
    columns += [(f"f_dc_{i}", gaussians.sh[:, 0, i]) for i in range(3)]
    rest = gaussians.sh[:, 1:, :].transpose(0, 2, 1).reshape(n, 3 * per_channel)
    columns += [(f"f_rest_{i}", rest[:, i]) for i in range(3 * per_channel)]
    columns.append(("opacity", gaussians.opacity_logits))
    columns += [(f"scale_{i}", gaussians.log_scales[:, i]) for i in range(3)]
    columns += [(f"rot_{i}", gaussians.quats[:, i]) for i in range(4)]
    columns += [(k, v) for k, v in gaussians.extras.items() if k not in _NORMALS]

    dtype = [(name, values.dtype.str if name in gaussians.extras else "<f4") for name, values in columns]
    table = np.empty(n, dtype=dtype)
    for name, values in columns:
        table[name] = values
    tmp = path.with_name(path.name + ".tmp")
    PlyData([PlyElement.describe(table, "vertex")], text=False, byte_order="<").write(str(tmp))
    tmp.replace(path)
