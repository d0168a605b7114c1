"""A flight plan that films every tree of the rows asked from both sides, from the orchard's layout, the camera, the
drone and the detector (issue 72).

Each side of each row is one pass: a line parallel to the row, on that side, flown sideways with the camera turned
to the row and pitched down ``pitch_deg`` below the horizon. Its height puts the apples on the facing canopy at the
detector's size (the model's ``apple_radius_px``, at the video's own resolution, by pomar.apple_scale's geometry, so
that the onboard node only ever shrinks frames); its offset from the row puts the optical axis on that face at the
canopy's middle height. A legal height limit lower than that brings the drone down and the apples up in size.

The speed follows from geometry: every apple in at least ``views`` frames at the rate the detector keeps up with
(an apple crosses the frame's width at the face in ``width / speed`` seconds), and its motion during the shutter
under ``blur_px``; then the drone's limits. The passes run serpentine, across the rows in order, each extended by half
the frame's width past the row's ends (so that the end trees get their views), turns outside the rows. A plan that
one battery cannot fly is split into flights of whole rows. Within a ``boundary`` (pomar.boundary) each pass keeps
its longest stretch inside; a pass with none is left out, and the plan says which, the trees that lose a side, and
each hop between passes that leaves it.

What it will give is measured with the same geometry the ground uses for ``trees.csv``'s coverage
(:mod:`pomar.coverage`): the planned cameras, every frame, against the layout's trees, a hedge of DEFAULT_HEDGE.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from pomar.apple_scale import APPLE_RADIUS_M, CANOPY_MID_M, envelope_height_m, expected_radius_px
from pomar.boundary import clip_segment, outside_m, read_boundary
from pomar.cli import InputError
from pomar.coverage import DEFAULT_HEDGE
from pomar.drones import Drone
from pomar.geo import Origin
from pomar.layout import LayoutRow, row_ends_enu, tree_positions

#: The file format written (plan.json's ``format``).
FORMAT = "pomar-plan/1"
#: Seconds a turn between passes takes besides its distance: slowing, yawing to the new side, settling.
TURN_S = 8.0
#: Speed on the way between passes and from and to the take-off point (m/s), at most.
TRANSIT_MPS = 8.0
#: Clearance over the canopy's top (m) a plan keeps at the least.
CLEARANCE_M = 2.0


class PlanError(InputError, ValueError):
    """A plan that cannot be made as asked: its message says which row or setting, and why."""


@dataclass
class PlanSettings:
    """How to fly (each field one setting of ``python -m pomar plan``)."""

    #: The camera's pitch below the horizon (deg): 90 looks straight down; 60 is the paper's oblique view.
    pitch_deg: float = 60.0
    #: Frames each apple is to be seen in, at least (the association wants several views of an apple).
    views: int = 5
    #: The most an apple may move in the image while the shutter is open (px).
    blur_px: float = 1.0
    #: The shutter time (s); default: the drone's.
    shutter_s: float | None = field(default=None, metadata={"type": float})
    #: Frames a second the detector keeps up with on board (default: the video's, for an after-flight replay).
    fps: float | None = field(default=None, metadata={"type": float})
    #: The highest the drone may fly above the take-off point (m): the legal limit where the grower flies.
    max_height_m: float = field(default=120.0, metadata={"flag": "--max-height"})
    #: The rows to film (the layout's numbers; default all).
    rows: list[int] = field(default_factory=list, metadata={"type": int, "nargs": "+", "metavar": "ROW"})
    #: A polygon the drone stays inside (GeoJSON, or a CSV of lat,lon vertices): the property's edge, a no-fly area
    #: left out.
    boundary: str | None = field(default=None, metadata={"type": str, "metavar": "FILE"})

    def __post_init__(self):
        for name in ("views", "blur_px", "max_height_m") + (("shutter_s",) if self.shutter_s is not None else ()) + (
                ("fps",) if self.fps is not None else ()):
            if not getattr(self, name) > 0:
                raise ValueError(f"--{name.replace('_', '-')} must be > 0, not {getattr(self, name)}")


@dataclass
class Pass:
    """One side of one row: where the drone flies (ENU, m about the plan's origin) and which way the camera looks."""

    row: int
    side: int  # +1: the row's left-hand side looking from its start to its end; -1 the right
    start: np.ndarray  # (2,) ENU
    end: np.ndarray
    look: np.ndarray  # (2,) unit, horizontal: from the drone to the row

    @property
    def length_m(self) -> float:
        return float(np.linalg.norm(self.end - self.start))


def pass_geometry(fx: float, width: int, target_px: float, min_px: float, pitch_deg: float, max_height_m: float,
                  hedge: dict = DEFAULT_HEDGE) -> dict:
    """Height (m above take-off), offset from the row's line (m), range to the face and the apples' radius at the
    video's resolution for a pass of a camera of focal length ``fx`` px: the height at which apples reach
    ``target_px`` (pomar.apple_scale.envelope_height_m), lowered to ``max_height_m``; a PlanError where that makes
    them smaller than ``min_px`` or leaves the drone less than CLEARANCE_M over the canopy."""
    off_nadir = 90.0 - pitch_deg
    if not 0.0 <= off_nadir < 80.0:
        raise PlanError(f"--pitch-deg {pitch_deg:g}: the camera must look down, 10-90 deg below the horizon")
    height = envelope_height_m(fx, off_nadir, target_px, 1.0)
    if height > max_height_m:
        height = max_height_m
    if height < hedge["top"] + CLEARANCE_M:
        raise PlanError(f"a height of {height:.1f} m is below the canopy's top ({hedge['top']:g} m) with "
                        f"{CLEARANCE_M:g} m of clearance: raise --max-height or use a camera of shorter focal length")
    radius = float(expected_radius_px(fx, height, off_nadir))
    if not radius >= min_px:
        raise PlanError(f"at {height:.1f} m (--max-height {max_height_m:g}) apples would be {radius:.1f} px across "
                        f"their radius, under the detector's reliable {min_px:g} px")
    rng = (height - CANOPY_MID_M) / np.cos(np.radians(off_nadir))
    offset = hedge["half_depth"] + rng * np.sin(np.radians(off_nadir))
    # the frame's width where the axis meets the face: an apple crosses it as the drone flies past
    footprint = width * rng / fx
    return {"height_m": float(height), "offset_m": float(offset), "range_m": float(rng), "apple_px": radius,
            "footprint_m": float(footprint), "off_nadir_deg": off_nadir}


def pass_speed(geom: dict, fx: float, fps: float, views: int, blur_px: float, shutter_s: float, drone: Drone) -> dict:
    """The speed (m/s) that gives every apple ``views`` frames at ``fps`` and under ``blur_px`` of motion blur, within
    the drone's limits, with which limit set it; a PlanError below the drone's slowest."""
    by_views = fps * geom["footprint_m"] / views
    by_blur = blur_px * geom["range_m"] / (fx * shutter_s)
    limits = {"views": by_views, "blur": by_blur, "drone": drone.max_speed_mps}
    which = min(limits, key=limits.get)
    speed = limits[which]
    if speed < drone.min_speed_mps:
        raise PlanError(f"{which} allow {speed:.2f} m/s, slower than the {drone.name}'s {drone.min_speed_mps:g} m/s: "
                        f"give a faster --fps or a shorter --shutter-s")
    return {"speed_mps": float(speed), "limited_by": which, "views": float(fps * geom["footprint_m"] / speed),
            "blur_px": float(fx * speed * shutter_s / geom["range_m"])}


def row_passes(rows: list[LayoutRow], origin: Origin, offset_m: float, run_in_m: float) -> list[Pass]:
    """Both sides of each row, as passes ``offset_m`` off its line, ``run_in_m`` past its ends."""
    out = []
    for r in rows:
        a, b = row_ends_enu(r, origin)
        u = (b - a) / np.linalg.norm(b - a)
        n = np.array([-u[1], u[0]])
        for side in (-1, 1):
            out.append(Pass(r.row, side, a - run_in_m * u + side * offset_m * n, b + run_in_m * u + side * offset_m * n,
                            -side * n))
    return out


def serpentine(passes: list[Pass]) -> list[Pass]:
    """The passes across the rows in order (by their offset along the rows' mean normal), every other one flown the
    other way, so that each turn is a short hop outside the rows' ends."""
    if not passes:
        return []
    u0 = passes[0].end - passes[0].start
    u0 = u0 / np.linalg.norm(u0)
    n0 = np.array([-u0[1], u0[0]])
    order = sorted(passes, key=lambda p: (float((p.start + p.end) @ n0 / 2), p.row, p.side))
    out = []
    for k, p in enumerate(order):
        along_ok = (p.end - p.start) @ u0 > 0
        if (k % 2 == 0) != along_ok:
            p = Pass(p.row, p.side, p.end, p.start, p.look)
        out.append(p)
    return out


def flight_time_s(passes: list[Pass], speed: float, height: float, drone: Drone,
                  home: np.ndarray | None = None) -> float:
    """Seconds to fly ``passes`` in order: climb, to the first, each pass at ``speed``, each hop and turn, back, down.
    ``home``: the take-off point (ENU; default the first pass's start)."""
    if not passes:
        return 0.0
    home = passes[0].start if home is None else home
    transit = min(TRANSIT_MPS, drone.max_speed_mps)
    t = 2 * height / drone.climb_mps
    t += float(np.linalg.norm(passes[0].start - home)) / transit
    for k, p in enumerate(passes):
        t += p.length_m / speed
        if k + 1 < len(passes):
            t += float(np.linalg.norm(passes[k + 1].start - p.end)) / transit + TURN_S
    return t + float(np.linalg.norm(passes[-1].end - home)) / transit


def split_flights(passes: list[Pass], speed: float, height: float, drone: Drone) -> list[list[Pass]]:
    """The rows in order, grouped into flights of whole rows that each fit the drone's usable battery; a PlanError
    for a row whose two passes alone do not."""
    order = []
    for p in serpentine(passes):
        if p.row not in order:
            order.append(p.row)
    by_row = {r: [p for p in passes if p.row == r] for r in order}
    flights, current = [], []
    for r in order:
        alone = flight_time_s(serpentine(by_row[r]), speed, height, drone)
        if alone > drone.usable_s:
            raise PlanError(f"row {r}'s two passes take {alone / 60:.1f} min, more than one battery's "
                            f"{drone.usable_s / 60:.1f} min of the {drone.name}")
        trial = serpentine(current + by_row[r])
        if current and flight_time_s(trial, speed, height, drone) > drone.usable_s:
            flights.append(serpentine(current))
            current = list(by_row[r])
        else:
            current = current + by_row[r]
    if current:
        flights.append(serpentine(current))
    return flights


def plan_cameras(flights: list[list[Pass]], speed: float, fps: float, height: float, pitch_deg: float) -> dict:
    """The planned frames' cameras as poses.csv's columns (ENU centres, ENU-to-camera quaternions), every frame at
    ``fps`` along each pass."""
    from scipy.spatial.transform import Rotation

    C, Q = [], []
    down = np.radians(pitch_deg)
    for passes in flights:
        for p in passes:
            n = max(2, int(np.ceil(p.length_m / speed * fps)) + 1)
            s = np.linspace(0.0, 1.0, n)[:, None]
            xy = p.start + s * (p.end - p.start)
            z_axis = np.array([*(np.cos(down) * p.look), -np.sin(down)])  # the optical axis, ENU
            x_axis = np.cross(z_axis, [0.0, 0.0, 1.0])
            x_axis /= np.linalg.norm(x_axis)
            y_axis = np.cross(z_axis, x_axis)
            R = np.stack([x_axis, y_axis, z_axis])  # ENU -> camera (x right, y down, z forward)
            C.append(np.column_stack([xy, np.full(n, height)]))
            Q.append(np.repeat(Rotation.from_matrix(R).as_quat()[None], n, 0))
    C, Q = np.concatenate(C), np.concatenate(Q)
    return {"frame": np.arange(len(C)), "x": C[:, 0], "y": C[:, 1], "z": C[:, 2], "qx": Q[:, 0], "qy": Q[:, 1],
            "qz": Q[:, 2], "qw": Q[:, 3]}


def layout_trees_enu(rows: list[LayoutRow], origin: Origin, hedge: dict = DEFAULT_HEDGE) -> tuple[list[dict], list[dict]]:
    """rows.csv-like and trees.csv-like records of the layout's rows and trees (ENU about ``origin``), as the ground's
    coverage reads them."""
    out_rows, out_trees = [], []
    for r in rows:
        a, b = row_ends_enu(r, origin)
        out_rows.append({"row": r.row, "start_x": float(a[0]), "start_y": float(a[1]), "end_x": float(b[0]),
                         "end_y": float(b[1])})
        u = (b - a) / np.linalg.norm(b - a)
        for k, t in enumerate(tree_positions(r, origin)):
            out_trees.append({"row": r.row, "tree": k + 1, "along_m": float((t - a) @ u), "x": float(t[0]),
                              "y": float(t[1])})
    return out_rows, out_trees


@dataclass
class Plan:
    settings: PlanSettings
    drone: Drone
    camera: dict
    detector: dict
    origin: Origin
    geometry: dict
    speed: dict
    flights: list[list[Pass]]
    trees: list[dict]
    minutes: list[float]
    #: What the plan cannot do as asked, one line each (a pass cut short or left out by the boundary, a hop leaving it).
    problems: list[str] = field(default_factory=list)

    def as_dict(self) -> dict:
        """plan.json: what the plan says and how it was made; waypoints in WGS84 with heights above take-off."""
        flights = []
        for k, (passes, minutes) in enumerate(zip(self.flights, self.minutes)):
            wps = []
            for p in passes:
                heading = float(np.degrees(np.arctan2(p.look[0], p.look[1])) % 360.0)  # the camera's, from north
                for xy in (p.start, p.end):
                    lat, lon, _ = self.origin.to_geodetic(np.array([[*xy, 0.0]]))[0]
                    wps.append({"lat": float(lat), "lon": float(lon), "row": p.row, "side": p.side,
                                "heading_deg": heading})
            flights.append({"flight": k + 1, "rows": sorted({p.row for p in passes}), "minutes": round(minutes, 2),
                            "passes": len(passes), "waypoints": wps})
        cov = np.array([t["coverage"] for t in self.trees], float)
        return {"format": FORMAT, "settings": asdict(self.settings), "drone": asdict(self.drone),
                "camera": self.camera, "detector": self.detector,
                "origin": {"lat": self.origin.lat, "lon": self.origin.lon},
                "heights": "above the take-off point (m), which is taken to be level with the orchard's floor",
                "height_m": round(self.geometry["height_m"], 2), "gimbal_pitch_deg": -self.settings.pitch_deg,
                "offset_m": round(self.geometry["offset_m"], 2), "range_m": round(self.geometry["range_m"], 2),
                "apple_px": round(self.geometry["apple_px"], 2), "speed_mps": round(self.speed["speed_mps"], 2),
                "speed_limited_by": self.speed["limited_by"], "views_per_apple": round(self.speed["views"], 1),
                "blur_px": round(self.speed["blur_px"], 2), "batteries": len(self.flights),
                "minutes": round(sum(self.minutes), 2),
                "coverage": {"mean": float(np.nanmean(cov)) if np.isfinite(cov).any() else None,
                             "trees": len(self.trees),
                             "trees_both_sides": int(sum(t["sides_seen"] == 2 for t in self.trees))},
                "problems": self.problems, "flights": flights}


def make_plan(layout: list[LayoutRow], camera, drone: Drone, detector: dict, settings: PlanSettings | None = None,
              camera_name: str = "") -> Plan:
    """The plan for ``layout``'s rows (all, or ``settings.rows``) with ``camera`` (pomar.camera.Camera at the video's
    size) on ``drone``, for a detector whose metadata is ``detector`` (its apple_radius_px, min_apple_radius_px)."""
    from pomar.coverage import Sight, tree_coverage

    s = settings or PlanSettings()
    rows = [r for r in layout if not s.rows or r.row in s.rows]
    missing = sorted(set(s.rows) - {r.row for r in layout})
    if missing:
        raise PlanError(f"--rows: the layout has no row {', '.join(map(str, missing))}")
    if not rows:
        raise PlanError("the layout has no rows")
    target = float(detector.get("apple_radius_px") or 0)
    min_px = float(detector.get("min_apple_radius_px") or 0)
    if not target > 0:
        raise PlanError("the detector's metadata gives no apple_radius_px: the plan cannot size the apples")
    origin = Origin(rows[0].start[0], rows[0].start[1], 0.0)
    geom = pass_geometry(camera.fx, camera.width, target, min_px, s.pitch_deg, s.max_height_m)
    fps = s.fps or drone.video_fps
    speed = pass_speed(geom, camera.fx, fps, s.views, s.blur_px, s.shutter_s or drone.shutter_s, drone)
    passes = row_passes(rows, origin, geom["offset_m"], geom["footprint_m"] / 2)
    problems = []
    fence = read_boundary(s.boundary, origin) if s.boundary else None
    if s.boundary:
        passes, problems = within_boundary(passes, fence, s.boundary, geom["footprint_m"] / 2)
        if not passes:
            raise PlanError(f"{s.boundary}: no pass of the rows asked lies inside the boundary")
    flights = split_flights(passes, speed["speed_mps"], geom["height_m"], drone)
    if s.boundary:
        problems += hops_outside(flights, fence, s.boundary)
    minutes = [flight_time_s(f, speed["speed_mps"], geom["height_m"], drone) / 60 for f in flights]
    cams = plan_cameras(flights, speed["speed_mps"], fps, geom["height_m"], s.pitch_deg)
    lrows, trees = layout_trees_enu(rows, origin)
    none = {k: np.zeros(0) for k in ("id", "x", "y", "z", "row")}
    sight = Sight(camera, min_px=min_px, scales=dict.fromkeys(range(len(cams["frame"])),
                                                              min(1.0, target / geom["apple_px"])))
    for t, c in zip(trees, tree_coverage(trees, lrows, none, cams, sight, default_hedge=DEFAULT_HEDGE)):
        t.update(c)
    if s.boundary:  # the trees the boundary costs a side, a line a row
        for r in rows:
            lost = [t["tree"] for t in trees if t["row"] == r.row and t["sides_seen"] < 2]
            if lost:
                problems.append(f"row {r.row}: trees {_spans(lost)} not seen from both sides (the boundary)")
    return Plan(s, drone, {"name": camera_name, "width": camera.width, "height": camera.height, "fx": camera.fx},
                {"apple_radius_px": target, "min_apple_radius_px": min_px}, origin, geom, speed, flights, trees,
                minutes, problems)


def _spans(numbers: list[int]) -> str:
    """1, 2, 3, 7 -> '1-3, 7'."""
    out, start = [], None
    for k, n in enumerate(sorted(numbers)):
        if start is None:
            start = prev = n
        elif n != prev + 1:
            out.append(f"{start}-{prev}" if prev > start else str(start))
            start = n
        prev = n
        if k == len(numbers) - 1:
            out.append(f"{start}-{prev}" if prev > start else str(start))
    return ", ".join(out)


def within_boundary(passes: list[Pass], poly: np.ndarray, name: str, run_in_m: float) -> tuple[list[Pass], list[str]]:
    """Each pass cut to its longest stretch inside ``poly`` (pomar.boundary.clip_segment), a pass with none left
    out; with a line for each pass cut into its row (past its run-in) or left out."""
    kept, lines = [], []
    for p in passes:
        side = "left" if p.side > 0 else "right"
        span = clip_segment(poly, p.start, p.end)
        if span is None:
            lines.append(f"row {p.row}, {side} side: its pass lies outside the boundary {name}: left out")
            continue
        t0, t1 = span
        d = p.end - p.start
        cut = [(t0 * p.length_m, "start"), ((1 - t1) * p.length_m, "end")]
        for metres, where in cut:
            if metres > run_in_m + 1e-6:
                lines.append(f"row {p.row}, {side} side: the boundary {name} stops its pass {metres - run_in_m:.1f} m "
                             f"inside the row's {where}")
        kept.append(Pass(p.row, p.side, p.start + t0 * d, p.start + t1 * d, p.look))
    return kept, lines


def hops_outside(flights: list[list[Pass]], poly: np.ndarray, name: str) -> list[str]:
    """A line for each hop between two passes (a straight line from one's end to the next's start) that leaves
    ``poly`` (pomar.boundary.outside_m): a boundary with a notch between the rows' ends, which the waypoints alone do
    not show."""
    lines = []
    for k, passes in enumerate(flights, start=1):
        for p, q in zip(passes, passes[1:]):
            out_m = outside_m(poly, p.end, q.start)
            if out_m > 0:
                sides = ["left" if x.side > 0 else "right" for x in (p, q)]
                lines.append(f"flight {k}: the hop from row {p.row}'s {sides[0]} side to row {q.row}'s {sides[1]} "
                             f"side leaves the boundary {name} for {out_m:.1f} m: fly it by hand, or add a waypoint")
    return lines


def write_plan(plan: Plan, out: Path) -> list[Path]:
    """plan.json, coverage.csv (each tree: its layout number, position, expected coverage, sides, frames) and each
    flight for the apps (pomar.plan_export: ``flight-N.plan``, ``.waypoints``, ``.litchi.csv``, ``.kmz``) and plan.png
    (pomar.plan_picture, where OpenCV is installed) in ``out``, each
    written whole or not at all."""
    import csv
    import io

    out.mkdir(parents=True, exist_ok=True)
    files = []
    body = json.dumps(plan.as_dict(), indent=1) + "\n"
    cols = ["row", "tree", "lat", "lon", "coverage", "sides_seen", "frames_seen", "range_m", "angle_deg", "apple_px"]
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(cols)
    for t in plan.trees:
        lat, lon, _ = plan.origin.to_geodetic(np.array([[t["x"], t["y"], 0.0]]))[0]
        vals = {**t, "lat": f"{lat:.9f}", "lon": f"{lon:.9f}"}
        w.writerow([vals[c] if not isinstance(vals[c], float) else f"{vals[c]:.4f}" for c in cols])
    from pomar.plan_export import WRITERS

    from pomar.plan_picture import plan_png

    texts = [("plan.json", body), ("coverage.csv", buf.getvalue())]
    png = plan_png(plan)
    if png is not None:
        texts.append(("plan.png", png))
    for k in range(len(plan.flights)):  # each flight (battery) for the apps growers fly with
        texts += [(f"flight-{k + 1}{suffix}", write(plan, k)) for suffix, write in WRITERS.items()]
    for name, text in texts:
        tmp = out / (name + ".tmp")
        tmp.write_bytes(text if isinstance(text, bytes) else text.encode())
        tmp.replace(out / name)
        files.append(out / name)
    return files
