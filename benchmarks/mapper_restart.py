"""What a mapper killed mid-flight costs the map (issue 74): a recorded stream played at 1x, as live, with the ground's
mapping process killed (SIGKILL) at given times, against clean runs of the same stream.

    python benchmarks/mapper_restart.py [FLIGHT] --recorded JOURNAL [--at 4 8 15 0.8] [--runs 5] [--out DIR]
                                        [--ground "--min-share-to-go-on 0.7"]

Each run is ``ground replay FLIGHT --recorded JOURNAL --speed 1``; a time under 1 is a share of the flight's duration.
The clock starts when the ground's journal appears (the stream begins). Printed per kill time and for the clean runs:
each run's F1 and count, their median and spread, the restarts report.json gives and the keyframes mapped again; then
each kill time's median F1 and count against the clean runs' median. Run it with nothing else on the machine: it
plays in real time. Make the journal with a lock-step replay first (``ground replay FLIGHT --out DIR``:
DIR/journal.bin). ``--ground``: more of ``ground replay``'s options for every run (a setting tried against the
clean runs); ``--at`` with no times: clean runs only.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ground.replay import child_pids  # noqa: E402
from pomar.flight import FlightDir  # noqa: E402


def descendants(pid: int) -> list[int]:
    out, todo = [], [pid]
    while todo:
        kids = child_pids(todo.pop())
        out += kids
        todo += kids
    return out


def mapper_pids(pid: int) -> list[int]:
    """The ground's mapping process (a multiprocessing child: spawn_main on its command line)."""
    found = []
    for p in descendants(pid):
        try:
            if "spawn_main" in open(f"/proc/{p}/cmdline").read():
                found.append(p)
        except OSError:
            pass
    return found


def run(flight: Path, journal: Path, out: Path, kill_at: float | None, extra: list[str] = ()) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    with open(out.with_suffix(".log"), "w") as log:
        p = subprocess.Popen([sys.executable, "-m", "ground", "replay", str(flight), "--recorded", str(journal),
                              "--speed", "1", "--out", str(out), *extra], stdout=log, stderr=subprocess.STDOUT,
                             cwd=ROOT)
        t0, killed = None, None
        while p.poll() is None:
            time.sleep(0.1)
            if t0 is None and (out / "journal.bin").exists():
                t0 = time.monotonic()
            if kill_at is not None and killed is None and t0 is not None and time.monotonic() - t0 >= kill_at:
                for pid in mapper_pids(p.pid):
                    os.kill(pid, signal.SIGKILL)
                    killed = round(time.monotonic() - t0, 1)
    if not (out / "report.json").is_file():  # the replay stopped before a map (a bad --ground option, ...)
        last = (out.with_suffix(".log").read_text().strip().splitlines() or ["(no output)"])[-1]
        raise SystemExit(f"error: {out.with_suffix('.log')}: the replay wrote no report.json: {last}")
    rep = json.loads((out / "report.json").read_text())
    ev = rep.get("evaluation") or {}
    restarts = rep["registration"].get("mapper_restarts") or []
    return {"f1": ev.get("f1"), "count": ev.get("count"), "killed_at_s": killed, "exit": p.returncode,
            "restarts": len(restarts), "mapped_again": sum(r.get("keyframes_remapped", 0) for r in restarts),
            "keyframes": rep["registration"].get("keyframes_processed")}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("flight", nargs="?", type=Path, default=ROOT / "replay_data" / "demo-flight")
    p.add_argument("--recorded", type=Path, required=True, help="the stream (a journal.bin) played at 1x")
    p.add_argument("--at", type=float, nargs="*", default=[4.0, 8.0, 15.0, 0.8],
                   help="kill times (s into the stream; under 1: a share of the flight)")
    p.add_argument("--runs", type=int, default=5, help="runs of each, and clean runs")
    p.add_argument("--out", type=Path, default=ROOT / "out" / "bench" / "mapper-restart")
    p.add_argument("--ground", default="", help="more ground replay options for every run, one string")
    a = p.parse_args(argv)
    meta = FlightDir(a.flight).meta()
    duration = meta.frame_count / meta.fps
    res: dict[str, list[dict]] = {}
    for label, at in [("clean", None)] + [(f"killed at {t:g}" + (" of the flight" if t < 1 else " s"),
                                           t * duration if t < 1 else t) for t in a.at]:
        res[label] = []
        for i in range(a.runs):
            r = run(a.flight, a.recorded, a.out / f"{label.replace(' ', '-')}-{i}", at, shlex.split(a.ground))
            res[label].append(r)
            print(f"{label}: run {i + 1}: F1 {r['f1']:.3f}, {r['count']} apples, killed at {r['killed_at_s']} s, "
                  f"{r['restarts']} restart(s), {r['mapped_again']} keyframes mapped again, "
                  f"{r['keyframes']} keyframes mapped", flush=True)
    ref_f1 = float(np.median([r["f1"] for r in res["clean"]]))
    ref_n = float(np.median([r["count"] for r in res["clean"]]))
    print(f"\n{'run':<28} {'F1 median':>9} {'F1 range':>13} {'count median':>12} {'vs clean F1':>11} {'count %':>8}")
    for label, rs in res.items():
        f1 = np.array([r["f1"] for r in rs])
        n = np.array([r["count"] for r in rs])
        print(f"{label:<28} {np.median(f1):>9.3f} {f1.min():>6.3f}-{f1.max():.3f} {np.median(n):>12.0f} "
              f"{np.median(f1) - ref_f1:>+11.3f} {100 * (np.median(n) / ref_n - 1):>+8.1f}")
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "summary.json").write_text(json.dumps(res, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
