"""Many flights at once (issue 73): the same flights through ``ground batch`` (its local Dask cluster) and through
``ground replay`` one after another, in one run on this machine; then, on paper, what a cluster does with a farm's day.

    python benchmarks/batch.py FLIGHT_DIR FLIGHT_DIR FLIGHT_DIR FLIGHT_DIR --out out/bench/batch \
        [--cpus-per-flight 2] [--machines 10 --cores 16 --flights-a-day 200]

Prints each flight's wall seconds, CPU-seconds and peak memory (from the batch's ``batch.json``), the batch's wall time
against the sum of the one-after-another replays (a ratio within the one run), and the scaling on paper: with
``--machines`` machines of ``--cores`` cores, flights of ``--flight-minutes`` at the measured CPU-seconds per second of
flight, each keeping the measured number of cores busy, the hours ``--flights-a-day`` flights take. Timings: run
it with nothing else on the machine.
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("flights", nargs="+", type=Path)
    p.add_argument("--out", type=Path, default=Path("out/bench/batch"))
    p.add_argument("--cpus-per-flight", type=float, default=2.0)
    p.add_argument("--machines", type=int, default=10)
    p.add_argument("--cores", type=int, default=16)
    p.add_argument("--flights-a-day", type=int, default=200)
    p.add_argument("--flight-minutes", type=float, default=10.0, help="a farm flight's length, on paper")
    a = p.parse_args(argv)
    for f in a.flights:
        if not (f / "flight.json").is_file():
            raise SystemExit(f"{f}: not a flight directory (no flight.json)")
    shutil.rmtree(a.out, ignore_errors=True)
    a.out.mkdir(parents=True)
    seq = []
    for i, f in enumerate(a.flights):  # one after another, as a grower does today
        t0 = time.monotonic()
        r = subprocess.run([sys.executable, "-m", "ground", "replay", str(f), "--out", str(a.out / "one" / f"{i}"),
                            "--quiet"], capture_output=True, text=True)
        if r.returncode:
            raise SystemExit(f"{f}: the replay failed: {r.stderr.strip().splitlines()[-1:]}")
        seq.append(time.monotonic() - t0)
        print(f"replay {f.name}: {seq[-1]:.0f} s", flush=True)
    csv = a.out / "flights.csv"
    csv.write_text("block,flight,name\n" + "".join(f"b{i},{f.resolve()},f{i}\n" for i, f in enumerate(a.flights)))
    t0 = time.monotonic()
    r = subprocess.run([sys.executable, "-m", "ground", "batch", "--flights", str(csv), "--out", str(a.out / "batch"),
                        "--cpus-per-flight", str(a.cpus_per_flight)], capture_output=True, text=True)
    wall = time.monotonic() - t0
    if r.returncode:
        raise SystemExit(f"the batch failed: {r.stderr.strip().splitlines()[-1:]}")
    rep = json.loads((a.out / "batch" / "batch.json").read_text())
    print(f"\n{'flight':<12} {'one by one s':>12} {'in batch s':>10} {'CPU-s':>8} {'peak MB':>8}")
    for f, s in zip(rep["flights"], seq):
        print(f"{f['name']:<12} {s:>12.0f} {f['seconds']:>10.0f} {f['cpu_s']:>8.0f} {f['max_rss_mb']:>8.0f}")
    print(f"one after another {sum(seq):.0f} s; ground batch {wall:.0f} s (its flights {rep['wall_s']:.0f} s, the rest "
          f"the cluster's start and the farm report): {sum(seq) / wall:.2f} times as fast, in one run")
    flown = [json.loads((a.out / "batch" / f["name"] / "report.json").read_text())["flight_seconds"]
             for f in rep["flights"]]
    per_s = sum(f["cpu_s"] for f in rep["flights"]) / sum(flown)  # CPU-seconds a second of flight takes
    par = np.mean([f["cpu_s"] / f["seconds"] for f in rep["flights"]])  # cores a replay keeps busy
    mem = max(f["max_rss_mb"] for f in rep["flights"])
    slots = a.machines * max(1, int(a.cores // a.cpus_per_flight))
    cpu = per_s * a.flight_minutes * 60
    hours = a.flights_a_day * cpu / min(par, a.cpus_per_flight) / slots / 3600
    print(f"on paper: {per_s:.1f} CPU-seconds a second of flight, {par:.2f} cores busy a replay, peak {mem:.0f} MB; "
          f"{a.machines} machines of {a.cores} cores run {slots} flights at once ({a.cpus_per_flight:g} cores each): "
          f"{a.flights_a_day} flights of {a.flight_minutes:g} min ({cpu / 3600:.2f} CPU-hours each) in {hours:.1f} h")
    return 0


if __name__ == "__main__":
    sys.exit(main())
