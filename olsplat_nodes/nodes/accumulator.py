"""accumulator: ``RegionFeatures`` -> per-view Gaussian observations in the store -> ``ObservationsAdded``.

Owns the prior Gaussian map and the method's settings: ``method`` and any of the method's
parameters (``tau_d``, ``q_min``, ``beta``, ``topk_max``, ... ``method.MethodParams``) are this
node's parameters; the resolved settings go into the store's manifest, which the refiner
reads, so the two never disagree. A store made with other settings is refused at start.

Per view: check the message against itself (label maps vs image size, regions vs feature rows,
one encoder for the whole run), run the method's per-view step (``method.add_view``), save the
photo and camera (``aggregate.views``) and append to the observation store; only then
acknowledge. A view already in the store (by name) is acknowledged again without being added
twice, so a restarted node or a re-sent frame never double-counts. ``EndOfStream`` is forwarded
on the observations topic after the views before it.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass, replace

from olsplat_msgs import EndOfStream, ObservationsAdded, RegionFeatures

from ..errors import OlsplatInputError
from ..method import MethodParams
from ..params import ParameterError
from ..transport import Diagnostics, Publisher, Subscriber
from .base import Node
from .convert import view_of

log = logging.getLogger(__name__)


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

    @classmethod
    def validate(cls, params: Params, where: str) -> None:
        from ..method import check_store, method_params_of

        method = method_params_of(params).resolve(where)  # a known method, values in range
        try:
            check_store(params.store, method)  # a resumed run keeps the settings its store was made with
        except OlsplatInputError as exc:
            raise ParameterError(f"{where}: {exc}") from exc

    def setup(self) -> None:
        from ..aggregate import ObservationStore  # heavy imports here: the launcher imports node classes
        from ..method import claim_store, method_params_of
        from ..scene import read_ply

        p = self.params
        self.limit_threads(p.threads)
        self.method = method_params_of(p).resolve()
        self.gaussians = read_ply(p.map)
        self.manifest = claim_store(p.store, self.method)
        self.store = ObservationStore(p.store, len(self.gaussians), writer=True)
        self.names = set(self.store.names())
        if self.names:
            log.info("resuming: %d views already in %s", len(self.names), p.store)
        limit = int(p.max_message_mb * 2**20)
        self.sub = self.own(Subscriber(self.context, [p.regions_in], [p.topic_regions], hwm=p.hwm, max_bytes=limit))
        self.pub = self.own(Publisher(self.context, p.observations_out, bind=True, hwm=100))
        self.diag = self.own(Diagnostics(self.context, p.diagnostics, self.name)) if p.diagnostics else None

    def spin(self) -> int | None:
        p = self.params
        batch = self.sub.drain(200)
        self.stats.count("received", len(batch))
        for _, message in batch:
            if isinstance(message, EndOfStream):
                self.publish(self.pub, p.topic_observations, message)
            elif isinstance(message, RegionFeatures):
                self._add(message)
            else:
                self.unexpected(message, p.topic_regions)
        if self.diag is not None:
            values = self.stats.with_sockets(self.sub.stats, queue_depth=len(batch), views=len(self.names))
            self.diag.beat(0, f"{len(self.names)} views in the store", values)
        return None

    def _add(self, message: RegionFeatures) -> None:
        from ..aggregate import save_view
        from ..method import add_view, write_manifest

        start = time.perf_counter()
        duplicate = message.name in self.names
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
                self.manifest = replace(self.manifest, encoder=message.encoder, feature_dim=int(bank[0].shape[1]))
                write_manifest(self.params.store, self.manifest)
            save_view(self.params.views, len(self.store), camera, image)
            kept = int(add_view(self.gaussians, camera, label_maps, bank, self.method, self.store)["kept"])
            self.names.add(message.name)
        added = ObservationsAdded(
            stamp_ns=message.stamp_ns,
            frame_id=message.frame_id,
            name=message.name,
            source_seq=message.source_seq,
            observations=kept,
            gaussians=len(self.gaussians),
            views_in_store=len(self.names),
            duplicate=duplicate,
        )
        self.publish(self.pub, self.params.topic_observations, added)
        self.stats.count("duplicates" if duplicate else "views_added")
        self.stats.handled(message.stamp_ns, time.perf_counter() - start)
