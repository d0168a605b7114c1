"""Which trees the grower should count by hand (issue 59): k trees spread over the rows and over what the map knows of
each tree, so that the calibration (ground.orchard.calibration) sees the whole range it predicts over.

The trees the map saw are ordered by the model's regressor (the count; the count over the coverage for ``coverage``)
and cut into k strata of equal size; from each, of the NEAREST trees nearest the stratum's median, the one of the
row with the fewest trees chosen so far. The sample so spans the regressor and is balanced on it (its mean near the
orchard's), where a random handful may bunch together; spreading over rows keeps a row's own effects (vigour, variety)
in it.
"""

from __future__ import annotations

import numpy as np

from ground.orchard.calibration import DEFAULT_MODEL, regressors


#: Of each stratum, the trees this near its median are the candidates; the one of the row least chosen so far wins.
#: 1: the nearest, whatever its row (on made-up orchards, tests/test_orchard_calibration.py, preferring rows among the
#: 3 nearest gave the linear model larger row errors than random draws).
NEAREST = 1


def choose_trees(trees: list[dict], k: int = 10, model: str = DEFAULT_MODEL) -> list[dict]:
    """``k`` of ``trees`` (trees.csv's records with count and coverage) to count by hand, in row and tree order."""
    if k <= 0:
        raise ValueError(f"k must be at least 1, got {k}")
    x = regressors(trees, model)[:, -1]
    cov = np.array([t.get("coverage", np.nan) for t in trees], float)
    seen = np.nonzero(~np.isfinite(cov) | (cov > 0))[0]  # a tree the camera never saw tells nothing of its count
    pool = seen if len(seen) >= k else np.arange(len(trees))
    order = pool[np.argsort(x[pool], kind="stable")]
    strata = np.array_split(order, min(k, len(order)))
    chosen: list[int] = []
    per_row: dict[int, int] = {}
    for s in strata:
        mid = np.median(x[s])
        near = sorted(s, key=lambda i: (abs(x[i] - mid), i))[:NEAREST]
        best = min(near, key=lambda i: (per_row.get(trees[i]["row"], 0), abs(x[i] - mid), i))
        chosen.append(int(best))
        per_row[trees[best]["row"]] = per_row.get(trees[best]["row"], 0) + 1
    # every row at least once where k allows: a row left out takes the stratum whose pick it can replace most closely
    # (of those picked from a row chosen twice or more)
    rows = sorted({trees[i]["row"] for i in pool})
    for r in rows:
        if per_row.get(r, 0) or len(per_row) >= len(strata):
            continue
        swaps = [(abs(x[i] - np.median(x[s])), j, i) for j, s in enumerate(strata)
                 if per_row[trees[chosen[j]]["row"]] >= 2 for i in s if trees[i]["row"] == r]
        if swaps:
            _, j, i = min(swaps)
            per_row[trees[chosen[j]]["row"]] -= 1
            chosen[j], per_row[r] = int(i), 1
    return [trees[i] for i in sorted(chosen, key=lambda i: (trees[i]["row"], trees[i]["tree"]))]
