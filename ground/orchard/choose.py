"""Which trees the grower should count by hand (issue 59): k trees spread over the rows and over what the map knows of
each tree, so that the calibration (ground.orchard.calibration) sees the whole range it predicts over.

First every row gets a tree (where k allows; else k rows spread evenly over the layout): the count says nothing of a
row the camera never saw, or saw from afar, and only a hand count there tells its level (rows differ in vigour, variety
and crop). In a row the camera saw, its seen tree whose regressor (the count; the count over the coverage for
``coverage``) is nearest the row's median; in a row it never saw, a tree placed systematically along the rows. The rest are stratified on the
regressor over the trees the camera saw: ordered by it and cut into strata of equal size, from each the tree nearest
the stratum's median, so that the sample spans the regressor and is balanced on it where a random handful may bunch
together.
"""

from __future__ import annotations

import numpy as np

from ground.orchard.calibration import DEFAULT_MODEL, never_seen, regressor


def _one_per_row(trees: list[dict], x: np.ndarray, seen: np.ndarray, k: int, rng=None) -> list[int]:
    """A tree of each row (of k rows spread evenly where there are more): the seen tree nearest the row's median
    regressor; in a row the camera never saw, a tree placed systematically along it, the m such rows' trees at 1/2m,
    3/2m, ... of their rows' lengths, so that a gradient along the rows (a slope, the irrigation, the headland) does
    not put every such tree on the same side of it. With ``rng``, a tree drawn at random from the same pool instead."""
    rows = sorted({t["row"] for t in trees})
    if k < len(rows):
        rows = [rows[int(i)] for i in np.round(np.linspace(0, len(rows) - 1, k))]
    of_row = {r: np.array([i for i, t in enumerate(trees) if t["row"] == r]) for r in rows}
    unseen = [r for r in rows if not seen[of_row[r]].any()]
    out = []
    for r in rows:
        idx = of_row[r]
        if rng is not None:
            pool = idx[seen[idx]] if r not in unseen else idx
            out.append(int(rng.choice(pool)))
            continue
        if r in unseen:
            place = (unseen.index(r) + 0.5) / len(unseen)
            out.append(int(idx[np.argsort([trees[i]["tree"] for i in idx], kind="stable")][int(place * len(idx))]))
            continue
        pool = idx[seen[idx]]
        mid_x, mid_tree = np.median(x[pool]), np.median([trees[i]["tree"] for i in pool])
        out.append(int(min(pool, key=lambda i: (abs(x[i] - mid_x), abs(trees[i]["tree"] - mid_tree), i))))
    return out


def choose_trees(trees: list[dict], k: int = 10, model: str = DEFAULT_MODEL,
                 counted: set[tuple[int, int]] = frozenset(), rng=None) -> list[dict]:
    """``k`` of ``trees`` (trees.csv's records with count and coverage) to count by hand, in row and tree order;
    ``counted``: (row, tree) of trees already counted, kept among the ``k`` (more trees asked for after a first
    sample): a row with one of them gets no other by the first rule, and the strata are drawn over the rest.
    ``rng`` (a numpy Generator): the same design drawn at random where the rule takes a middle (a row's tree, a
    stratum's), for judging the rule over many samples (``benchmarks/load_intervals.py``)."""
    if k <= 0:
        raise ValueError(f"k must be at least 1, got {k}")
    x = regressor(trees, model)
    seen = ~never_seen(trees)
    kept = [i for i, t in enumerate(trees) if (t["row"], t["tree"]) in counted]
    if kept:
        rows_kept = {trees[i]["row"] for i in kept}
        free = [i for i, t in enumerate(trees) if t["row"] not in rows_kept]
        more = _one_per_row([trees[i] for i in free], x[free], seen[free], max(min(k, len(trees)) - len(kept), 0),
                            rng)
        chosen = kept + [free[i] for i in more]
    else:
        chosen = _one_per_row(trees, x, seen, min(k, len(trees)), rng)
    left = np.setdiff1d(np.nonzero(seen)[0], chosen)
    if len(left) < k - len(chosen):  # too few seen trees: any tree not chosen yet
        left = np.setdiff1d(np.arange(len(trees)), chosen)
    strata = min(k - len(chosen), len(left))
    if strata > 0:
        order = left[np.argsort(x[left], kind="stable")]
        for s in np.array_split(order, strata):
            if rng is not None:
                chosen.append(int(rng.choice(s)))
                continue
            mid = np.median(x[s])
            chosen.append(int(min(s, key=lambda i: (abs(x[i] - mid), i))))
    return [trees[i] for i in sorted(chosen, key=lambda i: (trees[i]["row"], trees[i]["tree"]))]
