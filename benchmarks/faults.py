"""The ground's fault matrix: a live flight at 1x with one fault each, against the median of clean runs.

    python benchmarks/faults.py [FLIGHT] [--clean 3] [--only mapper-killed cpu-hogs ...] [--json OUT]

Each run is `onboard run FLIGHT --realtime` (truth-replay detector) to `ground run` on loopback, both separate
processes, as in the field. For each fault: F1 (the shape F1 at 0.10 m), count, frame delay p95, against the median
of ``--clean`` clean runs, and what the user saw (the ground's warnings and errors about it). Run it with nothing
else on the machine: the frame delays are timings.

Faults (more of issue 38's list are to come: ground and onboard killed and restarted, a 30-s outage on a longer
flight, a journal on a full disk, a keyframe stream that stops):
- ``mapper-killed``: the ground's mapping process killed (SIGKILL) 8 s in;
- ``tracker-killed``: multiprocessing's resource tracker killed 8 s in;
- ``cpu-hogs``: two busy processes beside the whole flight;
- ``ground-killed``: the ground killed (SIGKILL) 8 s in and started again at once with the same command (it resumes
  from its journal and asks the drone for what it missed);
- ``outage-2``, ``outage-8``: nothing reaches the ground for 2 or 8 s from 8 s in: the onboard node stopped with
  SIGSTOP, then let go. It then sends the frames it held, late; none are lost. An outage of the link itself, which
  loses what was sent meanwhile, is still to come.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ground.evaluation.scoring import evaluate_map  # noqa: E402
from ground.replay import child_pids, free_port  # noqa: E402
from pomar.flight import FlightDir  # noqa: E402

FAULTS = ("mapper-killed", "tracker-killed", "cpu-hogs", "outage-2", "outage-8", "ground-killed")
FAULT_AT_S = 8.0


def cmdline(pid: int) -> str:
    try:
        return open(f"/proc/{pid}/cmdline").read().replace("\0", " ")
    except OSError:
        return ""


def run(flight: FlightDir, out: Path, fault: str | None) -> dict:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    hogs = []
    if fault == "cpu-hogs":
        hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(2)]
    onboard = subprocess.Popen([sys.executable, "-m", "onboard", "run", str(flight.path), "--listen", endpoint,
                                "--detector", "truth-replay", "--realtime", "--wait-for-ground", "30", "--linger", "3"],
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env, cwd=ROOT)
    err_path = out.with_suffix(".err")
    ground_cmd = [sys.executable, "-m", "ground", "run", "--flight-id", flight.meta().flight_id, "--connect", endpoint,
                  "--out", str(out), "--idle-timeout", "60"]
    with open(err_path, "w") as errf:
        ground = subprocess.Popen(ground_cmd + ["--fresh"], stdout=subprocess.DEVNULL, stderr=errf, env=env, cwd=ROOT)
        t0, done = time.monotonic(), fault in (None, "cpu-hogs")
        try:
            while ground.poll() is None and time.monotonic() - t0 < 600:
                time.sleep(0.2)
                if not done and fault == "ground-killed" and time.monotonic() - t0 > FAULT_AT_S:
                    for pid in child_pids(ground.pid):
                        os.kill(pid, signal.SIGKILL)
                    ground.kill()
                    ground.wait()
                    ground = subprocess.Popen(ground_cmd, stdout=subprocess.DEVNULL, stderr=errf, env=env, cwd=ROOT)
                    done = True
                elif not done and fault.startswith("outage") and time.monotonic() - t0 > FAULT_AT_S:
                    os.kill(onboard.pid, signal.SIGSTOP)
                    time.sleep(float(fault.split("-")[1]))
                    os.kill(onboard.pid, signal.SIGCONT)
                    done = True
                elif not done and time.monotonic() - t0 > FAULT_AT_S:
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
    seen = [line.split(": ", 1)[-1].strip() for line in err_path.read_text().splitlines()
            if " ERROR " in line or " WARNING " in line]
    res = {"fault": fault or "clean", "exit_code": ground.returncode, "fault_done": done, "user_saw": seen[:6]}
    if (out / "report.json").is_file():
        rep = json.loads((out / "report.json").read_text())
        ev = evaluate_map(flight, out)
        res.update(f1=ev["f1"], count=ev["count"], truth=ev["truth_count"],
                   delay_p95_s=rep["timings"].get("frame_delay_p95_s"),
                   restarts=len(rep["registration"].get("mapper_restarts") or []), final=rep.get("final"))
    return res


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("flight", nargs="?", type=Path, default=ROOT / "replay_data" / "demo-flight")
    p.add_argument("--clean", type=int, default=3, help="clean runs (their median is the reference)")
    p.add_argument("--only", nargs="*", choices=FAULTS, default=list(FAULTS))
    p.add_argument("--repeats", type=int, default=1, help="runs of each fault")
    p.add_argument("--json", type=Path)
    a = p.parse_args(argv)
    flight = FlightDir(a.flight)
    work = Path(tempfile.mkdtemp(prefix="pomar-faults-"))
    results = []
    for i in range(a.clean):
        results.append(run(flight, work / f"clean-{i}", None))
        print(json.dumps(results[-1]), flush=True)
    for fault in a.only:
        for i in range(a.repeats):
            results.append(run(flight, work / f"{fault}-{i}", fault))
            print(json.dumps(results[-1]), flush=True)
    clean = [r for r in results if r["fault"] == "clean" and "f1" in r]
    ref = {k: statistics.median(r[k] for r in clean) for k in ("f1", "count", "delay_p95_s")} if clean else {}
    print(f"\nreference: median of {len(clean)} clean runs: F1 {ref.get('f1', float('nan')):.3f}, "
          f"count {ref.get('count', float('nan')):.0f}, frame delay p95 {ref.get('delay_p95_s', float('nan')):.2f} s")
    print(f"{'fault':<16}{'F1':>7}{'dF1':>8}{'count':>7}{'dcount %':>10}{'delay p95 s':>13}  what the user saw")
    for r in results:
        if "f1" not in r:
            print(f"{r['fault']:<16} no report (exit {r['exit_code']})")
            continue
        dc = 100 * (r["count"] - ref["count"]) / ref["count"] if ref else float("nan")
        print(f"{r['fault']:<16}{r['f1']:>7.3f}{r['f1'] - ref.get('f1', 0):>+8.3f}{r['count']:>7d}{dc:>+10.1f}"
              f"{r['delay_p95_s'] or float('nan'):>13.2f}  {(r['user_saw'] or ['-'])[0][:90]}")
    if a.json:
        a.json.parent.mkdir(parents=True, exist_ok=True)
        a.json.write_text(json.dumps({"reference": ref, "runs": results}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
