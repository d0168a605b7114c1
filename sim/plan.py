"""The simulator flies a flight plan (issue 72): ``python -m sim flight --config CFG --plan plan.json`` renders the
orchard of CFG along one flight of the plan (``--plan-flight N``): its passes' lines, in the order and direction
flown, at its height, speed and gimbal pitch. The plan is made on the orchard's layout (``python -m sim layout``, or
the grower's), so its waypoints (WGS84) fall on the simulated rows; the camera is the config's.

The simulator flies every pass over one along-row span: a plan whose passes span different stretches of the rows is
refused, as is a file that is not a plan of this tool.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np

from pomar.cli import InputError, read_json
from pomar.geo import Origin

#: Passes whose along-row ends differ by more than this (m) cannot be one simulated flight's.
SPAN_TOLERANCE_M = 0.5


class PlanFileError(InputError, ValueError):
    """A plan file this simulator cannot fly."""


def read_plan(path) -> dict:
    """plan.json of ``python -m pomar plan``; a PlanFileError naming the file for anything else."""
    path = Path(path)
    d = read_json(path, PlanFileError)
    if not isinstance(d, dict) or d.get("format") != "pomar-plan/1":
        raise PlanFileError(f"{path}: not a plan of python -m pomar plan (no format pomar-plan/1)")
    for key in ("height_m", "speed_mps", "gimbal_pitch_deg", "flights"):
        if key not in d:
            raise PlanFileError(f"{path}: the plan has no {key}")
    if not d["flights"] or any(len(f.get("waypoints", [])) < 2 or len(f["waypoints"]) % 2 for f in d["flights"]):
        raise PlanFileError(f"{path}: each flight needs its passes' waypoints in pairs (start, end)")
    if not (0 < d["height_m"] < 500 and 0 < d["speed_mps"] < 30 and -90 <= d["gimbal_pitch_deg"] < -10):
        raise PlanFileError(f"{path}: height {d['height_m']} m, speed {d['speed_mps']} m/s or gimbal pitch "
                            f"{d['gimbal_pitch_deg']} deg out of range")
    return d


def fly_plan(cfg, plan: dict, flight: int = 1, source: str = "plan.json"):
    """A copy of the simulator's config ``cfg`` (sim.config.SimConfig) whose flight is the plan's flight ``flight``
    (1-based)."""
    from sim.config import Pass
    from sim.orchard import orchard_to_enu_matrix

    if not 1 <= flight <= len(plan["flights"]):
        raise PlanFileError(f"{source}: the plan has {len(plan['flights'])} flight(s), not a flight {flight}")
    wps = plan["flights"][flight - 1]["waypoints"]
    origin = Origin(cfg.origin.lat, cfg.origin.lon, 0.0)
    enu = np.array([origin.to_enu(w["lat"], w["lon"], 0.0)[:2] for w in wps])
    to_enu = orchard_to_enu_matrix(cfg.orchard.row_azimuth_deg)  # columns: across, along (east, north)
    xy = enu @ to_enu  # orchard frame: x across the rows, y along them
    looks = np.array([[np.sin(np.radians(w["heading_deg"])), np.cos(np.radians(w["heading_deg"]))] for w in wps])
    starts, ends = xy[0::2], xy[1::2]
    span0 = (starts[0, 1], ends[0, 1])
    for k, (s, e) in enumerate(zip(starts, ends)):
        lo, hi = sorted((s[1], e[1]))
        if abs(lo - min(span0)) > SPAN_TOLERANCE_M or abs(hi - max(span0)) > SPAN_TOLERANCE_M:
            raise PlanFileError(f"{source}: pass {k + 1} spans {lo:.1f}..{hi:.1f} m along the rows, the first "
                                f"{min(span0):.1f}..{max(span0):.1f} m: the simulator flies one span")
        want_up = k % 2 == 0  # the simulator flies every other pass back
        if (e[1] > s[1]) != ((span0[1] > span0[0]) == want_up):
            raise PlanFileError(f"{source}: pass {k + 1} is not flown serpentine (each the other way from the last)")
    passes = [Pass(across_m=float((s[0] + e[0]) / 2), look=1 if (looks[2 * k] @ to_enu)[0] > 0 else -1)
              for k, (s, e) in enumerate(zip(starts, ends))]
    fl = dataclasses.replace(cfg.flight, altitude_m=float(plan["height_m"]), speed_mps=float(plan["speed_mps"]),
                             tilt_deg=float(90.0 + plan["gimbal_pitch_deg"]), start_m=float(span0[0]),
                             end_m=float(span0[1]), passes=passes)
    return dataclasses.replace(cfg, flight=fl)
