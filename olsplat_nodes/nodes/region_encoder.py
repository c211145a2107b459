"""region_encoder: ``ImageFrame`` -> multi-level regions and their fused 2D features -> ``RegionFeatures``.

The camera and the photo travel on with the features, so the accumulator never needs the
frame. ``EndOfStream`` is forwarded after the frames that came before it. With
``latest_wins`` (live cameras) only the newest queued frame is encoded and the older ones are
dropped and counted; without it (lossless replays) every frame is encoded in order. A frame
sent again by a lossless ingest is answered from a small cache of recent results instead of
being encoded twice.
"""

from __future__ import annotations

import logging
import time
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from olsplat_msgs import EndOfStream, ImageFrame, RegionFeatures

from ..encoders.spec import DEFAULT_SPEC
from ..transport import Diagnostics, Publisher, Subscriber
from ..transport.convert import camera_of, regions_message
from .base import Node

log = logging.getLogger(__name__)


def encode_frame(frame: ImageFrame, encoder, region_config) -> RegionFeatures:
    """Regions at every level and the encoder's feature per region, as the wire message."""
    from ..encoders import encode_regions
    from ..regions import propose_regions

    camera_of(frame)  # validates size and pose before spending seconds on it
    image = np.ascontiguousarray(frame.image)
    levels = propose_regions(image, region_config)
    bank = encode_regions(image, levels, encoder)
    return regions_message(frame, levels.label_maps, bank.features, encoder.name)


def warm_up(encoder, region_config) -> float:
    """Make regions and features of a 160x120 noise image once, so that numba compiles the
    region and crop kernels (or loads them from its cache) before the node says it is ready,
    not on a flight's first frame (~2 s on a fresh install). Returns the seconds it took."""
    from ..encoders import encode_regions
    from ..regions import propose_regions

    start = time.perf_counter()
    image = np.random.default_rng(0).integers(0, 256, (120, 160, 3), dtype=np.uint8)
    encode_regions(image, propose_regions(image, region_config), encoder)
    return time.perf_counter() - start


class RegionEncoderNode(Node):
    @dataclass(frozen=True)
    class Params:
        encoder: str = DEFAULT_SPEC  # encoder spec as in ``olsplat encode --encoders``
        encoder_weights: tuple[float, ...] = ()  # lambda_2D per encoder, e.g. [0.6, 0.4]; [] = the default
        # regions per level at 640x480, coarse to fine; the method aggregates the finest level
        # only (unless accumulator.level_weights says otherwise), so only that one is made
        level_counts: tuple[int, ...] = (240,)
        region_scale: float = 0.5  # superpixels and merging on the image resized by this (RegionConfig.work_scale)
        threads: int = 1  # onnxruntime and OpenCV threads (0 = one per core)
        latest_wins: bool = True
        recent: int = 8  # results kept to answer re-sent frames
        frames_in: str = "ipc://{run_dir}/frames.sock"
        regions_out: str = "ipc://{run_dir}/regions.sock"
        diagnostics: str = ""
        topic_frames: str = "frames"
        topic_regions: str = "regions"
        hwm: int = 4
        max_message_mb: float = 64.0  # frames_in limit; a 4K RGB frame is 25 MB

    def setup(self) -> None:
        from ..encoders.spec import encoder_from_spec
        from ..errors import OlsplatInputError
        from ..regions import RegionConfig

        p = self.params
        self.encoder = encoder_from_spec(p.encoder, p.encoder_weights or None, threads=p.threads)
        if p.threads > 0:
            import cv2

            cv2.setNumThreads(p.threads)
        try:
            self.region_config = RegionConfig(level_counts=p.level_counts, work_scale=p.region_scale)
        except ValueError as exc:
            raise OlsplatInputError(f"node {self.name!r}: {exc}") from exc
        log.info("region and feature kernels ready in %.1f s", warm_up(self.encoder, self.region_config))
        limit = int(p.max_message_mb * 2**20)
        self.sub = self.own(Subscriber(self.context, [p.frames_in], [p.topic_frames], hwm=p.hwm, max_bytes=limit))
        self.pub = self.own(Publisher(self.context, p.regions_out, bind=True, hwm=p.hwm))
        self.diag = self.own(Diagnostics(self.context, p.diagnostics, self.name)) if p.diagnostics else None
        self.recent: OrderedDict[str, RegionFeatures] = OrderedDict()

    def spin(self) -> int | None:
        p = self.params
        batch = self.sub.drain(200)
        self.stats.count("received", len(batch))
        frames = [m for _, m in batch if isinstance(m, ImageFrame)]
        if p.latest_wins and len(frames) > 1:
            self.stats.count("dropped", len(frames) - 1)
            frames = frames[-1:]
        chosen = {id(f) for f in frames}
        for _, message in batch:
            if isinstance(message, EndOfStream):
                self.publish(self.pub, p.topic_regions, message)
            elif id(message) in chosen:
                self._encode(message)
            elif not isinstance(message, ImageFrame):
                self.unexpected(message, p.topic_frames)
        if self.diag is not None:
            self.diag.beat(0, "encoding", self.stats.with_sockets(self.sub.stats, queue_depth=len(batch)))
        return None

    def _encode(self, frame: ImageFrame) -> None:
        start = time.perf_counter()
        try:
            out = self.recent.get(frame.name) or encode_frame(frame, self.encoder, self.region_config)
        except ValueError as exc:
            self.stats.count("bad_messages")
            log.warning("frame %s (seq %d) dropped: %s", frame.name, frame.seq, exc)
            return
        self.recent[frame.name] = out
        while len(self.recent) > self.params.recent:
            self.recent.popitem(last=False)
        self.publish(self.pub, self.params.topic_regions, out)
        self.stats.handled(frame.stamp_ns, time.perf_counter() - start)
