"""Do the load's 90 % intervals hold on orchards whose loads are known, and do they narrow as the sample grows? (issue 71)

Made-up orchards as ``benchmarks/choice_power.py`` makes them (ROWS rows of TREES trees; a tree's load Poisson about
its row's mean, MEAN apples a tree times a lognormal row level of sd ROW_SD, times its own vigour; the camera sees each
apple with the tree's seen share, SHARE times a lognormal row visibility of sd VIS_SD times its coverage over 0.5;
--unseen rows never seen). On each: the trees ``ground choose-trees`` names, counted exactly, and the load
(``ground.orchard.calibration``, ``linear``). Prints, per setting and sample size: the share of trees, rows and
flights whose interval holds the true load (goal 0.85-0.95 for rows and flights), the median relative half-width of
the rows' and the flight's intervals, and the share of fits that held a coefficient at 0.

    python benchmarks/load_intervals.py --orchards 200 --mean 120 --k 5 10 20 40

With ``--maps RUN FLIGHT ...`` the orchards are mapped flights instead (RUN: a ``benchmarks/yield_flights.py``
folder whose ``map/`` holds the flight's trees.csv; FLIGHT: the simulated flight, for its trees' true loads): the
trees ``ground choose-trees`` names, ``--orchards`` draws of k trees at random (``random``) and as its rule draws
them at random where it takes a middle (``rule``), each calibrated, and the same figures pooled over the draws (rows
seen and never seen apart), with the fit's tree and row spread (``residual_sd``, ``row_sd``) beside the true
ones (the rows' and trees' errors of the estimate from every tree counted). Last, what one evaluation set of these
flights can show: one rule draw per flight, its rows pooled, over many such sets (how often it lands in 80-95 %).

    python benchmarks/load_intervals.py --maps out/yield/runs/heavy-tune-1 out/yield/heavy-tune-1 --orchards 200
"""

from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from choice_power import orchard  # noqa: E402

from ground.orchard.calibration import estimate_load, never_seen  # noqa: E402
from ground.orchard.choose import choose_trees  # noqa: E402


def chosen(trees, k: int, model: str, rng=None) -> list[int]:
    """The indices of the trees ``ground choose-trees`` names (``rng``: its design drawn at random)."""
    index = {(t["row"], t["tree"]): i for i, t in enumerate(trees)}
    return [index[(t["row"], t["tree"])] for t in choose_trees(trees, k, model, rng=rng)]


def one(trees, load, k: int, model: str) -> dict:
    picked = chosen(trees, k, model)
    est = estimate_load(trees, {(trees[i]["row"], trees[i]["tree"]): int(load[i]) for i in picked}, model)
    return score(trees, load, picked, est)


def score(trees, load, picked, est) -> dict:
    """Which of the trees not counted, the rows and the flight the estimate's intervals hold, and their widths."""
    rows = np.array([t["row"] for t in trees])
    free = np.setdiff1d(np.arange(len(trees)), picked)
    tree_in = [est["trees"][i]["load_lo"] <= load[i] <= est["trees"][i]["load_hi"] for i in free]
    row_in, row_hw, row_err = [], [], []
    for r, e in est["rows"].items():
        truth = load[rows == r].sum()
        row_in.append(e["load_lo"] <= truth <= e["load_hi"])
        row_hw.append((e["load_hi"] - e["load_lo"]) / 2 / max(e["load"], 1.0))
        row_err.append(abs(e["load"] - truth) / max(truth, 1.0))
    f = est["flight"]
    return {"trees": float(np.mean(tree_in)), "rows": row_in, "row_hw": row_hw, "row_err": row_err,
            "flight": f["load_lo"] <= load.sum() <= f["load_hi"],
            "flight_hw": (f["load_hi"] - f["load_lo"]) / 2 / max(f["load"], 1.0),
            "flight_err": (f["load"] - load.sum()) / load.sum(), "held": bool(est["constraints"]["held_at_0"])}


def mapped(run: Path, flight: Path) -> tuple[list[dict], np.ndarray]:
    """A mapped flight's trees (trees.csv, numbers) and their true loads."""
    from yield_flights import numeric

    from ground.evaluation.yield_score import read_map, truth_of
    from pomar.flight import FlightDir

    trees = numeric(read_map(run / "map")[0])
    truth = truth_of(FlightDir(flight))["trees"]
    return trees, np.array([truth.get((t["row"], t["tree"]), (0, 0.0))[0] for t in trees], float)


def one_set(flights: list[list[list[bool]]], n: int, rng) -> float:
    """The rows held over one evaluation set of ``n`` flights (each flight's row hits per draw in ``flights``): every
    flight once where n is their number, else n drawn from them; one draw of trees per flight."""
    which = range(n) if n == len(flights) else rng.integers(len(flights), size=n)
    return float(np.mean([x for j in which for x in flights[j][rng.integers(len(flights[j]))]]))


def maps_main(a) -> int:
    """--maps: the intervals over draws of trees on mapped flights."""
    pairs = list(zip(a.maps[::2], a.maps[1::2]))
    print(f"{'flight':>16} {'draw':>6} {'k':>3} | {'trees':>5} {'rows':>5} {'seen':>5} {'unseen':>6} {'flight':>6} | "
          f"{'row hw':>6} {'flt hw':>6} {'|row err|':>9} | {'tree sd':>7} {'row sd':>6}")
    pooled, per_flight = {}, {}
    for run, flight in pairs:
        trees, load = mapped(Path(run), Path(flight))
        every = estimate_load(trees, {(t["row"], t["tree"]): int(n) for t, n in zip(trees, load)}, a.model)
        rows_of = np.array([t["row"] for t in trees])
        seen_rows = sorted(set(rows_of[~never_seen(trees)].tolist()))
        for k in a.k:
            for how in ("random", "rule", "chosen"):
                rng = np.random.default_rng(a.seed)
                got, sds = [], []
                for _ in range(1 if how == "chosen" else a.orchards):
                    picked = rng.choice(len(trees), k, replace=False) if how == "random" else \
                        chosen(trees, k, a.model, rng if how == "rule" else None)
                    est = estimate_load(trees, {(trees[i]["row"], trees[i]["tree"]): int(load[i]) for i in picked},
                                        a.model)
                    got.append(score(trees, load, picked, est))
                    sds.append((est["residual_sd"], est["row_sd"]))
                names = sorted(np.unique(rows_of).tolist())
                rows = [x for g in got for x in g["rows"]]
                seen = [x for g in got for r, x in zip(names, g["rows"]) if r in seen_rows]
                unseen = [x for g in got for r, x in zip(names, g["rows"]) if r not in seen_rows]
                pooled.setdefault(how, []).extend(rows)
                if how == "rule":
                    per_flight.setdefault(k, []).append([g["rows"] for g in got])
                print(f"{Path(flight).name:>16} {how:>6} {k:>3} | {np.mean([g['trees'] for g in got]):>5.2f} "
                      f"{np.mean(rows):>5.2f} {np.mean(seen) if seen else float('nan'):>5.2f} "
                      f"{np.mean(unseen) if unseen else float('nan'):>6.2f} "
                      f"{np.mean([g['flight'] for g in got]):>6.2f} | "
                      f"{np.median([x for g in got for x in g['row_hw']]):>6.2f} "
                      f"{np.median([g['flight_hw'] for g in got]):>6.2f} "
                      f"{np.median([x for g in got for x in g['row_err']]):>9.3f} | "
                      f"{np.median([s[0] for s in sds]):>7.1f} {np.median([s[1] for s in sds]):>6.1f}", flush=True)
        print(f"{'':>16} (every tree counted: residual sd {every['residual_sd']:.1f}, row sd {every['row_sd']:.1f}; "
              f"mean load {load.mean():.1f}; rows seen {seen_rows})")
    for how, rows in pooled.items():
        print(f"pooled, {how}: rows' intervals holding {np.mean(rows):.2f} of {len(rows)}")
    # What one evaluation set of these flights can show: one rule draw per flight, the rows pooled over the set, as
    # the goal measures it; over many such sets, how often that lands in the goal's 80-95 %.
    rng = np.random.default_rng(a.seed)
    for k, flights in per_flight.items():
        for n in (len(flights), 2 * len(flights), 4 * len(flights)):  # larger sets: these flights drawn again
            sets = np.array([one_set(flights, n, rng) for _ in range(4000)])
            lo, med, hi = np.quantile(sets, [0.05, 0.5, 0.95])
            print(f"one rule draw per flight, k {k}, a set of {n} flights: rows held {med:.2f} (90 % of sets "
                  f"{lo:.2f}-{hi:.2f}); sets within 0.80-0.95: {np.mean((sets >= 0.8) & (sets <= 0.95)):.2f}, "
                  f"above 0.95: {np.mean(sets > 0.95):.2f}")
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--orchards", type=int, default=200, help="orchards per setting (default 200)")
    p.add_argument("--rows", type=int, default=6)
    p.add_argument("--trees", type=int, default=30, help="trees a row (default 30)")
    p.add_argument("--mean", type=float, default=120.0, help="apples a tree (default 120)")
    p.add_argument("--share", type=float, default=0.15, help="the seen share of a tree half covered (default 0.15)")
    p.add_argument("--k", type=int, nargs="+", default=[5, 10, 20, 40], help="trees counted by hand")
    p.add_argument("--model", default="linear")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--maps", nargs="+", metavar="RUN FLIGHT", help="mapped flights instead of made-up orchards: pairs "
                   "of a yield_flights.py folder and its simulated flight")
    a = p.parse_args(argv)
    if a.maps:
        if len(a.maps) % 2:
            p.error("--maps takes pairs: RUN FLIGHT ...")
        return maps_main(a)
    print(f"{a.rows} rows of {a.trees} trees, {a.mean:g} apples a tree, seen share {a.share:g}, model {a.model}, "
          f"{a.orchards} orchards a line")
    print(f"{'unseen':>6} {'row sd':>6} {'vis sd':>6} {'k':>3} | {'trees':>5} {'rows':>5} {'flight':>6} | "
          f"{'row hw':>6} {'flt hw':>6} {'|flt err|':>9} {'held 0':>6}")
    for unseen, row_sd, vis_sd in itertools.product((0, 2), (0.1, 0.3), (0.0, 0.3)):
        for k in a.k:
            rng = np.random.default_rng(a.seed)
            got = [one(*orchard(rng, a.rows, a.trees, a.mean, row_sd, vis_sd, a.share, unseen)[:2], k, a.model)
                   for _ in range(a.orchards)]
            rows = [x for g in got for x in g["rows"]]
            print(f"{unseen:>6} {row_sd:>6.1f} {vis_sd:>6.1f} {k:>3} | {np.mean([g['trees'] for g in got]):>5.2f} "
                  f"{np.mean(rows):>5.2f} {np.mean([g['flight'] for g in got]):>6.2f} | "
                  f"{np.median([x for g in got for x in g['row_hw']]):>6.2f} "
                  f"{np.median([g['flight_hw'] for g in got]):>6.2f} "
                  f"{np.median([abs(g['flight_err']) for g in got]):>9.3f} "
                  f"{np.mean([g['held'] for g in got]):>6.2f}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
