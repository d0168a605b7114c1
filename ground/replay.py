"""Replay a recorded flight through both processes, as if live: onboard node + ground node over zenoh on loopback.

    python -m ground replay [FLIGHT_DIR] [--out DIR] [--realtime] [--detector onnx|truth-replay]
    python -m ground replay [FLIGHT_DIR] --recorded JOURNAL --speed 0 --out DIR   # a ground's journal, lock-step

Starts ``python -m onboard run`` (listening on a free 127.0.0.1 port) and ``python -m ground run``
(connecting to it) as two processes, shows the ground's progress, waits for the ground to finish,
then stops the onboard node by its PID. Lock-step (default): every frame is processed, as fast as
the machine goes; ``--realtime``: frames come at the video's rate and the onboard node takes the
newest one, dropping what it cannot keep up with. With the flight's ``truth/``, the map is scored
against it and the scores go to ``report.json`` under ``evaluation``, next to ``wall_seconds``,
``flight_seconds`` and ``realtime_factor``. With ``--recorded`` the recording's player stands in for the onboard
node; without a flight directory the stream alone says which flight it is, and nothing is scored.
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

from ground.evaluation.scoring import evaluate_map
from ground.outputs.tables import rescue_folder, write_json
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


def child_pids(pid: int) -> list[int]:
    """The processes whose parent is ``pid`` (read from /proc): a ground's mapping process and resource tracker."""
    out = []
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                stat = open(f"/proc/{d}/stat").read()
            except OSError:
                continue
            if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
                out.append(int(d))
    return out


def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def default_out(name: str) -> Path:
    """Where a replay writes when no folder is given: out/replay/<the flight's folder name, or its id>."""
    return Path("out/replay") / name


def recording_extent(recorded) -> tuple[str, int, float]:
    """A recorded stream's flight id, frame count and capture-time length (s), from the stream alone."""
    from ground.link.player import PlayerError, load_recording

    try:
        rec = load_recording(recorded)
    except PlayerError as exc:
        raise ReplayError(str(exc)) from None
    return rec.flight_id, rec.frames, rec.seconds


def replay(flight_dir=BUNDLED, out_dir=None, realtime: bool = False, detector: str = "onnx", model=None,
           keyframe_every: int | None = None, keyframe_width: int = 960, every: int = 1, rrd: bool = True,
           ground_args: list[str] | None = None, onboard_args: list[str] | None = None, timeout_s: float = 3600,
           quiet: bool = False, recorded=None, speed: float = 1.0) -> dict:
    """Both processes over zenoh on loopback; with ``recorded`` (a journal.bin), the recording's player
    (``python -m ground play``, at ``speed`` x its capture-time pace) stands in for the onboard node; with
    ``flight_dir`` None it alone says what the flight is (a flight of your own, with no truth to score against)."""
    flight = FlightDir(flight_dir) if flight_dir is not None else None
    if flight is not None:
        meta = flight.meta()
        flight_id, frame_count, flight_s = meta.flight_id, meta.frame_count, meta.frame_count / meta.fps
        name = flight.path.name
    elif recorded is not None:
        flight_id, frame_count, flight_s = recording_extent(recorded)
        name = flight_id
    else:
        raise ReplayError("a replay needs a flight directory, or a recorded stream (--recorded)")
    out = Path(out_dir) if out_dir else default_out(name)
    if recorded is not None and Path(recorded).resolve() == (out / "journal.bin").resolve():
        raise ReplayError(f"{recorded} is the journal this replay would write: give another --out")
    try:  # nothing is computed yet: an output folder it cannot write is refused at once
        out.mkdir(parents=True, exist_ok=True)
        for stale in ("journal.bin", "report.json"):
            (out / stale).unlink(missing_ok=True)
        logs = {name: open(out / f"{name}.log", "w") for name in ("onboard", "ground")}
    except OSError as exc:
        raise ReplayError(f"{out}: the replay cannot write there ({exc.strerror}): give another --out") from None
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    py = sys.executable
    if recorded is not None:  # the recording's player instead of the onboard node; the ground maps it live
        onboard_cmd = [py, "-m", "ground", "play", str(recorded), "--listen", endpoint, "--speed", str(speed),
                       "--flight-id", flight_id, "--linger", "600", "--summary", str(out / "onboard.json")]
    else:
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
    ground_cmd = [py, "-m", "ground", "run", "--flight-id", flight_id, "--connect", endpoint, "--out", str(out),
                  "--fresh", "--expected-frames", str(-(-frame_count // every))] + ([] if rrd else ["--no-rrd"]) \
        + ([] if realtime or (recorded is not None and speed > 0) else ["--mapping", "inline"]) \
        + (ground_args or [])  # lock-step (and --speed 0): mapping inline, deterministic
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    t0 = time.monotonic()
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
                if logs["ground"] is not None:
                    try:
                        logs["ground"].write(line)
                    except OSError as exc:  # a full disk: shown, no longer kept
                        log.warning("the ground's log cannot be written to %s (%s): it is shown only", out, exc)
                        _close(logs["ground"])
                        logs["ground"] = None
                if not quiet:
                    sys.stderr.write(line)
                if time.monotonic() - t0 > timeout_s:
                    raise TimeoutError(f"replay of {recorded or flight.path} ran past {timeout_s:.0f} s")
            ground.wait()
    finally:
        stopping.set()
        for proc in (procs.get("ground"), onboard):
            if proc is not None:
                stop_process(proc)
        for f in logs.values():
            _close(f)
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
    rescued = rescue_folder(flight_id, ground.pid) if ground is not None else None
    if ground is not None and ground.returncode == 1 and (rescued / "report.json").is_file():
        # the output folder refused the map files (a full disk): the ground wrote them there, and said so
        log.warning("the map files are in %s, not in %s: its disk refused them; this replay's report goes there too",
                    rescued, out)
        out = rescued
    elif ground is None or ground.returncode != 0:
        raise ReplayError(f"the ground node failed (exit {ground.returncode if ground else None}); see {out / 'ground.log'}")
    report = json.loads((out / "report.json").read_text())
    report.update(wall_seconds=wall, flight_seconds=flight_s, realtime_factor=flight_s / wall,
                  replay={"flight": str(flight.path) if flight is not None else None, "realtime": realtime,
                          "detector": detector,
                          "keyframe_every": keyframe_every, "keyframe_width": keyframe_width, "every": every,
                          "recorded": str(recorded) if recorded is not None else None,
                          "speed": speed if recorded is not None else None})
    if summary:
        report["onboard"] = summary
    report["onboard_exit_code"] = onboard.returncode
    if onboard_error:  # the map holds what came before the onboard node stopped
        report["onboard_error"] = onboard_error
    if flight is not None and flight.has_truth:
        report["evaluation"] = evaluate_map(flight, out)
    write_json(out / "report.json", report)
    report["out"] = str(out)
    return report


def _close(f) -> None:
    """Close a log file; what it still held for a full disk is lost, with nothing more said."""
    if f is None:
        return
    try:
        f.close()
    except OSError:
        pass
