"""A Luxonis OAK camera through ``depthai`` (3.x API): live frames, device calibration, reconnects.

One background thread owns the device: it looks for a device (``dai.Device.getAllAvailableDevices``)
every ``retry_s`` while none is found (status ERROR "no DepthAI device found"), opens it, reads
its calibration, builds a pipeline with one ``dai.node.Camera`` output (``width`` × ``height``
BGR at ``fps``, resize mode CROP) and moves frames to the reader. When the device goes away
(unplugged, crashed, no frame for ``frame_timeout_s``) it closes everything, reports ERROR
"DepthAI device lost: ..." and starts looking again. Nothing of this raises to the node.

Stamps: ``ImgFrame.getTimestamp()`` is the host-synced acquisition time on the host's steady
clock (``time.monotonic_ns`` on Linux); it is used as is to look up the flight controller's pose
(whose reader stamps receptions with the same clock) and converted to wall-clock ns for the
frame's ``stamp_ns``. The sequence number is the device's ``getSequenceNum()``.

Intrinsics: ``camera_from_calibration`` turns ``device.readCalibration()`` (K at the calibration
size, OpenCV rational-polynomial distortion, 14 coefficients) into a ``scene.Camera`` for the
requested output size, cropping the calibrated field of view to the output's aspect ratio and
scaling (DepthAI's CROP resize mode). Where the first frame carries a valid
``ImgTransformation`` whose intrinsic matrix differs, DepthAI's own per-frame matrix wins (logged).

Pose: from a ``FlightControllerPoses`` (frames wait, bounded by ``max_pending``, until the
telemetry brackets them; frames the telemetry rejects are counted in ``frames_without_pose`` and
dropped), else the fixed ``world_from_camera``.
"""

from __future__ import annotations

import collections
import datetime as dt
import logging
import threading
import time
from collections.abc import Callable, Iterator
from typing import cast

import numpy as np

from ..scene import Camera
from .base import ERROR, OK, WARN, Source, SourceFrame

log = logging.getLogger(__name__)

NO_DEVICE = "no DepthAI device found"


def crop_intrinsics(K, calibrated_size: tuple[int, int], size: tuple[int, int]) -> np.ndarray:
    """[3, 3] intrinsics of a centre crop to ``size``'s aspect ratio, then a scale to ``size``.

    K               # [3, 3] at calibrated_size = (width, height) pixels
    Pixel centres at +0.5 on both sides: a point at continuous coordinate u maps to s * u - offset.
    """
    (w0, h0), (w, h) = calibrated_size, size
    s = max(w / w0, h / h0)
    ox, oy = (w0 * s - w) / 2.0, (h0 * s - h) / 2.0
    out = np.asarray(K, np.float64).copy()
    out[0, :] *= s
    out[1, :] *= s
    out[0, 2] -= ox
    out[1, 2] -= oy
    return out


def trim_distortion(coefficients) -> np.ndarray:
    """OpenCV coefficients without trailing zeros, to the shortest length OpenCV accepts (0, 4, 5, 8, 12, 14)."""
    d = np.asarray(coefficients, np.float64).reshape(-1)
    nonzero = np.flatnonzero(d)
    need = int(nonzero[-1]) + 1 if len(nonzero) else 0
    length = next(n for n in (0, 4, 5, 8, 12, 14) if n >= need)
    return d[:length].copy()


def camera_from_calibration(
    calibration, socket, width: int, height: int, world_from_camera=None, name: str = "oak"
) -> Camera:
    """A ``depthai.CalibrationHandler`` -> ``scene.Camera`` for a ``width`` × ``height`` CROP output.

    Only the perspective (OpenCV) lens model is supported: a fisheye calibration raises ValueError.
    ``world_from_camera`` defaults to the identity (the pose is set per frame).
    """
    import depthai as dai

    if isinstance(socket, str):
        socket = getattr(dai.CameraBoardSocket, socket)
    model = calibration.getDistortionModel(socket)
    if model != dai.CameraModel.Perspective:
        raise ValueError(f"camera {socket.name}: lens model {model.name} is not supported (only Perspective)")
    K, w0, h0 = calibration.getDefaultIntrinsics(socket)
    dist = trim_distortion(calibration.getDistortionCoefficients(socket))
    models = {0: "PINHOLE", 4: "OPENCV", 8: "FULL_OPENCV"}
    return Camera(
        name,
        width,
        height,
        crop_intrinsics(K, (w0, h0), (width, height)),
        np.eye(4) if world_from_camera is None else world_from_camera,
        dist,
        models.get(len(dist), "OPENCV_RATIONAL"),
    )


def discover_devices(device: str = "") -> list:
    """DepthAI devices visible now (``depthai.DeviceInfo``), optionally only the one whose id or name is ``device``."""
    import depthai as dai

    infos = list(dai.Device.getAllAvailableDevices())
    return [i for i in infos if not device or device in (i.getDeviceId(), i.name)]


def _stamp_ns(delta: dt.timedelta) -> int:
    return (delta.days * 86_400 + delta.seconds) * 1_000_000_000 + delta.microseconds * 1000


def open_device_stream(
    info, socket: str, width: int, height: int, fps: float, frame_timeout_s: float, closing: threading.Event
) -> tuple[Camera, Iterator[tuple[int, int, np.ndarray]]]:
    """Open ``info``'s camera: (Camera with identity pose, iterator of (seq, steady-clock ns, BGR image)).

    The iterator raises RuntimeError when the device stops delivering, and closes the device
    when it ends or is closed. Needs a device: not exercised by the tests (see README.md).
    """
    import depthai as dai

    device = dai.Device(info)
    try:
        camera = camera_from_calibration(device.readCalibration(), socket, width, height, name=info.getDeviceId())
        pipeline = dai.Pipeline(device)
        node = pipeline.create(dai.node.Camera).build(getattr(dai.CameraBoardSocket, socket))
        output = node.requestOutput((width, height), dai.ImgFrame.Type.BGR888i, dai.ImgResizeMode.CROP, fps)
        queue = output.createOutputQueue(maxSize=4, blocking=False)
        pipeline.start()
    except BaseException:
        device.close()
        raise

    def frames():
        checked = False
        last = time.monotonic()
        try:
            while not closing.is_set():
                if not pipeline.isRunning() or device.isClosed():
                    raise RuntimeError("the pipeline stopped")
                message = cast("dai.ImgFrame | None", queue.tryGet())  # the queue of an ImgFrame output
                if message is None:
                    if time.monotonic() - last > frame_timeout_s:
                        raise RuntimeError(f"no frame for {frame_timeout_s:g} s")
                    time.sleep(0.005)
                    continue
                last = time.monotonic()
                if not checked:
                    checked = True
                    transformation = message.getTransformation()
                    if transformation.isValid():
                        K = np.asarray(transformation.getIntrinsicMatrix(), np.float64)
                        if not np.allclose(K, camera.K, rtol=1e-3, atol=0.5):
                            log.warning(
                                "frame intrinsics %s differ from the calibration's %s: using the frame's",
                                K.tolist(),
                                camera.K.tolist(),
                            )
                            camera.K = K
                yield message.getSequenceNum(), _stamp_ns(message.getTimestamp()), message.getCvFrame()
        finally:
            try:
                pipeline.stop()
            finally:
                device.close()

    return camera, frames()


class DepthAISource(Source):
    """Live frames of an OAK camera (see the module docstring). Never raises for a missing device."""

    kind = "depthai"
    live = True

    def __init__(
        self,
        device: str = "",
        socket: str = "CAM_A",
        width: int = 1280,
        height: int = 720,
        fps: float = 10.0,
        *,
        retry_s: float = 3.0,
        frame_timeout_s: float = 3.0,
        poses=None,
        world_from_camera=None,
        max_pending: int = 30,
        discover: Callable[[str], list] = discover_devices,
        open_stream: Callable = open_device_stream,
    ):
        super().__init__()
        import depthai as dai

        if not hasattr(dai.CameraBoardSocket, socket):
            raise ValueError(f"depthai_socket must name a dai.CameraBoardSocket (CAM_A, CAM_B, ...), got {socket!r}")
        if width <= 0 or height <= 0 or fps <= 0 or retry_s <= 0:
            raise ValueError(
                f"need positive width, height, fps and retry_s, got {width}x{height} at {fps} fps, retry_s={retry_s}"
            )
        self.device, self.socket, self.width, self.height, self.fps = (
            device,
            socket,
            int(width),
            int(height),
            float(fps),
        )
        self.retry_s, self.frame_timeout_s, self.max_pending = float(retry_s), float(frame_timeout_s), int(max_pending)
        self.poses = poses
        self.world_from_camera = np.eye(4) if world_from_camera is None else np.asarray(world_from_camera, np.float64)
        self._discover, self._open = discover, open_stream
        self.counts.update(
            discovery_attempts=0,
            connects=0,
            disconnects=0,
            device_frames=0,
            frames_without_pose=0,
            dropped_queue=0,
            dropped_pending=0,
            device_seq_gaps=0,
        )
        self._lock = threading.Lock()
        self._arrived = threading.Condition(self._lock)
        self._queue: collections.deque = (
            collections.deque()
        )  # (seq, steady ns, BGR image, Camera) from the device thread
        self._pending: collections.deque = collections.deque()  # frames waiting for a pose
        self._status = (WARN, "looking for a DepthAI device")
        self._closing = threading.Event()
        self._thread = threading.Thread(target=self._run, name="depthai-device", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ device thread
    def _set_status(self, level: int, message: str) -> None:
        with self._lock:
            if (level, message) != self._status:
                (log.error if level >= ERROR else log.info)("depthai: %s", message)
            self._status = (level, message)

    def _run(self) -> None:
        while not self._closing.is_set():
            try:
                self.counts["discovery_attempts"] += 1
                infos = self._discover(self.device)
                if not infos:
                    which = f" with id or name {self.device!r}" if self.device else ""
                    self._set_status(ERROR, f"{NO_DEVICE}{which}; retrying every {self.retry_s:g} s")
                else:
                    self._stream(infos[0])
            except Exception as exc:  # a device that fails while opening or streaming: report, retry
                self.counts["disconnects"] += 1
                self._set_status(
                    ERROR, f"DepthAI device lost: {type(exc).__name__}: {exc}; retrying every {self.retry_s:g} s"
                )
            self._closing.wait(self.retry_s)

    def _stream(self, info) -> None:
        device_id = getattr(info, "deviceId", "") or str(info)
        self._set_status(WARN, f"connecting to DepthAI device {device_id}")
        camera, frames = self._open(
            info, self.socket, self.width, self.height, self.fps, self.frame_timeout_s, self._closing
        )
        self.counts["connects"] += 1
        self._set_status(
            OK, f"streaming from DepthAI device {device_id} ({self.width}x{self.height} at {self.fps:g} fps)"
        )
        last_seq = None
        try:
            for seq, steady_ns, bgr in frames:
                self.counts["device_frames"] += 1
                if last_seq is not None and seq > last_seq + 1:
                    self.counts["device_seq_gaps"] += seq - last_seq - 1
                last_seq = seq
                with self._arrived:
                    if len(self._queue) >= 4:  # the reader is behind: latest wins
                        self._queue.popleft()
                        self.counts["dropped_queue"] += 1
                    self._queue.append((seq, steady_ns, bgr, camera))
                    self._arrived.notify_all()
        finally:
            close = getattr(frames, "close", None)
            if close is not None:
                close()
        if not self._closing.is_set():
            raise RuntimeError("the frame stream ended")

    # ------------------------------------------------------------------ reader side
    def read(self, timeout_s: float = 0.1) -> SourceFrame | None:
        deadline = time.monotonic() + max(timeout_s, 0.0)
        while True:
            if self.poses is not None:
                self.poses.poll(0.0)
            with self._lock:
                while self._queue:
                    self._pending.append(self._queue.popleft())
                    if len(self._pending) > self.max_pending:
                        self._pending.popleft()
                        self.counts["dropped_pending"] += 1
            frame = self._next_with_pose()
            if frame is not None:
                return frame
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            with self._arrived:
                if not self._queue:
                    self._arrived.wait(min(remaining, 0.01 if self.poses is not None else remaining))

    def _next_with_pose(self) -> SourceFrame | None:
        while self._pending:
            seq, steady_ns, bgr, camera = self._pending[0]
            if self.poses is None:
                pose = self.world_from_camera
            else:
                match = self.poses.lookup(steady_ns)
                if match.status == "wait":
                    return None
                if match.status == "rejected":
                    self._pending.popleft()
                    self.counts["frames_without_pose"] += 1
                    continue
                pose = match.world_from_camera
            self._pending.popleft()
            self.counts["frames"] += 1
            stamp_ns = steady_ns + (time.time_ns() - time.monotonic_ns())  # steady clock -> wall clock
            # names must stay unique across reconnects (the device restarts its sequence numbers)
            name = f"oak_{stamp_ns // 1_000_000}_{seq:06d}.jpg"
            frame_camera = Camera(name, camera.width, camera.height, camera.K, pose, camera.dist, camera.model)
            return SourceFrame(seq, stamp_ns, name, np.ascontiguousarray(bgr[..., ::-1]), frame_camera)
        return None

    @property
    def stats(self) -> dict[str, float]:
        out: dict[str, float] = dict(self.counts)
        out["pending_pose"] = len(self._pending)
        if self.poses is not None:
            out.update({f"telemetry_{k}": v for k, v in self.poses.stats.items()})
        return out

    def status(self) -> tuple[int, str]:
        with self._lock:
            level, message = self._status
        if self.poses is not None and self.poses.reader is not None and not self.poses.reader.stats.get("connected", 0):
            level, message = max(level, WARN), f"{message}; telemetry port {self.poses.config.url} not open"
        return level, message

    def close(self) -> None:
        self._closing.set()
        with self._arrived:
            self._arrived.notify_all()
        self._thread.join(timeout=self.frame_timeout_s + 2.0)
        if self.poses is not None:
            self.poses.close()
