"""refiner: observation store -> consistency-aware refinement -> versioned language map -> ``MapUpdated``.

The store on disk is the source of truth, its settings included: the method (and every
parameter) comes from the store's manifest that the accumulator wrote, never from this node's
own parameters. Each pass takes the views that arrived since the last one into the live map
(``aggregate.LiveMap``: with ``passes: fold`` the new views are folded into the running
features, a cost that does not grow with the flight; the first pass after a start and the final
one are exact; ``passes: exact`` recomputes every touched Gaussian from all its views each
time), and writes
``MAP_DIR/language_map_NNNNNN.npz`` atomically plus ``MAP_DIR/latest.json`` naming it (the
late-joiner snapshot: a query server that starts later reads it, never waits for a message).

A pass runs when new views are in and ``period_s`` has passed, and no sooner than
``(1 - max_duty) / max_duty`` times the last pass's length (passes grow with the flight; this
keeps them from starving the encoder on a small CPU); and at once on ``EndOfStream``, which
makes the final map (``final: true``); with ``exit_on_final`` the node then keeps announcing it
for ``final_linger_s`` (so that subscribers hear it before the socket closes) and exits 0.
``MapUpdated`` is repeated every second so that late subscribers learn the current version.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from olsplat_msgs import EndOfStream, MapUpdated, ObservationsAdded

from ..transport import CONTROL_MAX_BYTES, Diagnostics, Publisher, Subscriber
from .base import Node

log = logging.getLogger(__name__)


class RefinerNode(Node):
    @dataclass(frozen=True)
    class Params:
        map: str = ""  # the prior Gaussian map (INRIA PLY): its size
        store: str = "{run_dir}/store"
        map_dir: str = "{run_dir}/map"
        period_s: float = 15.0  # at least this long between passes ...
        max_duty: float = 0.25  # ... and long enough that passes take at most this share of the time
        # snapshot form: K > 0 codebook of K centres; 0: float16 rows, or for a map of more than
        # codebook_above Gaussians a codebook of 1024 (2.7 instead of 256 bytes per Gaussian
        # and version; the query server scores the centres: fast queries on millions)
        codebook: int = 0
        codebook_above: int = 2_000_000
        exit_on_final: bool = True
        final_linger_s: float = 0.5  # after the final map: keep announcing it this long, then exit
        observations_in: str = "ipc://{run_dir}/observations.sock"
        map_out: str = "ipc://{run_dir}/map.sock"
        diagnostics: str = ""
        topic_observations: str = "observations"
        topic_map: str = "map"
        threads: int = 1  # numba threads of the refinement (0 = one per core)
        # live passes: "fold" the new views into the running map (flat cost; the final pass is
        # exact) or "exact" (every touched Gaussian from all its views: grows with the flight)
        passes: str = "fold"
        refresh: float = 2.0  # a fold also recomputes exactly this many times its new observations
        # a fold only while it would read at most this share of an exact pass's observations
        # (a fold's scattered reads cost more per observation); otherwise the pass is exact
        # (0: every pass exact; 1e9: always a fold, as before this choice)
        fold_limit: float = 0.85

    @classmethod
    def validate(cls, params: Params, where: str) -> None:
        from ..params import ParameterError

        p = params
        if not 0.0 < p.max_duty <= 1.0 or p.codebook < 0 or p.codebook == 1 or p.codebook > 65_534:
            raise ParameterError(
                f"{where}: need 0 < max_duty <= 1 and codebook 0 or 2..65534, got {p.max_duty}, {p.codebook}"
            )
        if p.passes not in ("fold", "exact") or not p.refresh >= 0 or not p.fold_limit >= 0:
            raise ParameterError(
                f"{where}: passes must be fold or exact, refresh >= 0 and fold_limit >= 0, "
                f"got {p.passes!r}, {p.refresh}, {p.fold_limit}"
            )

    def setup(self) -> None:
        from ..aggregate.codebook import LiveCodebook
        from ..method.live import LiveMap
        from ..scene import read_ply
        from ..scene.ply import ply_vertex_count
        from ..storage import ObservationStore, latest_map  # heavy imports here: the launcher imports node classes

        p = self.params
        self.limit_threads(p.threads)
        self.store = ObservationStore(p.store, ply_vertex_count(p.map) or len(read_ply(p.map)))
        k = p.codebook or (1024 if self.store.n_gaussians > p.codebook_above else 0)
        self.codebook = LiveCodebook(k) if k else None
        self.map_dir = Path(p.map_dir)
        previous = latest_map(self.map_dir)
        self.version = previous["version"] if previous else 0
        self.record = previous
        # a restarted refiner recomputes everything once (its first pass is exact)
        self.live = LiveMap(self.store, refresh=p.refresh, fold_limit=p.fold_limit)
        self.sub = self.own(
            Subscriber(self.context, [p.observations_in], [p.topic_observations], hwm=1000, max_bytes=CONTROL_MAX_BYTES)
        )
        self.pub = self.own(Publisher(self.context, p.map_out, bind=True, hwm=100))
        self.diag = self.own(Diagnostics(self.context, p.diagnostics, self.name)) if p.diagnostics else None
        self.last_pass = time.monotonic()
        self.wait_s = p.period_s
        self.last_announce = 0.0
        # a run that had already ended (restarted after its final map, e.g. from a copy of its
        # folder): the final map stands and is announced as it is. A pass here would publish the
        # same views again as not final, after the ingest (which heard the final map and ended)
        # has sent its last EndOfStream: the graph would wait for a final map forever.
        self.final = bool(previous and previous.get("final") and previous.get("views") == len(self.store))
        if self.final:
            log.info(
                "the run had ended: map version %d is final (%d views); announcing it", self.version, len(self.store)
            )
        self.exit_at: float | None = None
        self.write_error = ""  # why the last snapshot could not be written ("" once one is)
        from ..method.live import warm_up

        # the refinement kernels now, while the accumulator compiles its own: not in the first pass
        log.info("refinement kernels ready in %.1f s", warm_up())

    def spin(self) -> int | None:
        p = self.params
        end_now = False
        for _, message in self.sub.drain(200):
            self.stats.count("received")
            if not isinstance(message, (ObservationsAdded, EndOfStream)):
                self.unexpected(message, p.topic_observations)
            end_now |= isinstance(message, EndOfStream) and not self.final  # repeats are ignored
        self.final |= end_now
        due = time.monotonic() - self.last_pass > self.wait_s
        if end_now or (due and (self._final_unwritten() or (len(self.store) > self.live.views and not self.final))):
            start = time.perf_counter()
            self._refine(self.final)
            from ..memory import release_free_memory  # here: the launcher imports node classes

            release_free_memory()  # a pass's temporaries, freed by its threads: not kept resident
            spent = time.perf_counter() - start
            self.stats.handled(0, spent)
            self.last_pass = time.monotonic()
            # a pass re-reads every touched Gaussian's views, so passes grow with the flight;
            # spacing them by their own length keeps the refiner from starving the encoder
            # and the accumulator on a small CPU
            self.wait_s = max(p.period_s, spent * (1.0 - p.max_duty) / p.max_duty)
            self.last_announce = 0.0
        if self.record and time.monotonic() - self.last_announce > 1.0:
            fields = ("version", "path", "views", "observed_gaussians", "encoder", "final")
            update = MapUpdated(stamp_ns=time.time_ns(), frame_id="map", **{k: self.record[k] for k in fields})
            self.publish(self.pub, p.topic_map, update)
            self.last_announce = time.monotonic()
        self._beat()
        if self.final and p.exit_on_final and not self._final_unwritten():
            if self.exit_at is None:
                self.exit_at = time.monotonic() + p.final_linger_s
            elif time.monotonic() >= self.exit_at:
                return 0
        return None

    def _final_unwritten(self) -> bool:
        """The stream has ended but its final map could not be written yet (a full disk)."""
        return self.final and not (self.record and self.record.get("final"))

    def teardown(self) -> None:
        if getattr(self, "diag", None) is not None:
            self._beat(force=True, text="stopping")

    def _beat(self, force: bool = False, text: str | None = None) -> None:
        if self.diag is None:
            return
        quarantined = self.store.quarantined
        values = self.stats.with_sockets(
            self.sub.stats, map_version=self.version, views=self.live.views, quarantined=len(quarantined)
        )
        text = text or f"map version {self.version}, {self.live.views} views"
        level = 0
        if quarantined:  # the map goes on without them, but a user must hear of it
            level = 2
            folder, why = next(iter(quarantined.items()))
            text += f"; {len(quarantined)} damaged view segment(s) skipped, e.g. {folder}: {why}"
        if self.write_error:
            level = 2
            text += f"; {self.write_error}"
        (self.diag.beat_now if force else self.diag.beat)(level, text, values)

    def _refine(self, final: bool) -> None:
        """One pass over the views that arrived since the last one; writes a new snapshot."""
        from ..method import read_manifest
        from ..storage import LanguageMap, write_snapshot

        views = len(self.store)
        if views == self.live.views and self.record is not None and not final:
            return
        manifest = read_manifest(self.params.store)
        if views == 0 or manifest is None or manifest.encoder is None:
            ended = " (the stream ended with none)" if final else ""
            log.warning("no view in the store yet: no map to write%s", ended)
            if final:  # announce the end anyway, or the ingest would wait for a final map forever
                self.record = {
                    "version": self.version,
                    "path": "",
                    "views": 0,
                    "observed_gaussians": 0,
                    "encoder": "",
                    "final": True,
                }
            return
        start = time.perf_counter()
        exact = final or self.params.passes == "exact"
        changed = self.live.update(manifest.method.aggregation, exact)
        if self.live.features is None or self.live.observed is None:
            return
        views, observed = self.live.views, self.live.observed
        self.version += 1
        language_map = LanguageMap(self.live.features, observed, manifest.encoder)  # unit float16 rows already
        if self.codebook is not None:
            language_map.codes, language_map.centres = self.codebook.update(
                self.live.features, observed, np.ones(len(observed), bool) if changed is None else changed
            )
        record = {
            "views": views,
            "observed_gaussians": int(observed.sum()),
            "encoder": manifest.encoder,
            "final": final,
            "refine_s": round(time.perf_counter() - start, 3),  # this pass, before the snapshot's write
            "exact": self.live.last_exact,  # False: a fold of the new views
            # the observations the pass took in, and those a fold and an exact pass would read
            "reads": self.live.last_reads,
            # the store's observations (one per Gaussian per view) once the pass ended: a fold's
            # cost follows the observations it adds, which a view of more of the map has more of
            "observations": int(self.store.observation_counts().sum()),
        }
        try:
            self.record = write_snapshot(self.map_dir, self.version, language_map, record, None)
        except OSError as exc:  # a full disk: the last written map stands, the next pass tries again
            self.version -= 1
            self.stats.count("snapshot_errors")
            self.write_error = f"map version {self.version + 1} not written: {exc}"
            log.error("%s; the map stays at version %d until a pass can write", self.write_error, self.version)
            return
        self.write_error = ""
        log.info(
            "map version %d (%s): %d views, %d Gaussians observed, %.1f s%s",
            self.version,
            manifest.method.name,
            views,
            int(observed.sum()),
            time.perf_counter() - start,
            " (final)" if final else "",
        )
