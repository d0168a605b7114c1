"""The count's checks decided again from replays already made: how each threshold moves F1 and the count on each flight.

    python benchmarks/count_checks.py out/bench/generalisation/base FLIGHT... [--size 0 0.6 0.8] [--views 0 0.15]

Reads each replay's candidates.csv (every confirmed apple with its radius, observations, expected views and what the
checks made of it), keeps those a pair of thresholds (size ratio to the median radius, detected share of the expected
views) would count, the parallax check as the replay decided it, and scores them against the flight's truth with the
replay's own poses (ground/evaluation/scoring.py). The radii are read as written (to 0.1 mm), so an apple right at a
threshold can fall the other way than in the replay (1 of 221 on the bundled flight). Tuning flights only: the evaluation flights are scored once, at the
end, with the thresholds fixed. Accuracy only.
"""

from __future__ import annotations

import argparse
import csv
import shutil
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ground.evaluation.scoring import evaluate_map, input_problem  # noqa: E402
from pomar.countable import MIN_VISIBLE  # noqa: E402
from pomar.flight import FlightDir  # noqa: E402

APPLE_COLUMNS = ["id", "x", "y", "z", "lat", "lon", "alt", "first_frame", "last_frame"]


def kept(cands: list[dict], size: float, views: float, parallax: bool = True) -> list[dict]:
    """The candidates these thresholds count (the parallax check as the replay decided it, or off)."""
    r = np.array([float(c["radius_m"]) for c in cands])
    med = np.nanmedian(r) if np.isfinite(r).any() else np.nan
    out = []
    for c, ri in zip(cands, r):
        if c["left_out"] == "narrow" and parallax:
            continue
        if size > 0 and np.isfinite(ri) and ri < size * med:
            continue
        exp = float(c["expected_views"]) if c["expected_views"] not in ("", "nan") else np.nan
        if views > 0 and np.isfinite(exp) and int(c["observations"]) < views * exp:
            continue
        out.append(c)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("run", type=Path, help="a generalisation.py output folder: one replay folder per flight")
    ap.add_argument("flights", type=Path, nargs="+", help="the flights replayed there (their replay: RUN/NAME)")
    ap.add_argument("--size", type=float, nargs="+", default=[0.0, 0.6, 0.7, 0.8])
    ap.add_argument("--views", type=float, nargs="+", default=[0.0, 0.1, 0.15, 0.2])
    ap.add_argument("--no-parallax", action="store_true",
                    help="count the apples the parallax check left out too (their size judged as the others'; their "
                         "expected views were never computed)")
    ap.add_argument("--min-visible", type=float, default=MIN_VISIBLE,
                    help="score against apples this visible (default: pomar.countable's definition)")
    a = ap.parse_args(argv)
    for path in a.flights:  # every input checked before any work: one line naming what is wrong
        problem = input_problem(path, a.run / path.name, "candidates.csv", f"no replay of {path.name} there")
        if problem:
            print(f"error: {problem}", file=sys.stderr)
            return 2
    work = Path(tempfile.mkdtemp(prefix="pomar-checks-"))
    print(f"{'flight':<14} {'size':>5} {'views':>5} {'F1':>6} {'count':>6} {'truth':>6} {'err %':>7} {'worst row':>9}")
    for path in a.flights:
        name, flight = path.name, FlightDir(path)
        out = a.run / name
        cands = list(csv.DictReader(open(out / "candidates.csv")))
        for size in a.size:
            for views in a.views:
                run = work / name
                shutil.rmtree(run, ignore_errors=True)
                run.mkdir(parents=True)
                shutil.copy(out / "poses.csv", run / "poses.csv")
                with open(run / "apples.csv", "w", newline="") as f:
                    w = csv.DictWriter(f, fieldnames=APPLE_COLUMNS, extrasaction="ignore", lineterminator="\n")
                    w.writeheader()
                    w.writerows(kept(cands, size, views, parallax=not a.no_parallax))
                ev = evaluate_map(flight, run, min_visible=a.min_visible)
                print(f"{name:<14} {size:>5.2f} {views:>5.2f} {ev['f1']:>6.3f} {ev['count']:>6} {ev['truth_count']:>6} "
                      f"{ev['count_error_pct']:>+7.1f} {ev['worst_row_error_pct']:>9.1f}", flush=True)
    shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
