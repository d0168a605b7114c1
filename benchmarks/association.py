"""Association benchmark: the figures of the Association issue, printed.

    python benchmarks/association.py [--flight replay_data/demo-flight] [--skip-offline] [--json OUT]

1. On the flight with truth poses, 1 px jitter, 10 % misses, 0.5 false positives per frame: the
   evaluation table for offline (the paper's algorithm, with and without the duplicate merge),
   windowed, and the two baselines (sum of detections, 2-D SORT tracker); then windowed against an
   oracle (the same detections grouped by their true apple, triangulated by least squares over
   reprojection error: the best any association can do on this input) over five perturbation seeds.
2. The offline DFS bound: how often it binds and what it costs in F1 (max_paths 20/100/500) on the
   first frames of the flight.
3. Windowed throughput at 100 detections per frame (synthetic, one process).
4. Windowed memory over a 5,000-frame synthetic sequence (tracemalloc, every 500 frames).
Run it with nothing else on the machine.
"""

from __future__ import annotations

import argparse
import json
import time
import tracemalloc
from dataclasses import replace
from pathlib import Path

import numpy as np

from ground.apples.association import AssociationParams, FrameDetections
from ground.apples.windowed import WindowedAssociation
from ground.evaluation.evaluate import Perturbation, evaluate, format_table
from pomar.countable import MIN_VIEWS, countable_ids
from ground.evaluation.synthetic import apples_along, camera_path, make_sequence
from pomar.camera import Camera

ROOT = Path(__file__).resolve().parents[1]


def throughput(n_frames=300, per_frame=100):
    # dense apples so that about `per_frame` are in view, plus 5 % false positives
    rng = np.random.default_rng(0)
    seq = make_sequence(n_frames=n_frames, apples=apples_along(n_frames * 0.2, 60 * n_frames // 10 * per_frame // 100, rng),
                        noise_px=1.0, miss=0.1, fp_per_frame=per_frame * 0.05, seed=1, max_per_frame=per_frame)
    dets = np.mean([len(f.xy) for f in seq.frames[50:]])
    w = WindowedAssociation()
    for f in seq.frames[:50]:
        w.add_frame(f)
    t0 = time.perf_counter()
    for f in seq.frames[50:]:
        w.add_frame(f)
    dt = time.perf_counter() - t0
    return {"detections_per_frame": float(dets), "frames_per_s": (n_frames - 50) / dt, "open_tracks": len(w.tracks)}


def memory(n_frames=5000, step=500):
    """Stream a long synthetic flight frame by frame (generated on the fly) and sample traced memory."""
    cam = Camera.from_fov(1280, 720, 50.0)
    rng = np.random.default_rng(2)
    R, t = camera_path(n_frames)
    apples = apples_along(n_frames * 0.2, n_frames * 2, rng)
    order = np.argsort(apples[:, 1])
    apples = apples[order]
    w = WindowedAssociation()
    tracemalloc.start()
    samples, emitted = [], 0
    t0 = time.perf_counter()
    for i in range(n_frames):
        y = i * 0.2
        lo, hi = np.searchsorted(apples[:, 1], [y - 15, y + 25])
        uv, z = cam.project(apples[lo:hi], R[i], t[i])
        ok = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < 1279) & (uv[:, 1] >= 0) & (uv[:, 1] < 719) & (rng.random(len(uv)) > 0.1)
        xy = uv[ok] + rng.normal(0, 1.0, (ok.sum(), 2))
        emitted += len(w.add_frame(FrameDetections(i, cam.projection_matrix(R[i], t[i]), xy)))
        if (i + 1) % step == 0:
            cur, peak = tracemalloc.get_traced_memory()
            samples.append({"frame": i + 1, "traced_mb": cur / 1e6, "open_tracks": len(w.tracks),
                            "recent_apples": len(w._recent), "emitted": emitted})
    tracemalloc.stop()
    return {"samples": samples, "seconds": time.perf_counter() - t0}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--flight", default=str(ROOT / "replay_data" / "demo-flight"))
    ap.add_argument("--skip-offline", action="store_true")
    ap.add_argument("--offline-max-paths", type=int, default=100)
    ap.add_argument("--bound-frames", type=int, default=40)
    ap.add_argument("--json")
    args = ap.parse_args()
    pert = Perturbation(noise_px=1.0, miss=0.1, fp_per_frame=0.5)
    out = {}

    print("== 1. bundled flight, truth poses, 1 px jitter, 10 % misses, 0.5 FP/frame ==")
    results = [evaluate(args.flight, "windowed", AssociationParams(), pert)]
    if not args.skip_offline:
        p = AssociationParams(max_paths=args.offline_max_paths)
        r = evaluate(args.flight, "offline", p, pert, baselines=False)
        r["mode"] = f"offline+merge (P{p.max_paths})"
        results.append(r)
        r = evaluate(args.flight, "offline", replace(p, merge_search_m=0.0), pert, baselines=False)
        r["mode"] = f"offline as paper (P{p.max_paths})"
        results.append(r)
    print(format_table(results))
    for r in results:
        print(f"  {r['mode']}: {r['seconds']:.1f} s, recall vs all apples of the rows seen "
              f"{r['recall_all_apples_in_rows_seen']:.3f}, stats {r['stats']}")
    out["table"] = results

    print("\n  windowed against the oracle association, perturbation seeds 0-4:")
    seeds = []
    for seed in range(5):
        pert_s = replace(pert, seed=seed)
        w = results[0] if seed == 0 else evaluate(args.flight, "windowed", AssociationParams(), pert_s, baselines=False)
        o = oracle(args.flight, pert_s)
        seeds.append({"seed": seed, "windowed": {k: w[k] for k in ("f1", "count_error_pct")}, "oracle": o})
        print(f"  seed {seed}: windowed F1 {w['f1']:.3f} count {w['count_error_pct']:+.1f} %   "
              f"oracle F1 {o['f1']:.3f} count {o['count_error_pct']:+.1f} %")
    print(f"  mean F1: windowed {np.mean([s['windowed']['f1'] for s in seeds]):.3f}, "
          f"oracle {np.mean([s['oracle']['f1'] for s in seeds]):.3f}")
    out["seeds"] = seeds

    if not args.skip_offline:
        print(f"\n== 2. offline DFS bound on the first {args.bound_frames} frames ==")
        bound = []
        for mp in (20, 100, 500):
            r = evaluate_prefix(args.flight, args.bound_frames, AssociationParams(max_paths=mp), pert)
            bound.append({"max_paths": mp, **r})
            print(f"  max_paths {mp:>4}: bound binds at {r['dfs_bound_hit_rate']:.0%} of vertices with paths, "
                  f"F1 {r['f1']:.3f}, count {r['count']} (truth {r['truth_count']}), {r['seconds']:.1f} s")
        out["dfs_bound"] = bound

    print("\n== 3. windowed throughput at 100 detections per frame (synthetic, one process) ==")
    tp = throughput()
    print(f"  {tp['detections_per_frame']:.0f} detections/frame: {tp['frames_per_s']:.1f} frames/s "
          f"({tp['open_tracks']} open tracks at the end)")
    out["throughput"] = tp

    print("\n== 4. windowed memory over a 5,000-frame synthetic sequence ==")
    mem = memory()
    for s in mem["samples"]:
        print(f"  frame {s['frame']:>5}: traced {s['traced_mb']:6.2f} MB, open tracks {s['open_tracks']:>4}, "
              f"recent apples {s['recent_apples']:>5}, apples emitted {s['emitted']:>6}")
    print(f"  ({mem['seconds']:.0f} s)")
    out["memory"] = mem
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2, default=float) + "\n")


def oracle(flight, pert, min_views=MIN_VIEWS):
    """Perfect association: the perturbed truth detections grouped by the apple they came from (false
    positives dropped), each apple with at least min_views views triangulated by least squares over
    its reprojection error, scored like the association."""
    from ground.evaluation.evaluate import projection_matrices, truth_detections
    from ground.evaluation.scoring import score_map
    from ground.apples.geometry import triangulate_nonlinear
    from pomar.flight import FlightDir

    fl = FlightDir(flight)
    meta = fl.meta()
    Ps = projection_matrices(fl, "truth")
    n = min(meta.frame_count, len(Ps))
    xy, src = truth_detections(fl, pert, n, meta.width, meta.height)
    frame = np.concatenate([np.full(len(s), f) for f, s in enumerate(src)])
    pts, ids = np.concatenate(xy), np.concatenate(src)
    pred = []
    for a in np.unique(ids[ids >= 0]):
        sel = ids == a
        if sel.sum() >= min_views:
            pred.append(triangulate_nonlinear(Ps[frame[sel]], pts[sel]))
    return score_map(fl, np.array(pred).reshape(-1, 3), pert.min_visible, MIN_VIEWS)


def evaluate_prefix(flight, n_frames, params, pert):
    """Offline on the first n frames; F1 against truth apples seen in those frames."""
    from ground.apples.paper import FruitAssociation
    from ground.evaluation.evaluate import projection_matrices, truth_detections
    from ground.evaluation.scoring import match
    from pomar.flight import FlightDir

    fl = FlightDir(flight)
    meta = fl.meta()
    Ps = projection_matrices(fl, "truth")
    xy, _ = truth_detections(fl, pert, meta.frame_count, meta.width, meta.height)
    frames = [FrameDetections(i, Ps[i], xy[i]) for i in range(n_frames)]
    t0 = time.perf_counter()
    fa = FruitAssociation(params)
    apples = fa.run(frames)
    seconds = time.perf_counter() - t0
    a = fl.truth_apples()
    d = fl.truth_detections()
    early = d["frame"] < n_frames
    vis = countable_ids(d["apple_id"][early], d["visible_fraction"][early], pert.min_visible)
    T = np.stack([a["x"], a["y"], a["z"]], 1)
    pi, ti, _ = match(np.array([x.X for x in apples]).reshape(-1, 3), T, 0.10)
    prec = len(pi) / max(len(apples), 1)
    rec = np.isin(vis, a["apple_id"][ti]).mean() if len(vis) else 0.0
    return {"f1": 2 * prec * rec / max(prec + rec, 1e-12), "count": len(apples), "truth_count": len(vis),
            "seconds": seconds, **{k: fa.stats[k] for k in ("dfs_bound_hit_rate", "dfs_bound_hits", "vertices_with_paths")}}


if __name__ == "__main__":
    main()
