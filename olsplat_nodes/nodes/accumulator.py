"""accumulator: ``RegionFeatures`` -> per-view Gaussian observations in the store -> ``ObservationsAdded``.

Owns the prior Gaussian map and the method's settings: ``method`` and any of the method's
parameters (``tau_d``, ``q_min``, ``beta``, ``topk_max``, ... ``method.MethodParams``) are this
node's parameters; the resolved settings go into the store's manifest, which the refiner
reads, so the two never disagree. A store made with other settings is refused at start.

Per view: check the message against itself (label maps vs image size, regions vs feature rows,
one encoder for the whole run), run the method's per-view step (``method.view_observations``),
save the photo and camera (``storage.views``) and record the view in the store, which is the
map's one tile (``storage.tiles.TileShard``: the shard a tiled or Ray run records into, the
same code); only then acknowledge. With ``features: 2d3d`` each view's region bank is first
fused with the 3D branch (the paper's dual branch, ``structure.StructuralBranch``): its point
features are made at the first view (from that view's camera centre), h_theta trains online as
views arrive, and its whole state is saved (``STORE/branch.npz``) after every stored view, so a restarted node goes on
with h as it was; the branch's settings are in the store's manifest. A view already in the
store (by name: the shard's rule) is acknowledged again without being added twice, so a
restarted node or a re-sent frame never double-counts. ``EndOfStream`` is forwarded
on the observations topic after the views before it. While a view is observed, the next queued
view is rendered on a second thread (``render_ahead``, ``method.render_ahead``): the same
observations, made while the observations' serial pass leaves a core free.

A view that does not see the prior map is refused (``method.coverage``: less than
``min_coverage`` of the frame covered by the map, or the camera less than ``min_height_m`` above
the map's ground under the view): a WARN names the view and its figures, the view is
acknowledged (``observations: 0``, so the ingest goes on) but not aggregated. When the first
``off_map_views`` views of a run are all refused, the node's status is ERROR ("views do not
overlap the map: wrong map, wrong georeference or wrong camera model?" and their figures) until
a view is taken. The prior map's path and SHA-256 go into ``STORE/prior_map.json`` once per
store (``storage.prior.record_prior_map``, hashed in the background), so that a run's map is
found from its folder alone (``olsplat ground web --run``).
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from dataclasses import dataclass, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from olsplat_msgs import DiagnosticStatus, EndOfStream, ObservationsAdded, RegionFeatures

from ..errors import OlsplatInputError
from ..extras import require

if TYPE_CHECKING:
    from ..method.view_step import ViewOffMap
from ..method import MethodParams
from ..params import ParameterError
from ..transport import Diagnostics, Publisher, Subscriber
from ..transport.convert import view_of
from .base import Node

log = logging.getLogger(__name__)
DISK_RECHECK_S = 5.0  # free space is read again this often between views (a statvfs: microseconds)


class AccumulatorNode(Node):
    @dataclass(frozen=True)
    class Params(MethodParams):
        map: str = ""  # the prior Gaussian map (INRIA PLY)
        store: str = "{run_dir}/store"
        views: str = "{run_dir}/views"
        regions_in: str = "ipc://{run_dir}/regions.sock"
        observations_out: str = "ipc://{run_dir}/observations.sock"
        diagnostics: str = ""
        topic_regions: str = "regions"
        topic_observations: str = "observations"
        hwm: int = 4
        # regions_in limit: the photo plus an int32 label map per level (4K, one level: ~60 MB)
        max_message_mb: float = 160.0
        # numba threads of the rasterizer and observations (0 = one per core); 2: the region encoder
        # now leaves most of the second core idle, and the accumulator is the graph's slowest stage
        threads: int = 2
        # render the next queued view while this one is observed (the observations' pass is
        # serial, the render's kernels use both cores): the same observations, the two cores kept
        # busy; off where numba's threading layer is not thread-safe (method/render_ahead.py)
        render_ahead: bool = True
        features: str = "2d"  # "2d3d": fuse the region features with the 3D branch before aggregating
        lambda_f: float = 0.7  # 2D share of that fusion (paper)
        # the 3D branch's point features: "" geometric descriptors, "shipped" the packaged
        # self-supervised MinkUNet, or a MinkUNet checkpoint file
        minkunet: str = ""
        # WARN once the store's disk holds fewer than this many more views at the run's rate so far
        # (its segments and photos per view; 600: ten minutes at 1 frame/s, time to land)
        disk_warn_views: int = 600
        # refuse a view that does not see the map: less than this share of its frame covered by the
        # map (figures of simulated and real flights: method/coverage.py; 0: off) ...
        min_coverage: float = 0.2
        # ... or its camera less than this (map units) above the map's ground under it (-1e9: off)
        min_height_m: float = 10.0
        # ERROR when the first this many views of a run are all refused (0: never)
        off_map_views: int = 5

    @classmethod
    def validate(cls, params: Params, where: str) -> None:
        from ..method import check_store, method_params_of

        method = method_params_of(params).resolve(where)  # a known method, values in range
        if params.features not in ("2d", "2d3d") or not 0.0 <= params.lambda_f <= 1.0:
            raise ParameterError(f"{where}: features must be 2d or 2d3d and 0 <= lambda_f <= 1, got {params}")
        if params.disk_warn_views < 0:
            raise ParameterError(f"{where}: disk_warn_views must be >= 0 (0: never), got {params.disk_warn_views}")
        if params.off_map_views < 0:
            raise ParameterError(f"{where}: off_map_views must be >= 0 (0: never), got {params.off_map_views}")
        from ..method.coverage import CoverageGate

        try:
            CoverageGate(params.min_coverage, params.min_height_m)
        except ValueError as exc:
            raise ParameterError(f"{where}: {exc}") from exc
        if params.features == "2d3d":  # the 3D branch: open3d always, torch for a MinkUNet
            require("open3d", f"{where}: features=2d3d (the 3D branch)")
            if params.minkunet:
                require("torch", f"{where}: minkunet={params.minkunet!r}")
        from ..structure.branch import minkunet_path

        checkpoint = minkunet_path(params.minkunet)
        if checkpoint is not None and not checkpoint.is_file():
            raise ParameterError(f"{where}.minkunet: {params.minkunet}: no such MinkUNet checkpoint")
        try:  # a resumed run keeps the settings its store was made with
            check_store(params.store, method, cls._structure_record(params))
        except OlsplatInputError as exc:
            raise ParameterError(f"{where}: {exc}") from exc

    @staticmethod
    def _structure(params: Params):
        """The 3D branch's settings, or None for 2D features only."""
        from ..structure.branch import StructureConfig, minkunet_path

        if params.features != "2d3d":
            return None
        return StructureConfig(lambda_f=params.lambda_f, minkunet=minkunet_path(params.minkunet))

    @classmethod
    def _structure_record(cls, params: Params) -> dict | None:
        from ..structure.branch import structure_record

        structure = cls._structure(params)
        return None if structure is None else structure_record(structure)

    def setup(self) -> None:
        from ..durable import DiskRunway
        from ..method import claim_store, method_params_of, warm_up
        from ..method.coverage import CoverageGate
        from ..method.render_ahead import RenderAhead
        from ..scene import read_ply
        from ..storage.tiles import TileShard  # heavy imports here: the launcher imports node classes

        p = self.params
        self.limit_threads(p.threads)
        self.method = method_params_of(p).resolve()
        self.gaussians = read_ply(p.map)
        self.manifest = claim_store(p.store, self.method, self._structure_record(p))
        # the store of the map's one tile: the shard a tiled or Ray run records into (storage/tiles.py)
        self.shard = TileShard(p.store, len(self.gaussians), writer=True)
        self.structure = self._structure(p)
        self.branch = None  # made at the first view, or restored from the store
        self.store_error = ""  # why the last view could not be stored ("" once one is)
        self.branch_file = Path(p.store) / "branch.npz"
        self.runway = DiskRunway()  # the bytes this run writes per view, to tell when the disk fills
        self.disk_checked = 0.0  # monotonic s of the last free-space reading
        self.disk_warning = ""
        self.disk_values: dict = {}
        self.gate = CoverageGate(p.min_coverage, p.min_height_m)
        # the prior map's path and SHA-256 into the store, hashed off the loop (a 1 GB map: ~1 s)
        threading.Thread(target=self._record_prior_map, name=f"{self.name}-prior-map", daemon=True).start()
        self.refused = ""  # the last view's refusal ("" once a view is taken)
        self.off_map = ""  # the ERROR when the run's first views were all refused ("" once one is taken)
        # the first views this node judged, by name: their figures (None: taken); a resumed store is past them
        self.first_views: dict[str, ViewOffMap | None] = (
            {} if not len(self.shard) else dict.fromkeys(f"(resumed {i})" for i in range(p.off_map_views))
        )
        self.seen_values: dict = {}
        if self.structure is not None and self.branch_file.exists():
            self.branch = self._restore_branch()
        # before "ready": a fresh install compiles the per-view kernels here, not on a flight's first frames
        log.info("per-view kernels ready in %.1f s", warm_up(self.gaussians, self.method))
        if len(self.shard):
            log.info("resuming: %d views already in %s", len(self.shard), p.store)
        self.pending: deque = deque()  # (topic, message) received, not yet handled, oldest first
        self.ahead = None  # the next view's render, made while this one is observed
        if p.render_ahead and RenderAhead.available():
            self.ahead = self.own(RenderAhead(self.gaussians, self.method, p.threads))  # closed with the sockets
        elif p.render_ahead:
            log.info("views are not rendered ahead: numba's threading layer is not thread-safe here")
        limit = int(p.max_message_mb * 2**20)
        self.sub = self.own(Subscriber(self.context, [p.regions_in], [p.topic_regions], hwm=p.hwm, max_bytes=limit))
        self.pub = self.own(Publisher(self.context, p.observations_out, bind=True, hwm=100))
        self.diag = self.own(Diagnostics(self.context, p.diagnostics, self.name)) if p.diagnostics else None

    def _receive(self, timeout_ms: float) -> None:
        batch = self.sub.drain(timeout_ms)
        self.stats.count("received", len(batch))
        self.pending.extend(batch)

    def _render_next(self) -> None:
        """Start the render of the next queued view that will be aggregated (not one already in
        the store), so that it is made while the view in hand is observed."""
        from ..transport.convert import camera_of

        assert self.ahead is not None
        for _, message in self.pending:
            if isinstance(message, RegionFeatures) and message.name not in self.shard.names:
                try:
                    camera = camera_of(message)
                except ValueError:  # a bad view: it is refused in its turn, with its error
                    return
                self.ahead.start(camera)
                return

    def spin(self) -> int | None:
        p = self.params
        if not self.pending:
            self._receive(200)
        for _ in range(len(self.pending)):  # what was there when this turn began; the rest next turn
            _, message = self.pending.popleft()
            if isinstance(message, EndOfStream):
                self.publish(self.pub, p.topic_observations, message)
            elif isinstance(message, RegionFeatures):
                if self.ahead is not None:
                    self._receive(0)  # what came meanwhile: the next view can be rendered now
                    self._render_next()
                try:
                    self._add(message)
                except OSError as exc:
                    self._not_stored(message, exc)
            else:
                self.unexpected(message, p.topic_regions)
        if time.monotonic() - self.disk_checked > DISK_RECHECK_S:
            self._disk_status()
        if self.diag is not None:
            values = self.stats.with_sockets(self.sub.stats, queue_depth=len(self.pending), views=len(self.shard))
            if self.ahead is not None:
                values.update(rendered_ahead=self.ahead.used, rendered_ahead_unused=self.ahead.missed)
            values.update(self.disk_values)
            values.update(self.seen_values)
            if self.store_error:
                self.diag.beat(DiagnosticStatus.ERROR, self.store_error, values)
            elif self.off_map:
                self.diag.beat(DiagnosticStatus.ERROR, self.off_map, values)
            elif self.disk_warning:
                self.diag.beat(DiagnosticStatus.WARN, self.disk_warning, values)
            elif self.refused:
                self.diag.beat(DiagnosticStatus.WARN, self.refused, values)
            else:
                self.diag.beat(DiagnosticStatus.OK, f"{len(self.shard)} views in the store", values)
        return None

    def _disk_after_view(self, nbytes: int) -> None:
        """Count a stored view's bytes and tell, while the flight goes on, when the store's disk
        will be full soon at this rate (a status, not an error: space can be made meanwhile)."""
        self.runway.add(nbytes)
        self._disk_status()

    def _disk_status(self) -> None:
        """The disk runway at the run's bytes per view so far, from the free space now (after a
        view, and every ``DISK_RECHECK_S`` meanwhile: a WARN ends once space is made, with or
        without new views)."""
        from ..durable import free_mb

        self.disk_checked = time.monotonic()
        if not self.runway.bytes_per_view:
            return
        free = free_mb(self.params.store) * 2**20
        warned, self.disk_warning, self.disk_values = bool(self.disk_warning), "", {}
        if not np.isfinite(free):  # the free space could not be read: nothing to tell
            return
        left = self.runway.views_left(free) or 0.0
        per_view = self.runway.bytes_per_view or 0.0
        self.disk_values = {
            "disk_free_mb": round(free / 2**20, 1),
            "disk_mb_per_view": round(per_view / 2**20, 3),
            "disk_views_left": int(left),
        }
        if left < self.params.disk_warn_views:
            self.disk_warning = (
                f"disk nearly full: room for ~{int(left)} more views at {per_view / 2**20:.1f} MB per view "
                f"({free / 2**20:,.0f} MB free on the disk of {self.params.store})"
            )
            if not warned:
                log.warning(self.disk_warning)

    def _judged(self, name: str, refusal) -> None:
        """Book a view the coverage gate judged (``refusal``: its ``ViewOffMap``, or None when
        taken): the WARN of a refused view, and the ERROR when the run's first views all were."""
        from ..method.coverage import off_map_error

        if len(self.first_views) < self.params.off_map_views:
            self.first_views.setdefault(name, refusal)
        if refusal is None:
            self.refused = self.off_map = ""
            return
        self.stats.count("views_refused")
        self.refused = str(refusal)
        log.warning("%s; acknowledged, not aggregated", refusal)
        first = list(self.first_views.values())
        n = self.params.off_map_views
        if n and not self.off_map and len(first) == n and all(r is not None for r in first):
            self.off_map = off_map_error([(r.name, r.seen) for r in first if r is not None], self.gate, self.params.map)
            log.error(self.off_map)
            if self.diag is not None:  # now: the operator should not wait for the next beat
                self.diag.beat_now(DiagnosticStatus.ERROR, self.off_map, self.stats.with_sockets(self.sub.stats))

    def _record_prior_map(self) -> None:
        from ..storage.prior import record_prior_map

        try:
            record = record_prior_map(self.params.store, self.params.map)
        except OSError as exc:  # the run goes on; a review of it will ask for --map
            log.warning("the prior map's record was not written to %s: %s", self.params.store, exc)
            return
        log.info(
            "prior map %s: SHA-256 %s (%.1f MB, hashed in %.2f s) recorded in the store",
            record.path,
            record.sha256[:16],
            record.bytes / 2**20,
            record.hash_seconds,
        )

    def _seen(self, coverage: float, height_m: float) -> None:
        """The last judged view's figures, for the heartbeat."""
        self.seen_values = {"map_coverage": round(float(coverage), 4)}
        if np.isfinite(height_m):
            self.seen_values["height_above_map_m"] = round(float(height_m), 2)

    def _not_stored(self, message: RegionFeatures, exc: OSError) -> None:
        """A view the disk would not take (full, a file-size limit, a folder gone): the node goes
        on, the view is not acknowledged (a lossless ingest sends it again, and it goes in once
        there is room), and the error is the node's status until a view is stored. What the
        failed attempt had changed in memory is put back as the disk has it: the 3D branch from
        its last saved state, so a re-sent view does not train h twice."""
        self.stats.count("store_errors")
        self.store_error = f"view {message.name!r} not stored: {exc}"
        log.error("%s; not acknowledged (a lossless ingest sends it again)", self.store_error)
        if self.structure is not None:
            self.branch = self._restore_branch() if self.branch_file.exists() else None
        if self.diag is not None:  # now: the operator should not wait for the next beat
            self.diag.beat_now(DiagnosticStatus.ERROR, self.store_error, self.stats.with_sockets(self.sub.stats))

    def _restore_branch(self):
        """The 3D branch as the last run left it (``STORE/branch.npz``); a damaged file is an
        error (silently starting h again would make the rest of the map another method's)."""
        from ..errors import SceneFormatError
        from ..structure.branch import StructuralBranch

        try:
            with np.load(self.branch_file) as data:
                state = {k: data[k] for k in data.files}
            branch = StructuralBranch.restore(self.gaussians, state, self.structure)
        except (OSError, KeyError, ValueError) as exc:
            raise SceneFormatError(self.branch_file, f"not a 3D-branch state ({exc})") from exc
        log.info(
            "3D branch resumed: h_theta trained on %d regions over %d views",
            branch.distiller.seen if branch.distiller else 0,
            len(branch.losses),
        )
        return branch

    def _save_branch(self) -> None:
        import io

        from ..durable import write_atomic

        assert self.branch is not None
        buffer = io.BytesIO()
        np.savez(buffer, **self.branch.state())
        write_atomic(self.branch_file, buffer.getvalue())

    def _add(self, message: RegionFeatures) -> None:
        from ..method import view_observations, write_manifest
        from ..method.view_step import ViewOffMap
        from ..storage import save_view
        from ..storage.store import segment_bytes

        start = time.perf_counter()
        duplicate = message.name in self.shard.names
        kept = 0
        if not duplicate:
            try:
                camera, label_maps, bank, image = view_of(
                    message, self.manifest.encoder, self.manifest.feature_dim, self.method.aggregation.level_weights
                )
            except ValueError as exc:
                self.stats.count("bad_messages")
                log.warning("view %s (seq %d) dropped: %s", message.name, message.seq, exc)
                return
            if self.manifest.encoder is None or self.manifest.feature_dim is None:
                manifest = replace(self.manifest, encoder=message.encoder, feature_dim=int(bank[0].shape[1]))
                write_manifest(self.params.store, manifest)
                self.manifest = manifest  # after the write: a failed one is tried again with the next view
            if self.structure is not None and self.branch is None:
                from ..structure.branch import StructuralBranch

                self.branch = StructuralBranch.build(self.gaussians, camera.center[None], self.structure)
            try:  # refused right after the render: the 3D branch does not train on a view off the map
                rendered = self.ahead.take(camera) if self.ahead is not None else None
                observations, stacked, stages = view_observations(
                    self.gaussians, camera, label_maps, bank, self.method, self.branch, self.gate, rendered
                )
            except ViewOffMap as refusal:
                self._seen(refusal.seen.coverage, refusal.seen.height_m)
                self._judged(message.name, refusal)
            else:
                self._seen(stages["coverage"], stages["height_m"])
                nbytes = save_view(self.params.views, len(self.shard.store), camera, image)
                self.shard.record(message.name, observations, stacked)
                self._disk_after_view(nbytes + segment_bytes(observations, stacked))
                kept = len(observations)
                if self.branch is not None:  # after the view is stored: a restart goes on from h as it is now
                    self._save_branch()
                self._judged(message.name, None)
        added = ObservationsAdded(
            stamp_ns=message.stamp_ns,
            frame_id=message.frame_id,
            name=message.name,
            source_seq=message.source_seq,
            observations=kept,
            gaussians=len(self.gaussians),
            views_in_store=len(self.shard),
            duplicate=duplicate,
        )
        self.store_error = ""  # a view is on the disk (or already was): the status is OK again
        self.publish(self.pub, self.params.topic_observations, added)
        self.stats.count("duplicates" if duplicate else "views_added")
        self.stats.handled(message.stamp_ns, time.perf_counter() - start)
