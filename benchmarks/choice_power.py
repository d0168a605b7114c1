"""How often can a choice of trees beat random draws, and an estimate's tree r come within 0.05 of the oracle's, on one
flight? Made-up orchards whose loads and seen shares are known, as issue 59's goals judge a flight (docs/benchmarks.md).

Each orchard: ROWS rows of TREES trees; a tree's load is Poisson about its row's mean (MEAN apples a tree, times a
lognormal row level of sd --row-sd) times its own vigour (gamma, CV 0.25); the camera sees each of its apples with a
probability, its seen share: SHARE times a lognormal row visibility (sd --vis-sd: a row seen nearer or from its other
side) times the tree's coverage (uniform 0.25-0.75) over 0.5; --unseen rows are never seen (count 0, coverage 0). On
each orchard: the trees ``ground choose-trees`` names (ground.orchard.choose) and 20 random draws of as many, counted
exactly; the median row load error of each (ground.orchard.calibration, ``linear``), and the tree r of the choice and
of the oracle (the ``coverage`` model given each tree's true seen share, from the same counted trees).

Prints, per setting: the mean row error of the choice and of the random draws' median; the share of orchards where the
choice's is no larger (one flight's chance of the goal "the choice no worse than random"), and that share to the sixth
power (six evaluation flights, each independent); the share where the tree r is within 0.05 of the oracle's, and its
sixth power; and the flight total's error: its mean (a bias) for the choice and for the random draws, and the share
within 10 % of the truth (issue 71's goal). Time: about 5 s per setting of 100 orchards.

    python benchmarks/choice_power.py --orchards 200
    python benchmarks/choice_power.py --mean 100 --vigour-cv 0.35 --trees 30 --rows 6    # heavy trees (issue 71)
"""

from __future__ import annotations

import argparse
import itertools
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from ground.orchard.calibration import estimate_load  # noqa: E402
from ground.orchard.choose import choose_trees  # noqa: E402


def orchard(rng, rows: int, trees: int, mean: float, row_sd: float, vis_sd: float, share: float,
            unseen: int, vigour_cv: float = 0.25) -> tuple[list[dict], np.ndarray, np.ndarray]:
    """(trees' records as trees.csv gives them, true loads, true seen shares); the last ``unseen`` rows never seen."""
    level = mean * rng.lognormal(0.0, row_sd, rows)
    vis = share * rng.lognormal(0.0, vis_sd, rows)
    out, load, seen = [], [], []
    for r, k in itertools.product(range(rows), range(trees)):
        n = rng.poisson(level[r] * rng.gamma(vigour_cv ** -2, vigour_cv ** 2))
        cov = rng.uniform(0.25, 0.75)
        p = 0.0 if r >= rows - unseen else min(1.0, vis[r] * cov / 0.5)
        out.append({"row": r + 1, "tree": k + 1, "count": int(rng.binomial(n, p)), "coverage": cov if p > 0 else 0.0})
        load.append(n)
        seen.append(p)
    return out, np.array(load, float), np.array(seen)


def figures(trees: list[dict], load: np.ndarray, picked: list[int], model: str = "linear") -> tuple[float, float, float]:
    """(median row load error, tree r over the trees not counted, the flight total's error) of the estimate from the
    ``picked`` trees."""
    est = estimate_load(trees, {(trees[i]["row"], trees[i]["tree"]): int(load[i]) for i in picked}, model)
    rows = np.array([t["row"] for t in trees])
    err = [abs(e["load"] - load[rows == r].sum()) / load[rows == r].sum() for r, e in est["rows"].items()]
    free = np.setdiff1d(np.arange(len(trees)), picked)
    pred = np.array([est["trees"][i]["load"] for i in free])
    r = float(np.corrcoef(pred, load[free])[0, 1]) if pred.std() > 0 and load[free].std() > 0 else 0.0
    return float(np.median(err)), r, float(est["flight"]["load"] / load.sum() - 1.0)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--orchards", type=int, default=100, help="orchards per setting (default 100)")
    p.add_argument("--rows", type=int, default=8)
    p.add_argument("--trees", type=int, default=25, help="trees a row (default 25)")
    p.add_argument("--mean", type=float, default=12.0, help="apples a tree (default 12, as on the simulated flights)")
    p.add_argument("--share", type=float, default=0.15, help="the seen share of a tree half covered (default 0.15)")
    p.add_argument("--k", type=int, default=10, help="trees counted by hand (default 10)")
    p.add_argument("--vigour-cv", type=float, default=0.25, help="a tree's own spread of load (default 0.25)")
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args()
    print(f"{'unseen':>6} {'row sd':>6} {'vis sd':>6} | {'choice':>6} {'random':>6} {'no worse':>8} {'^6':>5} | "
          f"{'r':>5} {'oracle':>6} {'within':>6} {'^6':>5} | {'total bias':>10} {'random':>6} {'<=10%':>5} {'random':>6}")
    for unseen, row_sd, vis_sd in itertools.product((0, 3, 6), (0.1, 0.3), (0.0, 0.6)):
        rng = np.random.default_rng(a.seed)
        mine, rand, win, r_ok, rs, ors, tot, tot_rand = [], [], [], [], [], [], [], []
        for _ in range(a.orchards):
            trees, load, seen = orchard(rng, a.rows, a.trees, a.mean, row_sd, vis_sd, a.share, unseen, a.vigour_cv)
            index = {(t["row"], t["tree"]): i for i, t in enumerate(trees)}
            picked = [index[(t["row"], t["tree"])] for t in choose_trees(trees, a.k)]
            err, r, total = figures(trees, load, picked)
            drawn = [figures(trees, load, list(rng.choice(len(trees), a.k, replace=False))) for _ in range(20)]
            draws = np.median([d[0] for d in drawn])
            oracle = [{**t, "coverage": s} for t, s in zip(trees, seen)]
            _, r_oracle, _ = figures(oracle, load, picked, "coverage")
            tot.append(total)
            tot_rand += [d[2] for d in drawn]
            mine.append(err), rand.append(draws), win.append(err <= draws)
            rs.append(r), ors.append(r_oracle), r_ok.append(r >= r_oracle - 0.05)
        w, ok = float(np.mean(win)), float(np.mean(r_ok))
        print(f"{unseen:>6} {row_sd:>6.1f} {vis_sd:>6.1f} | {np.mean(mine):>6.3f} {np.mean(rand):>6.3f} {w:>8.2f} "
              f"{w ** 6:>5.2f} | {np.median(rs):>5.2f} {np.median(ors):>6.2f} {ok:>6.2f} {ok ** 6:>5.2f} | "
              f"{np.mean(tot):>+10.3f} {np.mean(tot_rand):>+6.3f} {np.mean(np.abs(tot) <= 0.1):>5.2f} "
              f"{np.mean(np.abs(tot_rand) <= 0.1):>6.2f}", flush=True)


if __name__ == "__main__":
    main()
