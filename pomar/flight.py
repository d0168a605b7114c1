"""The replay flight directory format (see docs/flight-format.md).

A flight directory holds ``video.mp4``, ``telemetry.tlog``, ``camera.json``, ``flight.json``
and, for simulated flights, ``truth/`` (origin, apples, trees and their loads, true camera poses, true detections).
This module is the one place that names those files and their columns.
"""

from __future__ import annotations

import csv
import json
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pomar.cli import InputError
from pomar.camera import Camera
from pomar.geo import Origin

VIDEO = "video.mp4"
TLOG = "telemetry.tlog"
CAMERA = "camera.json"
FLIGHT = "flight.json"
TRUTH = "truth"

APPLES_COLUMNS = ["apple_id", "row", "variety", "x", "y", "z", "lat", "lon", "alt", "radius_m"]
#: Written by flights rendered since the trees' truth (issue 59): each apple's tree (1.. from its row's start) and mass.
APPLE_TREE_COLUMNS = ["tree", "mass_kg"]
TREES_COLUMNS = ["row", "tree", "x", "y", "z", "lat", "lon", "apples", "mass_kg"]
FRAMES_COLUMNS = ["frame", "t_unix", "qw", "qx", "qy", "qz", "tx", "ty", "tz", "lat", "lon", "alt"]
DETECTIONS_COLUMNS = ["frame", "apple_id", "u", "v", "r_px", "visible_fraction"]


class FlightFormatError(InputError, ValueError):
    """A flight directory or one of its files is missing or malformed."""


ID_PATTERN = re.compile(r"^[A-Za-z0-9_.\-]{1,128}$")


def check_id(name: str, value) -> str:
    """A flight or drone id: 1-128 letters, digits, '_', '-', '.' (ids name zenoh key expressions, which forbid
    '/', '*', '$', '?', '#' and spaces)."""
    if not isinstance(value, str) or not ID_PATTERN.match(value):
        raise ValueError(f"{name} {value!r} may hold only letters, digits, '_', '-', '.' (1 to 128 of them)")
    return value


def id_argument(name: str):
    """An argparse ``type`` for a flight or drone id: a bad one is a usage error, not a traceback."""
    import argparse

    def parse(value: str) -> str:
        try:
            return check_id(name, value)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None
    return parse


def write_csv(path: Path, columns: list[str], rows: dict[str, np.ndarray], formats: dict[str, str] | None = None) -> None:
    """Write columns (equal-length arrays) with a header; floats formatted per column."""
    formats = formats or {}
    n = len(next(iter(rows.values()))) if rows else 0
    tmp = Path(str(path) + ".tmp")
    with open(tmp, "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(columns)
        cols = [rows[c] for c in columns]
        fmts = [formats.get(c) for c in columns]
        for i in range(n):
            w.writerow([format(col[i], fmt) if fmt else col[i] for col, fmt in zip(cols, fmts)])
    tmp.replace(path)


def read_csv(path: Path, columns: list[str], str_columns: tuple[str, ...] = ()) -> dict[str, np.ndarray]:
    """Read a CSV written by :func:`write_csv`; checks the header names every expected column."""
    try:
        with open(path, newline="") as f:
            reader = csv.reader(f)
            header = next(reader, None)
            if header is None:
                raise FlightFormatError(f"{path}: empty file, expected header {','.join(columns)}")
            missing = [c for c in columns if c not in header]
            if missing:
                raise FlightFormatError(f"{path}: missing column(s) {missing}; header is {header}")
            idx = [header.index(c) for c in columns]
            data = [[row[i] for i in idx] for row in reader if row]
    except FileNotFoundError:
        raise FlightFormatError(f"{path}: file not found") from None
    out = {}
    for j, c in enumerate(columns):
        values = [r[j] for r in data]
        if c in str_columns:
            out[c] = np.array(values, dtype=str)
            continue
        try:
            arr = np.array(values, dtype=float)
        except ValueError as exc:
            raise FlightFormatError(f"{path}: column {c!r} is not numeric ({exc})") from None
        if c in ("frame", "apple_id", "row") and arr.size:
            arr = arr.astype(np.int64)
        out[c] = arr
    return out


@dataclass
class FlightMeta:
    flight_id: str
    drone_id: str
    video_start_utc: float  # unix seconds, by the camera's clock
    fps: float
    frame_count: int
    width: int
    height: int
    extra: dict

    def frame_time(self, frame: np.ndarray | int) -> np.ndarray | float:
        """Capture time (unix seconds, camera clock) of a frame index."""
        return self.video_start_utc + np.asarray(frame) / self.fps

    def to_dict(self) -> dict:
        from datetime import datetime, timezone

        d = {
            "flight_id": self.flight_id,
            "drone_id": self.drone_id,
            "video_start_utc": datetime.fromtimestamp(self.video_start_utc, timezone.utc).isoformat(timespec="microseconds"),
            "video_start_unix": self.video_start_utc,
            "fps": self.fps,
            "frame_count": self.frame_count,
            "width": self.width,
            "height": self.height,
        }
        d.update(self.extra)
        return d


def _parse_meta(d: dict, source: str) -> FlightMeta:
    required = ["flight_id", "drone_id", "video_start_unix", "fps", "frame_count", "width", "height"]
    missing = [k for k in required if k not in d]
    if missing:
        raise FlightFormatError(f"{source}: missing key(s) {missing}")
    extra = {k: v for k, v in d.items() if k not in required and k != "video_start_utc"}
    try:
        meta = FlightMeta(
            check_id("flight_id", d["flight_id"]), check_id("drone_id", d["drone_id"]), float(d["video_start_unix"]),
            float(d["fps"]), int(d["frame_count"]), int(d["width"]), int(d["height"]), extra,
        )
    except (TypeError, ValueError) as exc:
        raise FlightFormatError(f"{source}: {exc}") from None
    if not (meta.fps > 0 and np.isfinite(meta.fps)) or meta.frame_count < 0 or meta.width <= 0 or meta.height <= 0:
        raise FlightFormatError(f"{source}: fps must be > 0, frame_count >= 0, width and height > 0")
    return meta


class FlightDir:
    """Accessors for one flight directory."""

    def __init__(self, path: str | Path):
        self.path = Path(path)
        if not self.path.is_dir():
            raise FlightFormatError(f"{self.path}: not a flight directory (does not exist)")

    video = property(lambda self: self.path / VIDEO)
    tlog = property(lambda self: self.path / TLOG)

    @property
    def telemetry_log(self) -> Path:
        """The flight's telemetry: the log flight.json names (an assembled flight, pomar.assemble), else telemetry.tlog."""
        named = self.meta().extra.get("telemetry_log")
        return Path(named) if named else self.tlog
    truth_dir = property(lambda self: self.path / TRUTH)

    @property
    def has_truth(self) -> bool:
        return (self.truth_dir / "apples.csv").exists()

    def meta(self) -> FlightMeta:
        p = self.path / FLIGHT
        try:
            return _parse_meta(json.loads(p.read_text()), str(p))
        except FileNotFoundError:
            raise FlightFormatError(f"{p}: file not found") from None
        except json.JSONDecodeError as exc:
            raise FlightFormatError(f"{p}: not valid JSON ({exc})") from None

    def camera(self) -> Camera:
        return Camera.load(self.path / CAMERA)

    def origin(self) -> Origin:
        p = self.truth_dir / "origin.json"
        try:
            d = json.loads(p.read_text())
            return Origin(float(d["lat"]), float(d["lon"]), float(d["alt"]))
        except FileNotFoundError:
            raise FlightFormatError(f"{p}: file not found") from None
        except (KeyError, ValueError, TypeError) as exc:
            raise FlightFormatError(f"{p}: malformed origin ({exc})") from None

    def truth_apples(self, trees: bool = False) -> dict[str, np.ndarray]:
        """Every apple of the simulated orchard; with ``trees``, each one's tree and mass too (APPLE_TREE_COLUMNS:
        a flight rendered since the trees' truth)."""
        return read_csv(self.truth_dir / "apples.csv", APPLES_COLUMNS + (APPLE_TREE_COLUMNS if trees else []),
                        str_columns=("variety",))

    def truth_trees(self) -> dict[str, np.ndarray]:
        """Every tree of the simulated orchard (truth/trees.csv): row, tree (1.. from the row's start), canopy centre
        (ENU, WGS84), and its full load: the apples it carries, seen or not, and their mass (kg)."""
        return read_csv(self.truth_dir / "trees.csv", TREES_COLUMNS)

    def truth_frames(self) -> dict[str, np.ndarray]:
        return read_csv(self.truth_dir / "frames.csv", FRAMES_COLUMNS)

    def truth_detections(self) -> dict[str, np.ndarray]:
        return read_csv(self.truth_dir / "detections.csv", DETECTIONS_COLUMNS)

    def truth_poses(self) -> tuple[np.ndarray, np.ndarray]:
        """True world(ENU)-to-camera poses: R (F, 3, 3), t (F, 3), indexed by frame."""
        from pomar.rotations import quat_wxyz_to_rotation

        fr = self.truth_frames()
        order = np.argsort(fr["frame"])
        q = np.stack([fr[k][order] for k in ("qw", "qx", "qy", "qz")], axis=1)
        t = np.stack([fr[k][order] for k in ("tx", "ty", "tz")], axis=1)
        return quat_wxyz_to_rotation(q).as_matrix(), t
