"""Score the association against a simulated flight's truth.

    python -m ground evaluate FLIGHT_DIR [--detections truth|FILE] [--poses truth|FILE] [--noise-px S]
        [--miss P] [--fp N] [--dup P] [--mode offline|windowed] [--json OUT]

Detections come from ``truth/detections.csv`` (apples at least ``--min-visible`` visible), perturbed
deterministically from ``--seed``: pixel jitter, misses, false positives per frame (Poisson) and
duplicate detections; or from a CSV ``frame,u,v[,score]`` (OpenCV pixel convention). Poses come
from ``truth/frames.csv``, from the telemetry alone (GPS + gimbal), or a CSV with the same columns. Predicted apples are matched to truth
apples one-to-one (Hungarian) within ``--match-m`` (0.10 m).

Truth counts: an apple is *visible in the flight* when it appears, at least ``--min-visible``
visible, in at least ``--truth-min-views`` frames (3: fewer cannot be triangulated by the paper's
RANSAC); it does not depend on the method's parameters. Recall is reported against those and
against all apples of the rows the flight saw.
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment

from ground.association import AssociationParams, FrameDetections, FruitAssociation, WindowedAssociation
from ground.baselines import SortTracker, count_per_frame_sum
from ground.rows import direction_rows, kmeans_rows
from pomar.flight import FlightDir, FlightFormatError, read_csv
from pomar.rotations import quat_wxyz_to_rotation

log = logging.getLogger(__name__)


@dataclass
class Perturbation:
    noise_px: float = 0.0
    miss: float = 0.0
    fp_per_frame: float = 0.0
    dup: float = 0.0
    min_visible: float = 0.5
    seed: int = 0


def truth_detections(flight: FlightDir, pert: Perturbation, n_frames: int, width: int, height: int):
    """Per-frame detection centres from the truth, perturbed; also the source apple id (-1 = false positive)."""
    d = flight.truth_detections()
    rng = np.random.default_rng(pert.seed)
    keep = (d["visible_fraction"] >= pert.min_visible) & (d["u"] >= 0) & (d["u"] <= width - 1) \
        & (d["v"] >= 0) & (d["v"] <= height - 1)
    frame, aid, u, v, r = (d[k][keep] for k in ("frame", "apple_id", "u", "v", "r_px"))
    keep = rng.random(len(frame)) >= pert.miss
    frame, aid, u, v, r = frame[keep], aid[keep], u[keep], v[keep], r[keep]
    u = u + rng.normal(0, pert.noise_px, len(u)) if pert.noise_px else u
    v = v + rng.normal(0, pert.noise_px, len(v)) if pert.noise_px else v
    dup = rng.random(len(frame)) < pert.dup
    ang = rng.uniform(0, 2 * np.pi, dup.sum())
    off = np.maximum(r[dup], 2.0) * 1.5
    frame = np.concatenate([frame, frame[dup]])
    aid = np.concatenate([aid, aid[dup]])
    u = np.concatenate([u, u[dup] + off * np.cos(ang)])
    v = np.concatenate([v, v[dup] + off * np.sin(ang)])
    nfp = rng.poisson(pert.fp_per_frame, n_frames) if pert.fp_per_frame else np.zeros(n_frames, int)
    fpf = np.repeat(np.arange(n_frames), nfp)
    frame = np.concatenate([frame, fpf])
    aid = np.concatenate([aid, np.full(len(fpf), -1)])
    u = np.concatenate([u, rng.uniform(0, width - 1, len(fpf))])
    v = np.concatenate([v, rng.uniform(0, height - 1, len(fpf))])
    per_frame_xy, per_frame_src = [], []
    order = np.argsort(frame, kind="stable")
    frame, aid, u, v = frame[order], aid[order], u[order], v[order]
    bounds = np.searchsorted(frame, np.arange(n_frames + 1))
    for f in range(n_frames):
        s = slice(bounds[f], bounds[f + 1])
        per_frame_xy.append(np.stack([u[s], v[s]], 1))
        per_frame_src.append(aid[s])
    return per_frame_xy, per_frame_src


def detections_from_file(path: Path, n_frames: int):
    d = read_csv(path, ["frame", "u", "v"])
    out = [np.zeros((0, 2)) for _ in range(n_frames)]
    for f in np.unique(d["frame"]):
        if 0 <= f < n_frames:
            s = d["frame"] == f
            out[int(f)] = np.stack([d["u"][s], d["v"][s]], 1)
    return out, [np.full(len(x), -2) for x in out]


def projection_matrices(flight: FlightDir, poses: str) -> np.ndarray:
    cam = flight.camera()
    if poses == "truth":
        R, t = flight.truth_poses()
    elif poses == "telemetry":
        from ground.poses import telemetry_poses

        R, t, _ = telemetry_poses(flight)
    else:
        from pomar.flight import FRAMES_COLUMNS

        fr = read_csv(Path(poses), FRAMES_COLUMNS)
        order = np.argsort(fr["frame"])
        q = np.stack([fr[k][order] for k in ("qw", "qx", "qy", "qz")], 1)
        R = quat_wxyz_to_rotation(q).as_matrix()
        t = np.stack([fr[k][order] for k in ("tx", "ty", "tz")], 1)
    K = cam.K_opencv
    return np.einsum("ij,njk->nik", K, np.concatenate([R, t[:, :, None]], axis=2))


def match(pred: np.ndarray, truth: np.ndarray, max_dist: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One-to-one matching within max_dist (Hungarian on distance): (pred idx, truth idx, distances)."""
    if len(pred) == 0 or len(truth) == 0:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0)
    from scipy.spatial import cKDTree

    tree = cKDTree(truth)
    pairs = tree.query_ball_point(pred, max_dist)
    rows, cols, dist = [], [], []
    for i, js in enumerate(pairs):
        for j in js:
            rows.append(i)
            cols.append(j)
            dist.append(np.linalg.norm(pred[i] - truth[j]))
    if not rows:
        return np.zeros(0, int), np.zeros(0, int), np.zeros(0)
    # Hungarian on the predictions and truths that have a partner within reach
    ur, uc = np.unique(rows), np.unique(cols)
    dense = np.full((len(ur), len(uc)), 1e6)
    dense[np.searchsorted(ur, rows), np.searchsorted(uc, cols)] = dist
    a, b = linear_sum_assignment(dense)
    ok = dense[a, b] < 1e6
    r, c = ur[a[ok]], uc[b[ok]]
    d = np.linalg.norm(pred[r] - truth[c], axis=1)
    ok = d <= max_dist
    return r[ok], c[ok], d[ok]


def score_map(flight: FlightDir, pred: np.ndarray, min_visible: float = 0.5, truth_min_views: int = 3,
              match_m: float = 0.10) -> dict:
    """Score an apple map (N, 3), in the flight's truth ENU frame, against its truth: precision, recall
    (against apples visible in the flight, and against all apples of the rows seen), F1, counts,
    position errors, and per-row counts (row direction and K-means) next to the truth's."""
    a = flight.truth_apples()
    truth_xyz = np.stack([a["x"], a["y"], a["z"]], 1)
    d = flight.truth_detections()
    good = d["visible_fraction"] >= min_visible
    ids, nviews = np.unique(d["apple_id"][good], return_counts=True)
    visible_ids = ids[nviews >= truth_min_views]
    is_visible = np.isin(a["apple_id"], visible_ids)
    rows_seen = np.unique(a["row"][np.isin(a["apple_id"], np.unique(d["apple_id"]))])
    in_rows = np.isin(a["row"], rows_seen)

    pred = np.asarray(pred, float).reshape(-1, 3)
    pi, ti, dist = match(pred, truth_xyz, match_m)
    tp = len(pi)
    tp_visible = int(is_visible[ti].sum())
    count, truth_count = len(pred), int(is_visible.sum())
    precision = tp / count if count else 0.0
    recall = tp_visible / truth_count if truth_count else 0.0
    f1 = 2 * precision * recall / (precision + recall) if precision + recall else 0.0

    # rows: the truth row of each predicted apple is the nearest truth row line
    row_x = {r: np.median(truth_xyz[a["row"] == r, :2], axis=0) for r in np.unique(a["row"])}
    rows_pred, direction = direction_rows(pred[:, :2]) if len(pred) else (np.zeros(0, int), 0.0)
    n_rows_seen = len(np.unique(rows_pred)) if len(pred) else 0
    rows_km = kmeans_rows(pred[:, :2], n_rows_seen) if len(pred) else np.zeros(0, int)
    normal = np.array([-np.sin(direction), np.cos(direction)])
    per_row = []
    truth_rows_x = np.array([row_x[r] @ normal for r in row_x])
    truth_rows_id = np.array(list(row_x))
    for lab in range(n_rows_seen):
        sel = rows_pred == lab
        across = np.median(pred[sel, :2] @ normal)
        r = int(truth_rows_id[np.argmin(np.abs(truth_rows_x - across))])
        km_sel = rows_km == lab
        tv = int((is_visible & (a["row"] == r)).sum())
        per_row.append({"row": r, "count": int(sel.sum()), "count_kmeans": int(km_sel.sum()),
                        "truth_visible": tv, "truth_all": int((a["row"] == r).sum()),
                        "count_error_pct": 100.0 * (int(sel.sum()) - tv) / tv if tv else float("nan")})
    trees = per_tree(pred, truth_xyz[is_visible], a["row"][is_visible], truth_rows_id, truth_rows_x, direction)

    return {
        "precision": precision, "recall": recall, "f1": f1,
        "recall_all_apples_in_rows_seen": tp / int(in_rows.sum()) if in_rows.any() else 0.0,
        "count": count, "truth_count": truth_count,
        "count_error_pct": 100.0 * (count - truth_count) / truth_count if truth_count else float("nan"),
        "median_error_m": float(np.median(dist)) if tp else float("nan"),
        "p95_error_m": float(np.percentile(dist, 95)) if tp else float("nan"),
        "duplicates": duplicates(pred, truth_xyz),
        "rows": per_row,
        "worst_row_error_pct": max((abs(r["count_error_pct"]) for r in per_row
                                    if r["truth_visible"] >= MIN_ROW_APPLES), default=float("nan")),
        "trees": trees,
    }


#: Rows with fewer visible apples (the edge of the view) are left out of the per-row and per-tree scores.
MIN_ROW_APPLES = 30


def per_tree(pred: np.ndarray, truth: np.ndarray, truth_row: np.ndarray, rows_id: np.ndarray, rows_across: np.ndarray,
             direction: float, bin_m: float = 1.0) -> dict:
    """Per-tree counts against the truth: each row with at least MIN_ROW_APPLES visible apples is cut into
    ``bin_m`` bins along the row over its visible apples' span; predicted apples go to the nearest truth row.
    Pearson r of predicted against visible apples per bin, over all such rows' bins, and the bins' mean
    absolute error."""
    u = np.array([np.cos(direction), np.sin(direction)])
    n = np.array([-u[1], u[0]])
    pred_row = rows_id[np.argmin(np.abs(pred[:, :2] @ n - rows_across[None, :].T), axis=0)] if len(pred) else \
        np.zeros(0, int)
    p_all, t_all = [], []
    for r in rows_id:
        t_sel = truth_row == r
        if t_sel.sum() < MIN_ROW_APPLES:
            continue
        ta = truth[t_sel, :2] @ u
        lo = np.floor(ta.min())
        nb = int(np.ceil(ta.max() - lo + 1e-9 + 1e-6 / bin_m))
        edges = lo + np.arange(nb + 1) * bin_m
        t_all.append(np.histogram(ta, edges)[0])
        p_all.append(np.histogram(pred[pred_row == r, :2] @ u, edges)[0])
    if not t_all:
        return {"bins": 0, "r": float("nan"), "mae": float("nan")}
    p, t = np.concatenate(p_all).astype(float), np.concatenate(t_all).astype(float)
    r = float(np.corrcoef(p, t)[0, 1]) if len(p) > 2 and p.std() > 0 and t.std() > 0 else float("nan")
    return {"bins": int(len(t)), "r": r, "mae": float(np.abs(p - t).mean()), "truth_mean": float(t.mean())}


def duplicates(pred: np.ndarray, truth: np.ndarray, within_m: float = 0.15) -> int:
    """Apples counted twice: predicted apples beyond the first whose nearest truth apple (within ``within_m``) is the
    same one."""
    if not len(pred) or not len(truth):
        return 0
    from scipy.spatial import cKDTree

    d, j = cKDTree(truth).query(pred)
    _, n = np.unique(j[d <= within_m], return_counts=True)
    return int((n - 1).sum())


def evaluate(flight_dir, mode: str = "windowed", params: AssociationParams | None = None,
             pert: Perturbation | None = None, detections: str = "truth", poses: str = "truth",
             match_m: float = 0.10, baselines: bool = True, truth_min_views: int = 3,
             remove_pose_offset: bool = False) -> dict:
    flight = FlightDir(flight_dir)
    if not flight.has_truth:
        raise FlightFormatError(f"{flight.path}: no truth/ to evaluate against")
    params = params or AssociationParams()
    pert = pert or Perturbation()
    meta = flight.meta()
    Ps = projection_matrices(flight, poses)
    n = min(meta.frame_count, len(Ps))
    if detections == "truth":
        xy, src = truth_detections(flight, pert, n, meta.width, meta.height)
    else:
        xy, src = detections_from_file(Path(detections), n)
    frames = [FrameDetections(i, Ps[i], xy[i]) for i in range(n)]

    t0 = time.perf_counter()
    if mode == "offline":
        assoc = FruitAssociation(params)
        apples = assoc.run(frames)
    elif mode == "windowed":
        assoc = WindowedAssociation(params)
        apples = assoc.run(frames)
    else:
        raise ValueError(f"mode must be 'offline' or 'windowed', got {mode!r}")
    seconds = time.perf_counter() - t0

    pred = np.array([ap.X for ap in apples]).reshape(-1, 3)
    pose_offset = np.zeros(3)
    if remove_pose_offset:
        # the map's shape, not its absolute placement: take away the mean offset of the camera centres
        # from the truth (with GPS georeferencing, the GPS's bias over the flight)
        R_true, t_true = flight.truth_poses()
        K_inv = np.linalg.inv(flight.camera().K_opencv)
        Rt = np.einsum("ij,njk->nik", K_inv, Ps[:n])
        C = -np.einsum("nji,nj->ni", Rt[:, :, :3], Rt[:, :, 3])
        C_true = -np.einsum("nji,nj->ni", R_true[:n], t_true[:n])
        pose_offset = (C - C_true).mean(0)
        pred = pred - pose_offset
    scores = score_map(flight, pred, pert.min_visible, truth_min_views, match_m)
    truth_count = scores["truth_count"]

    result = {
        "flight": str(flight.path), "mode": mode, "params": asdict(params), "perturbation": asdict(pert),
        "detections": detections, "poses": poses, **scores,
        "pose_offset_removed_m": pose_offset.tolist(),
        "frames": n, "detections_total": count_per_frame_sum(xy), "seconds": seconds,
        "frames_per_s": n / seconds if seconds > 0 else float("inf"), "stats": dict(assoc.stats),
    }
    if baselines:
        tr = SortTracker(max_age=params.k)
        for x in xy:
            tr.update(x)
        s = count_per_frame_sum(xy)
        result["baselines"] = {
            "per_frame_sum": {"count": s, "count_error_pct": 100.0 * (s - truth_count) / truth_count},
            "sort_2d_tracker": {"count": tr.count, "count_error_pct": 100.0 * (tr.count - truth_count) / truth_count},
        }
    return result


def format_table(results: list[dict]) -> str:
    head = f"{'method':<22}{'count':>7}{'truth':>7}{'err %':>8}{'prec':>7}{'rec':>7}{'F1':>7}{'med m':>8}{'p95 m':>8}{'fps':>8}"
    lines = [head, "-" * len(head)]
    for r in results:
        lines.append(f"{r['mode']:<22}{r['count']:>7}{r['truth_count']:>7}{r['count_error_pct']:>8.1f}"
                     f"{r['precision']:>7.3f}{r['recall']:>7.3f}{r['f1']:>7.3f}{r['median_error_m']:>8.3f}"
                     f"{r['p95_error_m']:>8.3f}{r['frames_per_s']:>8.1f}")
        for name, b in r.get("baselines", {}).items():
            lines.append(f"{'  ' + name:<22}{b['count']:>7}{r['truth_count']:>7}{b['count_error_pct']:>8.1f}"
                         f"{'-':>7}{'-':>7}{'-':>7}{'-':>8}{'-':>8}{'-':>8}")
    r = results[-1]
    if r.get("rows"):
        lines.append("")
        lines.append(f"rows ({r['mode']}): row, count (direction), count (K-means), truth visible, truth all")
        for row in r["rows"]:
            lines.append(f"  row {row['row']:>2}: {row['count']:>5} {row['count_kmeans']:>5} {row['truth_visible']:>5} {row['truth_all']:>5}")
    return "\n".join(lines)
