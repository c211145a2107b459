"""refiner: observation store -> consistency-aware refinement -> versioned language map -> ``MapUpdated``.

The store on disk is the source of truth: each pass reads the views that arrived since the
last one, refines only the Gaussians they touched (the others keep their features), and
writes ``MAP_DIR/language_map_NNNNNN.npz`` atomically plus ``MAP_DIR/latest.json`` naming it
(the late-joiner snapshot: a query server that starts later reads it, never waits for a
message). A pass runs when new views are in and ``period_s`` has passed, and
no sooner than ``(1 - max_duty) / max_duty`` times the last pass's length (passes grow with
the flight; this keeps them from starving the encoder on a small CPU); and at once on
``EndOfStream``, which makes the final map (``final: true``); with ``exit_on_final`` the node
then exits 0. ``MapUpdated`` is repeated with every heartbeat so that late subscribers learn
the current version.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from pathlib import Path

from olsplat_msgs import EndOfStream, MapUpdated, ObservationsAdded

from ..transport import Diagnostics, Publisher, Subscriber
from .base import Node, NodeStats, SequenceCounter

log = logging.getLogger(__name__)
KEEP_VERSIONS = 3  # older snapshots are deleted; a reader that still holds one has it in memory


def latest_map(map_dir: str | Path) -> dict | None:
    """The record of the newest snapshot ({version, path, views, observed_gaussians, encoder,
    final}) or None when there is none yet."""
    try:
        return json.loads((Path(map_dir) / "latest.json").read_text())
    except FileNotFoundError:
        return None


def write_snapshot(map_dir: Path, version: int, language_map, record: dict, codebook: int | None) -> dict:
    """Write version ``version`` and point latest.json at it (both atomic); returns the record."""
    map_dir.mkdir(parents=True, exist_ok=True)
    path = map_dir / f"language_map_{version:06d}.npz"
    language_map.save(path, codebook)
    record = {**record, "version": version, "path": str(path.resolve())}
    tmp = map_dir / "latest.json.tmp"
    tmp.write_text(json.dumps(record))
    tmp.replace(map_dir / "latest.json")
    for old in sorted(map_dir.glob("language_map_*.npz"))[:-KEEP_VERSIONS]:
        old.unlink(missing_ok=True)
    return record


class RefinerNode(Node):
    DEFAULTS = {
        "map": "",  # the prior Gaussian map (INRIA PLY): its size
        "store": "{run_dir}/store",
        "map_dir": "{run_dir}/map",
        "method": "outlangsplat",
        "period_s": 15.0,  # at least this long between passes ...
        "max_duty": 0.25,  # ... and long enough that passes take at most this share of the time
        "codebook": 0,  # 0: float16 snapshot; K: codebook form with K centres
        "exit_on_final": True,
        "observations_in": "ipc://{run_dir}/observations.sock",
        "map_out": "ipc://{run_dir}/map.sock",
        "diagnostics": "",
        "topic_observations": "observations",
        "topic_map": "map",
    }

    def run(self, stop: threading.Event) -> int:
        from ..aggregate import ObservationStore  # heavy imports here: the launcher imports node classes
        from ..pipeline.offline import method
        from ..scene import read_ply

        p = self.params
        self.config = method(p["method"]).aggregation
        self.store = ObservationStore(p["store"], len(read_ply(p["map"])))
        self.map_dir = Path(p["map_dir"])
        previous = latest_map(self.map_dir)
        self.version = previous["version"] if previous else 0
        self.record = previous
        self.features = None  # a restarted refiner recomputes everything once
        self.observed = None
        self.views_done = 0
        stats = NodeStats()
        seqs = SequenceCounter()
        sub = Subscriber(self.context, [p["observations_in"]], [p["topic_observations"]], hwm=1000)
        pub = Publisher(self.context, p["map_out"], bind=True, hwm=100)
        diag = Diagnostics(self.context, p["diagnostics"], self.name) if p["diagnostics"] else None
        last_pass = time.monotonic()
        wait_s = p["period_s"]
        last_announce = 0.0
        final = False
        try:
            while not stop.is_set():
                end_now = False
                for _, message in sub.drain(200):
                    stats.count("received")
                    if not isinstance(message, (ObservationsAdded, EndOfStream)):
                        stats.count("bad_messages")
                        log.warning("unexpected %s on %s: dropped", type(message).__name__, p["topic_observations"])
                    end_now |= isinstance(message, EndOfStream) and not final  # repeats are ignored
                final |= end_now
                due = time.monotonic() - last_pass > wait_s
                if end_now or (due and len(self.store) > self.views_done):
                    start = time.perf_counter()
                    self._refine(final)
                    spent = time.perf_counter() - start
                    stats.handled(0, spent)
                    last_pass = time.monotonic()
                    # a pass re-reads every touched Gaussian's views, so passes grow with the
                    # flight; spacing them by their own length keeps the refiner from starving
                    # the encoder and the accumulator on a small CPU
                    wait_s = max(p["period_s"], spent * (1.0 - p["max_duty"]) / p["max_duty"])
                    last_announce = 0.0
                if self.record and time.monotonic() - last_announce > 1.0:
                    pub.send(
                        p["topic_map"],
                        seqs.stamp(
                            MapUpdated(
                                stamp_ns=time.time_ns(),
                                frame_id="map",
                                **{
                                    k: self.record[k]
                                    for k in ("version", "path", "views", "observed_gaussians", "encoder", "final")
                                },
                            )
                        ),
                    )
                    stats.count("published")
                    last_announce = time.monotonic()
                if diag is not None:
                    diag.beat(
                        0,
                        f"map version {self.version}, {self.views_done} views",
                        stats.with_sockets(sub.stats, map_version=self.version, views=self.views_done),
                    )
                if final and p["exit_on_final"]:
                    time.sleep(0.5)  # subscribers get the last announcement before the socket closes
                    return 0
            return 130
        finally:
            if diag is not None:
                diag.beat_now(
                    0, "stopping", stats.with_sockets(sub.stats, map_version=self.version, views=self.views_done)
                )
            for socket in (sub, pub, diag):
                if socket is not None:
                    socket.close()

    def _refine(self, final: bool) -> None:
        """One pass over the views that arrived since the last one; writes a new snapshot."""
        views = self.store.touch_views(self.views_done)
        if views == self.views_done and self.record is not None and not final:
            return
        encoder_file = Path(self.params["store"]) / "encoder.txt"
        if views == 0 or not encoder_file.exists():
            log.warning("no view in the store yet: no map to write%s", " (the stream ended with none)" if final else "")
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
        from ..aggregate.snapshot import LanguageMap

        start = time.perf_counter()
        self.features, observed = self.store.refine(self.features, self.config, only_touched=self.features is not None)
        if self.features is None:
            return
        if self.observed is not None:
            observed |= self.observed  # Gaussians outside this pass keep their state
        self.observed = observed
        self.views_done = views
        self.version += 1
        language_map = LanguageMap.from_features(self.features, observed, encoder_file.read_text())
        self.record = write_snapshot(
            self.map_dir,
            self.version,
            language_map,
            {
                "views": views,
                "observed_gaussians": int(observed.sum()),
                "encoder": language_map.encoder,
                "final": final,
            },
            self.params["codebook"] or None,
        )
        log.info(
            "map version %d: %d views, %d Gaussians observed, %.1f s%s",
            self.version,
            views,
            int(observed.sum()),
            time.perf_counter() - start,
            " (final)" if final else "",
        )
