"""Each tree's and row's load (every apple it carries, seen or not) from the map's counts, calibrated by the trees a
grower counted by hand (issue 59).

The camera sees a share of each tree's apples; the hand counts say how a tree's count (and its coverage,
ground.orchard.coverage) relates to its load. One regression, fitted on the counted trees, predicts every other tree:

- ``ratio``:    load = b * count              (the field's practice: scale the camera's count);
- ``linear``:   load = a + b * count;
- ``coverage``: load = a + b * count / coverage (the count over the share of the canopy seen).
In ``linear`` and ``coverage``, the trees the camera never saw (coverage 0) take a level of their own, fitted on the
counted trees among them (``ground choose-trees`` names some in every row): a count of 0 there is nothing looked at,
not an empty tree, and the line's intercept is an extrapolation from the trees seen least. Where no such tree was
counted, they take the intercept.
``linear`` is the default, chosen on the tuning flights sim/configs/yield/tune-1 and tune-2 (docs/benchmarks.md).

Its residuals give the intervals, as a regression's prediction intervals (Student's t, ``level``): a tree's from the
residual spread and the fit's own uncertainty there; a row's and the flight's from the sum over their trees not counted
(their residuals independent, the fit's uncertainty shared), plus the hand counts themselves, taken as exact. The
leave-one-out error of the sample refits without each counted tree and predicts it.
"""

from __future__ import annotations

import numpy as np

from pomar.cli import InputError

MODELS = ("ratio", "linear", "coverage")
#: The model used unless asked for another: chosen on issue 59's tuning flights (docs/design.md).
DEFAULT_MODEL = "linear"
#: Columns added to trees.csv and (load, load_lo, load_hi) to rows.csv: empty where there are no hand counts.
LOAD_COLUMNS = ["hand_count", "load", "load_lo", "load_hi"]


class CalibrationError(InputError, ValueError):
    """Hand counts that cannot calibrate the model (too few trees): the message says how many it needs."""


def regressor(trees: list[dict], model: str) -> np.ndarray:
    """(T,) each tree's regressor under ``model``: its count, or its count over its coverage (0 where never seen)."""
    count = np.array([t["count"] for t in trees], float)
    if model in ("ratio", "linear"):
        return count
    if model == "coverage":
        cov = np.array([t.get("coverage", np.nan) for t in trees], float)
        with np.errstate(divide="ignore", invalid="ignore"):
            return np.where(cov > 0, count / cov, 0.0)
    raise ValueError(f"unknown load model {model!r} (one of {', '.join(MODELS)})")


def never_seen(trees: list[dict]) -> np.ndarray:
    """(T,) whether the camera never saw each tree (its coverage 0; a coverage not known counts as seen)."""
    cov = np.array([t.get("coverage", np.nan) for t in trees], float)
    return np.isfinite(cov) & (cov <= 0)


def regressors(trees: list[dict], model: str) -> np.ndarray:
    """(T, p) each tree's regressors under ``model``. With an intercept (``linear``, ``coverage``) and trees the
    camera never saw, those get a level of their own: their count of 0 is no measurement (nothing was looked at), and
    on the fitted line they would take its intercept, an extrapolation from the trees seen least (the second
    evaluation set: every row never seen came out 20-55 % low)."""
    x = regressor(trees, model)
    if model == "ratio":
        return x[:, None]
    unseen = never_seen(trees)
    if not unseen.any():
        return np.column_stack([np.ones_like(x), x])
    return np.column_stack([(~unseen).astype(float), np.where(unseen, 0.0, x), unseen.astype(float)])


def _fit(Z: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Least squares: (coefficients, (Z'Z)^-1, the residual variance of a tree not in the fit). The variance is the
    mean square of the leave-one-out (PRESS) residuals, e_i / (1 - h_i), less the fit's own share: where the model
    is wrong for some trees (a row more vigorous, trees the camera saw less), those residuals grow and widen the
    intervals, where the fitted residuals would shrink them."""
    G = np.linalg.pinv(Z.T @ Z)
    beta = G @ Z.T @ y
    h = np.einsum("ij,jk,ik->i", Z, G, Z)
    e = (y - Z @ beta) / np.maximum(1.0 - h, 1e-6)
    return beta, G, float((e ** 2).mean() / (1.0 + h.mean()))


def leave_one_out(Z: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Each sample's prediction by the fit on the others."""
    out = np.empty(len(y))
    for j in range(len(y)):
        keep = np.arange(len(y)) != j
        beta, _, _ = _fit(Z[keep], y[keep])
        out[j] = max(0.0, float(Z[j] @ beta))
    return out


def estimate_load(trees: list[dict], samples: dict[tuple[int, int], int], model: str = DEFAULT_MODEL,
                  level: float = 0.9) -> dict:
    """The load of every tree of ``trees`` (trees.csv's records, with ``count`` and ``coverage``), of each row and of
    the flight, from the hand ``samples`` ((row, tree) -> apples): {"trees": LOAD_COLUMNS per tree, "rows": {row:
    (load, lo, hi)}, "flight": {...}, "loo": {...}}."""
    from scipy.stats import t as student

    Z = regressors(trees, model)
    key = [(int(t["row"]), int(t["tree"])) for t in trees]
    counted = np.array([k in samples for k in key])
    check_enough(int(counted.sum()), model)
    y = np.array([samples[k] for k in key if k in samples], float)
    beta, G, s2 = _fit(Z[counted], y)
    dof = max(len(y) - int(np.linalg.matrix_rank(Z[counted])), 1)
    q = float(student.ppf(0.5 + level / 2, dof))
    pred = Z @ beta
    half = q * np.sqrt(s2 * (1.0 + np.einsum("ij,jk,ik->i", Z, G, Z)))
    per_tree = []
    for i, k in enumerate(key):
        if counted[i]:
            n = float(samples[k])
            per_tree.append({"hand_count": int(samples[k]), "load": n, "load_lo": n, "load_hi": n})
        else:
            per_tree.append({"hand_count": float("nan"), "load": max(0.0, pred[i]),
                             "load_lo": max(0.0, pred[i] - half[i]), "load_hi": max(0.0, pred[i] + half[i])})

    def total(sel: np.ndarray) -> dict:
        """A group's load: its counted trees as counted, the others predicted, one interval for the sum."""
        u = sel & ~counted
        known = float(sum(samples[key[i]] for i in np.nonzero(sel & counted)[0]))
        zu = Z[u].sum(0)
        est = known + max(0.0, float(zu @ beta))
        h = q * np.sqrt(s2 * (u.sum() + zu @ G @ zu))
        return {"load": est, "load_lo": max(known, est - h), "load_hi": est + h, "trees": int(sel.sum()),
                "trees_counted": int((sel & counted).sum())}

    rows_of = np.array([k[0] for k in key])
    loo = leave_one_out(Z[counted], y)
    err = loo - y
    return {"model": model, "level": level, "coefficients": [float(b) for b in beta],
            "residual_sd": float(np.sqrt(s2)), "trees": per_tree,
            "rows": {int(r): total(rows_of == r) for r in np.unique(rows_of)},
            "flight": total(np.ones(len(key), bool)),
            "loo": {"trees": int(len(y)), "mean_abs_error": float(np.abs(err).mean()),
                    "rms_error": float(np.sqrt((err ** 2).mean())),
                    "median_abs_pct": float(np.median(np.abs(err) / np.maximum(y, 1.0)) * 100.0),
                    "predicted": [float(v) for v in loo], "counted": [int(v) for v in y]}}


def apply_load(trees: list[dict], rows: list[dict], est: dict) -> dict:
    """Write ``est`` (estimate_load's) into the trees' and rows' records (LOAD_COLUMNS); returns report.json's ``load``
    section: the model, its fit, the flight's load and the sample's leave-one-out error."""
    for t, e in zip(trees, est["trees"]):
        t.update(e)
    for r in rows:
        e = est["rows"].get(int(r["row"]))
        r.update({k: e[k] for k in ("load", "load_lo", "load_hi")} if e else
                 {"load": float("nan"), "load_lo": float("nan"), "load_hi": float("nan")})
    return {k: est[k] for k in ("model", "level", "coefficients", "residual_sd", "flight", "loo")}


def check_enough(n: int, model: str, path=None) -> None:
    """``n`` trees counted by hand calibrate ``model`` (its coefficients and two degrees of freedom for the
    intervals); CalibrationError (naming ``path``, the counts' file) otherwise."""
    need = regressors([{"count": 0, "coverage": 1.0}], model).shape[1] + 2
    if n < need:
        raise CalibrationError(f"{str(path) + ': ' if path else ''}{n} trees counted by hand: the {model!r} model needs "
                               f"at least {need} (count a few more trees)")
