"""The depthai source without a device: real discovery (none here), the retry loop, calibration ->
Camera with a real ``depthai.CalibrationHandler``, and the reconnect/pose logic behind a stand-in
device stream (the only part that is not the real library: there is no camera on this machine).

Not covered (needs an OAK device): ``open_device_stream`` (pipeline build, BGR frames, the real
timestamps and sequence numbers, the per-frame ImgTransformation check) and a real unplug/replug."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from olsplat_nodes.sources import (  # depthai itself is imported only when a device is used
    ERROR,
    OK,
    DepthAISource,
    camera_from_calibration,
    crop_intrinsics,
    discover_devices,
    open_source,
    trim_distortion,
)
from olsplat_nodes.telemetry import FlightControllerPoses, TelemetryConfig
from tests.helpers import wait_for

dai = pytest.importorskip("depthai")


@pytest.fixture(scope="module")
def no_device():
    if discover_devices():
        pytest.skip("a DepthAI device is attached: the no-device tests do not apply")


def test_no_device_is_a_clean_error_and_discovery_is_retried(no_device):
    source = open_source({"source_kind": "depthai", "depthai_retry_s": 0.1})
    try:
        wait_for(lambda: source.stats["discovery_attempts"] >= 3, 20, "three discovery attempts")
        level, message = source.status()
        assert level == ERROR and message.startswith("no DepthAI device found") and "retrying every 0.1 s" in message
        assert source.read(0.05) is None and not source.done and source.stats["connects"] == 0
    finally:
        start = time.monotonic()
        source.close()
        assert time.monotonic() - start < 5


def test_a_named_device_that_is_absent(no_device):
    with DepthAISource(device="1844301011B546F500", retry_s=0.1) as source:
        wait_for(
            lambda: source.stats["discovery_attempts"] >= 1 and source.status()[1].startswith("no DepthAI"),
            20,
            "a status",
        )
        assert "1844301011B546F500" in source.status()[1]


def calibration(model=None, dist=(0.1, -0.05, 0.001, 0.002, 0.01)):
    handler = dai.CalibrationHandler()
    handler.setCameraIntrinsics(
        dai.CameraBoardSocket.CAM_A, [[3000.0, 0, 2028.0], [0, 3000.0, 1520.0], [0, 0, 1]], 4056, 3040
    )
    handler.setDistortionCoefficients(dai.CameraBoardSocket.CAM_A, list(dist) + [0.0] * (14 - len(dist)))
    handler.setCameraType(dai.CameraBoardSocket.CAM_A, model or dai.CameraModel.Perspective)
    return handler


def test_calibration_to_camera():
    camera = camera_from_calibration(calibration(), "CAM_A", 1280, 720)
    s = 1280 / 4056  # width decides: 3040 * s = 959 rows, cropped to 720 (CROP keeps the aspect ratio)
    np.testing.assert_allclose(
        camera.K, [[3000 * s, 0, 2028 * s], [0, 3000 * s, 1520 * s - (3040 * s - 720) / 2], [0, 0, 1]]
    )
    np.testing.assert_allclose(camera.dist, [0.1, -0.05, 0.001, 0.002, 0.01], rtol=1e-6)  # float32 in the handler
    assert (camera.width, camera.height) == (1280, 720) and np.array_equal(camera.world_from_camera, np.eye(4))
    # same aspect ratio: equal to depthai's own scaling
    same = camera_from_calibration(calibration(), dai.CameraBoardSocket.CAM_A, 1352, 1013.333333 and 1013)
    ours = crop_intrinsics(
        np.asarray(calibration().getDefaultIntrinsics(dai.CameraBoardSocket.CAM_A)[0]), (4056, 3040), (2028, 1520)
    )
    theirs = calibration().getCameraIntrinsics(dai.CameraBoardSocket.CAM_A, 2028, 1520, keepAspectRatio=False)
    np.testing.assert_allclose(ours, theirs, rtol=1e-6)
    assert same.model == "OPENCV_RATIONAL" or len(same.dist) == 5
    with pytest.raises(ValueError, match="Fisheye"):
        camera_from_calibration(calibration(dai.CameraModel.Fisheye), "CAM_A", 640, 480)
    with pytest.raises(RuntimeError):  # no calibration for that socket: depthai's own error
        camera_from_calibration(calibration(), "CAM_B", 640, 400)


def test_trim_distortion():
    assert len(trim_distortion(np.zeros(14))) == 0
    np.testing.assert_array_equal(trim_distortion([1, 2, 3, 4, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0]), [1, 2, 3, 4])
    assert len(trim_distortion([1, 0, 0, 0, 0, 0.5] + [0] * 8)) == 8
    assert len(trim_distortion([0] * 13 + [1])) == 14


class StandInDevice:
    """What ``open_device_stream`` returns, without hardware: frames, then an unplug (an error)."""

    def __init__(self, frames_per_connect: int, stamps=None):
        self.connects = 0
        self.frames_per_connect = frames_per_connect
        self.stamps = stamps
        self.release = threading.Event()

    def discover(self, device):
        return ["standin-device"]

    def open(self, info, socket, width, height, fps, frame_timeout_s, closing):
        self.connects += 1
        camera = camera_from_calibration(calibration(), socket, width, height, name=info)

        def frames():
            for seq in range(self.frames_per_connect):
                stamp = self.stamps[seq] if self.stamps is not None else time.monotonic_ns()
                yield seq, stamp, np.full((height, width, 3), seq, np.uint8)
                time.sleep(0.01)
            self.release.wait(5)
            raise RuntimeError("X_LINK_ERROR (unplugged)")

        return camera, frames()


def test_unplug_is_reported_and_the_device_is_picked_up_again():
    device = StandInDevice(3)
    pose = np.eye(4)
    pose[:3, 3] = [1, 2, 3]
    with DepthAISource(
        width=64, height=48, retry_s=0.05, world_from_camera=pose, discover=device.discover, open_stream=device.open
    ) as source:
        names = []
        wait_for(
            lambda: (f := source.read(0.05)) is not None and names.append(f) is None and len(names) == 3,
            10,
            "three frames",
        )
        assert source.status() == (OK, "streaming from DepthAI device standin-device (64x48 at 10 fps)")
        device.release.set()  # unplug
        wait_for(lambda: source.stats["disconnects"] >= 1, 10, "the disconnect")
        wait_for(lambda: device.connects >= 2, 10, "a reconnect")
        wait_for(
            lambda: (f := source.read(0.05)) is not None and names.append(f) is None and len(names) == 4,
            10,
            "a frame after the reconnect",
        )
        assert len({f.name for f in names}) == 4  # names stay unique though the device restarts its sequence numbers
        frame = names[0]
        assert frame.image.shape == (48, 64, 3) and np.array_equal(frame.camera.world_from_camera, pose)
        assert abs(frame.stamp_ns - time.time_ns()) < 5e9  # wall clock
        assert frame.camera.K[0, 0] == pytest.approx(3000 * max(64 / 4056, 48 / 3040))


def test_poses_come_from_telemetry_and_frames_without_one_are_dropped():
    base = time.monotonic_ns()
    ms = 1_000_000
    poses = FlightControllerPoses(TelemetryConfig(tolerance_s=0.1, max_wait_s=0.2), clock=time.monotonic_ns)
    for t in range(0, 1001, 20):  # samples over 1 s of autopilot time, received without delay
        host = base + t * ms
        poses.add_message(mavlink.MAVLink_attitude_message(10_000 + t, 0.0, 0.0, 0.5, 0, 0, 0), host)
        poses.add_message(mavlink.MAVLink_local_position_ned_message(10_000 + t, t / 1000.0, 0.0, -50.0, 1, 0, 0), host)
    stamps = [base - 300 * ms, base + 500 * ms, base + 1100 * ms]  # before the samples, inside, after (never bracketed)
    device = StandInDevice(3, stamps)
    with DepthAISource(
        width=64, height=48, retry_s=0.05, poses=poses, discover=device.discover, open_stream=device.open
    ) as source:
        got = []

        def step():
            frame = source.read(0.05)
            if frame is not None:
                got.append(frame)
            return source.stats["frames_without_pose"] >= 2

        wait_for(step, 10, "two frames rejected for want of a pose")  # the last one after max_wait_s
        assert len(got) == 1 and source.stats["frames"] == 1
        np.testing.assert_allclose(
            got[0].camera.world_from_camera[:3, 3], [0.0, 0.5, 50.0], atol=1e-9
        )  # ENU of NED (0.5, 0, -50)
