"""ingest: frames from a camera source -> ``ImageFrame``.

Sources (``source_kind``, ``olsplat_nodes.sources``): ``replay`` (a replay log (MCAP) or an image
folder + COLMAP model), ``exif_folder`` (geotagged photos, EXIF pose priors), ``depthai`` (a live
OAK camera, poses from flight-controller telemetry or a fixed pose). The source's health is the
heartbeat's level and message (a missing camera: ERROR "no DepthAI device found ..." while the
node keeps running, heartbeating and looking for it); its counters go out as ``source_*`` values.

Two delivery modes (parameter ``lossless``):
- lossless (default for replays): at most ``window`` frames are in flight; a frame counts as
  delivered when the accumulator acknowledges it (``ObservationsAdded`` with its name) and is
  sent again when no acknowledgement came within ``ack_timeout_s``. Downstream nodes accept a
  view once (by name), so "at least once" here gives "exactly once" in the map, also across a
  crash and restart of any node.
- latest-wins (live cameras): frames go out at their pace; a slow consumer drops old frames
  (counted by the subscribers' sequence gaps), nothing waits.

At the end of a finite source the node sends ``EndOfStream`` on the frame topic (after every
frame was acknowledged, in lossless mode) once a second until the refiner announces the final
map, then exits 0. Replayed frames are re-stamped with the wall clock at publication (their
acquisition time in this run) so that latencies downstream are meaningful; live frames keep their
acquisition stamps. A live source never ends: the node runs until stopped.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict

import numpy as np

from olsplat_msgs import EndOfStream, ImageFrame, MapUpdated, ObservationsAdded

from ..sources import SOURCE_DEFAULTS, open_source
from ..transport import Diagnostics, Publisher, Subscriber
from .base import Node, NodeStats, SequenceCounter

log = logging.getLogger(__name__)


def frame_message(frame, seq: int, stamp_ns: int | None = None) -> ImageFrame:
    """A camera frame (``sources.SourceFrame``, e.g. from a replay log) as the wire message, stamped
    ``stamp_ns`` (default: now)."""
    camera = frame.camera
    return ImageFrame(
        stamp_ns=time.time_ns() if stamp_ns is None else stamp_ns,
        seq=seq,
        frame_id="camera",
        name=frame.name,
        image=np.ascontiguousarray(frame.image, np.uint8),
        K=camera.K,
        D=camera.dist,
        distortion_model="plumb_bob" if len(camera.dist) else "none",
        world_from_camera=camera.world_from_camera,
        width=camera.width,
        height=camera.height,
    )


class IngestNode(Node):
    DEFAULTS = {
        **SOURCE_DEFAULTS,  # source_kind, source, rate_hz, fast, exif_*, depthai_*, fixed_pose, telemetry_* (sources/README.md)
        "lossless": True,
        "window": 2,  # frames in flight without acknowledgement (lossless)
        "ack_timeout_s": 20.0,  # send a frame again when it was not acknowledged in time
        "frames_out": "ipc://{run_dir}/frames.sock",
        "acks_in": "ipc://{run_dir}/observations.sock",
        "map_in": "ipc://{run_dir}/map.sock",
        "diagnostics": "",  # collector endpoint ("" = no heartbeats)
        "topic_frames": "frames",
        "topic_observations": "observations",
        "topic_map": "map",
        "hwm": 4,
        "state_file": "{run_dir}/ingest_acknowledged.txt",  # acknowledged frame names: a restart skips them
    }

    def run(self, stop: threading.Event) -> int:
        p = self.params
        self.stats = NodeStats()
        self.pub = Publisher(self.context, p["frames_out"], bind=True, hwm=p["hwm"])
        self.acks = Subscriber(
            self.context, [p["acks_in"], p["map_in"]], [p["topic_observations"], p["topic_map"]], hwm=100
        )
        self.diag = Diagnostics(self.context, p["diagnostics"], self.name) if p["diagnostics"] else None
        self.seqs = SequenceCounter()
        self.acked = self._load_acknowledged()
        self.final_map = False
        self.pending: OrderedDict[str, tuple[object, float]] = OrderedDict()  # name -> (frame, last send time)
        pending = self.pending
        names: list[str] = []
        self.source = None
        try:
            self.source = source = open_source({key: p[key] for key in SOURCE_DEFAULTS})
            while not stop.is_set():
                frame = source.read(0.1)
                if frame is None:
                    if source.done:
                        break
                    self._service(pending, 0)
                    continue
                names.append(frame.name)
                if p["lossless"]:
                    while len(pending) >= p["window"] and not stop.is_set():
                        self._service(pending, 0.1)
                    if frame.name in self.acked:
                        continue  # a restarted ingest: this view is already in the map
                    pending[frame.name] = (frame, time.monotonic())
                self._send(frame)
                self._service(pending, 0)
            if stop.is_set():
                return 130
            while pending and not stop.is_set():
                self._service(pending, 0.1)
            log.info("all %d frames delivered; waiting for the final map", len(names))
            last_eos = 0.0
            while not self.final_map and not stop.is_set():
                if time.monotonic() - last_eos > 1.0:
                    self.pub.send(
                        p["topic_frames"],
                        self.seqs.stamp(
                            EndOfStream(
                                stamp_ns=time.time_ns(),
                                frame_id="camera",
                                source=str(p["source"]),
                                frames=len(names),
                                names=names,
                            )
                        ),
                    )
                    last_eos = time.monotonic()
                self._service(pending, 0.1)
            return 0 if self.final_map else 130
        finally:
            self._beat(force=True)
            if self.source is not None:
                self.source.close()
            for socket in (self.pub, self.acks, self.diag):
                if socket is not None:
                    socket.close()

    def _load_acknowledged(self) -> set[str]:
        path = self.params["state_file"]
        if not path:
            return set()
        try:
            with open(path) as f:
                names = {line.rstrip("\n") for line in f if line.strip()}
        except FileNotFoundError:
            return set()
        log.info("resuming: %d frames already acknowledged (%s)", len(names), path)
        return names

    def _send(self, frame) -> None:
        start = time.perf_counter()
        message = self.seqs.stamp(
            frame_message(frame, 0, frame.stamp_ns if self.source is not None and self.source.live else None)
        )
        self.pub.send(self.params["topic_frames"], message)
        self.stats.count("published")
        self.stats.handled(message.stamp_ns, time.perf_counter() - start)

    def _service(self, pending: OrderedDict, timeout_s: float) -> None:
        """Take in acknowledgements and map announcements; resend overdue frames; heartbeat."""
        for _, message in self.acks.drain(int(timeout_s * 1000)):
            if isinstance(message, ObservationsAdded) and message.name not in self.acked:
                self.acked.add(message.name)
                pending.pop(message.name, None)
                if self.params["state_file"]:
                    with open(self.params["state_file"], "a") as f:
                        f.write(message.name + "\n")
            elif isinstance(message, MapUpdated) and message.final:
                self.final_map = True
            elif not isinstance(
                message, (ObservationsAdded, MapUpdated, EndOfStream)
            ):  # (EndOfStream: forwarded by the accumulator)
                self.stats.count("bad_messages")
                log.warning("unexpected %s on %s: dropped", type(message).__name__, " / ".join(self.acks.topics))
        now = time.monotonic()
        for name, (frame, sent) in list(pending.items()):
            if now - sent > self.params["ack_timeout_s"]:
                log.warning("frame %s not acknowledged in %.0f s: sending it again", name, self.params["ack_timeout_s"])
                self.stats.count("resent")
                pending[name] = (frame, now)
                self._send(frame)
        self._beat()

    def _beat(self, force: bool = False) -> None:
        if self.diag is None:
            return
        values = self.stats.with_sockets(self.acks.stats, in_flight=len(self.pending), acknowledged=len(self.acked))
        level, message = (0, "starting")
        if self.source is not None:
            level, message = self.source.status()
            values.update({f"source_{key}": value for key, value in self.source.stats.items()})
        (self.diag.beat_now if force else self.diag.beat)(level, message, values)
