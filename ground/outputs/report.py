"""report.json: what the flight's map holds and how it was made (poses, tracking, corrections, association, timings,
the link), from the pipeline and what the ground's program measured around it."""

from __future__ import annotations

import numpy as np

from ground.memory import children_peak_rss_mb, peak_rss_mb
from ground.outputs.tables import harvest_correlation
from ground.poses.stage import no_pose_figures
from pomar.wire import above_sea_level

#: The kinds of pose a mapped frame gets, as the pipeline counts them.
POSE_SOURCES = ("registered", "tracked", "interpolated", "extrapolated", "apples", "telemetry", "frames_without_pose")


def delay_stats(delays: list[float]) -> dict:
    d = np.asarray(delays, float)
    if not len(d):
        return {"frame_delay_median_s": None, "frame_delay_p95_s": None, "frame_delay_max_s": None}
    return {"frame_delay_median_s": float(np.median(d)), "frame_delay_p95_s": float(np.percentile(d, 95)),
            "frame_delay_max_s": float(d.max())}


def _known(v):
    """A value for report.json: None for a float that is not finite (NaN is not JSON), in dicts and lists too."""
    if isinstance(v, dict):
        return {k: _known(x) for k, x in v.items()}
    if isinstance(v, list):
        return [_known(x) for x in v]
    return None if isinstance(v, float) and not np.isfinite(v) else v


def map_section(p) -> dict:
    """The map's ENU frame (x east, y north, z up, metres) as the outputs give it: its origin (the first frame's
    position) and what the drone's altitudes are measured from. A log of heights above take-off (a DJI SRT's ``H``)
    gives the map no altitude above sea level: the outputs' alt is then empty, and the origin's alt is a height above
    take-off."""
    ref = p.altitude_reference
    above = above_sea_level(ref)
    origin = p.poses.origin if p.poses is not None else None
    return {"origin": origin.as_dict() if origin is not None else None,
            "altitude_reference": ref or "msl (not said by the drone)", "above_sea_level": above,
            "heights": ("alt: metres above sea level" if above else
                        f"no altitude above sea level ({ref}): alt is empty, z is metres above the origin, whose alt "
                        + ("is its height above take-off" if ref == "takeoff" else "is not above sea level"))}


def scale_figures(scale: dict | None) -> dict:
    """report.json's ``registration.georeference_scale`` and ``georeference_scale_from`` for the map's ``scale``
    (ScaleEstimate.as_dict's); nothing where it is None (the mapper's stand)."""
    from ground.poses.scale import heaviest_source

    return {"georeference_scale": scale, "georeference_scale_from": heaviest_source(scale)} if scale else {}


def flight_report(p, table, rows, final: bool, *, apples_seen, wall_s: float, latency: list[float],
                  memory: list, progress: list, link: dict, errors: list[str], harvest=None, orchard=None,
                  load=None, scale=None) -> dict:
    """The report of pipeline ``p`` with its apple ``table`` and ``rows``; the rest comes from the ground's program:
    the detections' envelope (``apples_seen``), its wall time, the frames' latency, memory and progress samples, the
    link's figures and the errors it caught; ``orchard``: whose numbering the rows and trees use (MapTables.orchard);
    ``load``: the load estimated from the grower's hand counts (ground.orchard.calibration.apply_load)."""
    st = p.status
    poses = p.poses.figures() if p.poses is not None else no_pose_figures()
    counters = p.counters
    posed = max(1, sum(counters[j] for j in POSE_SOURCES))
    r = {
        "flight_id": p.flight_id, "drone_id": p.drone_id, "final": final,
        # a figure not known (no hand counts, no apple measured) is null: report.json stays strict JSON
        "apples": int(len(table["id"])), "rows": _known(rows),
        "orchard": _known(orchard or {"numbering": "map"}),
        "map": map_section(p),
        "counting": p.apples.count.report(),
        "frames": counters, "gaps": p.arrivals.gaps[:100],
        # the apples' radius as the drone's detector saw them, and the frames under the smallest it finds reliably
        "apple_size": apples_seen.report(),
        # the score the drone published detections from, against the one the tracks need
        "detections": apples_seen.detections(),
        # what share of the mapped frames got each kind of pose
        "pose_shares": {k: counters[k] / posed for k in POSE_SOURCES},
        # the mapping as the stream asked for it (or as set)
        "registration": {**poses["registration"], "mapping": p.s.mapping, **scale_figures(scale)},
        "tracking": poses["tracking"],
        # poses given earlier, corrected as the mapper moved the keyframes about them; the apples triangulated again
        "corrections": dict(p.corrections),
        "association": {"params": vars(p.s.association).copy(), "stats": dict(p.apples.assoc.stats),
                        "strong_views_needed": p.apples.count.views_needed(p.arrivals.steps),
                        # the map frame's unit in metres: its first georeference's scale error
                        "metres_per_unit": p.metres_per_unit()},
        "timings": {"wall_seconds": wall_s,
                    "pose_seconds": p.seconds["poses"],
                    **poses["timings"],
                    "association_seconds": p.seconds["association"],
                    "correction_seconds": p.seconds["corrections"],
                    "ground_latency_median_s": float(np.median(latency)) if latency else None,
                    # how long frames waited on the ground, from their message's arrival to being mapped
                    **delay_stats(p.arrivals.frame_delays),
                    # the same, of the frames that came once the first model was made (no wait for it)
                    **{f"{k}_after_first_model": v for k, v in delay_stats(p.arrivals.frame_delays_mapped).items()},
                    # from the first frame's arrival to the first model (frames before it wait for it)
                    "first_model_after_s": (p.arrivals.t_first_model - p.arrivals.t_first_frame
                                            if p.arrivals.t_first_model and p.arrivals.t_first_frame else None),
                    "peak_rss_mb": peak_rss_mb(),
                    # the mapping process's (live), once it has ended: its own peak, beside the ground's
                    "mapping_peak_rss_mb": children_peak_rss_mb() if p.s.mapping == "process" else None,
                    "rss_mb_by_frames_mapped": memory,
                    "frames_mapped_by_wall_s": progress},
        "onboard_status": vars(st).copy() if st else None,
        "link": link,
        "errors": errors[-50:],
    }
    if load is not None:
        r["load"] = load
    if harvest is not None:
        r["harvest_correlation"] = harvest_correlation(rows, harvest)
    return r
