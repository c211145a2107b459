"""A slow region encoder does not let memory grow without bound: frames published faster than it
encodes are dropped (by the small high-water marks between ingest and encoder, and by the
encoder's latest-wins choice among what is queued), the drops are counted in its heartbeats,
and the newest frame is still encoded."""

from __future__ import annotations

import pytest

from olsplat_msgs import EndOfStream, RegionFeatures
from olsplat_nodes.nodes.region_encoder import RegionEncoderNode
from olsplat_nodes.transport import Publisher
from tests.helpers import every, wait_for

from .conftest import Heartbeats, NodeThread, Tap, image_frame

pytestmark = pytest.mark.timeout(120)
BURST = 40


def test_slow_encoder_drops_and_counts_frames_and_still_encodes_the_last(ctx, sockdir, tiny_camera):
    camera, image = tiny_camera  # 320 x 240; the shipped encoder takes about a second per frame here
    # the sender is what ingest uses for a live camera: a PUB with a high-water mark of 4 frames
    frames = Publisher(ctx, f"ipc://{sockdir}/frames.sock", bind=True, hwm=4)
    beats = Heartbeats(ctx)
    regions = Tap(ctx, f"ipc://{sockdir}/regions.sock", ["regions"])
    node = RegionEncoderNode(
        "region_encoder",
        {
            "latest_wins": True,
            "hwm": 4,
            "frames_in": f"ipc://{sockdir}/frames.sock",
            "regions_out": f"ipc://{sockdir}/regions.sock",
            "diagnostics": beats.endpoint,
        },
    )
    burst = [image_frame(camera, image, seq=i + 1, name=f"f{i:03d}.jpg") for i in range(BURST)]
    try:
        with NodeThread(node) as running:
            wait_for(
                lambda: regions.got(EndOfStream),
                20,
                "the encoder to forward EndOfStream",
                step=every(0.1, lambda: frames.send("frames", EndOfStream(frame_id="sync", source="test"))),
            )
            for frame in burst:  # as fast as possible: nothing waits for the encoder
                frames.send("frames", frame)
            # the sender's own queue may have been full when the last frame went out (PUB drops
            # what does not fit); a camera keeps sending, so the newest frame comes again
            last = burst[-1].name
            wait_for(
                lambda: last in [m.name for m in regions.got(RegionFeatures)],
                30,
                f"the encoding of {last}",
                step=every(0.5, lambda: frames.send("frames", burst[-1])),
            )
            encoded = sorted({m.name for m in regions.of_type(RegionFeatures)})
            values = beats.wait(
                "region_encoder",
                lambda v: v.get("published", 0) >= len(regions.of_type(RegionFeatures)),
                10,
                "the last encoding counted",
            )
            running.assert_running()
        # every frame of the burst was either encoded or counted as a drop: skipped by latest-wins
        # (`dropped`) or lost between the sockets (`gaps` in seq); the queue never held the burst
        assert len(encoded) <= 8, encoded
        assert values["dropped"] + values["gaps"] >= BURST - len(encoded), values
        assert values["gaps"] > 0, values
        assert values["received"] < BURST, values  # most of the burst never reached the node's memory
        assert regions.undecodable == []
    finally:
        for sock in (frames, beats, regions):
            sock.close()
