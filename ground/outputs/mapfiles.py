"""The flight's map files in the output folder, written at each refresh (atomically): the apple tables, poses.csv,
candidates.csv at the end, report.json, and the COLMAP model files. A disk that refuses them (full, read-only) is a
warning: the flight goes on in memory, every refresh tries again, and at the end they go to a rescue folder."""

from __future__ import annotations

import logging
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ground.orchard.calibration import DEFAULT_MODEL
from ground.orchard.tables import orchard_tables
from ground.outputs.snapshot import MapSnapshot
from ground.outputs.tables import (apple_table, candidate_table, candidates_csv, pose_table, poses_csv, rescue_folder,
                                   write_atomic, write_json, write_map)

log = logging.getLogger(__name__)


@dataclass
class MapTables:
    """One refresh's tables: the counted apples (columns), the rows' direction (rad), the rows, the cameras, and
    whose numbering the rows and trees use (report.json's ``orchard``)."""
    apples: dict
    direction: float
    rows: list[dict]
    cameras: dict
    orchard: dict
    trees: list[dict]
    #: The load estimated from the hand counts (report.json's ``load``); None without them.
    load: dict | None = None
    #: The map's scale the tables were made at (ground.poses.scale.ScaleEstimate.as_dict: with the layout's row
    #: spacing where one was given); None before the map is scaled.
    scale: dict | None = None

    def drone_latlon(self) -> list[float] | None:
        return [self.cameras["lat"][-1], self.cameras["lon"][-1]] if len(self.cameras["frame"]) else None

    def trajectory_latlon(self, every: int = 5) -> np.ndarray | None:
        cams = self.cameras
        return np.stack([cams["lat"], cams["lon"]], 1)[::every] if len(cams["frame"]) else None


class MapFiles:
    """The map files of one flight in ``out``; ``failed`` says why the last refresh could not write them."""

    def __init__(self, out: Path, tree_spacing_m: float, growers=None, load_model: str = DEFAULT_MODEL):
        self.out = Path(out)
        self.tree_spacing_m = tree_spacing_m
        self.growers = growers  # the grower's layout and hand counts (ground.orchard.files.OrchardFiles)
        self.load_model = load_model
        self.failed: str | None = None  # why the map files could not be written at the last refresh
        self._was_failing = False  # the refresh before failed to write
        self.rescued_to: Path | None = None  # where the map files went when they could not be written to out

    def write_tables(self, snap: MapSnapshot, out: Path | None = None, sight=None) -> MapTables:
        """The tables of the map ``snap``, written to ``out`` (default: the flight's folder); candidates.csv where
        the snapshot was made at the end (it holds the candidates' checks). With ``sight``
        (pomar.coverage.Sight: how the drone saw), each tree's and row's coverage."""
        out = out or self.out
        table, direction = apple_table(snap)
        cams = pose_table(snap)
        if self.growers is not None and self.growers.layout is not None:
            from ground.orchard.register import scaled_to_layout

            scaled = scaled_to_layout(snap, table, cams, self.growers.layout)  # the layout's row spacing scales it too
            if scaled is not snap:
                snap = scaled
                table, direction = apple_table(snap)
                cams = pose_table(snap)
        rows, trees, orchard, load = orchard_tables(table, direction, snap, cams, sight, self.growers,
                                                    self.tree_spacing_m, self.load_model)
        self._was_failing, self.failed = self.failed is not None, None
        self._written(lambda: write_map(out, table, rows, trees))
        self._written(lambda: write_atomic(out / "poses.csv", poses_csv(cams)))
        if snap.checks is not None:
            candidates = candidate_table(snap)
            self._written(lambda: write_atomic(out / "candidates.csv", candidates_csv(candidates)))
        return MapTables(table, direction, rows, cams, orchard, trees, load, snap.scale)

    def write_report(self, report: dict, out: Path | None = None) -> None:
        out = out or self.out
        self._written(lambda: write_json(out / "report.json", report))
        if self._was_failing and self.failed is None and out == self.out:
            log.warning("the map files are written again")

    def _written(self, write):
        """``write()``'s result (True where it returns nothing); None, with a warning the first time, where the disk
        refuses it (full, read-only): the flight goes on in memory, the files already there stay whole (they are
        replaced atomically), and every refresh tries again."""
        try:
            out = write()
        except OSError as exc:
            if not self._was_failing and self.failed is None:
                log.warning("the map files cannot be written (%s): the flight goes on; every refresh tries again",
                            exc.strerror or exc)
            self.failed = f"{getattr(exc, 'filename', None) or self.out}: {exc.strerror or exc}"
            return None
        return True if out is None else out

    def rescue(self, flight_id: str | None, refresh) -> dict:
        """The map files could not be written where asked at the flight's end (a full disk): nothing computed is lost,
        ``refresh(out)`` writes them to a folder of the system's temporary directory (often another disk), and the
        report says where."""
        failed = self.failed
        self.rescued_to = rescue_folder(flight_id, os.getpid())
        report = refresh(self.rescued_to)
        if self.failed is None:
            log.warning("the map files could not be written to %s (%s): they are in %s", self.out, failed,
                        self.rescued_to)
        self.failed = failed
        report["link"]["outputs_write_failed"] = failed
        return report

    def write_model(self, poses) -> None:
        """The COLMAP model(s) of ``poses``' mapper, in ENU, as text (under ``model/``)."""
        self._written(lambda: self._write_model(poses))

    def _write_model(self, poses):
        import pycolmap

        for k, sm in enumerate(poses.submodels()):
            if sm.rec is None and sm.path is None:  # mapped in memory (its disk was full): only its poses came back
                log.warning("sub-model %d was mapped in memory: its model files cannot be written", k)
                continue
            d = self.out / "model" / str(k)
            d.mkdir(parents=True, exist_ok=True)
            rec = pycolmap.Reconstruction(sm.reconstruction())
            if poses.fit is not None:
                from pomar.align import compose

                S = compose(poses.fit, sm.to_first)
                rec.transform(pycolmap.Sim3d(S.scale, pycolmap.Rotation3d(S.R), S.t))
            rec.write_text(str(d))
