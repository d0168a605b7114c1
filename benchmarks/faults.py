"""The ground's fault matrix: a live flight at 1x with one fault each, against the median of clean runs.

    python benchmarks/faults.py [FLIGHT] [--clean 3] [--only mapper-killed cpu-hogs ...] [--json OUT]

Each run is `onboard run FLIGHT --realtime` (truth-replay detector) to `ground run` on loopback, both separate
processes, as in the field. For each fault: F1 (the shape F1 at 0.10 m), count, frame delay p95, against the median
of ``--clean`` clean runs, and what the user saw (the ground's warnings and errors about it). Run it with nothing
else on the machine: the frame delays are timings.

Faults:
- ``mapper-killed``: the ground's mapping process killed (SIGKILL) 8 s in;
- ``tracker-killed``: multiprocessing's resource tracker killed 8 s in;
- ``cpu-hogs``: two busy processes beside the whole flight;
- ``ground-killed``: the ground killed (SIGKILL) 8 s in and started again at once with the same command (it resumes
  from its journal and asks the drone for what it missed);
- ``onboard-restarted``: the onboard node killed (SIGKILL) 8 s into the flight and started again at once with the same
  command: its video is played as a camera that started with the flight (``--camera-started-at``), so the new node
  takes up the frames taken from then on; those taken while no node ran are lost;
- ``outage-2``, ``outage-8``: nothing reaches the ground for 2 or 8 s from 8 s in: the onboard node stopped with
  SIGSTOP, then let go. It then sends the frames it held, late; none are lost;
- ``link-lost-8``: the link itself cut for 8 s from 8 s in: a TCP relay between the two processes closes every
  connection and refuses new ones, so that what is sent meanwhile is lost to the link (zenoh reconnects; the
  ground may get it back from the drone's history);
- ``outage-30``: the same cut for 30 s, 20 s into a 92-s flight (``--long``, render it first:
  ``python -m sim flight --config sim/configs/outage-flight.toml --out out/sim/outage-flight``), against the
  median of ``--clean`` clean runs of that flight;
- ``disk-full``: the ground's output folder on an 8 MiB tmpfs, which its journal and mapping database fill within
  seconds (needs root to mount; skipped otherwise);
- ``keyframes-stop``: the first clean run's stream played again at 1x (``ground play``) with every keyframe after
  8 s left out: the frames go on without images.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ground.evaluation.scoring import evaluate_map  # noqa: E402
from ground.link.journal import Journal, read_journal  # noqa: E402
from ground.outputs.tables import rescue_folder  # noqa: E402
from ground.replay import child_pids, free_port  # noqa: E402
from pomar import wire  # noqa: E402
from pomar.flight import FlightDir  # noqa: E402

FAULTS = ("mapper-killed", "tracker-killed", "cpu-hogs", "outage-2", "outage-8", "ground-killed", "onboard-restarted",
          "link-lost-8", "disk-full", "keyframes-stop", "outage-30")
FAULT_AT_S = 8.0
LONG_FAULT_AT_S = 20.0  # outage-30, on the long flight
DISK_MB = 8
#: onboard-restarted: the camera starts this long after the node is launched (its model loaded, the ground connected)
ONBOARD_START_S = 10.0


class Relay:
    """A TCP relay on loopback between the ground (which connects to it) and the onboard node: ``cut(s)`` closes
    every connection and refuses new ones for s seconds, so that what is sent meanwhile is lost to the link."""

    def __init__(self, target_port: int):
        self.target = target_port
        self.port = free_port()
        self._srv = socket.create_server(("127.0.0.1", self.port))
        self._conns: list[socket.socket] = []
        self._down_until = 0.0
        self._lock = threading.Lock()
        threading.Thread(target=self._accept, daemon=True).start()

    def _accept(self) -> None:
        while True:
            try:
                a, _ = self._srv.accept()
            except OSError:
                return
            if time.monotonic() < self._down_until:
                a.close()
                continue
            try:
                b = socket.create_connection(("127.0.0.1", self.target))
            except OSError:
                a.close()
                continue
            with self._lock:
                self._conns += [a, b]
            for x, y in ((a, b), (b, a)):
                threading.Thread(target=self._pipe, args=(x, y), daemon=True).start()

    @staticmethod
    def _pipe(x: socket.socket, y: socket.socket) -> None:
        try:
            while data := x.recv(65536):
                y.sendall(data)
        except OSError:
            pass
        for c in (x, y):
            try:
                c.shutdown(socket.SHUT_RDWR)
            except OSError:
                pass

    def cut(self, seconds: float) -> None:
        self._down_until = time.monotonic() + seconds
        with self._lock:
            conns, self._conns = self._conns, []
        for c in conns:
            try:
                c.shutdown(socket.SHUT_RDWR)
                c.close()
            except OSError:
                pass

    def close(self) -> None:
        self._srv.close()
        self.cut(0)


def without_keyframes_after(journal: Path, after_s: float, out: Path) -> Path:
    """A copy of a recorded stream with every keyframe whose frame was taken more than ``after_s`` after the first
    frame left out."""
    records = [(payload, wire.decode(payload)) for payload in read_journal(journal)]
    t_frame = {m.frame: m.t_capture for _, m in records if isinstance(m, wire.FrameMessage)}
    t0 = min(t_frame.values())
    keep = [payload for payload, m in records
            if not (isinstance(m, wire.KeyframeMessage) and t_frame.get(m.frame, float("inf")) - t0 > after_s)]
    out.unlink(missing_ok=True)
    j = Journal(out)
    for payload in keep:
        j.append(payload)
    j.close()
    return out


def cmdline(pid: int) -> str:
    try:
        return open(f"/proc/{pid}/cmdline").read().replace("\0", " ")
    except OSError:
        return ""


def run(flight: FlightDir, out: Path, fault: str | None, recorded: Path | None = None) -> dict:
    """One live flight with ``fault``; ``recorded``: a recorded stream played at 1x instead of the onboard node."""
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    hogs, relay, mounted = [], None, False
    if fault == "cpu-hogs":
        hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(2)]
    if fault in ("link-lost-8", "outage-30"):
        relay = Relay(port)
    if fault == "disk-full":
        out.mkdir(parents=True, exist_ok=True)
        mounted = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={DISK_MB}m", "tmpfs", str(out)],
                                 capture_output=True).returncode == 0
        if not mounted:
            return {"fault": fault, "skipped": "cannot mount a tmpfs (not root)"}
    source = ([sys.executable, "-m", "ground", "play", str(recorded), "--listen", endpoint, "--speed", "1",
               "--wait-for-ground", "30", "--linger", "3"] if recorded is not None else
              [sys.executable, "-m", "onboard", "run", str(flight.path), "--listen", endpoint,
               "--detector", "truth-replay", "--realtime", "--wait-for-ground", "30", "--linger", "3"])
    camera_t0 = None
    if fault == "onboard-restarted":
        camera_t0 = time.time() + ONBOARD_START_S
        source += ["--camera-started-at", f"{camera_t0:.3f}"]
    onboard = subprocess.Popen(source, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env, cwd=ROOT)
    err_path = out.parent / (out.name + ".err")
    ground_cmd = [sys.executable, "-m", "ground", "run", "--flight-id", flight.meta().flight_id, "--connect",
                  f"tcp/127.0.0.1:{relay.port}" if relay else endpoint, "--out", str(out), "--idle-timeout", "60"]
    at = LONG_FAULT_AT_S if fault == "outage-30" else FAULT_AT_S
    if camera_t0 is not None:  # 8 s into the flight: its camera's time
        at += ONBOARD_START_S
    with open(err_path, "w") as errf:
        ground = subprocess.Popen(ground_cmd + ["--fresh"], stdout=subprocess.DEVNULL, stderr=errf, env=env, cwd=ROOT)
        t0, done = time.monotonic(), fault in (None, "cpu-hogs", "disk-full", "keyframes-stop")
        try:
            while ground.poll() is None and time.monotonic() - t0 < 900:
                time.sleep(0.2)
                if done or time.monotonic() - t0 < at:
                    continue
                if fault == "ground-killed":
                    for pid in child_pids(ground.pid):
                        os.kill(pid, signal.SIGKILL)
                    ground.kill()
                    ground.wait()
                    ground = subprocess.Popen(ground_cmd, stdout=subprocess.DEVNULL, stderr=errf, env=env, cwd=ROOT)
                    done = True
                elif fault == "onboard-restarted":
                    onboard.kill()
                    onboard.wait()
                    onboard = subprocess.Popen(source, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env,
                                               cwd=ROOT)
                    done = True
                elif relay is not None:
                    relay.cut(float(fault.split("-")[-1]))
                    done = True
                elif fault.startswith("outage"):
                    os.kill(onboard.pid, signal.SIGSTOP)
                    time.sleep(float(fault.split("-")[1]))
                    os.kill(onboard.pid, signal.SIGCONT)
                    done = True
                else:
                    want = "spawn_main" if fault == "mapper-killed" else "resource_tracker"
                    for pid in child_pids(ground.pid):
                        if want in cmdline(pid):
                            os.kill(pid, signal.SIGKILL)
                            done = True
        finally:
            for p in (ground, onboard, *hogs):
                if p.poll() is None:
                    p.send_signal(signal.SIGINT if p in (ground, onboard) else signal.SIGKILL)
                    try:
                        p.wait(20)
                    except subprocess.TimeoutExpired:
                        p.kill()
            if relay is not None:
                relay.close()
    seen = [line.split(": ", 1)[-1].strip() for line in err_path.read_text().splitlines()
            if " ERROR " in line or " WARNING " in line]
    res = {"fault": fault or "clean", "exit_code": ground.returncode, "fault_done": done, "user_saw": seen[:6]}
    # map files that could not be written to the output folder are in the folder the ground names as it exits
    rescued = rescue_folder(flight.meta().flight_id, ground.pid)
    if (rescued / "report.json").is_file():
        res["rescued"] = True
        shutil.rmtree(out.parent / (out.name + "-rescued"), ignore_errors=True)
        shutil.move(str(rescued), str(out.parent / (out.name + "-rescued")))
        scored = out.parent / (out.name + "-rescued")
    else:
        scored = out
    if (scored / "report.json").is_file():
        rep = json.loads((scored / "report.json").read_text())
        ev = evaluate_map(flight, scored)
        res.update(f1=ev["f1"], count=ev["count"], truth=ev["truth_count"],
                   delay_p95_s=rep["timings"].get("frame_delay_p95_s"),
                   restarts=len(rep["registration"].get("mapper_restarts") or []), final=rep.get("final"),
                   journal_failed=rep.get("link", {}).get("journal_write_failed"),
                   missing_frames=rep.get("frames", {}).get("missing_frames"))
    if mounted:
        keep = out.parent / (out.name + "-kept")
        subprocess.run(["cp", "-r", str(out), str(keep)], capture_output=True)
        subprocess.run(["umount", str(out)], capture_output=True)
    return res


def table(results: list[dict], title: str) -> None:
    clean = [r for r in results if r["fault"] == "clean" and "f1" in r]
    ref = {k: statistics.median(r[k] for r in clean) for k in ("f1", "count", "delay_p95_s")} if clean else {}
    print(f"\n{title}: reference, the median of {len(clean)} clean runs: F1 {ref.get('f1', float('nan')):.3f}, "
          f"count {ref.get('count', float('nan')):.0f}, frame delay p95 {ref.get('delay_p95_s', float('nan')):.2f} s")
    print(f"{'fault':<16}{'F1':>7}{'dF1':>8}{'count':>7}{'dcount %':>10}{'delay p95 s':>13}  what the user saw")
    for r in results:
        if "f1" not in r:
            print(f"{r['fault']:<16} {r.get('skipped') or 'no report (exit %s)' % r.get('exit_code')}")
            continue
        # without clean runs there is nothing to compare with: the differences are left blank
        df1 = f"{r['f1'] - ref['f1']:>+8.3f}" if ref else f"{'-':>8}"
        dc = f"{100 * (r['count'] - ref['count']) / ref['count']:>+10.1f}" if ref else f"{'-':>10}"
        print(f"{r['fault']:<16}{r['f1']:>7.3f}{df1}{r['count']:>7d}{dc}"
              f"{r['delay_p95_s'] or float('nan'):>13.2f}  {(r['user_saw'] or ['-'])[0][:90]}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("flight", nargs="?", type=Path, default=ROOT / "replay_data" / "demo-flight")
    p.add_argument("--long", type=Path, default=ROOT / "out" / "sim" / "outage-flight",
                   help="the flight of at least 90 s for outage-30")
    p.add_argument("--clean", type=int, default=3, help="clean runs of each flight (their median is the reference)")
    p.add_argument("--only", nargs="*", choices=FAULTS, default=list(FAULTS))
    p.add_argument("--repeats", type=int, default=1, help="runs of each fault")
    p.add_argument("--json", type=Path)
    a = p.parse_args(argv)
    work = Path(tempfile.mkdtemp(prefix="pomar-faults-"))
    plan = [(FlightDir(a.flight), [f for f in a.only if f != "outage-30"])]
    if "outage-30" in a.only:
        plan.append((FlightDir(a.long), ["outage-30"]))
    everything = {}
    for flight, faults in plan:
        if not faults:
            continue
        name = flight.meta().flight_id
        results = everything[name] = []
        for i in range(a.clean):
            results.append(run(flight, work / f"{name}-clean-{i}", None))
            print(json.dumps(results[-1]), flush=True)
        for fault in faults:
            recorded = None
            if fault == "keyframes-stop":
                recorded = without_keyframes_after(work / f"{name}-clean-0" / "journal.bin", FAULT_AT_S,
                                                   work / "keyframes-stop.bin")
            for i in range(a.repeats):
                results.append(run(flight, work / f"{name}-{fault}-{i}", fault, recorded))
                print(json.dumps(results[-1]), flush=True)
    for name, results in everything.items():
        table(results, name)
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps(everything, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
