"""report.json: what the flight's map holds and how it was made (poses, tracking, corrections, association, timings,
the link), from the pipeline and what the ground's program measured around it."""

from __future__ import annotations

import numpy as np

from ground.memory import children_peak_rss_mb, peak_rss_mb
from ground.outputs.tables import harvest_correlation

#: The kinds of pose a mapped frame gets, as the pipeline counts them.
POSE_SOURCES = ("registered", "tracked", "interpolated", "apples", "telemetry", "frames_without_pose")


def delay_stats(delays: list[float]) -> dict:
    d = np.asarray(delays, float)
    if not len(d):
        return {"frame_delay_median_s": None, "frame_delay_p95_s": None, "frame_delay_max_s": None}
    return {"frame_delay_median_s": float(np.median(d)), "frame_delay_p95_s": float(np.percentile(d, 95)),
            "frame_delay_max_s": float(d.max())}


def flight_report(p, table, rows, final: bool, *, apples_seen, wall_s: float, latency: list[float],
                  memory: list, progress: list, link: dict, errors: list[str], harvest=None) -> dict:
    """The report of pipeline ``p`` with its apple ``table`` and ``rows``; the rest comes from the ground's program:
    the detections' envelope (``apples_seen``), its wall time, the frames' latency, memory and progress samples, the
    link's figures and the errors it caught."""
    st = p.status
    reg = p.poses.mapper.stats() if p.poses is not None else None
    counters = p.counters
    posed = max(1, sum(counters[j] for j in POSE_SOURCES))
    r = {
        "flight_id": p.flight_id, "drone_id": p.drone_id, "final": final,
        "apples": int(len(table["id"])), "rows": rows,
        "counting": p.apples.count.report(),
        "frames": counters, "gaps": p.arrivals.gaps[:100],
        # the apples' radius as the drone's detector saw them, and the frames under the smallest it finds reliably
        "apple_size": apples_seen.report(),
        # the score the drone published detections from, against the one the tracks need
        "detections": apples_seen.detections(),
        # what share of the mapped frames got each kind of pose
        "pose_shares": {k: counters[k] / posed for k in POSE_SOURCES},
        "registration": {
            "keyframes_processed": reg["keyframes_processed"] if reg else 0,
            "registered": len(p.poses.model_pose) if p.poses else 0,
            "failed": reg["failed"] if reg else 0,
            "submodels": reg["submodels"] if reg else 0,
            # the mapping process died by itself (exit code, keyframes mapped and lost); each restart, and how its
            # new model was placed in the map's frame (keyframes shared, residuals) or null if it never was
            "mapper_died": p.poses.mapper.died if p.poses else None,
            "mapper_restarts": list(p.poses.mapper.restarts) if p.poses else [],
            # the keyframe from which the mapping folder refused writes (a full disk): mapped in memory since,
            # and those sub-models' model files are not written
            "in_memory_from_keyframe": reg.get("in_memory_from") if reg else None,
            # across passes: keyframes matched to earlier keyframes of the same place, re-anchorings of a
            # sub-model onto earlier passes' points, sub-models placed by telemetry after the chain broke
            "revisits": reg["revisits"] if reg else 0,
            "reanchored": reg["reanchored"] if reg else 0,
            "rejoined": reg["rejoined"] if reg else 0,
            # the map's drift from the GPS along the flight, and whether the outputs were corrected for it
            "drift_m": p.poses.assoc.drift_m if p.poses else 0.0,
            "drift_corrected": p.poses.assoc.drift_corrected if p.poses else False,
            # the map's turn from the gimbal's attitudes along the flight, and whether it was taken back out
            "bend_deg": p.poses.assoc.bend_deg if p.poses else 0.0,
            "bend_corrected": p.poses.assoc.bend_corrected if p.poses else False,
            "seconds_per_keyframe_median": float(np.median(reg["seconds"])) if reg and reg["seconds"] else None,
            "stage_seconds_median": reg["stage_seconds_median"] if reg else None,
            "mapping": p.s.mapping,  # as the stream asked for it (or as set)
            # proposals the mapping process replaced with a newer one before it was free
            "proposals_skipped": p.poses.mapper.skipped if p.poses else 0,
            # keyframes before the first model whose SIFT features this process extracted, the mapper being busy
            "features_extracted_here": p.poses.mapper.early_extracted if p.poses else 0,
            "georeference_gps_rms_m": p.poses.fit_residual_m if p.poses else None,
            # what scales the map: the GPS positions, or the heights above take-off against the floor it sees
            "georeference_scale_from": reg.get("scale_from", "positions") if reg else None,
            "origin": p.poses.origin.as_dict() if p.poses and p.poses.origin else None,
        },
        "tracking": {"tracked": p.poses.tracking.tracker.tracked if p.poses else 0,
                     # frames that tracking could not place, even after the mapper had mapped them (flagged)
                     "failed": len(p.poses.tracking.failed_frames) if p.poses else 0,
                     # frames tracked once the mapper, handed them when tracking failed, had mapped them
                     "retried_after_mapping": p.poses.tracking.retried if p.poses else 0,
                     # times the frames waited for a busy mapper to take a keyframe (mapping behind the flight)
                     "waits_for_mapper": p.poses.tracking.waits_for_mapper if p.poses else 0,
                     "failed_frames": p.poses.tracking.failed_frames[-100:] if p.poses else []},
        # poses given earlier, corrected as the mapper moved the keyframes about them; the apples triangulated again
        "corrections": dict(p.corrections),
        "association": {"params": vars(p.s.association).copy(), "stats": dict(p.apples.assoc.stats),
                        "strong_views_needed": p.apples.count.views_needed(p.arrivals.steps),
                        # the association frame's unit in metres: its first georeference's scale error
                        "metres_per_unit": p.metres_per_unit()},
        "timings": {"wall_seconds": wall_s,
                    "pose_seconds": p.seconds["poses"],
                    "tracking_seconds": p.poses.tracking.seconds["tracking"] if p.poses else 0.0,
                    "inline_mapping_seconds": p.poses.tracking.seconds["mapping_inline"] if p.poses else 0.0,
                    "mapping_seconds": float(sum(reg["seconds"])) if reg else 0.0,
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
    if harvest is not None:
        r["harvest_correlation"] = harvest_correlation(rows, harvest)
    return r
