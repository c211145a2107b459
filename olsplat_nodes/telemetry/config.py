"""Parameters of the flight-controller pose source (launch-file ``params``, typed)."""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Literal

import numpy as np

from .pose import CameraMount


@dataclass(frozen=True)
class TelemetryConfig:
    url: str = ""  # serial device or pyserial URL: "/dev/ttyACM0", "loop://", "socket://HOST:PORT"
    baudrate: int = 57600
    dialect: str = "all"  # pymavlink dialect the checksums are verified with
    attitude: Literal["ATTITUDE", "ATTITUDE_QUATERNION"] = "ATTITUDE"  # which attitude message to use
    position: Literal["local", "global"] = "local"  # LOCAL_POSITION_NED, or GLOBAL_POSITION_INT around `reference`
    reference: tuple[float, float, float] | None = (
        None  # (lat deg, lon deg, alt m AMSL) of the world origin; None = first fix
    )
    mount_rpy_deg: tuple[float, float, float] = (
        0.0,
        -90.0,
        0.0,
    )  # camera-body angles w.r.t. the vehicle (default nadir)
    mount_matrix: tuple[float, ...] | None = (
        None  # 9 numbers, row-major body_from_camera (OpenCV axes); overrides the angles
    )
    lever_arm_m: tuple[float, float, float] = (0.0, 0.0, 0.0)  # camera centre in body FRD, metres
    tolerance_s: float = 0.1  # a frame needs a sample of each track this close on both sides
    max_wait_s: float = 1.0  # a frame still waiting for a later sample after this long (host clock) is rejected
    buffer_len: int = 1000  # samples kept per track
    clock: Literal["receive", "system_time"] = "receive"  # boot time -> host time rule (matching.py)
    clock_window_s: float = 10.0  # "receive": sliding window of the minimum-delay estimate

    def __post_init__(self) -> None:
        for name in ("reference", "mount_rpy_deg", "mount_matrix", "lever_arm_m"):
            value = getattr(self, name)
            if value is not None:  # YAML gives lists
                object.__setattr__(self, name, tuple(float(v) for v in value))
        if self.attitude not in ("ATTITUDE", "ATTITUDE_QUATERNION"):
            raise ValueError(f"attitude must be 'ATTITUDE' or 'ATTITUDE_QUATERNION', got attitude={self.attitude!r}")
        if self.position not in ("local", "global"):
            raise ValueError(f"position must be 'local' or 'global', got position={self.position!r}")
        if self.reference is not None and len(self.reference) != 3:
            raise ValueError(f"reference must be (lat_deg, lon_deg, alt_m), got reference={self.reference!r}")
        if len(self.mount_rpy_deg) != 3 or (self.mount_matrix is not None and len(self.mount_matrix) != 9):
            raise ValueError(
                f"need 3 mount angles and 9 matrix entries, got mount_rpy_deg={self.mount_rpy_deg!r}, "
                f"mount_matrix={self.mount_matrix!r}"
            )
        if not (self.tolerance_s > 0 and self.max_wait_s >= 0 and self.baudrate > 0):
            raise ValueError(
                f"need tolerance_s > 0, max_wait_s >= 0, baudrate > 0, got {self.tolerance_s}, {self.max_wait_s}, "
                f"{self.baudrate}"
            )
        self.mount()  # a bad rotation or lever arm fails here, at configuration time

    @classmethod
    def from_params(cls, params: dict) -> TelemetryConfig:
        """From a launch file's dict; unknown keys raise ValueError naming them."""
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(params) - known)
        if unknown:
            raise ValueError(f"unknown telemetry parameters {unknown}; known: {sorted(known)}")
        return cls(**params)

    def mount(self) -> CameraMount:
        if self.mount_matrix is not None:
            return CameraMount(np.reshape(self.mount_matrix, (3, 3)), np.asarray(self.lever_arm_m))
        return CameraMount.from_angles(*self.mount_rpy_deg, lever_arm_m=self.lever_arm_m)
