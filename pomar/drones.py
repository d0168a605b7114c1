"""The drones a flight plan (pomar.plan) is made for: each one's flight time per battery, its speed limits and its
camera's video, built in by name, or read from a JSON file with the same fields.

Flight times are the makers' rated figures (hovering, no wind, to an empty battery); a plan uses USABLE_SHARE of
them, as a grower lands with a quarter or more left (DJI's low-battery return comes at 25-30 %).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields
from pathlib import Path

from pomar.cli import InputError, read_json

#: The share of a battery's rated flight time a plan uses.
USABLE_SHARE = 0.7


@dataclass(frozen=True)
class Drone:
    name: str
    #: What it is, and where its figures come from.
    what: str
    #: Rated flight time per battery (minutes).
    battery_min: float
    #: The fastest it flies a waypoint mission (m/s), and the slowest it holds.
    max_speed_mps: float
    min_speed_mps: float
    #: Climb and descent rates (m/s).
    climb_mps: float
    #: Its camera (a built-in camera's name, python -m pomar cameras) and the video's size and frame rate.
    camera: str
    video_width: int
    video_height: int
    video_fps: float
    #: The shutter time a plan assumes where none is given (s): bright daylight in auto exposure.
    shutter_s: float = 1 / 500

    @property
    def usable_s(self) -> float:
        return 60.0 * self.battery_min * USABLE_SHARE


DRONES = {d.name: d for d in (
    Drone("phantom-4-pro", "DJI Phantom 4 Pro / Pro V2.0: 30 min rated, 14 m/s in P mode (DJI's specifications)",
          30.0, 14.0, 0.5, 5.0, "phantom-4-pro", 3840, 2160, 30.0),
    Drone("mavic-3", "DJI Mavic 3: 46 min rated, 15 m/s in N mode (DJI's specifications)",
          46.0, 15.0, 0.5, 6.0, "mavic-3", 3840, 2160, 30.0),
    Drone("generic-quad", "An ArduPilot or PX4 quadcopter (QGroundControl, Mission Planner): 20 min a battery, "
          "10 m/s; give a JSON file of these fields for your own", 20.0, 10.0, 0.5, 3.0, "phantom-4-pro", 3840,
          2160, 30.0),
)}


class DroneError(InputError, ValueError):
    """A drone the planner does not know, or a drone file that does not read."""


def load_drone(name_or_path: str) -> Drone:
    """A built-in drone by name, or a JSON file with Drone's fields."""
    if name_or_path in DRONES:
        return DRONES[name_or_path]
    path = Path(name_or_path)
    if not path.suffix.lower() == ".json":
        raise DroneError(f"{name_or_path}: not a drone this tool knows ({', '.join(DRONES)}), nor a .json file "
                         f"with a drone's fields")
    d = read_json(path, DroneError)
    names = {f.name for f in fields(Drone)}
    if not isinstance(d, dict):
        raise DroneError(f"{path}: a drone file needs an object of a drone's fields")
    missing = sorted(names - set(d) - {"shutter_s"})
    if missing:
        raise DroneError(f"{path}: a drone file needs {', '.join(missing)}")
    try:
        drone = Drone(**{k: v for k, v in d.items() if k in names})
    except TypeError as e:
        raise DroneError(f"{path}: {e}") from None
    bad = [k for k in ("battery_min", "max_speed_mps", "climb_mps", "video_fps", "shutter_s")
           if not (isinstance(getattr(drone, k), (int, float)) and getattr(drone, k) > 0)]
    if bad or not 0 <= drone.min_speed_mps < drone.max_speed_mps:
        raise DroneError(f"{path}: {', '.join(bad) or 'min_speed_mps'} must be > 0 (and min_speed_mps under "
                         f"max_speed_mps)")
    return drone


def drone_dict(d: Drone) -> dict:
    return asdict(d)
