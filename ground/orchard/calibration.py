"""Each tree's and row's load (every apple it carries, seen or not) from the map's counts, calibrated by the trees a
grower counted by hand (issue 59).

The camera sees a share of each tree's apples; the hand counts say how a tree's count (and its coverage,
pomar.coverage) relates to its load. One regression, fitted on the counted trees, predicts every other tree:

- ``ratio``:    load = b * count              (the field's practice: scale the camera's count);
- ``linear``:   load = a + b * count;
- ``coverage``: load = a + b * count / coverage (the count over the share of the canopy seen).
Every coefficient is at least 0 (issue 71): a load does not fall as the count rises, and no level is below 0. Where
the counted trees alone would fit one below 0 it is held at 0 and the model falls to the better-constrained one (no
slope: each tree the sample's level); ``constraints`` in report.json says which and why.
In every model, the trees the camera never saw (coverage 0) take a level of their
own, fitted on the counted trees among them (``ground choose-trees`` names some in every row): a count of 0 there is
nothing looked at, not an empty tree, and the line's intercept is an extrapolation from the trees seen least. Where
none of them was counted, each takes the sample's level (its mean, with the interval of one more tree drawn from the
sample), never 0.
``linear`` is the default, chosen on the tuning flights sim/configs/yield/tune-1 and tune-2 (docs/benchmarks.md).

Its residuals give the intervals, as a regression's prediction intervals (Student's t, ``level``): a tree's from the
residual spread and the fit's own uncertainty there; a row's and the flight's from the sum over their trees not counted
(their own scatter; each row's shared error, a variance component of the counted trees' leave-one-out residuals by row,
once per tree of the row; the fit's uncertainty, shared by all), plus the hand counts themselves, taken as exact.
``benchmarks/load_intervals.py`` checks them on made-up orchards. The
leave-one-out error of the sample refits without each counted tree and predicts it.
"""

from __future__ import annotations

import numpy as np

from pomar.cli import InputError

MODELS = ("ratio", "linear", "coverage")
#: The model used unless asked for another: chosen on issue 59's tuning flights (docs/design.md).
DEFAULT_MODEL = "linear"
#: The flight total's 90 % half-width a grower aims at (share of the load): ``ground load`` says how many trees counted
#: by hand would give it (issue 71's goal: the flight's total within 10 %).
TOTAL_TARGET = 0.10
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
    """(T,) whether the camera never saw each tree (its coverage 0; a coverage not known counts as seen). A tree with
    coverage 0 and apples counted on it stays unseen: on the heavy tuning flights those apples were the next row's,
    put in its strip by a map lying 1-2 m across from the layout (docs/benchmarks.md, twenty-second session); taken as
    seen, they put the median row error of tune-1 at 0.477 against 0.250."""
    cov = np.array([t.get("coverage", np.nan) for t in trees], float)
    return np.isfinite(cov) & (cov <= 0)


def regressors(trees: list[dict], model: str) -> np.ndarray:
    """(T, p) each tree's regressors under ``model``. With an intercept (``linear``, ``coverage``) and trees the
    camera never saw, those get a level of their own: their count of 0 is no measurement (nothing was looked at), and
    on the fitted line they would take its intercept, an extrapolation from the trees seen least (the second
    evaluation set: every row never seen came out 20-55 % low)."""
    x = regressor(trees, model)
    unseen = never_seen(trees)
    if model == "ratio":  # no intercept; the trees never seen still take a level of their own, never 0
        return x[:, None] if not unseen.any() else np.column_stack([np.where(unseen, 0.0, x), unseen.astype(float)])
    if not unseen.any():
        return np.column_stack([np.ones_like(x), x])
    return np.column_stack([(~unseen).astype(float), np.where(unseen, 0.0, x), unseen.astype(float)])


def _ols(Z: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Least squares: (coefficients, (Z'Z)^-1, the residual variance of a tree not in the fit). The variance is the
    mean square of the leave-one-out (PRESS) residuals, e_i / (1 - h_i), less the fit's own share: where the model
    is wrong for some trees (a row more vigorous, trees the camera saw less), those residuals grow and widen the
    intervals, where the fitted residuals would shrink them."""
    G = np.linalg.pinv(Z.T @ Z)
    beta = G @ Z.T @ y
    h = np.einsum("ij,jk,ik->i", Z, G, Z)
    e = (y - Z @ beta) / np.maximum(1.0 - h, 1e-6)
    return beta, G, float((e ** 2).mean() / (1.0 + h.mean()))


def _fit(Z: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, float, np.ndarray, np.ndarray]:
    """Least squares with every coefficient at least 0: each is a level (a tree seen with nothing counted on it, a tree
    never seen) or a slope (a load does not fall as the count rises), and none can be negative in an orchard. Where the
    sample asks for one below 0 (ten trees whose loads happen to fall as their counts rise), it is held at 0 and the
    others are fitted without it: the model falls to the better-constrained one (no slope: each tree the sample's
    level). Returns the least squares' outputs on the free coefficients (G and the variance as ``_ols``'s, zero
    for those held), the unconstrained coefficients and which are free."""
    beta, G, s2 = _ols(Z, y)
    if (beta >= 0).all():
        return beta, G, s2, beta, np.ones(len(beta), bool)
    from scipy.optimize import nnls

    free = nnls(Z, y)[0] > 0
    if not free.any():  # nothing but 0 fits: keep the level of the sample, whatever the model
        free = np.zeros(Z.shape[1], bool)
        free[0] = True
    b, g, s2 = _ols(Z[:, free], y)
    out, Gout = np.zeros(Z.shape[1]), np.zeros((Z.shape[1],) * 2)
    out[free] = b
    Gout[np.ix_(free, free)] = g
    return out, Gout, s2, beta, free


def row_variance(residuals: np.ndarray, rows: np.ndarray, tree_variance: float) -> float:
    """The variance of a row's shared error (one-way random effects, method of moments): what the counted trees'
    leave-one-out residuals have in common within a row beyond the trees' own scatter (a row seen nearer, or from
    its other side, or more vigorous than its count says). Every tree of a row shares it, so a row's sum carries it
    once per tree, not averaged away. Rows with one counted tree give no within-row spread: the trees' variance is
    taken for it. 0 where fewer than two rows were counted."""
    names, k = np.unique(rows, return_inverse=True)
    if len(names) < 2:
        return 0.0
    n = np.bincount(k).astype(float)
    means = np.bincount(k, residuals) / n
    N = float(len(residuals))
    msb = float((n * (means - residuals.mean()) ** 2).sum() / (len(names) - 1))
    within = residuals - means[k]
    msw = float((within ** 2).sum() / (N - len(names))) if N > len(names) else tree_variance
    n0 = (N - (n ** 2).sum() / N) / (len(names) - 1)
    return max(0.0, (msb - msw) / max(n0, 1.0))


def coefficient_names(Z: np.ndarray, model: str) -> list[str]:
    """What each of ``regressors``' columns multiplies, for report.json."""
    x = "count / coverage" if model == "coverage" else "count"
    if model == "ratio":
        return [f"slope ({x})", "level (a tree never seen)"][:Z.shape[1]]
    return ["level (a tree seen)", f"slope ({x})", "level (a tree never seen)"][:Z.shape[1]]


def leave_one_out(Z: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Each sample's prediction by the fit on the others."""
    out = np.empty(len(y))
    for j in range(len(y)):
        keep = np.arange(len(y)) != j
        beta = _fit(Z[keep], y[keep])[0]
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
    check_enough({k: samples[k] for k in key if k in samples}, model)
    y = np.array([samples[k] for k in key if k in samples], float)
    beta, G, s2, free_beta, free = _fit(Z[counted], y)
    names = coefficient_names(Z, model)
    held = [n for n, f in zip(names, free) if not f]
    dof = max(len(y) - int(np.linalg.matrix_rank(Z[counted][:, free])), 1)
    q = float(student.ppf(0.5 + level / 2, dof))
    pred = Z @ beta
    half = q * np.sqrt(s2 * (1.0 + np.einsum("ij,jk,ik->i", Z, G, Z)))
    # Trees never seen, none of them counted: nothing relates them to the line, so each takes the sample's level, with
    # the interval of one more tree drawn from the sample (its spread, and the uncertainty of its mean, shared).
    unseen = never_seen(trees)
    guessed = unseen & ~counted & (not (unseen & counted).any())
    y_mean, y_sd = float(y.mean()), float(y.std(ddof=1)) if len(y) > 1 else 0.0
    q_level = float(student.ppf(0.5 + level / 2, max(len(y) - 1, 1)))
    pred[guessed] = y_mean
    half[guessed] = q_level * y_sd * np.sqrt(1.0 + 1.0 / len(y))
    per_tree = []
    for i, k in enumerate(key):
        if counted[i]:
            n = float(samples[k])
            per_tree.append({"hand_count": int(samples[k]), "load": n, "load_lo": n, "load_hi": n})
        else:
            per_tree.append({"hand_count": float("nan"), "load": max(0.0, pred[i]),
                             "load_lo": max(0.0, pred[i] - half[i]), "load_hi": max(0.0, pred[i] + half[i])})

    rows_of = np.array([k[0] for k in key])
    row_index = np.unique(rows_of, return_inverse=True)[1]
    loo = leave_one_out(Z[counted], y)
    err = loo - y
    tau2 = row_variance(y - loo, rows_of[counted], s2)

    def total(sel: np.ndarray) -> dict:
        """A group's load: its counted trees as counted, the others predicted, one interval for the sum."""
        u = sel & ~counted & ~guessed
        g = int((sel & guessed).sum())
        known = float(sum(samples[key[i]] for i in np.nonzero(sel & counted)[0]))
        zu = Z[u].sum(0)
        est = known + max(0.0, float(zu @ beta)) + g * y_mean
        # the line's trees: their own scatter, each row's shared error (once per tree of it) and the fit's, shared;
        # the guessed ones: their own scatter and the mean's, shared
        per_row = np.bincount(row_index[u], minlength=1).astype(float)
        own = q ** 2 * s2 * u.sum() + q_level ** 2 * y_sd ** 2 * g  # each tree's own scatter: no sample shrinks it
        shared = q ** 2 * (s2 * zu @ G @ zu + tau2 * float((per_row ** 2).sum())) + q_level ** 2 * y_sd ** 2 * g * g / len(y)
        h = np.sqrt(own + shared)
        # the trees to count for the interval to reach TOTAL_TARGET of the load: the shared part shrinks as 1/trees
        # counted (the fit's and the rows' errors, the sample mean's), the own part does not; None where it alone
        # is wider than that
        room = (TOTAL_TARGET * est) ** 2 - own
        needed = int(np.ceil(len(y) * shared / room)) if room > 0 and est > 0 else None
        return {"load": est, "load_lo": max(known, est - h), "load_hi": est + h, "trees": int(sel.sum()),
                "trees_counted": int((sel & counted).sum()),
                "target": TOTAL_TARGET, "trees_for_target": max(needed, len(y)) if needed is not None else None}

    why = ("; ".join(f"{n} held at 0 (the sample alone gives {f:.3g})" for n, f, ok in zip(names, free_beta, free)
                     if not ok) + ": a load does not fall as the count rises, nor below 0") if held else \
        "none held: the sample's own fit has every coefficient at least 0"
    never = {"trees": int(unseen.sum()), "counted": int((unseen & counted).sum()),
             "estimated_by": ("the sample's level (no tree never seen was counted): mean "
                              f"{y_mean:.1f}, sd {y_sd:.1f}" if guessed.any() else
                              "their own level, fitted on the counted trees among them"
                              if unseen.any() else "the model")}
    return {"model": model, "level": level, "coefficients": [float(b) for b in beta],
            "coefficient_names": names, "constraints": {"held_at_0": held, "why": why}, "never_seen": never,
            "residual_sd": float(np.sqrt(s2)), "row_sd": float(np.sqrt(tau2)), "trees": per_tree,
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
    return {k: est[k] for k in ("model", "level", "coefficients", "coefficient_names", "constraints", "never_seen",
                                "residual_sd", "row_sd", "flight", "loo")}


def check_enough(samples: dict, model: str, path=None) -> None:
    """The hand ``samples`` ((row, tree) -> apples) calibrate ``model``: enough trees for its coefficients and two
    degrees of freedom for the intervals, and not every one of them empty (0 apples on every counted tree says nothing
    of how a count relates to a load); CalibrationError (naming ``path``, the counts' file) otherwise."""
    where = f"{path}: " if path else ""
    n = len(samples)
    need = regressors([{"count": 0, "coverage": 1.0}], model).shape[1] + 2
    if n < need:
        raise CalibrationError(f"{where}{n} trees counted by hand: the {model!r} model needs at least {need} (count a "
                               f"few more trees)")
    if not any(v > 0 for v in samples.values()):
        raise CalibrationError(f"{where}every one of the {n} trees counted by hand holds 0 apples: nothing relates the "
                               f"camera's count to a load (count trees that carry fruit)")
