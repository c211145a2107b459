"""The 24 real photos of ../shared/data/caliterra as a ROS 2 bag (written here with rosbags'
Writer: their JPEG bytes, the exif_folder source's pose priors as /tf) replay through the bag
source as the exif_folder source gives them: same names, stamps, bytes, pixels, K and poses."""

from __future__ import annotations

import numpy as np
import pytest

from olsplat_nodes.scene.camera import k_to_opencv
from olsplat_nodes.sources import open_source
from olsplat_nodes.sources.replay_log import read_replay

from ..conftest import SHARED_DATA
from ..promised import skip_unless_ci
from .bags import LINK_FROM_OPTICAL, camera_info, compressed, tf_message, transform, write_bag


@pytest.fixture(scope="module")
def photos():
    shared = SHARED_DATA / "caliterra"
    if not shared.is_dir():
        skip_unless_ci("shared data", f"the shared real photos are absent ({shared})")
    return list(open_source({"source_kind": "exif_folder", "source": str(shared), "fast": True}))


@pytest.mark.parametrize(("chain", "storage"), [("optical", "mcap"), ("link", "sqlite3")])
def test_real_photos_replay_through_a_bag_as_the_exif_source_gives_them(tmp_path, photos, chain, storage):
    messages = []
    if chain == "link":  # map -> camera_link on /tf, camera_link -> camera_optical_frame on /tf_static
        link = transform(photos[0].stamp_ns, "camera_link", "camera_optical_frame", LINK_FROM_OPTICAL)
        messages.append(("/tf_static", photos[0].stamp_ns, tf_message(link)))
    for frame in photos:
        stamp, camera = frame.stamp_ns, frame.camera
        pose = (
            camera.world_from_camera @ np.linalg.inv(LINK_FROM_OPTICAL) if chain == "link" else camera.world_from_camera
        )
        child = "camera_link" if chain == "link" else "camera_optical_frame"
        messages += [
            ("/tf", stamp, tf_message(transform(stamp, "map", child, pose))),
            (
                "/camera/camera_info",
                stamp,
                camera_info(stamp, camera.width, camera.height, K=k_to_opencv(camera.K), D=[0.0] * 5),
            ),
            ("/camera/image/compressed", stamp, compressed(stamp, frame.jpeg)),
        ]
    bag = write_bag(
        tmp_path / "caliterra_bag", messages, storage=storage, custom={"olsplat.frame_names": [f.name for f in photos]}
    )
    frames = list(read_replay(bag))
    assert [f.name for f in frames] == [f.name for f in photos] and len(frames) == 24
    for got, want in zip(frames, photos, strict=True):
        assert got.stamp_ns == want.stamp_ns and got.jpeg == want.jpeg
        np.testing.assert_array_equal(got.image, want.image)
        np.testing.assert_array_equal(got.camera.K, want.camera.K)
        np.testing.assert_allclose(got.camera.world_from_camera, want.camera.world_from_camera, atol=1e-9)
        assert (got.camera.width, got.camera.height, got.camera.dist.size) == (1000, 750, 0)
