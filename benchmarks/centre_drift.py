"""How far the detector's box centres stray from the true apple centres, and what that does in 3-D.

    python -m ground replay replay_data/demo-flight --out out/demo          # a lock-step replay
    python benchmarks/centre_drift.py replay_data/demo-flight out/demo [--json OUT]

Reads the detections the ground received (the replay's journal.bin), its camera poses (poses.csv) and
the simulated flight's truth. Each detection is paired with the true apple whose centre lies within
that apple's radius (at least 3 px). It prints:

1. The pixel error of the detector's centres against the true centres, by the apple's visible fraction.
2. Per apple, the drift of that error along the image motion, in px per 1,000 px travelled (the slope
   of u_detected - u_true against u_true). A leaf nearer the camera moves faster across the image than
   the apple behind it, so the visible part of a partly hidden apple slides with the motion. The
   drift is shown by the apples' visible fraction.
3. In 3-D: for each apple detected in at least 3 frames, the point triangulated from the detector's
   centres and from the true centres of the same frames, through the same replay poses (mapped into
   the truth's frame by the georeferencing fit, as the replay's evaluation does). The error along
   the viewing ray (negative = towards the camera) and across it, by the number of frames. Extra drift
   across a track reads as extra parallax, which puts the apple nearer the camera; the fewer the
   frames, the shorter the baseline and the larger the error.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from ground.apples.geometry import triangulate_nonlinear
from ground.link.journal import read_journal
from ground.evaluation.scoring import replay_cameras, shape_fit
from pomar import wire
from pomar.flight import FlightDir


def paired_detections(flight: FlightDir, journal: Path) -> dict[str, np.ndarray]:
    """Every true (frame, apple) with a detection centre within the apple's radius (>= 3 px)."""
    dets = {}
    for payload in read_journal(journal):
        m = wire.decode(payload)
        if isinstance(m, wire.FrameMessage) and len(m.boxes):
            dets[m.frame] = m.centres
    td = flight.truth_detections()
    rows = []
    for f, aid, u, v, r, vf in zip(td["frame"].astype(int), td["apple_id"].astype(int), td["u"], td["v"],
                                   td["r_px"], td["visible_fraction"]):
        c = dets.get(f)
        if c is None:
            continue
        d = np.hypot(c[:, 0] - u, c[:, 1] - v)
        j = int(np.argmin(d))
        if d[j] <= max(r, 3.0):
            rows.append((f, aid, u, v, c[j, 0], c[j, 1], vf))
    a = np.array(rows, float).reshape(-1, 7)
    return {"frame": a[:, 0].astype(int), "apple": a[:, 1].astype(int), "true": a[:, 2:4], "det": a[:, 4:6],
            "visible": a[:, 6]}


def drift_slopes(p: dict, min_visible: float, min_frames: int = 5, min_travel_px: float = 50.0) -> np.ndarray:
    """Per apple, d(u_det - u_true) / d(u_true) * 1000 over its detections at least min_visible visible."""
    out = []
    for aid in np.unique(p["apple"]):
        s = (p["apple"] == aid) & (p["visible"] >= min_visible)
        u = p["true"][s, 0]
        if s.sum() >= min_frames and np.ptp(u) >= min_travel_px:
            out.append(1000.0 * np.polyfit(u, p["det"][s, 0] - u, 1)[0])
    return np.array(out)


def ray_errors(flight: FlightDir, out: Path, p: dict) -> np.ndarray:
    """(apples, 5): frames, along-ray and across-ray error of the detector's and the truth's points (m)."""
    frames, C, R = replay_cameras(flight, out)
    S = shape_fit(flight, frames, C, R).similarity
    C_t = S.apply(C)  # the replay's cameras in the truth's frame
    R_t = R @ S.R.T
    K = flight.camera().K_opencv
    P = {int(f): K @ np.hstack([r, -(r @ c)[:, None]]) for f, c, r in zip(frames, C_t, R_t)}
    a = flight.truth_apples()
    X_true = dict(zip(a["apple_id"].astype(int), np.stack([a["x"], a["y"], a["z"]], 1)))
    rows = []
    for aid in np.unique(p["apple"]):
        s = np.nonzero((p["apple"] == aid) & np.isin(p["frame"], list(P)))[0]
        if len(s) < 3:
            continue
        Ps = np.array([P[int(f)] for f in p["frame"][s]])
        X = X_true[int(aid)]
        centre = C_t[np.isin(frames, p["frame"][s])].mean(0)
        ray = (X - centre) / np.linalg.norm(X - centre)
        row = [len(s)]
        for key in ("det", "true"):
            e = triangulate_nonlinear(Ps, p[key][s]) - X
            row += [e @ ray, np.linalg.norm(e - (e @ ray) * ray)]
        rows.append(row)
    return np.array(rows, float).reshape(-1, 5)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("flight_dir", help="a simulated flight (with truth/)")
    ap.add_argument("replay_out", help="a replay's output folder (journal.bin, poses.csv)")
    ap.add_argument("--json", help="write the figures here")
    args = ap.parse_args()
    flight, out = FlightDir(args.flight_dir), Path(args.replay_out)
    if not flight.has_truth:
        raise SystemExit(f"{flight.path}: no truth/ to compare with")
    for name in ("journal.bin", "poses.csv"):
        if not (out / name).is_file():
            raise SystemExit(f"{out / name}: not found (run python -m ground replay first)")
    p = paired_detections(flight, out / "journal.bin")
    res: dict = {"flight": str(flight.path), "replay": str(out), "paired_detections": len(p["frame"])}

    print(f"{len(p['frame'])} detections paired with a true apple")
    print("1. centre error (px), by visible fraction")
    res["centre_error_px"] = []
    for lo, hi in ((0.0, 0.5), (0.5, 0.8), (0.8, 0.95), (0.95, 1.01)):
        s = (p["visible"] >= lo) & (p["visible"] < hi)
        if s.any():
            e = p["det"][s] - p["true"][s]
            row = {"visible_from": lo, "visible_to": min(hi, 1.0), "n": int(s.sum()),
                   "mean_u": float(e[:, 0].mean()), "mean_v": float(e[:, 1].mean()),
                   "median_abs": float(np.median(np.hypot(e[:, 0], e[:, 1])))}
            res["centre_error_px"].append(row)
            print(f"   visible {lo:.2f}-{min(hi, 1):.2f}: {row['n']:5d} detections, mean (u, v) "
                  f"({row['mean_u']:+.2f}, {row['mean_v']:+.2f}), median |error| {row['median_abs']:.2f}")

    print("2. drift along the image motion (px per 1,000 px travelled), per apple")
    res["drift_px_per_1000px"] = []
    for lo in (0.0, 0.8, 0.95):
        d = drift_slopes(p, lo)
        if len(d):
            row = {"min_visible": lo, "apples": len(d), "mean": float(d.mean()), "median": float(np.median(d)),
                   "sem": float(d.std() / np.sqrt(len(d)))}
            res["drift_px_per_1000px"].append(row)
            print(f"   detections >= {lo:.2f} visible: {len(d):3d} apples, mean {row['mean']:+.2f} "
                  f"(+- {row['sem']:.2f}), median {row['median']:+.2f}")

    print("3. 3-D error along the viewing ray (m, median; - = towards the camera), by frames detected in")
    q = ray_errors(flight, out, p)
    res["ray_error_m"] = []
    for lo, hi in ((3, 10), (10, 20), (20, 40), (40, 10**6)):
        s = (q[:, 0] >= lo) & (q[:, 0] < hi)
        if s.any():
            row = {"frames_from": lo, "frames_to": hi if hi < 10**6 else None, "apples": int(s.sum()),
                   "detector_along": float(np.median(q[s, 1])), "detector_across": float(np.median(q[s, 2])),
                   "truth_along": float(np.median(q[s, 3])), "truth_across": float(np.median(q[s, 4]))}
            res["ray_error_m"].append(row)
            span = f"{lo}-{hi - 1}" if hi < 10**6 else f"{lo}+"
            print(f"   {span:>6} frames: {row['apples']:3d} apples; detector centres along {row['detector_along']:+.3f}"
                  f" across {row['detector_across']:.3f}; true centres along {row['truth_along']:+.3f}"
                  f" across {row['truth_across']:.3f}")
    if args.json:
        Path(args.json).write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
