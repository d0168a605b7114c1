"""Score the association against a simulated flight's truth.

    python -m ground evaluate FLIGHT_DIR [--detections truth|FILE] [--poses truth|FILE] [--noise-px S]
        [--miss P] [--fp N] [--dup P] [--pose-noise-deg D] [--pose-noise-m M] [--mode offline|windowed] [--json OUT]

Detections come from ``truth/detections.csv`` (apples at least ``--min-visible`` visible), perturbed
deterministically from ``--seed``: pixel jitter, misses, false positives per frame (Poisson) and
duplicate detections; or from a CSV ``frame,u,v[,score]`` (OpenCV pixel convention). Poses come
from ``truth/frames.csv``, from the telemetry alone (GPS + gimbal), or a CSV with the same columns, each frame's pose
perturbed on its own if asked (tracking's jitter: a random turn and a random shift of its centre). Predicted apples are matched to truth
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

from ground.apples.association import AssociationParams, FrameDetections
from ground.apples.paper import FruitAssociation
from ground.apples.windowed import WindowedAssociation
from ground.evaluation.baselines import SortTracker, count_per_frame_sum
from ground.evaluation.scoring import MATCH_M, score_map
from pomar.countable import MIN_VIEWS, MIN_VISIBLE
from pomar.flight import FlightDir, FlightFormatError, read_csv
from pomar.rotations import quat_wxyz_to_rotation

log = logging.getLogger(__name__)


@dataclass
class Perturbation:
    noise_px: float = 0.0
    miss: float = 0.0
    fp_per_frame: float = 0.0
    dup: float = 0.0
    min_visible: float = MIN_VISIBLE
    seed: int = 0
    #: Each frame's camera turned at random by this much (degrees, per axis, normal; each frame on its own).
    pose_noise_deg: float = 0.0
    #: Each frame's camera centre moved at random by this much (metres, per axis, normal; each frame on its own).
    pose_noise_m: float = 0.0


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


def projection_matrices(flight: FlightDir, poses: str, pert: Perturbation | None = None) -> np.ndarray:
    """Every frame's camera matrix from ``poses`` ('truth', 'telemetry' or a CSV), each pose perturbed by ``pert``'s
    pose noise (a random stream of its own: the detections' perturbation stays the same for a seed)."""
    cam = flight.camera()
    if poses == "truth":
        R, t = flight.truth_poses()
    elif poses == "telemetry":
        from ground.poses.telemetry_poses import telemetry_poses

        R, t, _ = telemetry_poses(flight)
    else:
        from pomar.flight import FRAMES_COLUMNS

        fr = read_csv(Path(poses), FRAMES_COLUMNS)
        order = np.argsort(fr["frame"])
        q = np.stack([fr[k][order] for k in ("qw", "qx", "qy", "qz")], 1)
        R = quat_wxyz_to_rotation(q).as_matrix()
        t = np.stack([fr[k][order] for k in ("tx", "ty", "tz")], 1)
    if pert is not None and (pert.pose_noise_deg or pert.pose_noise_m):
        from scipy.spatial.transform import Rotation

        rng = np.random.default_rng([pert.seed, 1])
        C = -np.einsum("nji,nj->ni", R, t) + rng.normal(0, pert.pose_noise_m, (len(R), 3))
        R = Rotation.from_rotvec(rng.normal(0, np.radians(pert.pose_noise_deg), (len(R), 3))).as_matrix() @ R
        t = -np.einsum("nij,nj->ni", R, C)
    K = cam.K_opencv
    return np.einsum("ij,njk->nik", K, np.concatenate([R, t[:, :, None]], axis=2))


def evaluate(flight_dir, mode: str = "windowed", params: AssociationParams | None = None,
             pert: Perturbation | None = None, detections: str = "truth", poses: str = "truth",
             match_m: float = MATCH_M, baselines: bool = True, truth_min_views: int = MIN_VIEWS,
             remove_pose_offset: bool = False) -> dict:
    flight = FlightDir(flight_dir)
    if not flight.has_truth:
        raise FlightFormatError(f"{flight.path}: no truth/ to evaluate against")
    params = params or AssociationParams()
    pert = pert or Perturbation()
    meta = flight.meta()
    Ps = projection_matrices(flight, poses, pert)
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
