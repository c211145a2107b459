"""The evaluation world: what the simulated flight adds to the town beyond its geometry and labels.

A ``WorldSpec`` is a frozen record of every setting, grouped by effect; ``WORLDS`` names the
worlds ``olsplat sim make --world`` knows:

- ``v1``: the world before issue 43 (every output file of ``sim make`` byte-identical to what it
  was, except that scene.json records ``options.world``): a flight at one altitude, exactly
  nadir views, view-independent colours, no haze, no cloud shadows, the old camera.
- ``v2``: calibrated against 24 real UAV photos (caliterra) with ``olsplat bench diagnose``, within
  the band fixed in docs/world.md: the altitude varies over the flight, nadir views tilt, roofs,
  cars and glass are specular towards the sun's mirror direction and vegetation has a hot spot
  (spherical harmonics of the true Gaussians), haze grows with depth, cloud shadows drift with the
  wind, and the camera's vignetting, exposure steps and focus blur are those of a corrected JPEG.
  The nadir views' tilt (0.8 degrees per axis) follows the real photos' tilt between consecutive
  frames (``flight.relative_tilt_deg``), the other settings the ground patches' colour and
  sharpness change (docs/world.md gives the figures).
- ``v2g``: v2 with geometry that follows its labels at full strength (``GeometryWorld``).

``with_settings`` applies ``--world-set KEY=VALUE`` overrides (dotted keys, YAML scalar values).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field, fields, is_dataclass, replace
from typing import Any, Literal

import numpy as np

from .sensor import SensorSpec

# Streams of the world's own draws, apart from the town's and the flight's (make._streams): the
# town's materials from SeedSequence(seed, spawn_key=(5,)), the flight's weather and wobble from
# SeedSequence(seed, spawn_key=(6,)) or, with a flight seed M, SeedSequence(M, spawn_key=(4, 3))
# (a fourth child of the flight seed's stream, whose first three are its flight, sensor, pose).
TOWN_WORLD_KEY = (5,)
FLIGHT_WORLD_KEY = (6,)
FLIGHT_SEED_WORLD_KEY = (4, 3)


@dataclass(frozen=True)
class FlightWorld:
    """How the UAV flies beyond the lawnmowers and the orbit of ``flight.plan_flight``."""

    # max - min of the camera heights over the flight, as a fraction of the preset's altitude
    # (0: held at the altitude, v1). The profile is centred on the preset's altitude.
    altitude_span: float = 0.0
    # "smooth": a smooth random profile (``altitude_waves`` random cosines over the flight);
    # "climb": a steady climb from the lowest to the highest altitude, plus a smaller smooth wobble
    altitude_profile: Literal["smooth", "climb"] = "smooth"
    altitude_waves: int = 3  # cosine terms of the smooth profile (periods of 2/j flights, j = 1..waves)
    nadir_tilt_deg: float = 0.0  # std of the nadir views' tilt from straight down, per axis (gimbal, wind), degrees


@dataclass(frozen=True)
class AppearanceWorld:
    """View-dependent appearance of the true scene: lobes projected onto the SH of its Gaussians.

    A lobe is ``strength * ((1 + cos a) / 2) ** exponent`` of the angle ``a`` between the viewing
    direction (camera to Gaussian) and the lobe's axis, band-limited to ``sh_degree`` (broader and
    lower at its peak than before band-limiting; ``appearance.lobe_coefficients``)."""

    sh_degree: int = 0  # 0: view-independent colours (v1); 2 or 3: the truth's SH degree
    sun_azimuth_deg: float = 215.0  # from +x (east) towards +y (north); the baked shading's sun (layout.py)
    sun_elevation_deg: float = 52.0  # above the horizon
    # specular: white sunlight added (linear 0..1 per channel at the lobe's peak), axis the mirror
    # direction of the sun in the Gaussian's surface (only surfaces facing the sun)
    roof_specular: tuple[float, float] = (0.0, 0.0)  # per building, uniform in this range: some roofs shine more
    car_specular: float = 0.0  # car paint
    glass_specular: float = 0.0  # windows and car glass
    specular_exponent: float = 6.0  # sharpness of the specular lobes (6: half the peak 38 degrees off its axis)
    # hot spot (backscatter): vegetation (trees, lawn) brighter by this fraction of its own colour
    # at the lobe's peak, axis the direction away from the sun (a camera with the sun behind it)
    hotspot: float = 0.0
    hotspot_exponent: float = 4.0


@dataclass(frozen=True)
class HazeWorld:
    """Aerial perspective: rgb = rgb * t + airlight * (1 - t), t = exp(-beta * depth)."""

    # extinction per metre; depth is the render's (metres along the optical axis, not along the
    # ray: up to 10 % less at the corners of a 50 degree view), the ground plane's beyond the town
    beta: float = 0.0
    airlight: tuple[float, float, float] = (0.78, 0.80, 0.84)  # the haze's colour, linear rgb 0..1


@dataclass(frozen=True)
class CloudWorld:
    """Drifting cloud shadows: a smooth random field on the ground plane, moved by the wind.

    The field is a sum of ``modes`` random plane waves (unit variance); the ground is in shadow
    where it exceeds the quantile that leaves ``coverage`` of it in shadow, with a soft edge. A
    pixel's light is the field's at the point where the sun's ray through the pixel's surface
    point (camera centre + ray * render depth) meets z = 0: a roof's cloud shadow is offset from
    the ground's below it by the roof's height, as a real one is."""

    coverage: float = 0.0  # fraction of the ground in shadow (0: no clouds, v1)
    darkness: float = 0.6  # light multiplier in full shadow (1: none)
    scale_m: float = 60.0  # wavelength of the field's plane waves, metres (a shadow is about half of it)
    wind_mps: tuple[float, float] = (4.0, 1.5)  # the field's velocity on the ground, m/s east, north
    softness: float = 0.3  # width of the shadow edge, in standard deviations of the field
    modes: int = 16  # plane waves summed


# the town's geometry draws (geometry.py), only made when geometry.strength > 0
GEOMETRY_WORLD_KEY = (7,)


@dataclass(frozen=True)
class GeometryWorld:
    """Geometry that partly follows labels (sim/geometry.py; docs/world.md, "Geometry that follows
    labels"). ``strength`` S in [0, 1] scales every tie: with probability S a roof takes the colour
    tied to its building's type and size (large flat: grey/white; gabled: mostly red; small flat:
    mostly white/blue), else today's independent draw; pavements stand 0.12 m x S above the road
    behind a vertical kerb face; lawn Gaussians rise by 0-6 cm x S (blades) plus +-4 cm x S (turf
    bumps) and tilt by N(0, 12 degrees x S), roads and parking stay flat; tree crowns' vertical
    semi-axis grows from 0.85 to 0.85 + 0.45 S of their radius, base kept. 0 (v1 and v2): the town
    of before, byte for byte (no draw is made from any stream)."""

    strength: float = 0.0  # 0: labels independent of geometry (today); 1: the full ties above


@dataclass(frozen=True)
class WorldSpec:
    name: str = "v1"  # the world it was made from (``WORLDS``); "v2+" once a setting is overridden
    flight: FlightWorld = field(default_factory=FlightWorld)
    appearance: AppearanceWorld = field(default_factory=AppearanceWorld)
    haze: HazeWorld = field(default_factory=HazeWorld)
    clouds: CloudWorld = field(default_factory=CloudWorld)
    sensor: SensorSpec = field(default_factory=SensorSpec)
    geometry: GeometryWorld = field(default_factory=GeometryWorld)


V1 = WorldSpec()
V2 = WorldSpec(
    name="v2",
    flight=FlightWorld(altitude_span=0.5, altitude_profile="smooth", nadir_tilt_deg=0.8),
    appearance=AppearanceWorld(
        sh_degree=3, roof_specular=(0.02, 0.25), car_specular=0.3, glass_specular=0.5, hotspot=0.1
    ),
    haze=HazeWorld(beta=0.0008),
    clouds=CloudWorld(coverage=0.1, darkness=0.88, softness=1.0, wind_mps=(2.0, 0.8)),
    sensor=SensorSpec(exposure_drift=0.015, exposure_range=(0.9, 1.1), vignette=0.03, focus_blur_px=(0.0, 1.0)),
)
# v2 whose geometry follows its labels (geometry.py at full strength): the condition under which a
# 3D feature has something to add; v1 and v2 keep strength 0 (issue 43 part 4)
V2G = replace(V2, name="v2g", geometry=GeometryWorld(strength=1.0))
WORLDS = {"v1": V1, "v2": V2, "v2g": V2G}


def world_keys(spec: Any = V1, prefix: str = "") -> list[str]:
    """Every settable dotted key of a WorldSpec (``name`` is not one: it names the base world)."""
    keys = []
    for f in fields(spec):
        value = getattr(spec, f.name)
        if is_dataclass(value):
            keys += world_keys(value, f"{prefix}{f.name}.")
        elif f.name != "name" or prefix:
            keys.append(prefix + f.name)
    return keys


def _coerce(key: str, old: Any, value: Any) -> Any:
    """``value`` (parsed YAML) as the type of the setting's current ``old`` value, or ValueError."""
    if isinstance(old, tuple):
        if not isinstance(value, list | tuple) or len(value) != len(old):
            raise ValueError(f"--world-set {key}: needs a list of {len(old)} values like {list(old)}, got {value!r}")
        return tuple(_coerce(key, o, v) for o, v in zip(old, value, strict=True))
    if isinstance(old, bool) or isinstance(old, str):
        if type(value) is not type(old):
            raise ValueError(f"--world-set {key}: needs a {type(old).__name__}, got {value!r}")
        return value
    if isinstance(old, int) and not isinstance(value, bool) and isinstance(value, int):
        return value
    if isinstance(old, float) and not isinstance(value, bool) and isinstance(value, int | float):
        return float(value)
    raise ValueError(f"--world-set {key}: needs a {type(old).__name__}, got {value!r}")


def with_settings(spec: WorldSpec, settings: list[str]) -> WorldSpec:
    """``spec`` with each ``KEY=VALUE`` applied in turn (dotted keys as ``world_keys``; values parsed
    as YAML scalars or flow lists, e.g. ``sensor.vignette=0``, ``clouds.wind_mps=[3, 0]``). A changed
    world is renamed ``<name>+`` (the settings themselves are in scene.json). Raises ValueError."""
    import yaml

    known = world_keys()
    for setting in settings:
        key, sep, text = setting.partition("=")
        key = key.strip()
        if not sep or key not in known:
            raise ValueError(f"--world-set {setting!r}: unknown key {key!r}; known keys: {', '.join(known)}")
        try:
            value = yaml.safe_load(text)
        except yaml.YAMLError:
            raise ValueError(f"--world-set {setting!r}: {text!r} is not a YAML value") from None
        *groups, name = key.split(".")
        spec = _replaced(spec, groups, name, value, key)
    if settings and not spec.name.endswith("+"):
        spec = replace(spec, name=spec.name + "+")
    return spec


def _replaced(record: Any, groups: list[str], name: str, value: Any, key: str) -> Any:
    if groups:
        inner = getattr(record, groups[0])
        return replace(record, **{groups[0]: _replaced(inner, groups[1:], name, value, key)})
    new = _coerce(key, getattr(record, name), value)
    check = replace(record, **{name: new})
    _validate(check, key)
    return check


def _validate(record: Any, key: str) -> None:
    """Ranges a setting must respect, checked as it is set (ValueError quoting the value)."""
    problems = {
        AppearanceWorld: lambda r: r.sh_degree not in (0, 1, 2, 3) and "sh_degree must be 0, 1, 2 or 3",
        CloudWorld: lambda r: (
            (not 0.0 <= r.coverage <= 1.0 or r.scale_m <= 0 or r.modes < 1)
            and "need 0 <= coverage <= 1, scale_m > 0, modes >= 1"
        ),
        HazeWorld: lambda r: r.beta < 0 and "beta must be >= 0",
        GeometryWorld: lambda r: not 0.0 <= r.strength <= 1.0 and "need 0 <= strength <= 1",
        FlightWorld: lambda r: (
            (not 0.0 <= r.altitude_span < 1.5 or r.nadir_tilt_deg < 0 or r.altitude_waves < 1)
            and "need 0 <= altitude_span < 1.5, nadir_tilt_deg >= 0, altitude_waves >= 1"
        ),
    }
    check = problems.get(type(record))
    problem = check(record) if check else None
    if problem:
        raise ValueError(f"--world-set {key}: {problem}, got {dataclasses.asdict(record)}")


def world_streams(seed: int, flight_seed: int | None) -> tuple[np.random.Generator, np.random.Generator]:
    """(town world rng, flight world rng): the town's materials depend on the seed alone, the
    weather and the flight's altitude and tilt on the flight (the seed's own, or flight seed M)."""
    town = np.random.default_rng(np.random.SeedSequence(seed, spawn_key=TOWN_WORLD_KEY))
    if flight_seed is None:
        flight = np.random.SeedSequence(seed, spawn_key=FLIGHT_WORLD_KEY)
    else:
        flight = np.random.SeedSequence(flight_seed, spawn_key=FLIGHT_SEED_WORLD_KEY)
    return town, np.random.default_rng(flight)
