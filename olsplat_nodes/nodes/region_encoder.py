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
import threading
import time
from collections import OrderedDict

import numpy as np

from olsplat_msgs import EndOfStream, ImageFrame, RegionFeatures

from ..transport import Diagnostics, Publisher, Subscriber
from .base import Node, NodeStats, SequenceCounter

log = logging.getLogger(__name__)


def camera_of(message):
    """The scene.Camera of an ImageFrame / RegionFeatures; ValueError when its fields are inconsistent."""
    from ..scene import Camera

    camera = Camera(message.name, message.width, message.height, message.K, message.world_from_camera, message.D)
    if message.image is not None and message.image.shape != (message.height, message.width, 3):
        raise ValueError(f"image is {message.image.shape}, but the camera says {message.height}x{message.width}x3")
    return camera


def encode_frame(frame: ImageFrame, encoder, region_config) -> RegionFeatures:
    """Regions at every level and the encoder's feature per region, as the wire message."""
    from ..encoders import encode_regions
    from ..regions import propose_regions

    camera_of(frame)  # validates size and pose before spending seconds on it
    image = np.ascontiguousarray(frame.image)
    levels = propose_regions(image, region_config)
    bank = encode_regions(image, levels, encoder)
    return RegionFeatures(
        stamp_ns=frame.stamp_ns,
        seq=frame.seq,
        frame_id=frame.frame_id,
        name=frame.name,
        source_seq=frame.seq,
        encoder=encoder.name,
        label_maps=levels.label_maps.astype(np.int32),
        level_sizes=np.array([len(f) for f in bank.features], np.int32),
        features=np.concatenate(bank.features).astype(np.float16),
        image=image,
        K=frame.K,
        D=frame.D,
        distortion_model=frame.distortion_model,
        world_from_camera=frame.world_from_camera,
        width=frame.width,
        height=frame.height,
    )


class RegionEncoderNode(Node):
    DEFAULTS = {
        "encoder": "shipped",  # encoder spec as in ``olsplat encode --encoder``
        "encoder_weights": "",  # lambda_2D weights, e.g. "0.6,0.4" ("" = the default)
        "latest_wins": True,
        "recent": 8,  # results kept to answer re-sent frames
        "frames_in": "ipc://{run_dir}/frames.sock",
        "regions_out": "ipc://{run_dir}/regions.sock",
        "diagnostics": "",
        "topic_frames": "frames",
        "topic_regions": "regions",
        "hwm": 4,
    }

    def run(self, stop: threading.Event) -> int:
        from ..encoders.spec import encoder_from_spec
        from ..regions import RegionConfig

        p = self.params
        encoder = encoder_from_spec(p["encoder"], p["encoder_weights"] or None)
        region_config = RegionConfig()
        stats = NodeStats()
        sub = Subscriber(self.context, [p["frames_in"]], [p["topic_frames"]], hwm=p["hwm"])
        pub = Publisher(self.context, p["regions_out"], bind=True, hwm=p["hwm"])
        diag = Diagnostics(self.context, p["diagnostics"], self.name) if p["diagnostics"] else None
        recent: OrderedDict[str, RegionFeatures] = OrderedDict()
        seqs = SequenceCounter()
        try:
            while not stop.is_set():
                batch = sub.drain(200)
                stats.count("received", len(batch))
                frames = [m for _, m in batch if isinstance(m, ImageFrame)]
                if p["latest_wins"] and len(frames) > 1:
                    stats.count("dropped", len(frames) - 1)
                    frames = frames[-1:]
                chosen = {id(f) for f in frames}
                for _, message in batch:
                    if isinstance(message, EndOfStream):
                        pub.send(p["topic_regions"], seqs.stamp(message))
                    elif id(message) in chosen:
                        start = time.perf_counter()
                        try:
                            out = recent.get(message.name) or encode_frame(message, encoder, region_config)
                        except ValueError as exc:
                            stats.count("bad_messages")
                            log.warning("frame %s (seq %d) dropped: %s", message.name, message.seq, exc)
                            continue
                        recent[message.name] = out
                        while len(recent) > p["recent"]:
                            recent.popitem(last=False)
                        pub.send(p["topic_regions"], seqs.stamp(out))
                        stats.count("published")
                        stats.handled(message.stamp_ns, time.perf_counter() - start)
                    elif not isinstance(message, ImageFrame):
                        stats.count("bad_messages")
                        log.warning("unexpected %s on %s: dropped", type(message).__name__, p["topic_frames"])
                if diag is not None:
                    diag.beat(0, "encoding", stats.with_sockets(sub.stats, queue_depth=len(batch)))
            return 130
        finally:
            for socket in (sub, pub, diag):
                if socket is not None:
                    socket.close()
