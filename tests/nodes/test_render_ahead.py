"""The accumulator renders the next queued view while it observes the one in hand
(``render_ahead``, method/render_ahead.py): on real sockets, views sent in a burst are stored with
the observations the per-view step gives each alone, bit for bit, and the node's status counts
the renders it made ahead."""

from __future__ import annotations

import numpy as np
import pytest
import zmq

from olsplat_msgs import DiagnosticStatus, ObservationsAdded, encode
from tests.helpers import every, wait_for

from .conftest import Heartbeats, NodeThread, Tap, accumulator_params, image_frame, raw_socket, read_rgb, send

pytestmark = pytest.mark.timeout(240)


def test_views_queued_at_the_accumulator_are_rendered_ahead_and_stored_as_each_alone(ctx, sockdir, tmp_path, tiny):
    from olsplat_nodes.encoders.spec import encoder_from_spec
    from olsplat_nodes.method import named_method, view_observations
    from olsplat_nodes.method.render_ahead import RenderAhead
    from olsplat_nodes.nodes.accumulator import AccumulatorNode
    from olsplat_nodes.nodes.region_encoder import encode_frame
    from olsplat_nodes.regions import RegionConfig
    from olsplat_nodes.scene import read_colmap, read_ply
    from olsplat_nodes.storage import ObservationStore
    from olsplat_nodes.transport.convert import camera_of, split_bank

    scene, _ = tiny
    cameras = read_colmap(scene / "sparse" / "0")[:5]
    encoder, config = encoder_from_spec(), RegionConfig()
    frames = [encode_frame(image_frame(c, read_rgb(scene / "images" / c.name)), encoder, config) for c in cameras]
    regions = raw_socket(ctx, zmq.PUB, f"ipc://{sockdir}/regions.sock", bind=True)
    beats = Heartbeats(ctx)
    observations = Tap(ctx, f"ipc://{sockdir}/observations.sock", ["observations"])
    params = accumulator_params(scene, tmp_path, sockdir, beats)
    try:
        with NodeThread(AccumulatorNode("accumulator", params)) as running:
            if not RenderAhead.available():
                pytest.skip("numba's threading layer is not thread-safe here: nothing is rendered ahead")
            wait_for(  # the sockets joined: the first view in
                lambda: observations.got(ObservationsAdded),
                60,
                "the first view acknowledged",
                step=every(1.0, lambda: send(regions, encode(frames[0], "regions"))),
            )
            for frame in frames[1:]:  # the rest in one burst: they queue at the accumulator
                send(regions, encode(frame, "regions"))
            wait_for(
                lambda: max(m.views_in_store for m in observations.got(ObservationsAdded)) == len(frames),
                60,
                "every view stored",
            )

            def ahead_counted() -> list[DiagnosticStatus]:
                beats.poll(50)
                return [
                    s
                    for s in beats.of_type(DiagnosticStatus)
                    if s.node == "accumulator" and s.values.get("views") == len(frames) and "rendered_ahead" in s.values
                ]

            status = wait_for(ahead_counted, 30, "a status after the last view")[-1]
            running.assert_running()
    finally:
        regions.close()
        beats.close()
        observations.close()
    assert status.level == DiagnosticStatus.OK, status
    # the burst queued: each of its views after the first rendered ahead, while the one before it was observed
    ahead, unused = status.values["rendered_ahead"], status.values["rendered_ahead_unused"]
    assert ahead >= 2 and ahead + unused <= len(frames), status.values

    gaussians = read_ply(scene / "map" / "point_cloud.ply")
    method = named_method("outlangsplat")
    store = ObservationStore(tmp_path / "store", len(gaussians))
    assert store.names() == [f.name for f in frames]
    for i, frame in enumerate(frames):
        label_maps, bank = split_bank(frame)
        alone, stacked = view_observations(gaussians, camera_of(frame), label_maps, bank, method)[:2]
        stored, stored_bank = store.load(i)
        for field in ("gaussians", "strength", "offsets", "slots", "weights"):
            got, expected = getattr(stored, field), getattr(alone, field)
            np.testing.assert_array_equal(got, expected, err_msg=f"{frame.name} {field}")
        np.testing.assert_array_equal(np.asarray(stored_bank), stacked)
        assert len(alone) > 100
