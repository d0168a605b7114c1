"""The map at one refresh, made once (:func:`snapshot`) and read by the tables, the node and rerun, so that none of
them reaches into the pipeline's parts."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from pomar.align import Similarity, compose
from pomar.geo import Origin
from pomar.wire import above_sea_level


@dataclass
class MapSnapshot:
    """What the map's outputs read, in the map frame with what takes it to ENU and WGS84."""
    #: Every apple the count holds, by id (ground.apples.association.Apple), and the ids counted.
    apples: dict
    counted_ids: list[int]
    #: Each apple's fruit radius (association units) where known: its least hidden views' (apples.csv's radius_m;
    #: candidates.csv gives the radius the size check compared, its views' median, from ``checks``).
    size: dict[int, float]
    #: Map frame index -> frame number.
    frame_of: list[int]
    #: Frame number -> its pose (ground.poses.georeference.Pose, map frame).
    poses: dict
    #: Map frame -> ENU; None before the poses exist.
    to_enu: Similarity | None
    #: The map's bend and drift corrections at every posed frame (frames, ENU offsets, ENU rotations), computed once.
    corrections: tuple[np.ndarray, np.ndarray, np.ndarray] | None
    origin: Origin | None
    #: Frame number -> capture time (unix s).
    frame_times: dict[int, float]
    metres_per_unit: float
    #: The counting's checks of every apple it was chosen from (candidates.csv), at the flight's end.
    checks: dict | None = None
    #: What the frames' altitudes were measured from (pomar.wire.ALTITUDE_REFERENCES; None: not said, sea level).
    altitude_reference: str | None = None
    #: The map's scale, its 1-sigma and each source's estimate and weight (ground.poses.scale.ScaleEstimate.as_dict);
    #: None before the map is scaled.
    scale: dict | None = None

    @property
    def scale_sigma_rel(self) -> float:
        """The map scale's relative 1-sigma, which every size carries; NaN where not known."""
        return float(self.scale["sigma_pct"]) / 100.0 if self.scale else float("nan")

    @property
    def above_sea_level(self) -> bool:
        """Whether the map's heights can be given as altitudes above sea level (not with heights above take-off)."""
        return above_sea_level(self.altitude_reference)


def snapshot(pipe, final: bool = False) -> MapSnapshot:
    """The map of a ground.pipeline.GroundPipeline now; the candidates' checks too at the end (``final``)."""
    frames = pipe.apples.frames
    corr = None
    if pipe.poses is not None:
        posed = np.array(sorted(frames.poses), int)
        corr = (posed, *pipe.poses.correction(posed, pipe.s.drift_sigma_s * (pipe.fps or 0.0)))
    count = pipe.apples.count
    return MapSnapshot(apples=count.apples, counted_ids=count.counted_ids(), size=count.size,
                       frame_of=frames.frame,
                       poses=frames.poses, to_enu=pipe.poses.map_to_enu() if pipe.poses is not None else None,
                       corrections=corr, origin=pipe.poses.origin if pipe.poses is not None else None,
                       frame_times=pipe.arrivals.frame_times, metres_per_unit=pipe.metres_per_unit(),
                       checks=count.checks(all_expected=True) if final else None,
                       altitude_reference=pipe.altitude_reference,
                       scale=pipe.poses.scale_estimate() if pipe.poses is not None else None)


def rescaled(snap: MapSnapshot, scale: dict) -> MapSnapshot:
    """The map ``snap`` at another estimate of its scale (``scale``, ScaleEstimate.as_dict's, e.g. with one more
    source): stretched by the ratio of the two about its cameras' centre in ENU, where the GPS track holds it."""
    if snap.to_enu is None or not snap.scale or not snap.poses:
        return replace(snap, scale=scale)
    f = float(scale["scale"]) / float(snap.scale["scale"])
    c = snap.to_enu.apply(np.array([p.centre for p in snap.poses.values()], float).reshape(-1, 3)).mean(0)
    about = Similarity(f, np.eye(3), (1.0 - f) * c)  # x -> c + f (x - c)
    return replace(snap, to_enu=compose(about, snap.to_enu), metres_per_unit=snap.metres_per_unit * f, scale=scale)
