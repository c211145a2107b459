"""ingest: frames from a camera source -> ``ImageFrame``.

Sources (``source_kind``, ``olsplat_nodes.sources``): ``replay`` (a replay log (MCAP) or an image
folder + COLMAP model), ``exif_folder`` (geotagged photos, EXIF pose priors), ``depthai`` (a live
OAK camera, poses from flight-controller telemetry or a fixed pose). The source's health is the
heartbeat's level and message (a missing camera: ERROR "no DepthAI device found ..." while the
node keeps running, heartbeating and looking for it); its counters go out as ``source_*`` values.

Two delivery modes (parameter ``lossless``):
- lossless (default for replays): at most ``window`` frames are in flight; a frame counts as
  delivered when the accumulator acknowledges it (``ObservationsAdded`` with its name) and is
  sent again when no acknowledgement came within ``ack_timeout_s`` (sooner while the graph is
  starting, ``ack_timeout_start_s``). Downstream nodes accept a
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
import time
from collections import OrderedDict
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

from olsplat_msgs import EndOfStream, MapUpdated, ObservationsAdded

from ..durable import append_line
from ..extras import require
from ..scene.geodesy import write_georef
from ..sources import SourceParams, open_source
from ..transport import CONTROL_MAX_BYTES, Diagnostics, Publisher, Subscriber
from ..transport.convert import frame_message
from .base import Node

log = logging.getLogger(__name__)


class IngestNode(Node):
    @dataclass(frozen=True)
    class Params(SourceParams):  # source_kind, source, rate_hz, fast, exif_*, depthai_*, fixed_pose, telemetry_*
        lossless: bool = True
        window: int = 4  # frames in flight without acknowledgement (lossless): the encoder works ahead
        ack_timeout_s: float = 20.0  # send a frame again when it was not acknowledged in time
        # ... but until the first acknowledgement of this run, after this long, doubling up to
        # ack_timeout_s: frames published before the graph's subscribers have connected are
        # lost (ZeroMQ's late joiners), and waiting the full timeout for them was most of the
        # start-up time. A frame sent twice is answered from the region encoder's cache.
        ack_timeout_start_s: float = 2.0
        frames_out: str = "ipc://{run_dir}/frames.sock"
        acks_in: str = "ipc://{run_dir}/observations.sock"
        map_in: str = "ipc://{run_dir}/map.sock"
        diagnostics: str = ""  # collector endpoint ("" = no heartbeats)
        topic_frames: str = "frames"
        topic_observations: str = "observations"
        topic_map: str = "map"
        hwm: int = 4
        state_file: str = "{run_dir}/ingest_acknowledged.txt"  # acknowledged frame names: a restart skips them
        # where the source's georeference goes (photos with GPS: the ENU origin), so that the
        # run's answers carry latitude and longitude; "" = nowhere
        georef_out: str = "{run_dir}/map/georef.json"

    @classmethod
    def validate(cls, params: Params, where: str) -> None:
        if params.source_kind == "depthai":  # a live OAK camera: refused at launch, not retried for ever
            require("depthai", f"{where}: source_kind=depthai (a live OAK camera)")

    def setup(self) -> None:
        p = self.params
        self.pub = self.own(Publisher(self.context, p.frames_out, bind=True, hwm=p.hwm))
        self.acks = self.own(
            Subscriber(
                self.context,
                [p.acks_in, p.map_in],
                [p.topic_observations, p.topic_map],
                hwm=100,
                max_bytes=CONTROL_MAX_BYTES,
            )
        )
        self.diag = self.own(Diagnostics(self.context, p.diagnostics, self.name)) if p.diagnostics else None
        self.acked = self._load_acknowledged()
        self.final_map = False
        # name -> (frame, last send time, sends so far)
        self.pending: OrderedDict[str, tuple[object, float, int]] = OrderedDict()
        self.first_sent: dict[str, float] = {}  # frame -> when it was first sent (monotonic s)
        self.heard_back = False  # an acknowledgement came: the graph is connected
        self.names: list[str] = []
        self.state_error = ""  # why the last acknowledged frame could not be recorded
        self.phase = "streaming"  # -> "delivering" (source done, frames in flight) -> "ending" (EndOfStream sent)
        self.last_eos = 0.0
        self.source: Any = None  # a sources.Source once open
        self.source = self.own(open_source({f.name: getattr(p, f.name) for f in fields(SourceParams)}))
        self._write_georeference()

    def _write_georeference(self) -> None:
        """The source's georeference into ``georef_out`` (the query service reads it from the
        run's map folder when the prior map has none beside its PLY)."""
        georef = self.source.georeference()
        if georef is None or not self.params.georef_out:
            return
        path = Path(self.params.georef_out)
        path.parent.mkdir(parents=True, exist_ok=True)
        write_georef(path, georef)
        log.info("georeference of the source (%s) written to %s", georef.source, path)

    def spin(self) -> int | None:
        if self.phase == "streaming":
            self._stream_one()
        elif self.phase == "delivering":
            self._service(0.1)
            if not self.pending:
                log.info("all %d frames delivered; waiting for the final map", len(self.names))
                self.phase = "ending"
        else:
            if time.monotonic() - self.last_eos > 1.0:
                eos = EndOfStream(
                    stamp_ns=time.time_ns(),
                    frame_id="camera",
                    source=str(self.params.source),
                    frames=len(self.names),
                    names=self.names,
                )
                self.publish(self.pub, self.params.topic_frames, eos)
                self.last_eos = time.monotonic()
            self._service(0.1)
            if self.final_map:
                return 0
        return None

    def teardown(self) -> None:
        if hasattr(self, "acks"):
            self._beat(force=True)

    def _stream_one(self) -> None:
        """Read one frame (waiting up to 0.1 s) and send it; in lossless mode first wait for room
        in the window of unacknowledged frames."""
        frame = self.source.read(0.1)
        if frame is None:
            if self.source.done:
                self.phase = "delivering"
            self._service(0)
            return
        self.names.append(frame.name)
        if self.params.lossless:
            while len(self.pending) >= self.params.window and not self.stop.is_set():
                self._service(0.1)
            if frame.name in self.acked:
                return  # a restarted ingest: this view is already in the map
            self.pending[frame.name] = (frame, time.monotonic(), 1)
            self.first_sent[frame.name] = time.monotonic()
        self._send(frame)
        self._service(0)

    def _load_acknowledged(self) -> set[str]:
        path = self.params.state_file
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
        message = frame_message(frame, 0, frame.stamp_ns if self.source.live else None)
        self.publish(self.pub, self.params.topic_frames, message)
        self.stats.handled(message.stamp_ns, time.perf_counter() - start)

    def _service(self, timeout_s: float) -> None:
        """Take in acknowledgements and map announcements; resend overdue frames; heartbeat."""
        p = self.params
        for _, message in self.acks.drain(int(timeout_s * 1000)):
            self.heard_back |= isinstance(message, ObservationsAdded)
            if isinstance(message, ObservationsAdded) and message.name not in self.acked:
                self.acked.add(message.name)
                self.pending.pop(message.name, None)
                self.first_sent.pop(message.name, None)
                if p.state_file:  # fsynced: a frame once acknowledged is never sent again, power cut or not
                    self._record_acknowledged(message.name)
            elif isinstance(message, MapUpdated) and message.final:
                self.final_map = True
            elif not isinstance(message, (ObservationsAdded, MapUpdated, EndOfStream)):
                # (EndOfStream: forwarded by the accumulator)
                self.unexpected(message, " / ".join(self.acks.topics))
        now = time.monotonic()
        for name, (frame, sent, sends) in list(self.pending.items()):
            timeout = p.ack_timeout_s
            if not self.heard_back:
                timeout = min(timeout, p.ack_timeout_start_s * 2 ** (sends - 1))
            if now - sent > timeout:
                if self.heard_back:
                    log.warning("frame %s not acknowledged in %.0f s: sending it again", name, timeout)
                else:
                    log.info("frame %s: no acknowledgement yet (graph starting?): sending it again", name)
                self.stats.count("resent")
                self.pending[name] = (frame, now, sends + 1)
                self._send(frame)
        self._beat()

    def _record_acknowledged(self, name: str) -> None:
        """Append ``name`` to the state file. A full disk does not stop the flight: the frame is
        delivered; only a restart would send it again, and the accumulator answers that with a
        duplicate acknowledgement. The error is the node's status until a line is written."""
        try:
            append_line(self.params.state_file, name)
            self.state_error = ""
        except OSError as exc:
            self.stats.count("state_errors")
            self.state_error = f"frame {name!r} not recorded as acknowledged: {exc}"
            log.error("%s (a restart would send it again; the accumulator takes it once)", self.state_error)

    def _beat(self, force: bool = False) -> None:
        if self.diag is None:
            return
        values = self.stats.with_sockets(self.acks.stats, in_flight=len(self.pending), acknowledged=len(self.acked))
        level, message = (0, "starting")
        if self.source is not None:
            level, message = self.source.status()
            values.update({f"source_{key}": value for key, value in self.source.stats.items()})
        if self.state_error:
            level, message = max(level, 1), f"{message}; {self.state_error}"
        waiting = self._longest_wait()
        if waiting is not None:
            name, seconds = waiting
            values["oldest_unacknowledged_s"] = round(seconds, 1)
            sends = self.pending[name][2] if name in self.pending else 0
            level = max(level, 1)
            message = f"{message}; frame {name} unacknowledged for {seconds:.0f} s (sent {sends}x)"
        if self.stats.finished:
            message = f"finished: {len(self.acked)} frames acknowledged, the final map received"
        (self.diag.beat_now if force else self.diag.beat)(level, message, values)

    def _longest_wait(self) -> tuple[str, float] | None:
        """(frame, seconds) of the frame waiting longest for its acknowledgement, when that is
        longer than ``ack_timeout_s`` after the graph first answered (before, the graph is
        starting: frames wait for its subscribers, not for a stuck stage)."""
        if not self.heard_back or not self.first_sent:
            return None
        name, first = min(self.first_sent.items(), key=lambda item: item[1])
        seconds = time.monotonic() - first
        return (name, seconds) if seconds > self.params.ack_timeout_s else None
