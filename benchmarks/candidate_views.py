"""What the apples a map counts are, by the truth: a simulated flight's recorded stream fed to the ground pipeline in
this one process (lock-step, mapping inline), then each candidate apple's views matched to the truth's projected
apples in their frames (the nearest centre, within the apple's radius or 4 px). An apple is *visible* when the
truth counts it (at least half visible in 3 frames), *hidden* when it is a real apple the truth does not count
(seen through leaves, or in too few frames), *false* when its views match no apple.

    python benchmarks/candidate_views.py FLIGHT_DIR JOURNAL [--json OUT]

Prints, for the apples counted and those the count's checks left out, how many are of each kind; where the
visible apples the count misses were lost (never detected, detected in fewer than 3 frames, detected but in no
apple, in an apple with too few strong views to be confirmed, or left out by a check); then the quartiles of what
tells the kinds apart: the detection score (median over the apple's views), the views, the radius (as a share of
the map's median), the boxes' roundness (short side over long side), the best view's visible fraction, the depth
and the parallax of the views.
"""

from __future__ import annotations

import argparse
import json
import logging
import tempfile
from pathlib import Path

import numpy as np

from ground.link.journal import read_journal
from ground.pipeline import GroundPipeline, GroundSettings
from pomar import wire
from pomar.countable import MIN_VIEWS, MIN_VISIBLE, countable_ids
from pomar.flight import FlightDir

KINDS = ("visible", "hidden", "false")
FEATURES = ("score", "views", "radius", "roundness", "best_visible", "depth_m", "parallax_deg")


def truth_index(flight: FlightDir, min_visible: float = MIN_VISIBLE, min_views: int = MIN_VIEWS):
    """The truth's projected apples by frame, and the ids of the apples it counts as visible."""
    td = flight.truth_detections()
    by_frame: dict[int, np.ndarray] = {}
    order = np.argsort(td["frame"], kind="stable")
    frames, starts = np.unique(td["frame"][order], return_index=True)
    for f, part in zip(frames, np.split(order, starts[1:])):
        by_frame[int(f)] = part
    return td, by_frame, set(countable_ids(td["apple_id"], td["visible_fraction"], min_visible, min_views).tolist())


def candidates(flight: FlightDir, journal: Path) -> tuple[list[dict], dict[str, int]]:
    """Every candidate apple of the lock-step map, with its kind and features; and where the visible apples the
    count misses were lost (:func:`missed`)."""
    td, by_frame, visible = truth_index(flight)
    boxes, scores = {}, {}
    emitted = {}  # every apple the association gave, confirmed or not
    with tempfile.TemporaryDirectory() as work:
        pipe = GroundPipeline(Path(work), GroundSettings(mapping="inline"))
        confirm = pipe.apples.count.confirm

        def _confirm(apples, steps):
            emitted.update((a.id, a) for a in apples)
            return confirm(apples, steps)

        pipe.apples.count.confirm = _confirm
        for payload in read_journal(journal):
            m = wire.decode(payload)
            if isinstance(m, wire.FrameMessage):  # the detections as the pipeline keeps them (it forgets old ones)
                keep = np.asarray(m.scores) >= pipe.s.min_score
                boxes[m.frame] = np.asarray(m.boxes, float).reshape(-1, 4)[keep]
                scores[m.frame] = np.asarray(m.scores)[keep]
            pipe.take(m)
        pipe.finish()
        checks = pipe.apples.count.checks(all_expected=True)
        out = []
        for k, i in enumerate(checks["id"]):
            a = pipe.apples.count.apples[int(i)]
            votes: dict[int, int] = {}
            views = []
            for o in a.observations:
                seq, d = o.frame, o.index
                f = pipe.apples.frames.frame[seq]
                b = boxes[f][d]
                pose = pipe.apples.frames.poses.get(f)
                depth = float((pose.R @ a.X + pose.t)[2]) if pose is not None else np.nan
                vis = np.nan
                j = _truth_row(b, f, td, by_frame)
                if j is not None:
                    t = int(td["apple_id"][j])
                    votes[t] = votes.get(t, 0) + 1
                    vis = float(td["visible_fraction"][j])
                views.append((b[2] - b[0], b[3] - b[1], depth, scores[f][d], vis))
            V = np.array(views)
            w, h = V[:, 0], V[:, 1]
            tid = max(votes, key=votes.get) if votes else None
            out.append({
                "id": int(i), "kind": "false" if tid is None else ("visible" if tid in visible else "hidden"),
                "left_out": str(checks["left_out"][k]), "score": float(np.median(V[:, 3])), "views": len(V),
                "radius_m": float(checks["radius"][k] * pipe.metres_per_unit()),
                "roundness": float(np.median(np.minimum(w, h) / np.maximum(w, h))),
                "best_visible": float(np.nanmax(V[:, 4])) if np.isfinite(V[:, 4]).any() else float("nan"),
                "depth_m": float(np.nanmedian(V[:, 2])), "parallax_deg": float(pipe.apples.count.parallax_deg(a))})
        lost = missed(pipe, emitted, out, td, by_frame, visible, boxes)
    return out, lost


def _truth_row(b: np.ndarray, f: int, td, by_frame) -> int | None:
    """The truth detection (its row in ``td``) a box in frame f shows: the nearest projected centre, within its
    radius or 4 px."""
    if f not in by_frame:
        return None
    J = by_frame[f]
    dist = np.hypot(td["u"][J] - (b[0] + b[2]) / 2, td["v"][J] - (b[1] + b[3]) / 2)
    j = J[np.argmin(dist)]
    return int(j) if dist.min() < max(4.0, td["r_px"][j]) else None


def _truth_of(b: np.ndarray, f: int, td, by_frame) -> int | None:
    """The truth apple a box in frame f shows (:func:`_truth_row`)."""
    j = _truth_row(b, f, td, by_frame)
    return None if j is None else int(td["apple_id"][j])


def missed(pipe, emitted: dict, rows: list[dict], td, by_frame, visible: set, boxes: dict) -> dict[str, int]:
    """Where each visible apple that no counted apple shows was lost, the furthest it got: left out by a check
    (small, narrow, few_views), in an apple without enough strong views (unconfirmed), detected in 3 frames or more
    but in no apple, detected in fewer, never detected."""
    det = {}  # truth apple -> frames it was detected in
    for f, B in boxes.items():
        for b in B:
            t = _truth_of(b, f, td, by_frame)
            if t is not None:
                det[t] = det.get(t, 0) + 1
    left = {r["id"]: r["left_out"] for r in rows}
    stage = {}  # truth apple -> (rank, stage), the furthest any apple showing it got
    for i, a in emitted.items():
        votes: dict[int, int] = {}
        for o in a.observations:
            seq, d = o.frame, o.index
            f = pipe.apples.frames.frame[seq]
            t = _truth_of(boxes[f][d], f, td, by_frame)
            if t is not None:
                votes[t] = votes.get(t, 0) + 1
        if not votes:
            continue
        t = max(votes, key=votes.get)
        st = ((2, f"left out: {left[i]}") if left[i] else (3, "counted")) if i in left else (1, "unconfirmed")
        stage[t] = max(stage.get(t, (0, "")), st)
    out: dict[str, int] = {}
    for t in visible:
        st = stage.get(t, (0, ""))[1] or ("never detected" if not det.get(t) else
                                           "detected in < 3 frames" if det[t] < 3 else "detected, in no apple")
        out[st] = out.get(st, 0) + 1
    return out


def report(rows: list[dict], lost: dict[str, int]) -> str:
    r_med = np.nanmedian([r["radius_m"] for r in rows]) if rows else np.nan
    kind = np.array([r["kind"] for r in rows])
    counted = np.array([r["left_out"] == "" for r in rows], bool)
    lines = []
    for name, sel in (("counted", counted), ("left out", ~counted)):
        lines.append(f"{name}: {int(sel.sum())} (" + ", ".join(f"{k} {int((sel & (kind == k)).sum())}" for k in KINDS) + ")")
    n_visible = sum(lost.values())
    lines.append(f"visible apples: {n_visible}; " + ", ".join(f"{k} {v}" for k, v in sorted(lost.items(), key=lambda kv: -kv[1])))
    lines.append("\napples counted, quartiles (25 / 50 / 75) by kind:")
    lines.append("| feature | " + " | ".join(KINDS) + " |")
    lines.append("| --- | " + " | ".join("---" for _ in KINDS) + " |")
    for feat in FEATURES:
        v = np.array([r["radius_m"] / r_med if feat == "radius" else r[feat] for r in rows], float)
        cells = []
        for k in KINDS:
            x = v[counted & (kind == k)]
            x = x[np.isfinite(x)]
            cells.append(" / ".join(f"{q:.2f}" for q in np.percentile(x, [25, 50, 75])) if len(x) else "–")
        lines.append(f"| {feat} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("flight_dir")
    ap.add_argument("journal", type=Path, help="its recorded stream (a ground's journal.bin)")
    ap.add_argument("--json", type=Path, help="write every candidate's kind and features here")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    rows, lost = candidates(FlightDir(args.flight_dir), args.journal)
    if args.json:
        args.json.write_text(json.dumps({"candidates": rows, "visible_apples_by_stage": lost}, indent=1))
    print(report(rows, lost))


if __name__ == "__main__":
    main()
