"""Simulator configuration: dataclasses with defaults, loaded from TOML.

Every key of a config file must name a field here; a misspelt key, a wrong type or an
out-of-range value raises :class:`ConfigError` naming the file and the key.
"""

from __future__ import annotations

import dataclasses
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, get_args, get_origin, get_type_hints

from pomar.cli import InputError
from pomar.geo import VACARIA


class ConfigError(InputError, ValueError):
    """A simulator config file has an unknown key, a value of the wrong type, or one out of range."""


@dataclass
class Origin:
    lat: float = VACARIA.lat
    lon: float = VACARIA.lon
    alt: float = VACARIA.alt


@dataclass
class Orchard:
    rows: int = 10
    row_spacing_m: float = 4.0
    tree_spacing_m: float = 1.0
    row_length_m: float = 40.0
    #: Direction of the rows, degrees clockwise from north.
    row_azimuth_deg: float = 0.0
    #: Rows at each end with no interest (the paper's plot has one border row each side).
    border_rows: int = 1
    canopy_height_m: float = 3.0
    canopy_base_m: float = 0.8
    canopy_width_m: float = 1.4
    leaves_per_tree: int = 2600
    leaf_radius_m: float = 0.04
    #: Variety of each row, cycled across the rows.
    varieties: list[str] = field(default_factory=lambda: ["Gala", "Fuji"])


#: Named sets of [apples] values (issue 71), under a config's own keys: ``[apples] preset = "tall-spindle"``.
#: ``tall-spindle``: a mature high-density orchard as this project flies (trees 1 m apart in rows 4 m apart, about
#: 2,500 a hectare, as the simulator's default orchard). Robinson et al. (Cornell, "A vision for apple orchard systems of
#: the future", NY Fruit Quarterly) give the tall spindle at 1,000-1,200 trees an acre (2,500-3,000 a hectare) and
#: mature yields of 1,500 bushels an acre (about 70 t/ha): 23-28 kg a tree, 110-140 fruit of 0.2 kg. Fruit of
#: 150-265 g (the packers' counts of 72-125 fruit a 19.05-kg box; Marini et al., HortScience 54(11):1947, 2019) is
#: 69-84 mm across at a whole apple's density (pomar.fruit). Tree-to-tree vigour: the CV of 0.3 the tuning flights
#: used (no published figure found for it yet).
APPLE_PRESETS = {
    "tall-spindle": {"per_tree": 120.0, "diameter_min_m": 0.069, "diameter_max_m": 0.084, "tree_vigour_cv": 0.3},
}


@dataclass
class Apples:
    #: A named set of these values (APPLE_PRESETS), under the keys the config gives itself ("": none).
    preset: str = ""
    per_tree: float = 8.0
    #: Each row's load as a factor of per_tree, cycled across the rows (empty: every row alike): a whole-plot flight
    #: whose rows differ in load, for the count against the load (the paper's per-row figure of merit).
    row_load: list[float] = field(default_factory=list)
    diameter_min_m: float = 0.06
    diameter_max_m: float = 0.09
    #: Each row's apple diameters (m) as [min, max], cycled across the rows (empty: diameter_min_m..diameter_max_m for
    #: every row): rows whose fruit differ in size, as two cultivars or two crop loads do.
    row_diameter_m: list[list[float]] = field(default_factory=list)
    #: Tree-to-tree vigour: each tree's expected load is multiplied by a gamma factor of mean 1 and this coefficient of
    #: variation (0: every tree of a row alike, a Poisson load of the same mean, as before).
    tree_vigour_cv: float = 0.0
    #: Depth of an apple inside the canopy, as a fraction of the canopy radius (1 = surface);
    #: apples deeper than about 0.9 are mostly hidden by leaves.
    depth_min: float = 0.80
    depth_max: float = 1.05


@dataclass
class Pass:
    #: Across-row position of the flight line (m, orchard frame; rows sit at multiples of row_spacing_m
    #: around 0). The camera looks across the rows towards +x (look = 1) or -x (look = -1).
    across_m: float = -8.0
    look: int = 1


@dataclass
class Flight:
    altitude_m: float = 12.0
    speed_mps: float = 2.0
    #: Camera tilt off nadir, degrees (0 = straight down).
    tilt_deg: float = 30.0
    #: Along-row start and end of each pass (m, orchard frame, rows centred on 0).
    start_m: float = -15.0
    end_m: float = 15.0
    passes: list[Pass] = field(default_factory=lambda: [Pass()])
    #: Turns at the row ends: 0 = corners (straight lines between passes, as before); T > 0 = the path and the
    #: heading smoothed over about T seconds, so the drone slows into the turn, swings round and may look over
    #: the headland.
    turn_s: float = 0.0
    fps: float = 10.0
    #: UTC start of the video (ISO 8601), by the autopilot's (true) clock.
    start_utc: str = "2018-12-13T14:00:00Z"
    #: Seconds the autopilot had been up when the video starts.
    boot_s_before_start: float = 180.0
    # Wobble (standard deviations of smooth random processes).
    speed_wobble: float = 0.08
    lateral_wobble_m: float = 0.25
    altitude_wobble_m: float = 0.25
    attitude_wobble_deg: float = 1.5
    vehicle_tilt_wobble_deg: float = 3.0


@dataclass
class CameraCfg:
    width: int = 1280
    height: int = 720
    hfov_deg: float = 50.0
    #: Misalignment of the camera on the gimbal (small rotation, degrees), unknown to telemetry.
    mount_error_deg: float = 0.0


@dataclass
class Telemetry:
    gps_rate_hz: float = 5.0
    gps_noise_m: float = 0.5
    gps_alt_noise_m: float = 0.8
    position_rate_hz: float = 5.0
    attitude_rate_hz: float = 20.0
    attitude_noise_deg: float = 0.3
    gimbal_rate_hz: float = 10.0
    gimbal_noise_deg: float = 0.3
    #: Camera clock minus autopilot clock (s): flight.json's video start is off by this much.
    clock_offset_s: float = 0.0
    #: Delay between the autopilot sending a message and the ground station logging it (s).
    link_latency_s: float = 0.02
    #: "CAMERA_FEEDBACK" (ArduPilot) or "CAMERA_TRIGGER" (PX4), one per video frame.
    capture_message: str = "CAMERA_FEEDBACK"
    system_id: int = 1
    #: Where the autopilot's EKF takes its height from (GLOBAL_POSITION_INT's alt and relative_alt): "gps", the GPS's
    #: vertical error (gps_alt_noise_m), as every flight rendered before this option; or "baro", ArduPilot's default
    #: (EK3_SRC1_POSZ = 1): the true height plus a barometer's slow drift (sim.telemetry.BARO_DRIFT_M).
    height_source: str = "gps"


@dataclass
class Render:
    #: Motion-blur exposure time (s); 0 disables blur.
    exposure_s: float = 0.004
    #: Standard deviation of the slow exposure drift (fraction of brightness).
    exposure_wobble: float = 0.06
    #: Sun elevation and azimuth (degrees, azimuth clockwise from north).
    sun_elevation_deg: float = 55.0
    sun_azimuth_deg: float = 40.0
    ambient: float = 0.45
    sensor_noise: float = 2.0
    ground_resolution_m: float = 0.02
    #: x264 constant rate factor of the video (lower is better quality, larger file).
    video_crf: int = 20


@dataclass
class SimConfig:
    seed: int = 0
    flight_id: str = "sim-flight"
    drone_id: str = "drone-1"
    origin: Origin = field(default_factory=Origin)
    orchard: Orchard = field(default_factory=Orchard)
    apples: Apples = field(default_factory=Apples)
    flight: Flight = field(default_factory=Flight)
    camera: CameraCfg = field(default_factory=CameraCfg)
    telemetry: Telemetry = field(default_factory=Telemetry)
    render: Render = field(default_factory=Render)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)


# Ranges checked after loading: (section.key, predicate, message)
_CHECKS = [
    ("orchard.rows", lambda v: v >= 1, "must be >= 1"),
    ("orchard.row_spacing_m", lambda v: v > 0, "must be > 0"),
    ("orchard.tree_spacing_m", lambda v: v > 0, "must be > 0"),
    ("orchard.row_length_m", lambda v: v > 0, "must be > 0"),
    ("orchard.leaves_per_tree", lambda v: v >= 0, "must be >= 0"),
    ("orchard.varieties", lambda v: len(v) > 0, "must name at least one variety"),
    ("apples.per_tree", lambda v: v >= 0, "must be >= 0"),
    ("apples.row_load", lambda v: all(x >= 0 for x in v), "must hold factors >= 0"),
    ("apples.diameter_min_m", lambda v: v > 0, "must be > 0"),
    ("apples.row_diameter_m", lambda v: all(len(d) == 2 and 0 < d[0] <= d[1] for d in v),
     "must hold [min, max] pairs with 0 < min <= max"),
    ("apples.tree_vigour_cv", lambda v: 0 <= v <= 2, "must be in [0, 2]"),
    ("flight.altitude_m", lambda v: v > 0, "must be > 0"),
    ("flight.speed_mps", lambda v: v > 0, "must be > 0"),
    ("flight.fps", lambda v: v > 0, "must be > 0"),
    ("flight.tilt_deg", lambda v: 0 <= v < 80, "must be in [0, 80)"),
    ("flight.passes", lambda v: len(v) > 0, "must hold at least one pass"),
    ("flight.turn_s", lambda v: 0 <= v <= 30, "must be in [0, 30]"),
    ("camera.width", lambda v: 16 <= v <= 3840 and v % 2 == 0, "must be even, in [16, 3840]"),
    ("camera.height", lambda v: 16 <= v <= 2160 and v % 2 == 0, "must be even, in [16, 2160]"),
    ("camera.hfov_deg", lambda v: 5 < v < 150, "must be in (5, 150)"),
    ("telemetry.gps_rate_hz", lambda v: v > 0, "must be > 0"),
    ("telemetry.position_rate_hz", lambda v: v > 0, "must be > 0"),
    ("telemetry.attitude_rate_hz", lambda v: v > 0, "must be > 0"),
    ("telemetry.gimbal_rate_hz", lambda v: v > 0, "must be > 0"),
    ("telemetry.height_source", lambda v: v in ("gps", "baro"), "must be gps or baro"),
    ("telemetry.capture_message", lambda v: v in ("CAMERA_FEEDBACK", "CAMERA_TRIGGER"),
     "must be 'CAMERA_FEEDBACK' (ArduPilot) or 'CAMERA_TRIGGER' (PX4)"),
    ("render.video_crf", lambda v: 0 <= v <= 51, "must be in [0, 51]"),
]


def _coerce(value: Any, typ: Any, key: str, source: str) -> Any:
    if dataclasses.is_dataclass(typ):
        if not isinstance(value, dict):
            raise ConfigError(f"{source}: [{key}] must be a table, got {type(value).__name__}")
        return _build(typ, value, key, source)
    origin = get_origin(typ)
    if origin is list:
        (item,) = get_args(typ)
        if not isinstance(value, list):
            raise ConfigError(f"{source}: {key} must be a list, got {value!r}")
        return [_coerce(v, item, f"{key}[{i}]", source) for i, v in enumerate(value)]
    if typ is bool:
        if not isinstance(value, bool):
            raise ConfigError(f"{source}: {key} must be true or false, got {value!r}")
        return value
    if typ is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{source}: {key} must be an integer, got {value!r}")
        return value
    if typ is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{source}: {key} must be a number, got {value!r}")
        return float(value)
    if typ is str:
        if not isinstance(value, str):
            raise ConfigError(f"{source}: {key} must be a string, got {value!r}")
        return value
    raise TypeError(f"unsupported config type {typ!r} for {key}")


def _build(cls, data: dict, prefix: str, source: str):
    hints = get_type_hints(cls)
    names = [f.name for f in dataclasses.fields(cls)]
    kwargs = {}
    for key, value in data.items():
        full = f"{prefix}.{key}" if prefix else key
        if key not in names:
            raise ConfigError(f"{source}: unknown key {full!r} (known keys here: {', '.join(names)})")
        kwargs[key] = _coerce(value, hints[key], full, source)
    return cls(**kwargs)


def _get(cfg: SimConfig, dotted: str):
    obj = cfg
    for part in dotted.split("."):
        obj = getattr(obj, part)
    return obj


def from_dict(data: dict, source: str = "<config>") -> SimConfig:
    apples = data.get("apples")
    if isinstance(apples, dict) and apples.get("preset"):
        if apples["preset"] not in APPLE_PRESETS:
            raise ConfigError(f"{source}: apples.preset {apples['preset']!r} is not one of "
                              f"{', '.join(sorted(APPLE_PRESETS))}")
        data = {**data, "apples": {**APPLE_PRESETS[apples["preset"]], **apples}}
    cfg = _build(SimConfig, data, "", source)
    for key, ok, msg in _CHECKS:
        value = _get(cfg, key)
        if not ok(value):
            raise ConfigError(f"{source}: {key} {msg}, got {value!r}")
    for i, p in enumerate(cfg.flight.passes):
        if p.look not in (-1, 1):
            raise ConfigError(f"{source}: flight.passes[{i}].look must be 1 or -1, got {p.look!r}")
    if cfg.apples.diameter_max_m < cfg.apples.diameter_min_m:
        raise ConfigError(f"{source}: apples.diameter_max_m must be >= apples.diameter_min_m")
    if cfg.flight.end_m == cfg.flight.start_m:
        raise ConfigError(f"{source}: flight.end_m must differ from flight.start_m")
    try:
        parse_utc(cfg.flight.start_utc)
    except ValueError:
        raise ConfigError(f"{source}: flight.start_utc must be an ISO 8601 time, got {cfg.flight.start_utc!r}") from None
    return cfg


def rendered_config(flight_dir: str | Path) -> SimConfig:
    """The config a flight was rendered with (its sim_config.json); the defaults where a field came later than the
    render, or where the flight is not a simulated one (no sim_config.json)."""
    import json

    p = Path(flight_dir) / "sim_config.json"
    return from_dict(json.loads(p.read_text()), str(p)) if p.is_file() else SimConfig()


def parse_utc(text: str) -> float:
    from datetime import datetime, timezone

    dt = datetime.fromisoformat(text.replace("Z", "+00:00"))
    if dt.tzinfo is None:
        dt = dt.replace(tzinfo=timezone.utc)
    return dt.timestamp()


def load(path: str | Path) -> SimConfig:
    path = Path(path)
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"{path}: config file not found") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML ({exc})") from None
    return from_dict(data, str(path))
