"""Issue 59's yield figures on simulated flights: each flight mapped with its orchard's layout, then, for each load model,
the trees `ground choose-trees` names counted by hand (from the truth, exact or with a human's counting error), the
load estimated, and scored against the truth, beside 20 random draws of as many trees and the oracle (the same
estimate given each tree's true seen share).

    python benchmarks/yield_flights.py out/yield/tune-1 out/yield/tune-2 --out out/yield/runs
    python benchmarks/yield_flights.py FLIGHTS... --count-error-cv 0.1 --reuse

Prints, per flight and model: the median per-row load error (chosen trees, median of the random draws, oracle), the
per-tree r (and the oracle's), the rows' interval coverage and median half-width, the median per-row diameter error
against a constant median's, and the median kilogram error; writes them to OUT/NAME/yield.json. Lock-step replays
(deterministic); timings are not its subject.
"""

from __future__ import annotations

import argparse
import copy
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from ground.evaluation.yield_score import oracle_trees, read_map, score_yield, seen_share, truth_of  # noqa: E402
from ground.orchard.calibration import MODELS, apply_load, estimate_load  # noqa: E402
from ground.orchard.choose import choose_trees  # noqa: E402
from ground.orchard.size import row_kilograms  # noqa: E402
from pomar.flight import FlightDir  # noqa: E402
from pomar.layout import write_layout  # noqa: E402
from sim.counts import sample_counts  # noqa: E402
from sim.layout import truth_layout  # noqa: E402


def numeric(trees: list[dict]) -> list[dict]:
    return [{**t, "row": int(t["row"]), "tree": int(t["tree"]), "count": int(t["count"]),
             "coverage": float(t["coverage"] or "nan")} for t in trees]


def estimate_and_score(trees, rows, samples, model, truth) -> dict:
    t, r = copy.deepcopy(trees), copy.deepcopy(rows)
    for x in r:
        x["row"] = int(x["row"])
    est = estimate_load(t, samples, model)
    apply_load(t, r, est)
    row_kilograms(r)
    return {**score_yield(t, r, truth), "loo": est["loo"]["median_abs_pct"]}


def flight_figures(flight: Path, out: Path, models, k: int, draws: int, cv: float, seed: int, reuse: bool) -> dict:
    fd = FlightDir(flight)
    out.mkdir(parents=True, exist_ok=True)
    layout = out / "orchard.csv"
    write_layout(truth_layout(fd), layout)
    mapped = out / "map"
    if not (reuse and (mapped / "trees.csv").is_file()):
        r = subprocess.run([sys.executable, "-m", "ground", "replay", str(flight), "--out", str(mapped), "--orchard",
                            str(layout), "--quiet"], capture_output=True, text=True)
        if r.returncode != 0:
            raise SystemExit(f"{flight}: the replay failed: {r.stderr.strip().splitlines()[-1:]}")
    trees, rows = read_map(mapped)
    trees = numeric(trees)
    truth, share = truth_of(fd), seen_share(fd)
    rng = np.random.default_rng(seed)

    def counted(picked):
        got = sample_counts(fd, [(t["row"], t["tree"]) for t in picked], count_error_cv=cv,
                            seed=int(rng.integers(1 << 30)))
        return {(c["row"], c["tree"]): c["apples"] for c in got}

    figures = {}
    for model in models:
        chosen = choose_trees(trees, k, model)
        samples = counted(chosen)
        mine = estimate_and_score(trees, rows, samples, model, truth)
        random = [estimate_and_score(trees, rows, counted([trees[i] for i in rng.choice(len(trees), k, replace=False)]),
                                     model, truth)["row_load_error_median"] for _ in range(draws)]
        oracle = estimate_and_score(oracle_trees(trees, share), rows, samples, "coverage", truth)
        figures[model] = {"chosen": mine, "random_row_error_median": float(np.median(random)),
                          "oracle": {"row_load_error_median": oracle["row_load_error_median"],
                                     "tree_r": oracle["trees"]["r"]}}
    (out / "yield.json").write_text(json.dumps(figures, indent=1, default=float) + "\n")
    return figures


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("flights", nargs="+", help="simulated flight directories (rendered with the trees' truth)")
    p.add_argument("--out", default="out/yield/runs", help="a folder per flight: its layout, map and yield.json")
    p.add_argument("--models", nargs="+", default=list(MODELS), choices=MODELS)
    p.add_argument("--trees", type=int, default=10, help="trees counted by hand (default 10)")
    p.add_argument("--draws", type=int, default=20, help="random draws of as many trees (default 20)")
    p.add_argument("--count-error-cv", type=float, default=0.0, help="the hand counts' error (0: exact)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--reuse", action="store_true", help="keep a flight's map where it is already made")
    args = p.parse_args(argv)
    head = (f"{'flight':<22} {'model':<9} {'row err':>7} {'random':>7} {'oracle':>7} {'tree r':>6} {'orac r':>6} "
            f"{'cover':>5} {'half-w':>6} {'diam mm':>7} {'const':>6} {'kg err':>6} {'LOO %':>6}")
    print(head)
    for i, flight in enumerate(args.flights):
        name = Path(flight).name
        figs = flight_figures(Path(flight), Path(args.out) / name, args.models, args.trees, args.draws,
                              args.count_error_cv, args.seed + i, args.reuse)
        for model, f in figs.items():
            c = f["chosen"]
            d = [r["diameter_error_mm"] for r in c["rows"] if np.isfinite(r["diameter_error_mm"])]
            g = [r["constant_error_mm"] for r in c["rows"] if np.isfinite(r["diameter_error_mm"])]
            kg = [abs(r["kg_error"]) for r in c["rows"] if np.isfinite(r["kg_error"])]
            print(f"{name:<22} {model:<9} {c['row_load_error_median']:>7.3f} {f['random_row_error_median']:>7.3f} "
                  f"{f['oracle']['row_load_error_median']:>7.3f} {c['trees']['r'] or float('nan'):>6.2f} "
                  f"{f['oracle']['tree_r'] or float('nan'):>6.2f} {c['coverage']:>5.2f} {c['half_width_median']:>6.2f} "
                  f"{np.median(np.abs(d)) if d else float('nan'):>7.1f} {np.median(np.abs(g)) if g else float('nan'):>6.1f} "
                  f"{np.median(kg) if kg else float('nan'):>6.3f} {c['loo']:>6.1f}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
