"""Replay a recorded flight through both processes, as if live: onboard node + ground node over zenoh on loopback.

    python -m ground replay [FLIGHT_DIR] [--out DIR] [--realtime] [--detector onnx|truth-replay]

Starts ``python -m onboard run`` (listening on a free 127.0.0.1 port) and ``python -m ground run``
(connecting to it) as two processes, shows the ground's progress, waits for the ground to finish,
then stops the onboard node by its PID. Lock-step (default): every frame is processed, as fast as
the machine goes; ``--realtime``: frames come at the video's rate and the onboard node takes the
newest one, dropping what it cannot keep up with. With the flight's ``truth/``, the map is scored
against it and the scores go to ``report.json`` under ``evaluation``, next to ``wall_seconds``,
``flight_seconds`` and ``realtime_factor``.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

from pomar.flight import FlightDir

log = logging.getLogger(__name__)

BUNDLED = Path(__file__).resolve().parents[1] / "replay_data" / "demo-flight"


class ReplayError(RuntimeError):
    """A replay whose onboard or ground node failed; the message carries the node's own error."""


def _onboard_error(out: Path) -> str:
    """The onboard node's error: its summary's, else its log's error lines, else its log's last lines."""
    summary = out / "onboard.json"
    if summary.is_file():
        try:
            err = json.loads(summary.read_text()).get("error")
        except (ValueError, AttributeError):
            err = None
        if err:
            return err
    lines = (out / "onboard.log").read_text(errors="replace").splitlines() if (out / "onboard.log").is_file() else []
    errors = [ln for ln in lines if ln.startswith("error:")]
    return " / ".join(errors[-3:]) if errors else " / ".join(lines[-5:]) or "no output"


def stop_process(proc: subprocess.Popen, timeout_s: float = 10.0) -> None:
    """Stop a node we started, by its PID: SIGINT (it writes what it has), then SIGKILL after timeout_s."""
    if proc.poll() is None:
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout_s)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _enu(flight: FlightDir, path: Path) -> np.ndarray:
    from pomar.flight import read_csv

    d = read_csv(path, ["lat", "lon", "alt"])
    geo = np.stack([d["lat"], d["lon"], d["alt"]], 1).reshape(-1, 3)
    return flight.origin().to_enu(geo[:, 0], geo[:, 1], geo[:, 2]).reshape(-1, 3)


def replay_cameras(flight: FlightDir, out: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A run's camera poses (poses.csv): frames (n,), centres (n, 3) in the flight's truth ENU frame and
    world-to-camera rotations (n, 3, 3)."""
    from pomar.flight import read_csv
    from pomar.rotations import quat_wxyz_to_rotation

    d = read_csv(out / "poses.csv", ["frame", "qw", "qx", "qy", "qz"])
    R = quat_wxyz_to_rotation(np.stack([d[k] for k in ("qw", "qx", "qy", "qz")], 1)).as_matrix().reshape(-1, 3, 3)
    return d["frame"].astype(int), _enu(flight, out / "poses.csv"), R


def shape_fit(flight: FlightDir, frames: np.ndarray, centres: np.ndarray, R: np.ndarray):
    """The similarity fit that best takes these camera poses onto the true ones (the georeferencing
    error, which only the GPS sets); ``.similarity`` maps a run's ENU points into the truth's."""
    from ground.georeference import fit_similarity

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


def evaluate_map(flight: FlightDir, out: Path, min_visible: float = 0.5, match_m: float = 0.10) -> dict:
    """Score the written apples.csv against the flight's truth (in the truth's ENU frame).

    Two scores. ``absolute``: the map where GPS put it. The headline: the map's *shape*, after taking
    away the georeferencing error, i.e. the similarity that best takes our camera poses (poses.csv:
    centres and orientations) onto the true ones. That error comes from the GPS (its bias over the
    flight, and the scale it gives over a short straight line), which no image processing can see;
    its size is reported as ``georeference_error``."""
    from ground.evaluate import score_map
    from pomar.flight import read_csv

    keys = ("precision", "recall", "f1", "count", "truth_count", "count_error_pct", "median_error_m", "p95_error_m",
            "recall_all_apples_in_rows_seen", "duplicates", "rows", "worst_row_error_pct", "trees")
    apples = _enu(flight, out / "apples.csv")
    frames, cams, R_ours = replay_cameras(flight, out)
    res = {}
    if len(frames) >= 3:
        R_true, t_true = flight.truth_poses()
        C_true = -np.einsum("nji,nj->ni", R_true, t_true)[frames]
        fit = shape_fit(flight, frames, cams, R_ours)
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
        C_fit = S.apply(cams)
        off, win = local_offsets(frames, C_fit, C_true, LOCAL_WINDOW_S * flight.meta().fps)
        a = read_csv(out / "apples.csv", ["first_frame", "last_frame"])
        mid = (np.asarray(a["first_frame"]) + np.asarray(a["last_frame"])).reshape(-1) / 2
        at = np.clip(np.searchsorted(frames, mid), 0, len(frames) - 1)
        local = score_map(flight, S.apply(apples) + off[win[at]], min_visible=min_visible, match_m=match_m)
        d = C_fit + off[win] - C_true
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


def replay(flight_dir=BUNDLED, out_dir=None, realtime: bool = False, detector: str = "onnx", model=None,
           keyframe_every: int | None = None, keyframe_width: int = 960, every: int = 1, rrd: bool = True,
           ground_args: list[str] | None = None, onboard_args: list[str] | None = None, timeout_s: float = 3600,
           quiet: bool = False, recorded=None, speed: float = 1.0) -> dict:
    """Both processes over zenoh on loopback; with ``recorded`` (a journal.bin), the recording's player
    (``python -m ground play``, at ``speed`` x its capture-time pace) stands in for the onboard node."""
    flight = FlightDir(flight_dir)
    meta = flight.meta()
    out = Path(out_dir or f"out/replay/{flight.path.name}")
    if recorded is not None and Path(recorded).resolve() == (out / "journal.bin").resolve():
        raise ReplayError(f"{recorded} is the journal this replay would write: give another --out")
    out.mkdir(parents=True, exist_ok=True)
    for stale in ("journal.bin", "report.json"):
        (out / stale).unlink(missing_ok=True)
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    py = sys.executable
    onboard_cmd = [py, "-m", "onboard", "run", str(flight.path), "--listen", endpoint, "--detector", detector,
                   "--keyframe-width", str(keyframe_width), "--every", str(every), "--linger", "600",
                   "--summary", str(out / "onboard.json")]
    if keyframe_every is not None:  # else the onboard node's default: a keyframe every 0.2 s of capture time
        onboard_cmd += ["--keyframe-every", str(keyframe_every)]
    if realtime:  # still waits for its ground: a replay has no reason to start before the ground listens
        onboard_cmd += ["--realtime", "--wait-for-ground", "30"]
    if model:
        onboard_cmd += ["--model", str(model)]
    onboard_cmd += onboard_args or []
    if recorded is not None:  # the recording's player instead of the onboard node; the ground maps it live
        onboard_cmd = [py, "-m", "ground", "play", str(recorded), "--listen", endpoint, "--speed", str(speed),
                       "--flight-id", meta.flight_id, "--linger", "600", "--summary", str(out / "onboard.json")]
    ground_cmd = [py, "-m", "ground", "run", "--flight-id", meta.flight_id, "--connect", endpoint, "--out", str(out),
                  "--fresh", "--expected-frames", str(-(-meta.frame_count // every))] + ([] if rrd else ["--no-rrd"]) \
        + ([] if realtime or (recorded is not None and speed > 0) else ["--mapping", "inline"]) \
        + (ground_args or [])  # lock-step (and --speed 0): mapping inline, deterministic
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    t0 = time.monotonic()
    logs = {name: open(out / f"{name}.log", "w") for name in ("onboard", "ground")}
    (out / "onboard.json").unlink(missing_ok=True)
    onboard = subprocess.Popen(onboard_cmd, stdout=logs["onboard"], stderr=subprocess.STDOUT, env=env)
    procs: dict[str, subprocess.Popen] = {}
    failed = threading.Event()

    def watch_onboard():
        # an onboard node that exits by itself has failed (it lingers until stopped otherwise): stop the ground,
        # which then writes what it has
        if onboard.wait() != 0 and not stopping.is_set():
            failed.set()
            # SIGTERM: a ground still starting ends quietly (SIGINT would print a KeyboardInterrupt traceback from
            # wherever its imports were); one running takes it as Ctrl-C (pomar.shutdown) and writes what it has
            if "ground" in procs and procs["ground"].poll() is None:
                procs["ground"].send_signal(signal.SIGTERM)

    stopping = threading.Event()
    threading.Thread(target=watch_onboard, daemon=True).start()
    try:
        time.sleep(0.5)
        if not failed.is_set():
            procs["ground"] = ground = subprocess.Popen(ground_cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                                        env=env, text=True)
            if failed.is_set():
                ground.send_signal(signal.SIGTERM)
            for line in ground.stdout:  # the ground's progress, shown and kept
                logs["ground"].write(line)
                if not quiet:
                    sys.stderr.write(line)
                if time.monotonic() - t0 > timeout_s:
                    raise TimeoutError(f"replay of {flight.path} ran past {timeout_s:.0f} s")
            ground.wait()
    finally:
        stopping.set()
        for proc in (procs.get("ground"), onboard):
            if proc is not None:
                stop_process(proc)
        for f in logs.values():
            f.close()
    wall = time.monotonic() - t0
    # the onboard node failed only if it exited by itself (the watcher saw it) or said so in its summary: the exit code
    # after our own stop (SIGINT, then SIGKILL when closing its zenoh session outlasts stop_process) is not its failure
    onboard_error = _onboard_error(out) if failed.is_set() else None
    onboard_json = out / "onboard.json"
    summary = json.loads(onboard_json.read_text()) if onboard_json.is_file() else {}
    onboard_error = onboard_error or summary.get("error")
    if onboard_error and not summary.get("frames_processed"):
        raise ReplayError(f"the onboard node failed before it sent a frame: {onboard_error} (log: {out / 'onboard.log'})")
    ground = procs.get("ground")
    if ground is None or ground.returncode != 0:
        raise ReplayError(f"the ground node failed (exit {ground.returncode if ground else None}); see {out / 'ground.log'}")
    report = json.loads((out / "report.json").read_text())
    flight_s = meta.frame_count / meta.fps
    report.update(wall_seconds=wall, flight_seconds=flight_s, realtime_factor=flight_s / wall,
                  replay={"flight": str(flight.path), "realtime": realtime, "detector": detector,
                          "keyframe_every": keyframe_every, "keyframe_width": keyframe_width, "every": every,
                          "recorded": str(recorded) if recorded is not None else None,
                          "speed": speed if recorded is not None else None})
    if summary:
        report["onboard"] = summary
    report["onboard_exit_code"] = onboard.returncode
    if onboard_error:  # the map holds what came before the onboard node stopped
        report["onboard_error"] = onboard_error
    if flight.has_truth:
        report["evaluation"] = evaluate_map(flight, out)
    from ground.outputs import write_json

    write_json(out / "report.json", report)
    return report
