"""The evaluation harness and the row assignment."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest

from ground.apples.association import AssociationParams
from ground.evaluation.evaluate import Perturbation, evaluate, truth_detections
from ground.evaluation.scoring import detected, input_problem, match
from ground.apples.rows import direction_rows, kmeans_rows, row_direction
from tests.conftest import BUNDLED, ROOT


def test_rows_from_direction_and_gaps():
    rng = np.random.default_rng(0)
    az = np.radians(25.0)  # rows along this direction, 4 m apart, 30 m long
    along = np.array([np.cos(az), np.sin(az)])
    across = np.array([-np.sin(az), np.cos(az)])
    pts, truth = [], []
    for r in range(4):
        n = 60 + 10 * r
        s = rng.uniform(0, 30, n)
        o = 4.0 * r + rng.normal(0, 0.3, n)
        pts.append(s[:, None] * along + o[:, None] * across)
        truth += [r] * n
    xy, truth = np.concatenate(pts), np.array(truth)
    assert abs(((np.degrees(row_direction(xy)) - 25.0) + 90) % 180 - 90) < 1.0
    labels, _ = direction_rows(xy)
    assert np.array_equal(labels, truth)
    counts = np.bincount(kmeans_rows(xy, 4), minlength=4)
    assert counts.sum() == len(xy)  # K-means, as the paper: a partition into K groups


def test_match_is_one_to_one_within_radius():
    truth = np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0.0]])
    pred = np.array([[0.01, 0, 0], [0.02, 0, 0], [1.5, 0, 0], [2.05, 0, 0]])
    p, t, d = match(pred, truth, 0.1)
    assert sorted(t.tolist()) == [0, 2] and len(set(p.tolist())) == 2 and (d <= 0.1).all()


def test_a_detection_finds_the_apple_its_centre_lies_in():
    """scoring.detected: a truth apple in a frame is found when a detection's centre lies within its radius, or 2 px
    for a tiny one; a frame the stream does not carry finds nothing."""
    d = {"frame": np.array([0, 0, 0, 1]), "u": np.array([10.0, 50.0, 80.0, 10.0]), "v": np.full(4, 10.0),
         "r_px": np.array([5.0, 1.0, 5.0, 5.0])}
    centres = {0: np.array([[12.0, 11.0], [51.5, 10.0], [86.0, 10.0]])}
    assert detected(d, centres).tolist() == [True, True, False, False]


def test_a_benchmarks_inputs_are_judged_in_one_line(tmp_path):
    """scoring.input_problem: a folder that is no flight, and a replay folder without the file a benchmark reads, each
    give one line naming the file; good inputs give none."""
    assert "flight.json" in input_problem(tmp_path)
    assert input_problem(BUNDLED, tmp_path, "journal.bin", "no recorded stream there") == \
        f"{tmp_path / 'journal.bin'}: no recorded stream there"
    (tmp_path / "journal.bin").write_bytes(b"")
    assert input_problem(BUNDLED) is None and input_problem(BUNDLED, tmp_path, "journal.bin") is None


def test_the_detector_scale_benchmark_refuses_a_missing_flight_in_one_line(tmp_path):
    """benchmarks/detector_scale.py checks every flight before it starts: a path that is no flight is one line naming
    it, exit 2, no traceback."""
    r = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "detector_scale.py"), str(BUNDLED),
                        str(tmp_path / "nowhere")], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 2 and "Traceback" not in r.stderr, r.stderr
    assert r.stderr.strip().splitlines() == [f"error: {tmp_path / 'nowhere'}: not a flight directory (does not exist)"]


def test_perturbation_is_deterministic_and_does_what_it_says(bundled_flight):
    meta = bundled_flight.meta()
    clean, src = truth_detections(bundled_flight, Perturbation(), meta.frame_count, meta.width, meta.height)
    p = Perturbation(noise_px=1.0, miss=0.2, fp_per_frame=2.0, dup=0.1, seed=3)
    a, sa = truth_detections(bundled_flight, p, meta.frame_count, meta.width, meta.height)
    b, _ = truth_detections(bundled_flight, p, meta.frame_count, meta.width, meta.height)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    n_clean = sum(len(x) for x in clean)
    n_fp = sum((s == -1).sum() for s in sa)
    assert abs(n_fp / meta.frame_count - 2.0) < 0.5
    n_true = sum((s >= 0).sum() for s in sa)
    assert 0.8 * 1.1 * n_clean * 0.9 < n_true < 0.8 * 1.1 * n_clean * 1.1  # misses, then duplicates


def test_pose_noise_turns_and_moves_each_camera_as_asked_and_leaves_the_detections(bundled_flight):
    from ground.evaluation.evaluate import projection_matrices

    K_inv = np.linalg.inv(bundled_flight.camera().K_opencv)

    def poses(Ps):
        Rt = np.einsum("ij,njk->nik", K_inv, Ps)
        return Rt[:, :, :3], -np.einsum("nji,nj->ni", Rt[:, :, :3], Rt[:, :, 3])

    R0, C0 = poses(projection_matrices(bundled_flight, "truth"))
    p = Perturbation(noise_px=1.0, seed=3, pose_noise_deg=0.05, pose_noise_m=0.01)
    R1, C1 = poses(projection_matrices(bundled_flight, "truth", p))
    assert np.array_equal(projection_matrices(bundled_flight, "truth", p), projection_matrices(bundled_flight, "truth", p))
    turn = np.degrees(np.arccos(np.clip((np.einsum("nij,nij->n", R1, R0) - 1) / 2, -1, 1)))
    shift = C1 - C0
    # per axis sigma s: the turn's size is a chi with 3 degrees of freedom (mean 1.596 s); the shift's spread is s
    assert 0.9 * 1.596 * 0.05 < turn.mean() < 1.1 * 1.596 * 0.05
    assert 0.009 < shift.std() < 0.011 and abs(shift.mean()) < 0.002
    # the detections' own perturbation does not change with the poses'
    meta = bundled_flight.meta()
    a, _ = truth_detections(bundled_flight, Perturbation(noise_px=1.0, seed=3), meta.frame_count, meta.width, meta.height)
    b, _ = truth_detections(bundled_flight, p, meta.frame_count, meta.width, meta.height)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))


def test_evaluate_cli_on_the_bundled_flight(tmp_path):
    out = tmp_path / "eval.json"
    r = subprocess.run([sys.executable, "-m", "ground", "evaluate", str(BUNDLED), "--noise-px", "0.5",
                        "--miss", "0.05", "--fp", "0.2", "--json", str(out)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "sort_2d_tracker" in r.stdout and "per_frame_sum" in r.stdout
    res = json.loads(out.read_text())
    for key in ("precision", "recall", "f1", "count", "truth_count", "count_error_pct", "median_error_m",
                "p95_error_m", "frames", "seconds", "frames_per_s", "rows"):
        assert key in res, key
    # on near-clean input the method counts within 10 % and places apples within 3 cm (median)
    assert abs(res["count_error_pct"]) < 10 and res["median_error_m"] < 0.03 and res["f1"] > 0.75
    # and beats both baselines' count error
    for b in res["baselines"].values():
        assert abs(b["count_error_pct"]) > abs(res["count_error_pct"])
    assert sum(r["count"] for r in res["rows"]) == res["count"]


def test_evaluate_needs_truth(tmp_path):
    import shutil

    from pomar.flight import FlightFormatError

    flight = tmp_path / "f"
    shutil.copytree(BUNDLED, flight, ignore=shutil.ignore_patterns("video.mp4", "truth"))
    try:
        evaluate(flight, "windowed", AssociationParams())
    except FlightFormatError as exc:
        assert "truth" in str(exc)
    else:
        raise AssertionError("expected a FlightFormatError")


def test_poses_and_detections_from_files(tmp_path, bundled_flight):
    """--poses FILE and --detections FILE give the same result as the truth they were written from."""
    import shutil

    from pomar.flight import write_csv

    shutil.copy(bundled_flight.truth_dir / "frames.csv", tmp_path / "poses.csv")
    meta = bundled_flight.meta()
    xy, _ = truth_detections(bundled_flight, Perturbation(), meta.frame_count, meta.width, meta.height)
    frames = np.concatenate([np.full(len(x), i) for i, x in enumerate(xy)])
    uv = np.concatenate(xy)
    write_csv(tmp_path / "dets.csv", ["frame", "u", "v"], {"frame": frames, "u": uv[:, 0], "v": uv[:, 1]},
              {"u": ".6f", "v": ".6f"})
    a = evaluate(BUNDLED, "windowed", AssociationParams(), Perturbation(), baselines=False)
    b = evaluate(BUNDLED, "windowed", AssociationParams(), Perturbation(), detections=str(tmp_path / "dets.csv"),
                 poses=str(tmp_path / "poses.csv"), baselines=False)
    assert a["count"] == b["count"] and abs(a["f1"] - b["f1"]) < 1e-9
    # poses that are off move the apples: the score must drop
    fr = (tmp_path / "poses.csv").read_text().splitlines()
    header, rows = fr[0], [r.split(",") for r in fr[1:]]
    tx = header.split(",").index("tx")
    for r in rows:
        r[tx] = str(float(r[tx]) + 0.5)
    (tmp_path / "bad.csv").write_text("\n".join([header] + [",".join(r) for r in rows]) + "\n")
    c = evaluate(BUNDLED, "windowed", AssociationParams(), Perturbation(), poses=str(tmp_path / "bad.csv"), baselines=False)
    assert c["f1"] < 0.2


def test_local_offsets_take_away_a_wander_per_window_and_nothing_else():
    """The local score's windows: a camera error that wanders from window to window (the GPS over a long flight) is
    taken away window by window; what varies within a window stays."""
    from ground.evaluation.scoring import local_offsets

    frames = np.arange(0, 600)
    truth = np.stack([np.zeros(600), frames * 0.3, np.full(600, 12.0)], 1)
    wander = np.stack([np.sin(frames / 300.0), np.cos(frames / 200.0), np.zeros(600)], 1)
    jitter = np.random.default_rng(0).normal(0, 0.01, (600, 3))
    off, win = local_offsets(frames, truth + wander + jitter, truth, 100)
    assert win.max() == 5 and np.array_equal(win, frames // 100)
    left = truth + wander + jitter + off[win] - truth
    assert np.sqrt((left ** 2).sum(1).mean()) < 0.2 < 0.8 < np.sqrt((wander ** 2).sum(1).mean())
    for k in range(6):  # each window's mean error is gone
        assert np.allclose(left[win == k].mean(0), 0, atol=1e-9)


def test_the_shape_is_judged_on_the_cameras_the_map_placed(replayed_test_flight, tmp_path):
    """Frames with telemetry poses (no image: GPS and gimbal alone) do not enter the shape fit: their attitudes, a few
    degrees off, once pulled a map whose first half was right to F1 0.04 (benchmarks/faults.py keyframes-stop)."""
    import csv

    from scipy.spatial.transform import Rotation

    from ground.evaluation.scoring import evaluate_map

    flight, out, _ = replayed_test_flight
    scores = []
    for turn_deg in (0.0, 3.0):
        run = tmp_path / f"turned-{turn_deg:g}"
        shutil.copytree(out, run, ignore=shutil.ignore_patterns("work", "model", "*.rrd", "journal.bin"))
        rows = list(csv.DictReader(open(run / "poses.csv")))
        for r in rows[len(rows) // 2:]:  # the second half: telemetry poses, turned
            q = Rotation.from_quat([float(r[k]) for k in ("qx", "qy", "qz", "qw")])
            q = q * Rotation.from_euler("x", turn_deg, degrees=True)
            r["qx"], r["qy"], r["qz"], r["qw"] = (f"{v:.9f}" for v in q.as_quat())
            r["source"] = "telemetry"
        with open(run / "poses.csv", "w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=list(rows[0]), lineterminator="\n")
            w.writeheader()
            w.writerows(rows)
        scores.append(evaluate_map(flight, run))
    assert scores[0]["f1"] > 0.3 and scores[1]["f1"] == scores[0]["f1"], [s["f1"] for s in scores]
    assert scores[1]["georeference_error"]["scale_error_pct"] == scores[0]["georeference_error"]["scale_error_pct"]


def test_the_count_against_the_load_and_a_repeat_pair():
    from ground.evaluation.scoring import MIN_ROW_APPLES, against_load, repeat_pair

    def row(r, count, visible, total):
        return {"row": r, "count": count, "truth_visible": visible, "truth_all": total}

    same_share = [row(1, 40, 40, 80), row(2, 60, 60, 120), row(3, 50, 50, 100), row(4, 5, MIN_ROW_APPLES - 1, 90)]
    load = against_load(same_share)
    assert load["rows"] == 3 and load["r"] == pytest.approx(1.0) and load["cv"] == pytest.approx(0.0)
    uneven = against_load([row(1, 40, 40, 80), row(2, 30, 60, 120), row(3, 50, 50, 100)])
    assert uneven["cv"] > 0.2 and uneven["r"] < 0.5
    assert np.isnan(against_load(same_share[:2])["r"])  # too few rows to say
    pair = repeat_pair([row(1, 36, 40, 80), row(2, 60, 60, 120)], [row(2, 57, 60, 120), row(1, 40, 40, 80)])
    assert [r["row"] for r in pair["rows"]] == [1, 2] and pair["worst"] == pytest.approx(0.1)
