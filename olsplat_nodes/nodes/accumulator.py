"""accumulator: ``RegionFeatures`` -> per-view Gaussian observations in the store -> ``ObservationsAdded``.

Owns the prior Gaussian map. Per view: check the message against itself (label maps vs image
size, regions vs feature rows, one encoder for the whole run), render the view's adaptive
Top-K, observe, save the photo and camera (``pipeline.views``) and append to the observation
store; only then acknowledge. A view already in the store (by name) is acknowledged again
without being added twice, so a restarted node or a re-sent frame never double-counts.
``EndOfStream`` is forwarded on the observations topic after the views before it.
"""

from __future__ import annotations

import logging
import threading
import time
from pathlib import Path

import numpy as np

from olsplat_msgs import EndOfStream, ObservationsAdded, RegionFeatures

from ..transport import Diagnostics, Publisher, Subscriber
from .base import Node, NodeStats, SequenceCounter
from .region_encoder import camera_of

log = logging.getLogger(__name__)


def split_bank(message: RegionFeatures) -> tuple[np.ndarray, list[np.ndarray]]:
    """(label maps [L, H, W] int32, bank per level) of a RegionFeatures; ValueError naming the
    inconsistency when the message does not describe itself correctly."""
    labels, sizes, features = message.label_maps, message.level_sizes, message.features
    if labels.ndim != 3 or labels.shape[1:] != (message.height, message.width):
        raise ValueError(f"label maps are {labels.shape}, the image is {message.height}x{message.width}")
    if len(sizes) != len(labels) or (sizes < 0).any() or int(sizes.sum()) != len(features):
        raise ValueError(
            f"level sizes {sizes.tolist()} do not match {len(labels)} levels and {len(features)} feature rows"
        )
    if not np.isfinite(features).all():
        raise ValueError("the feature bank holds NaN or infinite values")
    offsets = np.cumsum([0, *sizes.tolist()])
    for level, (label_map, size) in enumerate(zip(labels, sizes)):
        if label_map.min() < -1 or label_map.max() >= size:
            raise ValueError(
                f"level {level}: labels span {label_map.min()}..{label_map.max()}, the level has {size} regions"
            )
    return labels, [np.asarray(features[offsets[i] : offsets[i + 1]], np.float32) for i in range(len(sizes))]


class AccumulatorNode(Node):
    DEFAULTS = {
        "map": "",  # the prior Gaussian map (INRIA PLY)
        "store": "{run_dir}/store",
        "views": "{run_dir}/views",
        "method": "outlangsplat",
        "regions_in": "ipc://{run_dir}/regions.sock",
        "observations_out": "ipc://{run_dir}/observations.sock",
        "diagnostics": "",
        "topic_regions": "regions",
        "topic_observations": "observations",
        "hwm": 4,
    }

    def run(self, stop: threading.Event) -> int:
        from ..aggregate import ObservationStore  # heavy imports here: the launcher imports node classes
        from ..pipeline.offline import add_view, method
        from ..pipeline.views import save_view
        from ..scene import read_ply

        p = self.params
        chosen = method(p["method"])
        gaussians = read_ply(p["map"])
        store = ObservationStore(p["store"], len(gaussians))
        names = set(store.names())
        encoder_file = Path(p["store"]) / "encoder.txt"
        encoder = encoder_file.read_text() if encoder_file.exists() else None
        if names:
            log.info("resuming: %d views already in %s", len(names), p["store"])
        stats = NodeStats()
        seqs = SequenceCounter()
        sub = Subscriber(self.context, [p["regions_in"]], [p["topic_regions"]], hwm=p["hwm"])
        pub = Publisher(self.context, p["observations_out"], bind=True, hwm=100)
        diag = Diagnostics(self.context, p["diagnostics"], self.name) if p["diagnostics"] else None
        try:
            while not stop.is_set():
                batch = sub.drain(200)
                stats.count("received", len(batch))
                for _, message in batch:
                    if isinstance(message, EndOfStream):
                        pub.send(p["topic_observations"], seqs.stamp(message))
                        continue
                    if not isinstance(message, RegionFeatures):
                        stats.count("bad_messages")
                        log.warning("unexpected %s on %s: dropped", type(message).__name__, p["topic_regions"])
                        continue
                    start = time.perf_counter()
                    duplicate = message.name in names
                    kept = 0
                    if not duplicate:
                        try:
                            if encoder is not None and message.encoder != encoder:
                                raise ValueError(
                                    f"encoder {message.encoder!r}, but this run's store holds {encoder!r} features"
                                )
                            camera = camera_of(message)
                            label_maps, bank = split_bank(message)
                        except ValueError as exc:
                            stats.count("bad_messages")
                            log.warning("view %s (seq %d) dropped: %s", message.name, message.seq, exc)
                            continue
                        if encoder is None:
                            encoder = message.encoder
                            encoder_file.write_text(encoder)
                        save_view(p["views"], len(store), camera, message.image)
                        kept = int(add_view(gaussians, camera, label_maps, bank, chosen, store)["kept"])
                        names.add(message.name)
                    pub.send(
                        p["topic_observations"],
                        seqs.stamp(
                            ObservationsAdded(
                                stamp_ns=message.stamp_ns,
                                frame_id=message.frame_id,
                                name=message.name,
                                source_seq=message.source_seq,
                                observations=kept,
                                gaussians=len(gaussians),
                                views_in_store=len(names),
                                duplicate=duplicate,
                            )
                        ),
                    )
                    stats.count("published")
                    stats.count("duplicates" if duplicate else "views_added")
                    stats.handled(message.stamp_ns, time.perf_counter() - start)
                if diag is not None:
                    diag.beat(
                        0,
                        f"{len(names)} views in the store",
                        stats.with_sockets(sub.stats, queue_depth=len(batch), views=len(names)),
                    )
            return 130
        finally:
            for socket in (sub, pub, diag):
                if socket is not None:
                    socket.close()
