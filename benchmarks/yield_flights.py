"""Issue 59's yield figures on simulated flights: each flight mapped with its orchard's layout, then, for each load model,
the trees `ground choose-trees` names counted by hand (from the truth, exact or with a human's counting error), the
load estimated, and scored against the truth, beside 20 random draws of as many trees and the oracle (the same
estimate given each tree's true seen share).

    python benchmarks/yield_flights.py out/yield/tune-1 out/yield/tune-2 --out out/yield/runs
    python benchmarks/yield_flights.py FLIGHTS... --count-error-cv 0.1 --reuse
    python benchmarks/yield_flights.py FLIGHTS... --detector truth-replay --out out/yield/runs-truth
    python benchmarks/yield_flights.py A B --pair A B      # a repeat pair: the same trees counted for each flight
    python benchmarks/yield_flights.py FLIGHTS... --model CANDIDATE.onnx --out out/yield/runs-candidate
    python benchmarks/yield_flights.py FLIGHTS... -- --confirm-score 0.8     # arguments after -- go to each replay

Prints, per flight and model: the median per-row load error (chosen trees, median of the random draws, oracle), the
per-tree r (and the oracle's), the rows' interval coverage and median half-width, the median per-row diameter error
against a constant median's, and the median kilogram error; the same over the rows the camera saw (coverage above 0)
alone; writes them to OUT/NAME/yield.json. ``--detector truth-replay`` maps each flight from its truth's detections
instead of the shipped detector's (what the detector costs). ``--pair A B`` (flight names): a repeat pair, the same
orchard flown twice; the trees chosen on A's map are counted for each flight (their own counts: errors drawn apart)
and each flight is calibrated by its own; printed: the share of rows whose loads lie within each other's 90 %
intervals. Beside the goals: each flight's total (its rows' loads summed) against the truth, the random draws' and
the oracle's. Lock-step replays (deterministic); timings are not its subject.
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
from ground.orchard.calibration import DEFAULT_MODEL, MODELS, apply_load, estimate_load  # noqa: E402
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
    score = score_yield(t, r, truth)
    true_total = sum(x["true_load"] for x in score["rows"])
    f = est["flight"]
    return {**score, "loo": est["loo"]["median_abs_pct"],
            "total": {"load": f["load"], "lo": f["load_lo"], "hi": f["load_hi"], "true": true_total,
                      "covered": bool(f["load_lo"] <= true_total <= f["load_hi"])}}


def seen_rows(score: dict, trees: list[dict]) -> dict:
    """The row figures of ``score`` over the rows the camera saw (a tree of the row with coverage above 0)."""
    seen = {t["row"] for t in trees if np.isfinite(t["coverage"]) and t["coverage"] > 0}
    rows = [r for r in score["rows"] if r["row"] in seen]
    return {"rows": len(rows),
            "row_load_error_median": float(np.median([abs(r["load_error"]) for r in rows])) if rows else None,
            "coverage": float(np.mean([r["covered"] for r in rows])) if rows else None,
            "half_width_median": float(np.median([r["half_width"] for r in rows])) if rows else None}


def map_flight(flight: Path, out: Path, detector: str, reuse: bool, model: Path | None = None,
               extra: tuple[str, ...] = ()) -> tuple[list[dict], list[dict]]:
    """The flight replayed (lock-step) with its orchard's layout (``model``: another ONNX detector than the shipped
    one); its trees and rows."""
    fd = FlightDir(flight)
    out.mkdir(parents=True, exist_ok=True)
    layout = out / "orchard.csv"
    write_layout(truth_layout(fd), layout)
    mapped = out / "map"
    if not (reuse and (mapped / "trees.csv").is_file()):
        r = subprocess.run([sys.executable, "-m", "ground", "replay", str(flight), "--out", str(mapped), "--orchard",
                            str(layout), "--detector", detector, "--quiet", *(["--model", str(model)] if model else []),
                            *extra],
                           capture_output=True, text=True)
        if r.returncode != 0:
            raise SystemExit(f"{flight}: the replay failed: {r.stderr.strip().splitlines()[-1:]}")
    trees, rows = read_map(mapped)
    return numeric(trees), rows


def repeat_pair(a: Path, b: Path, out: Path, model: str, k: int, cv: float, seed: int) -> dict:
    """Issue 59's repeatable goal on two flights of one orchard (already mapped under OUT/NAME/map): the trees chosen
    on A's map counted for each flight (errors drawn apart), each flight's rows estimated from its own counts; per row
    seen by both, whether each load lies within the other's interval."""
    rng = np.random.default_rng(seed)
    maps = [(FlightDir(f), *read_map(out / f.name / "map")) for f in (a, b)]
    picked = [(t["row"], t["tree"]) for t in choose_trees(numeric(maps[0][1]), k, model)]
    loads = []
    for fd, trees, rows in maps:
        trees = numeric(trees)
        got = sample_counts(fd, picked, count_error_cv=cv, seed=int(rng.integers(1 << 30)))
        r = copy.deepcopy(rows)
        for x in r:
            x["row"] = int(x["row"])
        apply_load(trees, r, estimate_load(trees, {(c["row"], c["tree"]): c["apples"] for c in got}, model))
        seen = {t["row"] for t in trees if np.isfinite(t["coverage"]) and t["coverage"] > 0}
        loads.append({x["row"]: (float(x["load"]), float(x["load_lo"]), float(x["load_hi"])) for x in r
                      if x["row"] in seen})
    both = sorted(set(loads[0]) & set(loads[1]))
    within = [bool(loads[1][r][1] <= loads[0][r][0] <= loads[1][r][2] and loads[0][r][1] <= loads[1][r][0] <= loads[0][r][2])
              for r in both]
    return {"rows": both, "within": within, "share": float(np.mean(within)) if within else None,
            "loads": {str(r): [loads[0][r], loads[1][r]] for r in both}}


def flight_figures(flight: Path, out: Path, models, k: int, draws: int, cv: float, seed: int, reuse: bool,
                   detector: str = "onnx", onnx: Path | None = None, extra: tuple[str, ...] = ()) -> dict:
    fd = FlightDir(flight)
    trees, rows = map_flight(flight, out, detector, reuse, onnx, extra)
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
                                     model, truth) for _ in range(draws)]
        oracle = estimate_and_score(oracle_trees(trees, share), rows, samples, "coverage", truth)
        figures[model] = {"chosen": mine, "seen_rows": seen_rows(mine, trees),
                          "random_row_error_median": float(np.median([x["row_load_error_median"] for x in random])),
                          "random_total_errors": [x["total_error"] for x in random],
                          "random_total_covered": float(np.mean([x["total"]["covered"] for x in random])),
                          "oracle": {"row_load_error_median": oracle["row_load_error_median"],
                                     "total_error": oracle["total_error"],
                                     "tree_r": oracle["trees"]["r"],
                                     "row_errors": [abs(x["load_error"]) for x in oracle["rows"]]}}
    (out / "yield.json").write_text(json.dumps(figures, indent=1, default=float) + "\n")
    return figures


def goals(figs: dict[str, dict], pairs: dict[str, dict], model: str) -> list[str]:
    """Issue 59's goals over every flight given (``figs``: flight name -> flight_figures' output; ``pairs``: name ->
    repeat_pair's), for ``model``: lines to print."""
    rows = [x for f in figs.values() for x in f[model]["chosen"]["rows"]]
    oracle = [e for f in figs.values() for e in f[model]["oracle"]["row_errors"]]
    err = float(np.median([abs(x["load_error"]) for x in rows]))
    orc = float(np.median(oracle))
    sized = [x for x in rows if np.isfinite(x["diameter_error_mm"])]
    d = float(np.median([abs(x["diameter_error_mm"]) for x in sized])) if sized else float("nan")
    c = float(np.median([abs(x["constant_error_mm"]) for x in sized])) if sized else float("nan")
    kg = [x for x in rows if np.isfinite(x["kg_error"])]
    out = [f"goals ({model}, {len(figs)} flights, {len(rows)} rows):",
           f"  rows' 90 % intervals hold the true load: {np.mean([x['covered'] for x in rows]):.2f} (goal 0.80-0.95); "
           f"median half-width {np.median([x['half_width'] for x in rows]):.2f}",
           f"  median row error {err:.3f}, the oracle's {orc:.3f}: {err / orc:.2f} times (goal <= 1.25)"]
    for name, f in figs.items():
        m = f[model]
        r_, o = m["chosen"]["trees"]["r"], m["oracle"]["tree_r"]
        out.append(f"  {name}: tree r {r_ if r_ is None else round(r_, 2)} against the oracle's "
                   f"{o if o is None else round(o, 2)} (goal: no more than 0.05 below it); chosen trees' row error "
                   f"{m['chosen']['row_load_error_median']:.3f} against random draws' median "
                   f"{m['random_row_error_median']:.3f} (goal no larger)")
        tot = np.abs(m["random_total_errors"])
        t = m["chosen"]["total"]
        out.append(f"  {name}: flight total {100 * m['chosen']['total_error']:+.1f} % (goal within 10 %), its 90 % "
                   f"interval {100 * (t['lo'] / t['load'] - 1):+.0f} to {100 * (t['hi'] / t['load'] - 1):+.0f} % "
                   f"{'holds' if t['covered'] else 'misses'} the truth; random draws within 10 % {np.mean(tot <= 0.10):.2f}"
                   f" (median |error| {100 * np.median(tot):.1f} %, intervals holding {m['random_total_covered']:.2f}), "
                   f"the oracle's {100 * m['oracle']['total_error']:+.1f} %")
    for name, rp in pairs.items():
        out.append(f"  repeat pair {name}: row loads within each other's intervals {sum(rp['within'])}/{len(rp['within'])}")
    out.append(f"  diameter per row: median error {d:.1f} mm, rows within 2 mm {np.mean([abs(x['diameter_error_mm']) <= 2 for x in sized]) if sized else float('nan'):.2f}, "
               f"a constant median's {c:.1f} mm (goal within 2 mm and at most half the constant's)")
    out.append(f"  kilograms per row within the load interval's relative half-width + 3 %: "
               f"{np.mean([abs(x['kg_error']) <= x['half_width'] + 0.03 for x in kg]) if kg else float('nan'):.2f} of "
               f"{len(kg)} rows; median kg error {np.median([abs(x['kg_error']) for x in kg]) if kg else float('nan'):.3f}")
    return out


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
    p.add_argument("--detector", choices=["onnx", "truth-replay"], default="onnx",
                   help="the shipped detector (default) or the truth's detections")
    p.add_argument("--model", type=Path, help="another ONNX detector than the shipped one (with its .json beside)")
    p.add_argument("--pair", nargs=2, metavar=("A", "B"), action="append", default=[],
                   help="two of FLIGHTS (by name) that fly one orchard: the repeat pair's figures")
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = tuple(argv[argv.index("--") + 1:]) if "--" in argv else ()
    args = p.parse_args(argv[:argv.index("--")] if "--" in argv else argv)
    if args.model and args.detector != "onnx":
        p.error("--model is an ONNX detector: not with --detector truth-replay")
    by_name = {Path(f).name: Path(f) for f in args.flights}
    for a, b in args.pair:
        if a not in by_name or b not in by_name:
            p.error(f"--pair {a} {b}: both must be among the flights given")
    head = (f"{'flight':<22} {'model':<9} {'row err':>7} {'random':>7} {'oracle':>7} {'tree r':>6} {'orac r':>6} "
            f"{'cover':>5} {'half-w':>6} {'diam mm':>7} {'const':>6} {'kg err':>6} {'LOO %':>6}")
    print(head)
    every = {}
    for i, flight in enumerate(args.flights):
        name = Path(flight).name
        figs = every[name] = flight_figures(Path(flight), Path(args.out) / name, args.models, args.trees, args.draws,
                              args.count_error_cv, args.seed + i, args.reuse, args.detector, args.model, extra)
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
            v = f["seen_rows"]
            if v["rows"]:
                print(f"{'':<22} {'seen':<9} {v['row_load_error_median']:>7.3f} {'':>7} {'':>7} {'':>6} {'':>6} "
                      f"{v['coverage']:>5.2f} {v['half_width_median']:>6.2f}   ({v['rows']} rows seen)")
    pairs = {}
    for a, b in args.pair:
        rp = pairs[f"{a}/{b}"] = repeat_pair(by_name[a], by_name[b], Path(args.out), DEFAULT_MODEL, args.trees,
                                             args.count_error_cv, args.seed)
        (Path(args.out) / f"pair-{a}-{b}.json").write_text(json.dumps(rp, indent=1) + "\n")
        print(f"repeat pair {a} / {b} ({DEFAULT_MODEL}): rows seen by both {len(rp['rows'])}, loads within each other's 90 % "
              f"intervals {sum(rp['within'])}/{len(rp['within'])}")
    if DEFAULT_MODEL in args.models:
        print("\n".join(goals(every, pairs, DEFAULT_MODEL)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
