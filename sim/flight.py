"""UAV flights over a town: lawnmower and orbit trajectories with nadir and oblique views.

A flight is a list of frames, each a true camera pose and a timestamp. Views are split
between a nadir lawnmower (half), an oblique lawnmower looking forward along its track
(a quarter) and an oblique orbit looking inwards across the town (a quarter); view centres
stay on the town. Oblique pitch is
measured from nadir (0 = straight down) and drawn in [30, 60] degrees per flight.
Timestamps advance at ``rate_hz`` from a fixed epoch, so a flight is bit-for-bit repeatable.
Another flight over the same town (``olsplat sim make --flight-seed``) turns the whole pattern
about the town's centre by ``turn_deg`` and names its frames with a ``name_prefix``.
World v2 (``world.FlightWorld``) varies the altitude over the flight (``altitude_profile``) and
tilts the nadir views; world v1 holds the altitude (with a GPS-grade wobble) and looks straight down.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from olsplat_nodes.scene import Camera, intrinsics, look_at

from .world import FlightWorld

EPOCH_NS = 1_767_225_600_000_000_000  # 2026-01-01T00:00:00Z: flights start here


@dataclass(frozen=True)
class FlightSpec:
    n_views: int
    width: int
    height: int
    fov_deg: float = 50.0  # horizontal field of view (a 35 mm-equivalent lens)
    altitude_m: float = 80.0  # above the ground, 60-120 m in the paper's data
    rate_hz: float = 1.0  # frames per second
    oblique_deg: tuple[float, float] = (30.0, 60.0)  # pitch range of oblique views, from nadir
    turn_deg: float = 0.0  # the pattern turned about the town's centre, counterclockwise seen from above
    name_prefix: str = ""  # frames are named f"{name_prefix}frame_NNNN.jpg"


@dataclass
class FlightFrame:
    camera: Camera  # true pose (OpenCV axes)
    stamp_ns: int
    kind: str  # "nadir", "oblique" or "orbit"


def _lawnmower(
    n: int, extent: float, altitudes: np.ndarray, pitch: float, rng
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """n (eye, target, up) on boustrophedon lines whose view centres cover [-extent, extent]^2,
    view i at ``altitudes[i]`` (metres, [>= n]).

    The camera looks ``pitch`` from nadir, forwards along its track; the point it looks at
    (not the drone) follows the lines, so oblique views stay on the town.
    """
    if n <= 0:
        return []
    lines = max(2, int(round(np.sqrt(n / 2))))
    per_line = int(np.ceil(n / lines))
    out: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    for k in range(lines):
        x = -extent + 2 * extent * k / (lines - 1)
        ys = np.linspace(-extent, extent, per_line)
        heading = np.array([0.0, 1.0, 0.0])
        if k % 2:
            ys, heading = ys[::-1], -heading
        for y in ys:
            altitude = altitudes[min(len(out), len(altitudes) - 1)]
            reach = altitude * np.tan(pitch)
            target = np.array([x, y, 0.0]) + np.r_[rng.normal(0, 0.5, 2), 0.0]  # GPS-grade wobble
            eye = target - heading * reach + np.array([0.0, 0.0, altitude + rng.normal(0, 0.5)])
            out.append((eye, target + heading * 1e-3, heading))
    return out[:n]


def _orbit(
    n: int, ring: float, altitudes: np.ndarray, pitch: float, rng
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """n views around the town looking inwards at points of a ring of radius ``ring``, view i at
    ``altitudes[i]`` (metres)."""
    start = rng.uniform(0, 2 * np.pi)
    out = []
    for i in range(n):
        altitude = altitudes[i]
        reach = altitude * np.tan(pitch)
        angle = start + 2 * np.pi * i / max(n, 1)
        outward = np.array([np.cos(angle), np.sin(angle), 0.0])
        target = ring * outward
        eye = target + outward * reach + np.array([0.0, 0.0, altitude])
        out.append((eye, target, np.array([0.0, 0.0, 1.0])))
    return out


def _turned(poses: list, turn_deg: float) -> list:
    """(kind, eye, target, up) poses, [3] vectors in metres, turned by ``turn_deg`` about the
    vertical axis through the town's centre (counterclockwise seen from above)."""
    t = np.radians(turn_deg)
    rotation = np.array([[np.cos(t), -np.sin(t), 0.0], [np.sin(t), np.cos(t), 0.0], [0.0, 0.0, 1.0]])
    return [(kind, rotation @ eye, rotation @ target, rotation @ up) for kind, eye, target, up in poses]


def _turned_extent(extent: float, turn_deg: float, size_m: float) -> float:
    """The lawnmowers' half-side (metres) so that their square, turned by ``turn_deg``, keeps its
    view centres on the town: a square of half-side e turned by t reaches e (|cos t| + |sin t|)
    along x and y, up to 1.41 e. That is on the town at the presets' altitudes and the default
    field of view (``extent`` unchanged), beyond it with a narrow field of view (shrunk to fit)."""
    t = np.radians(turn_deg)
    reach = extent * (abs(np.cos(t)) + abs(np.sin(t)))
    return extent * min(1.0, 0.5 * size_m / max(reach, 1e-9))


def altitude_profile(n: int, altitude_m: float, world: FlightWorld, rng: np.random.Generator | None) -> np.ndarray:
    """[n] camera altitude of each view (metres, before the GPS wobble): ``altitude_m`` for all
    (no draw) when ``world.altitude_span`` is 0; else a profile over the flight whose max - min is
    exactly ``altitude_span * altitude_m``, centred on ``altitude_m``:

    - "smooth": sum_j a_j cos(pi j t + phase_j) / j, j = 1..altitude_waves, t = 0..1 over the
      flight, a_j ~ N(0, 1), phase_j ~ U(0, 2 pi);
    - "climb": t plus that smooth profile at a quarter of its amplitude (a climb with wobbles).
    """
    if world.altitude_span <= 0 or n == 0:
        return np.full(n, altitude_m)
    if rng is None:
        raise ValueError("a varying altitude needs the flight world's generator")
    t = np.linspace(0.0, 1.0, n)
    j = np.arange(1, world.altitude_waves + 1)
    amplitudes, phases = rng.normal(0.0, 1.0, len(j)), rng.uniform(0.0, 2 * np.pi, len(j))
    smooth = (amplitudes / j * np.cos(np.pi * np.outer(t, j) + phases)).sum(1)
    if world.altitude_profile == "climb":
        smooth = t + 0.25 * smooth / max(np.ptp(smooth), 1e-9)
    elif world.altitude_profile != "smooth":
        raise ValueError(f"altitude_profile must be 'smooth' or 'climb', got {world.altitude_profile!r}")
    unit = (smooth - smooth.min()) / max(np.ptp(smooth), 1e-9) - 0.5  # max - min = 1, centred
    return altitude_m * (1.0 + world.altitude_span * unit)


def _tilted(pose: np.ndarray, tilt_deg: float, rng: np.random.Generator) -> np.ndarray:
    """[4, 4] world_from_camera turned about its centre by N(0, tilt_deg) about each horizontal
    world axis (a gimbal that does not quite hold nadir)."""
    ax, ay = np.radians(rng.normal(0.0, tilt_deg, 2))
    rx = np.array([[1.0, 0.0, 0.0], [0.0, np.cos(ax), -np.sin(ax)], [0.0, np.sin(ax), np.cos(ax)]])
    ry = np.array([[np.cos(ay), 0.0, np.sin(ay)], [0.0, 1.0, 0.0], [-np.sin(ay), 0.0, np.cos(ay)]])
    out = pose.copy()
    out[:3, :3] = ry @ rx @ pose[:3, :3]
    return out


def plan_flight(
    size_m: float,
    spec: FlightSpec,
    rng: np.random.Generator,
    world: FlightWorld | None = None,
    world_rng: np.random.Generator | None = None,
) -> list[FlightFrame]:
    """The frames of one flight over a town of side ``size_m`` centred on the origin.

    ``rng`` draws the same numbers whatever ``spec.turn_deg``: a turn changes the poses, not the draws.
    ``world`` (world v2: altitude profile, nadir tilt) draws from ``world_rng`` only, so that world
    v1 (the default, None) flies exactly as before the world existed.
    """
    world = world or FlightWorld()
    focal = 0.5 * spec.width / np.tan(np.radians(spec.fov_deg) / 2)
    K = intrinsics(focal, focal, spec.width / 2, spec.height / 2)
    n_nadir = spec.n_views // 2
    n_oblique = (spec.n_views - n_nadir) // 2
    n_orbit = spec.n_views - n_nadir - n_oblique
    pitch = np.radians(rng.uniform(*spec.oblique_deg))
    altitudes = altitude_profile(spec.n_views, spec.altitude_m, world, world_rng)  # [V] in flight order
    # nadir view width on the ground, at the highest altitude: the widest view stays on the town
    footprint = 2 * float(altitudes.max(initial=spec.altitude_m)) * np.tan(np.radians(spec.fov_deg) / 2)
    extent = max(0.0, 0.5 * size_m - 0.4 * footprint)
    if spec.turn_deg:  # unturned: not even a rotation by 0, so that the default flight keeps its bytes
        extent = _turned_extent(extent, spec.turn_deg, size_m)
    poses = [("nadir", *p) for p in _lawnmower(n_nadir, extent, altitudes[:n_nadir], 0.0, rng)]
    poses += [
        ("oblique", *p)
        for p in _lawnmower(n_oblique, 0.8 * extent, altitudes[n_nadir : n_nadir + n_oblique], pitch, rng)
    ]
    poses += [("orbit", *p) for p in _orbit(n_orbit, 0.2 * size_m, altitudes[n_nadir + n_oblique :], pitch, rng)]
    if spec.turn_deg:
        poses = _turned(poses, spec.turn_deg)
    frames = []
    for i, (kind, eye, target, up) in enumerate(poses):
        pose = look_at(eye, target, up)
        if kind == "nadir" and world.nadir_tilt_deg > 0 and world_rng is not None:
            pose = _tilted(pose, world.nadir_tilt_deg, world_rng)
        name = f"{spec.name_prefix}frame_{i:04d}.jpg"
        stamp = EPOCH_NS + int(round(i * 1e9 / spec.rate_hz))
        frames.append(FlightFrame(Camera(name, spec.width, spec.height, K, pose), stamp, kind))
    return frames


def overview_cameras(size_m: float, altitude_m: float = 80.0, width: int = 960, height: int = 720) -> list[Camera]:
    """A nadir view over the centre and four oblique (45 degree) views from the sides."""
    focal = 0.5 * width / np.tan(np.radians(35.0))  # 70 degree horizontal field of view
    K = intrinsics(focal, focal, width / 2, height / 2)
    cameras = [Camera("nadir.png", width, height, K, look_at([0, 0, altitude_m], [0, 0, 0], (0, 1, 0)))]
    for i, azimuth in enumerate(np.radians([270, 0, 90, 180])):
        eye = np.array([np.cos(azimuth) * altitude_m, np.sin(azimuth) * altitude_m, altitude_m])
        cameras.append(Camera(f"oblique_{i}.png", width, height, K, look_at(eye, [0, 0, 0], (0, 0, 1))))
    return cameras
