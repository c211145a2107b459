"""A minimal tf buffer: a tree of static and timed transforms, looked up between two frames at a stamp.

Pure (no ROS, no I/O): the ROS 2 bag source (``sources/rosbag.py``) fills it from ``/tf`` and
``/tf_static`` and asks for ``world_from_camera``; the rules are tf2's where they matter here.

- Edges are keyed by child frame: each child has one parent (tf is a tree); a second parent, or a
  child on both ``/tf`` and ``/tf_static``, is refused (``TfTreeError``).
- Static edges: the latest ``add_static`` for a child wins (repeated ``/tf_static`` messages
  merge); their stamps mean nothing and are not kept.
- Dynamic edges: samples in any order; sorted by stamp, a duplicate stamp keeps the sample added
  last. An edge's transform at a stamp follows ``matching.bracket`` (a sample at or before and one
  at or after, each within the tolerance, no extrapolation, like tf2): translation linear,
  rotation ``matching.slerp``. A failure names the edge (``gap odom->base_link``) and raises
  ``TfTimeError``.
- ``lookup(target, source, stamp)`` walks both frames up to their lowest common ancestor:
  ``T_target_source = inv(T_lca_target) @ T_lca_source``.

Transforms are [4, 4] float64 rigid matrices ``T_parent_child`` (a point in the child frame ->
the parent frame, metres). Quaternions are wxyz here (``scene/rotations.py``); ROS messages carry
xyzw: convert with ``quat_from_ros`` at the message boundary.

REP-103/105 frames: ``map``/``odom`` ENU, ``base_link``/``camera_link`` FLU (x forward, y left,
z up), ``*_optical_frame`` x right, y down, z forward: OpenCV's camera axes, so
``world_from_camera = lookup(world, optical_frame, t)`` with no axis change, and a body or link
frame's camera is ``T_world_link @ LINK_FROM_OPTICAL``.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..scene.rotations import quat_to_rotmat
from .matching import bracket, slerp

__all__ = [
    "LINK_FROM_OPTICAL",
    "TfBuffer",
    "TfError",
    "TfTimeError",
    "TfTreeError",
    "quat_from_ros",
    "transform_matrix",
]

# camera_link (FLU) from camera_optical_frame (x right, y down, z forward): the static rpy
# (-pi/2, 0, -pi/2) every ROS camera driver publishes; ROS xyzw (-0.5, 0.5, -0.5, 0.5)
LINK_FROM_OPTICAL = np.array([[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])


class TfError(ValueError):
    """A transform that cannot be had; the message says which frames or edge and why."""


class TfTreeError(TfError):
    """The frames do not form a tree that joins the two frames asked for (a structural fault)."""


class TfTimeError(TfError):
    """The chain exists, but an edge has no sample close enough to the stamp asked for."""

    def __init__(self, reason: str, edge: str):
        self.reason, self.edge = reason, edge  # e.g. "gap", "odom->base_link"
        super().__init__(f"{reason} {edge}")


def quat_from_ros(x: float, y: float, z: float, w: float) -> np.ndarray:
    """A ROS quaternion (x, y, z, w) as olsplat's wxyz [4], normalised (a zero one is refused)."""
    q = np.array([w, x, y, z], np.float64)
    norm = float(np.linalg.norm(q))
    if not np.isfinite(norm) or norm < 1e-9:
        raise TfError(f"invalid rotation quaternion (x, y, z, w) = ({x}, {y}, {z}, {w})")
    return q / norm


def transform_matrix(translation, q_wxyz) -> np.ndarray:
    """[4, 4] rigid transform from a translation [3] (metres) and a rotation wxyz [4]."""
    matrix = np.eye(4)
    matrix[:3, :3] = quat_to_rotmat(q_wxyz)
    matrix[:3, 3] = np.asarray(translation, np.float64).reshape(3)
    return matrix


def _inverse(matrix: np.ndarray) -> np.ndarray:
    inverse = np.eye(4)
    inverse[:3, :3] = matrix[:3, :3].T
    inverse[:3, 3] = -matrix[:3, :3].T @ matrix[:3, 3]
    return inverse


@dataclass
class _Edge:
    parent: str
    static: bool
    matrix: np.ndarray | None = None  # static: T_parent_child [4, 4]
    samples: list[tuple[int, np.ndarray, np.ndarray]] = field(default_factory=list)  # dynamic, as added
    stamps: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))  # [N] strictly increasing
    translations: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))  # [N, 3] metres
    quats: np.ndarray = field(default_factory=lambda: np.zeros((0, 4)))  # [N, 4] wxyz
    dirty: bool = False

    def sort(self) -> None:
        """Samples by stamp; of equal stamps the one added last (a stable sort keeps add order)."""
        stamps = np.array([s for s, _, _ in self.samples], np.int64)
        order = np.argsort(stamps, kind="stable")
        keep = np.ones(len(order), bool)
        keep[:-1] = stamps[order][1:] != stamps[order][:-1]  # the last of each run of equal stamps
        order = order[keep]
        self.stamps = stamps[order]
        self.translations = np.array([self.samples[i][1] for i in order]).reshape(-1, 3)
        self.quats = np.array([self.samples[i][2] for i in order]).reshape(-1, 4)
        self.dirty = False


class TfBuffer:
    """Static and dynamic transforms between named frames (rules in the module docstring)."""

    def __init__(self) -> None:
        self._edges: dict[str, _Edge] = {}  # child frame -> edge to its parent

    def _edge(self, parent: str, child: str, static: bool) -> _Edge:
        if not parent or not child or parent == child:
            raise TfTreeError(f"a transform needs two different named frames, got {parent!r} -> {child!r}")
        edge = self._edges.get(child)
        if edge is None:
            edge = self._edges[child] = _Edge(parent, static)
        elif edge.parent != parent:
            raise TfTreeError(f"frame {child!r} has two parents, {edge.parent!r} and {parent!r} (tf is a tree)")
        elif edge.static != static:
            raise TfTreeError(f"{parent}->{child} is both static (/tf_static) and dynamic (/tf)")
        return edge

    def add_static(self, parent: str, child: str, translation, q_wxyz) -> None:
        """A static ``T_parent_child`` (translation [3] metres, rotation wxyz [4]); a later one replaces it."""
        self._edge(parent, child, True).matrix = transform_matrix(translation, q_wxyz)

    def add(self, parent: str, child: str, stamp_ns: int, translation, q_wxyz) -> None:
        """A timed sample of ``T_parent_child`` at ``stamp_ns`` (any order; a repeated stamp replaces)."""
        edge = self._edge(parent, child, False)
        edge.samples.append(
            (int(stamp_ns), np.asarray(translation, np.float64).reshape(3), np.asarray(q_wxyz, np.float64).reshape(4))
        )
        edge.dirty = True

    @property
    def frames(self) -> list[str]:
        """Every frame named by an edge, sorted."""
        return sorted({*self._edges, *(edge.parent for edge in self._edges.values())})

    def parent(self, frame: str) -> str | None:
        edge = self._edges.get(frame)
        return None if edge is None else edge.parent

    def is_static(self, child: str) -> bool:
        return self._edges[child].static

    def samples(self, child: str) -> np.ndarray:
        """The sorted, de-duplicated stamps [N] int64 of a dynamic edge (empty for a static one)."""
        edge = self._edges[child]
        if edge.dirty:
            edge.sort()
        return edge.stamps

    def root_path(self, frame: str) -> list[str]:
        """[frame, its parent, ..., the root]."""
        path = [frame]
        while (parent := self.parent(path[-1])) is not None:
            if parent in path:
                raise TfTreeError(f"the tf frames form a loop: {' -> '.join([*path, parent])}")
            path.append(parent)
        return path

    def check_chain(self, target: str, source: str) -> None:
        """Raise ``TfTreeError`` when no chain joins ``target`` and ``source`` (names the known frames)."""
        self._chain(target, source)

    def _chain(self, target: str, source: str) -> tuple[list[str], list[str]]:
        """The child frames from each frame up to (not including) their lowest common ancestor."""
        known = self.frames
        for frame in (target, source):
            if frame not in known:
                raise TfTreeError(f"no tf frame {frame!r}; known frames: {', '.join(known) or 'none'}")
        up_target, up_source = self.root_path(target), self.root_path(source)
        if up_target[-1] != up_source[-1]:
            raise TfTreeError(
                f"no tf chain from {target!r} to {source!r}: {target!r} is under root {up_target[-1]!r}, "
                f"{source!r} under root {up_source[-1]!r}; known frames: {', '.join(known)}"
            )
        on_target = set(up_target)
        lca = next(frame for frame in up_source if frame in on_target)
        return up_target[: up_target.index(lca)], up_source[: up_source.index(lca)]

    def edge_transform(self, child: str, stamp_ns: int, tolerance_ns: int) -> np.ndarray:
        """``T_parent_child`` [4, 4] at ``stamp_ns``; raises ``TfTimeError`` naming the edge."""
        edge = self._edges[child]
        if edge.static:
            assert edge.matrix is not None
            return edge.matrix
        if edge.dirty:
            edge.sort()
        status, reason, i0, i1, s = bracket(edge.stamps, int(stamp_ns), int(tolerance_ns))
        if status != "ok":
            raise TfTimeError(reason, f"{edge.parent}->{child}")
        translation = (1.0 - s) * edge.translations[i0] + s * edge.translations[i1]
        return transform_matrix(translation, slerp(edge.quats[i0], edge.quats[i1], s))

    def lookup(self, target: str, source: str, stamp_ns: int, tolerance_ns: int) -> np.ndarray:
        """``T_target_source`` [4, 4] at ``stamp_ns``: maps points in ``source`` to ``target``.

        Raises ``TfTreeError`` when no chain joins the frames, ``TfTimeError`` when an edge of
        the chain has no samples around the stamp within ``tolerance_ns``.
        """
        up_target, up_source = self._chain(target, source)
        lca_from_source, lca_from_target = np.eye(4), np.eye(4)
        for child in up_source:  # source, its parent, ...: each edge maps into the next frame up
            lca_from_source = self.edge_transform(child, stamp_ns, tolerance_ns) @ lca_from_source
        for child in up_target:
            lca_from_target = self.edge_transform(child, stamp_ns, tolerance_ns) @ lca_from_target
        return _inverse(lca_from_target) @ lca_from_source

    def tree_lines(self) -> list[str]:
        """The tree as indented lines, roots first: ``map``, ``  odom (dynamic, 250 samples)``, ..."""
        children: dict[str, list[str]] = {}
        for child, edge in self._edges.items():
            children.setdefault(edge.parent, []).append(child)
        lines: list[str] = []

        def walk(frame: str, depth: int) -> None:
            edge = self._edges.get(frame)
            what = (
                "" if edge is None else " (static)" if edge.static else f" (dynamic, {len(self.samples(frame))} stamps)"
            )
            lines.append(f"{'  ' * depth}{frame}{what}")
            for child in sorted(children.get(frame, [])):
                walk(child, depth + 1)

        for root in sorted(frame for frame in children if frame not in self._edges):
            walk(root, 0)
        return lines
