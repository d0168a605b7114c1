"""Scoring against a simulated flight's truth: one place for every score the project gives (``ground replay``'s
evaluation, ``ground evaluate``, ``ground register``, the benchmarks).

An apple of the truth *counts* as pomar.countable defines it (at least MIN_VISIBLE visible in at least MIN_VIEWS
frames); a predicted apple matches a true one within MATCH_M, one to one.

- :func:`score_map`: an apple map (ENU, the truth's frame) against the truth: precision, recall, F1, counts, rows
  and trees;
- :func:`evaluate_map`: a run's output folder (apples.csv, poses.csv) scored after taking away the georeferencing
  error (the map's *shape*), besides where GPS put it;
- :func:`label_candidates`: what each apple a run's count was chosen from is in truth (the count's checks studied);
- :func:`score_poses`: a run's camera poses against the true ones.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from scipy.optimize import linear_sum_assignment
from scipy.spatial.transform import Rotation

from ground.apples.rows import direction_rows, kmeans_rows
from ground.poses.georeference import fit_similarity, georeference_poses
from pomar.countable import MIN_VIEWS, MIN_VISIBLE, countable_ids, visible
from pomar.flight import FlightDir, read_csv
from pomar.rotations import quat_wxyz_to_rotation

#: A predicted apple matches a true one within this distance (m).
MATCH_M = 0.10


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



def score_map(flight: FlightDir, pred: np.ndarray, min_visible: float = MIN_VISIBLE,
              truth_min_views: int = MIN_VIEWS, match_m: float = MATCH_M) -> dict:
    """Score an apple map (N, 3), in the flight's truth ENU frame, against its truth: precision, recall
    (against apples visible in the flight, and against all apples of the rows seen), F1, counts,
    position errors, and per-row counts (row direction and K-means) next to the truth's."""
    a = flight.truth_apples()
    truth_xyz = np.stack([a["x"], a["y"], a["z"]], 1)
    d = flight.truth_detections()
    visible_ids = countable_ids(d["apple_id"], d["visible_fraction"], min_visible, truth_min_views)
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
        "load": against_load(per_row),
    }


def against_load(per_row: list[dict]) -> dict:
    """The count against the load, the paper's per-row figure of merit: over the rows with MIN_ROW_APPLES countable
    apples or more, Pearson r of each row's count against all its apples (hidden ones included), and the coefficient
    of variation of count / all across those rows (0: the count is one fixed share of the load in every row). NaN
    with fewer than 3 such rows. Meaningful where the flight saw the rows' whole length (a whole-plot flight)."""
    rows = [r for r in per_row if r["truth_visible"] >= MIN_ROW_APPLES and r["truth_all"]]
    if len(rows) < 3:
        return {"rows": len(rows), "r": float("nan"), "cv": float("nan")}
    count = np.array([r["count"] for r in rows], float)
    load = np.array([r["truth_all"] for r in rows], float)
    share = count / load
    r = float(np.corrcoef(count, load)[0, 1]) if count.std() > 0 and load.std() > 0 else float("nan")
    return {"rows": len(rows), "r": r, "cv": float(share.std() / share.mean()) if share.mean() else float("nan")}


def repeat_pair(rows_a: list[dict], rows_b: list[dict]) -> dict:
    """The same orchard flown twice: per row with MIN_ROW_APPLES countable apples or more in both flights, the
    count's ratio to that flight's countable apples, and how far the two ratios are apart (the count's bias must not
    move with the flight). ``rows_*``: score_map's per-row lists."""
    b = {r["row"]: r for r in rows_b if r["truth_visible"] >= MIN_ROW_APPLES}
    out = []
    for r in rows_a:
        if r["truth_visible"] >= MIN_ROW_APPLES and r["row"] in b:
            ra, rb = r["count"] / r["truth_visible"], b[r["row"]]["count"] / b[r["row"]]["truth_visible"]
            out.append({"row": r["row"], "ratio_a": ra, "ratio_b": rb, "difference": abs(ra - rb)})
    return {"rows": out, "worst": max((x["difference"] for x in out), default=float("nan"))}



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



def _enu(flight: FlightDir, path: Path) -> np.ndarray:
    """A map file's points (its lat, lon, alt) in the flight's truth ENU frame. A map without altitudes above sea level
    (its log gave heights above take-off; alt empty) is placed by its own ENU (x, y, z) about the origin report.json
    names, whose height above take-off goes on the truth's take-off point (the simulator's home, its origin)."""
    import json

    from pomar.geo import Origin

    d = read_csv(path, ["lat", "lon", "alt", "x", "y", "z"])
    geo = np.stack([d["lat"], d["lon"], d["alt"]], 1).reshape(-1, 3)
    if len(geo) and not np.isfinite(geo[:, 2]).all():
        o = json.loads((path.parent / "report.json").read_text())["map"]["origin"]
        home = Origin(o["lat"], o["lon"], o["alt"] + flight.origin().alt)
        geo = home.to_geodetic(np.stack([d["x"], d["y"], d["z"]], 1)).reshape(-1, 3)
    return flight.origin().to_enu(geo[:, 0], geo[:, 1], geo[:, 2]).reshape(-1, 3)



def replay_cameras(flight: FlightDir, out: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A run's camera poses (poses.csv): frames (n,), centres (n, 3) in the flight's truth ENU frame and
    world-to-camera rotations (n, 3, 3)."""
    d = read_csv(out / "poses.csv", ["frame", "qw", "qx", "qy", "qz"])
    R = quat_wxyz_to_rotation(np.stack([d[k] for k in ("qw", "qx", "qy", "qz")], 1)).as_matrix().reshape(-1, 3, 3)
    return d["frame"].astype(int), _enu(flight, out / "poses.csv"), R



def shape_fit(flight: FlightDir, frames: np.ndarray, centres: np.ndarray, R: np.ndarray):
    """The similarity fit that best takes these camera poses onto the true ones (the georeferencing
    error, which only the GPS sets); ``.similarity`` maps a run's ENU points into the truth's."""
    R_true, t_true = flight.truth_poses()
    C_true = -np.einsum("nji,nj->ni", R_true, t_true)[frames]
    return fit_similarity(centres, C_true, 0.05, R, R_true[frames], np.radians(0.05))



#: The local score's windows (s of flight): the GPS error the map follows barely moves in this long.
LOCAL_WINDOW_S = 20.0



def local_offsets(frames: np.ndarray, centres: np.ndarray, C_true: np.ndarray, window_frames: float):
    """The mean camera error of each window of ``window_frames`` frames (centres against the truth's), and each frame's
    window: what is left of the GPS error after one similarity for the whole flight, taken as a translation per
    window."""
    win = ((frames - frames.min()) // max(window_frames, 1.0)).astype(int)
    off = np.zeros((win.max() + 1, 3))
    for k in np.unique(win):
        off[k] = (C_true[win == k] - centres[win == k]).mean(0)
    return off, win



def map_shape_fit(flight: FlightDir, out: Path, cameras=None):
    """The similarity that takes a run's cameras (poses.csv) onto the true ones, and which cameras it was fitted on:
    those the map placed. A frame with a telemetry pose (GPS and gimbal alone, no image) sits where the GPS put it,
    and its attitude, weighed as a mapped camera's, would turn the fit. ``cameras``: :func:`replay_cameras`'s, if
    already read."""
    frames, cams, R_ours = cameras if cameras is not None else replay_cameras(flight, out)
    own = read_csv(out / "poses.csv", ["source"], str_columns=("source",))["source"] != "telemetry"
    own = own if own.sum() >= 3 else np.ones(len(frames), bool)
    return shape_fit(flight, frames[own], cams[own], R_ours[own]), own


def label_candidates(flight: FlightDir, out: Path, min_visible: float = MIN_VISIBLE,
                     match_m: float = MATCH_M) -> dict[str, np.ndarray]:
    """What each apple a run's count was chosen from (candidates.csv, in its order) is in truth, on the map's shape
    (:func:`map_shape_fit`): ``countable`` (matched to an apple of the definition), ``partial`` (matched to an apple
    the definition does not count: too little of it seen in too few frames), ``misplaced`` (no apple within
    ``match_m``, but in the middle frame of its views it projects onto one the truth sees there, within that apple's
    radius: a real apple placed off along its rays) or ``none``; beside it the truth's ``apple_id`` of a match (-1
    otherwise) and ``ray_apple``, the apple a misplaced one lies on (-1 otherwise), and, for every countable apple,
    whether any candidate matched it (``found``) and in how many frames it is countable (``views``)."""
    import csv

    with open(out / "candidates.csv", newline="") as f:
        cands = list(csv.DictReader(f))
    X = map_shape_fit(flight, out)[0].similarity.apply(_enu(flight, out / "candidates.csv"))
    a = flight.truth_apples()
    d = flight.truth_detections()
    countable = countable_ids(d["apple_id"], d["visible_fraction"], min_visible)
    pi, ti, _ = match(X, np.stack([a["x"], a["y"], a["z"]], 1), match_m)
    apple_id = np.full(len(cands), -1)
    apple_id[pi] = a["apple_id"][ti]
    label = np.where(apple_id < 0, "none", np.where(np.isin(apple_id, countable), "countable", "partial"))
    ray_apple = np.full(len(cands), -1)
    R, t = flight.truth_poses()
    cam = flight.camera()
    d_frame, d_id, d_u, d_v, d_r = (np.asarray(d[k]) for k in ("frame", "apple_id", "u", "v", "r_px"))
    for k in np.nonzero(apple_id < 0)[0]:
        f = (int(cands[k]["first_frame"]) + int(cands[k]["last_frame"])) // 2
        there = np.nonzero(d_frame == f)[0]
        if f >= len(R) or not len(there):
            continue
        uv, z = cam.project(X[k][None], R[f], t[f])
        j = there[int(np.argmin(np.hypot(d_u[there] - uv[0, 0], d_v[there] - uv[0, 1])))]
        if z[0] > 0 and on_apple(np.hypot(d_u[j] - uv[0, 0], d_v[j] - uv[0, 1]), float(d_r[j])):
            ray_apple[k] = int(d_id[j])
            label[k] = "misplaced"
    ids, views = np.unique(d["apple_id"][np.asarray(d["visible_fraction"], float) >= min_visible], return_counts=True)
    return {"label": label, "apple_id": apple_id, "ray_apple": ray_apple, "countable": countable,
            "found": np.isin(countable, apple_id), "views": views[np.searchsorted(ids, countable)]}


#: A point lies on an apple in an image within the apple's radius, and never less than this (px): a projection or a box
#: centre 1–2 px off a tiny apple still means it.
MIN_ON_APPLE_PX = 2.0


def on_apple(dist_px, r_px):
    """Whether points ``dist_px`` from an apple's centre in the image lie on it (its radius ``r_px``, at least
    MIN_ON_APPLE_PX)."""
    return np.asarray(dist_px) <= np.maximum(r_px, MIN_ON_APPLE_PX)


def input_problem(flight: Path, replay: Path | None = None, needs: str = "", why: str = "") -> str | None:
    """What is wrong with a benchmark's inputs, as one line (None if nothing): a simulated flight that does not read,
    or a replay folder without the file ``needs`` (``why``: what that says about the folder)."""
    from pomar.flight import FlightFormatError

    try:
        FlightDir(flight).meta()
    except FlightFormatError as exc:
        return str(exc)
    if replay is not None and not (Path(replay) / needs).is_file():
        return f"{Path(replay) / needs}: {why or 'missing'}"
    return None


def stream_detections(journal: Path, score: float) -> dict[int, np.ndarray]:
    """Per frame, the box centres (n, 2) of the detections scored ``score`` or more that a recorded stream (a ground's
    journal.bin) carries, in the frame's pixels."""
    from ground.link.journal import read_journal
    from pomar import wire

    out = {}
    for payload in read_journal(journal):
        m = wire.decode(payload)
        if isinstance(m, wire.FrameMessage):
            out[m.frame] = box_centres(m.boxes, m.scores, score)
    return out


def box_centres(boxes, scores, score: float) -> np.ndarray:
    """The centres (n, 2) of the boxes (x0, y0, x1, y1) scored ``score`` or more."""
    b = np.asarray(boxes, float).reshape(-1, 4)[np.asarray(scores, float).reshape(-1) >= score]
    return np.column_stack([(b[:, 0] + b[:, 2]) / 2, (b[:, 1] + b[:, 3]) / 2])


def detected(truth_detections: dict, centres: dict[int, np.ndarray]) -> np.ndarray:
    """For each row of a flight's truth detections (an apple in a frame): whether one of the frame's detection centres
    (:func:`box_centres`) lies on the apple (:func:`on_apple`)."""
    d = truth_detections
    found = np.zeros(len(d["frame"]), bool)
    for k, (f, u, v, r) in enumerate(zip(d["frame"], d["u"], d["v"], d["r_px"])):
        c = centres.get(int(f))
        found[k] = c is not None and len(c) and bool(on_apple(np.hypot(c[:, 0] - u, c[:, 1] - v).min(), r))
    return found


def found_by_visibility(flight: FlightDir, centres: dict[int, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """(visible fraction, found) for each apple in each frame that ``centres`` holds detections for (frame -> box
    centres: a stream's, :func:`stream_detections`, or a model's)."""
    d = flight.truth_detections()
    keep = np.isin(d["frame"], list(centres))
    d = {k: np.asarray(d[k])[keep] for k in ("frame", "u", "v", "r_px", "visible_fraction")}
    return d["visible_fraction"], detected(d, centres)


def evaluate_map(flight: FlightDir, out: Path, min_visible: float = MIN_VISIBLE, match_m: float = MATCH_M) -> dict:
    """Score the written apples.csv against the flight's truth (in the truth's ENU frame).

    Two scores. ``absolute``: the map where GPS put it. The headline: the map's *shape*, after taking
    away the georeferencing error, i.e. the similarity that best takes our camera poses (poses.csv:
    centres and orientations) onto the true ones. That error comes from the GPS (its bias over the
    flight, and the scale it gives over a short straight line), which no image processing can see;
    its size is reported as ``georeference_error``."""
    keys = ("precision", "recall", "f1", "count", "truth_count", "count_error_pct", "median_error_m", "p95_error_m",
            "recall_all_apples_in_rows_seen", "duplicates", "rows", "worst_row_error_pct", "trees", "load")
    apples = _enu(flight, out / "apples.csv")
    frames, cams, R_ours = replay_cameras(flight, out)
    res = {}
    if len(frames) >= 3:
        R_true, t_true = flight.truth_poses()
        C_true = -np.einsum("nji,nj->ni", R_true, t_true)[frames]
        fit, own = map_shape_fit(flight, out, (frames, cams, R_ours))
        S = fit.similarity
        shape = score_map(flight, S.apply(apples), min_visible=min_visible, match_m=match_m)
        res = {k: shape[k] for k in keys}
        res["georeference_error"] = {
            "offset_m": float(np.linalg.norm((cams - C_true).mean(0))),
            "offset_enu_m": (cams - C_true).mean(0).tolist(),
            "scale_error_pct": 100.0 * (1.0 / S.scale - 1.0),
            "rotation_deg": float(np.degrees(np.arccos(np.clip((np.trace(S.R) - 1) / 2, -1, 1)))),
            "camera_rms_after_m": fit.position_rms_m,
            # where GPS put the cameras (poses.csv): a map that drifts along a long flight shows here
            "camera_error_median_m": float(np.median(np.linalg.norm(cams - C_true, axis=1))),
            "camera_error_max_m": float(np.linalg.norm(cams - C_true, axis=1).max()),
        }
        # local: over minutes of flight the map follows the GPS's slow wander (a metre), which one similarity cannot
        # take away; a translation per LOCAL_WINDOW_S of flight more does, and scores the map's shape at tree scale
        C_fit = S.apply(cams[own])
        off, win = local_offsets(frames[own], C_fit, C_true[own], LOCAL_WINDOW_S * flight.meta().fps)
        a = read_csv(out / "apples.csv", ["first_frame", "last_frame"])
        mid = (np.asarray(a["first_frame"]) + np.asarray(a["last_frame"])).reshape(-1) / 2
        at = np.clip(np.searchsorted(frames[own], mid), 0, int(own.sum()) - 1)
        local = score_map(flight, S.apply(apples) + off[win[at]], min_visible=min_visible, match_m=match_m)
        d = C_fit + off[win] - C_true[own]
        res["local"] = {**{k: local[k] for k in ("precision", "recall", "f1", "median_error_m", "p95_error_m")},
                        "window_s": LOCAL_WINDOW_S, "windows": int(win.max() + 1),
                        "camera_rms_m": float(np.sqrt((d ** 2).sum(1).mean()))}
    absolute = score_map(flight, apples, min_visible=min_visible, match_m=match_m)
    res["absolute"] = {k: absolute[k] for k in keys if k != "rows"}
    if not res.get("rows"):
        res.update({k: absolute[k] for k in keys})
    return res



def format_evaluation(ev: dict) -> str:
    g = ev.get("georeference_error")
    lines = []
    if g:
        lines.append(f"the map's shape, scored after removing the georeferencing error (GPS: offset {g['offset_m']:.2f} m, "
                     f"scale {g['scale_error_pct']:+.2f} %, rotation {g['rotation_deg']:.2f} deg; cameras "
                     f"{g['camera_error_median_m']:.2f} m off, at most {g['camera_error_max_m']:.2f} m)")
    lines += [f"{'count':>7}{'truth':>7}{'err %':>8}{'prec':>7}{'rec':>7}{'F1':>7}{'med m':>8}{'p95 m':>8}",
             f"{ev['count']:>7}{ev['truth_count']:>7}{ev['count_error_pct']:>8.1f}{ev['precision']:>7.3f}"
             f"{ev['recall']:>7.3f}{ev['f1']:>7.3f}{ev['median_error_m']:>8.3f}{ev['p95_error_m']:>8.3f}"]
    if ev.get("rows"):
        lines.append("rows: truth row, count (row direction), count (K-means), truth visible")
        for r in ev["rows"]:
            lines.append(f"  row {r['row']:>2}: {r['count']:>5} {r['count_kmeans']:>5} {r['truth_visible']:>5}")
    tr = ev.get("trees")
    if tr and tr["bins"]:
        lines.append(f"trees (1-m bins along rows of 30+ visible apples): {tr['bins']} bins, r {tr['r']:.3f}, mean "
                     f"absolute error {tr['mae']:.2f} apples (truth mean {tr['truth_mean']:.2f})")
    loc = ev.get("local")
    if loc:
        lines.append(f"local (a translation more per {loc['window_s']:g} s of flight: the GPS's wander over a long flight): "
                     f"F1 {loc['f1']:.3f}, median error {loc['median_error_m']:.3f} m, cameras {loc['camera_rms_m']:.2f} m "
                     f"RMS, {loc['windows']} windows")
    a = ev["absolute"]
    lines.append(f"absolute (where GPS put the map): F1 {a['f1']:.3f}, median error "
                 f"{a['median_error_m'] if a['median_error_m'] == a['median_error_m'] else float('nan'):.3f} m")
    return "\n".join(lines)



def score_poses(fl: FlightDir, R: np.ndarray, t: np.ndarray, source: np.ndarray, kf: np.ndarray,
                sources=None) -> dict:
    """Errors in ENU against truth/frames.csv (after georeferencing, no fresh alignment), also by each of
    ``sources`` (default: those the frames have)."""
    R_true, t_true = fl.truth_poses()
    C, C_true = -np.einsum("nji,nj->ni", R, t), -np.einsum("nji,nj->ni", R_true, t_true)
    pos = np.linalg.norm(C - C_true, axis=1)
    rot = np.degrees(np.linalg.norm(Rotation.from_matrix(np.einsum("nij,nkj->nik", R, R_true)).as_rotvec(), axis=1))
    e = apple_reprojection_errors(fl, R, t, R_true, t_true)
    reg = source == "registered"
    out = {
        "position_error_median_m": float(np.median(pos[reg])) if reg.any() else float("nan"),
        "position_error_p95_m": float(np.percentile(pos[reg], 95)) if reg.any() else float("nan"),
        "rotation_error_median_deg": float(np.median(rot[reg])) if reg.any() else float("nan"),
        "apple_reprojection_error_median_px": float(np.median(e)) if len(e) else float("nan"),
        "by_source": {src: {"frames": int((source == src).sum()),
                            "position_error_median_m": float(np.median(pos[source == src])) if (source == src).any() else None,
                            "rotation_error_median_deg": float(np.median(rot[source == src])) if (source == src).any() else None}
                      for src in (sources or dict.fromkeys(np.asarray(source).tolist()))},
    }
    # the same after removing the mean position offset: what is left once the GPS bias is set aside
    off = (C - C_true)[reg].mean(0) if reg.any() else np.zeros(3)
    out["mean_offset_enu_m"] = off.tolist()
    out["position_error_median_without_mean_offset_m"] = float(np.median(np.linalg.norm(C[reg] - off - C_true[reg], axis=1))) if reg.any() else float("nan")
    # the model's own accuracy: the registered poses taken onto the true ones by the best similarity
    # (positions and orientations, as georeferencing fits it), then the true apples reprojected
    if reg.sum() >= 3:
        fit = fit_similarity(C[reg], C_true[reg], 0.01, R[reg], R_true[reg], np.radians(0.05))
        R_s, t_s = georeference_poses(R[reg], t[reg], fit.similarity)
        R_a, t_a = R.copy(), t.copy()
        R_a[reg], t_a[reg] = R_s, t_s
        e = apple_reprojection_errors(fl, R_a, t_a, R_true, t_true, frames=np.flatnonzero(reg))
        out["apple_reprojection_error_after_similarity_median_px"] = float(np.median(e)) if len(e) else float("nan")
    return out



def apple_reprojection_errors(fl: FlightDir, R, t, R_true, t_true, frames=None) -> np.ndarray:
    """Pixel distances between the true apples (at least half visible) projected through (R, t) and
    through the true poses, over ``frames`` (default all)."""
    cam = fl.camera()
    a, d = fl.truth_apples(), fl.truth_detections()
    X = np.stack([a["x"], a["y"], a["z"]], 1)
    errs = []
    for f in np.unique(d["frame"]) if frames is None else frames:
        sel = (d["frame"] == f) & visible(d["visible_fraction"])
        if not sel.any():
            continue
        idx = np.searchsorted(a["apple_id"], d["apple_id"][sel])
        uv, _ = cam.project(X[idx], R[f], t[f])
        uv_t, _ = cam.project(X[idx], R_true[f], t_true[f])
        errs.append(np.linalg.norm(uv - uv_t, axis=1))
    return np.concatenate(errs) if errs else np.zeros(0)
