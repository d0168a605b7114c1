"""The fruit's size per row, and the load in kilograms (issue 59): each counted apple's diameter from its 3-D fit
(apples.csv's radius_m), the row's median and its share in each size class, and the row's load (apples, from the
hand counts) times the mean mass of its measured apples (pomar.fruit, by the row's cultivar where the layout says it),
or of the flight's where the camera measured none of the row's (its diameter_mm empty).
"""

from __future__ import annotations

import numpy as np

from pomar.fruit import apple_mass_kg

#: Size classes' bounds (mm): < 60, 60-70, 70-80, > 80.
CLASS_BOUNDS_MM = (60.0, 70.0, 80.0)
#: Columns added to rows.csv: median diameter (mm), the share of each class, the mean mass of an apple (kg), the load
#: in kg with its interval (empty without hand counts), and the median diameter's 90 % interval (its apples' sampling
#: and the map scale's uncertainty).
SIZE_COLUMNS = ["diameter_mm", "share_lt60", "share_60_70", "share_70_80", "share_gt80", "apple_kg", "kg", "kg_lo",
                "kg_hi", "diameter_mm_lo", "diameter_mm_hi"]
#: The standard normal's 95th percentile: a 90 % interval's half-width in sigmas.
Z90 = 1.6449


def size_figures(diameter_m: np.ndarray, cultivar: str = "") -> dict:
    """The median diameter (mm), the share of each class and the mean mass (kg) of apples of these diameters (m; NaN
    ones left out); NaN where none is measured."""
    d = np.asarray(diameter_m, float)
    d = d[np.isfinite(d) & (d > 0)]
    if not len(d):
        return {c: float("nan") for c in SIZE_COLUMNS[:6] + SIZE_COLUMNS[9:]}
    mm = np.sort(d * 1000.0)
    lo, mid, hi = CLASS_BOUNDS_MM
    # the median's 90 % interval from the order statistics (ranks n/2 -/+ 1.645 sqrt(n) / 2)
    k = Z90 * np.sqrt(len(mm)) / 2.0
    rank = np.clip(np.round([(len(mm) - 1) / 2.0 - k, (len(mm) - 1) / 2.0 + k]).astype(int), 0, len(mm) - 1)
    return {"diameter_mm": float(np.median(mm)), "diameter_mm_lo": float(mm[rank[0]]),
            "diameter_mm_hi": float(mm[rank[1]]), "share_lt60": float((mm < lo).mean()),
            "share_60_70": float(((mm >= lo) & (mm < mid)).mean()), "share_70_80": float(((mm >= mid) & (mm < hi)).mean()),
            "share_gt80": float((mm >= hi).mean()), "apple_kg": float(apple_mass_kg(d, cultivar).mean())}


def row_sizes(table: dict, rows: list[dict], cultivars: dict[int, str] | None = None,
              scale_sigma_rel: float = float("nan")) -> dict:
    """SIZE_COLUMNS into each row's record, from its apples in ``table`` (apple_table's columns); returns report.json's
    ``size`` section for the flight (the same figures over every apple; kg the sum of the rows'). ``scale_sigma_rel``:
    the map scale's relative 1-sigma (ground.poses.scale), which every size carries: the diameters' intervals take it,
    the kilograms' three times (a mass goes with the cube)."""
    cultivars = cultivars or {}
    diameter = 2.0 * np.asarray(table["radius_m"], float) if len(table["id"]) else np.zeros(0)
    row_of = np.asarray(table["row"])
    far = far_out(diameter)
    diameter = np.where(far, np.nan, diameter)  # a fit's failure, not a fruit: its mass (the cube) would swamp the mean
    measured = diameter[np.isfinite(diameter) & (diameter > 0)]
    for r in rows:
        cultivar = cultivars.get(r["row"], "")
        r.update(size_figures(diameter[row_of == r["row"]], cultivar))
        if not np.isfinite(r["apple_kg"]) and len(measured):  # a row the camera measured no apple of: the flight's
            r["apple_kg"] = float(apple_mass_kg(measured, cultivar).mean())
        r.update({k: r.get(k, np.nan) for k in ("load", "load_lo", "load_hi")})
        r["diameter_mm_lo"], r["diameter_mm_hi"] = with_scale(r["diameter_mm"], r["diameter_mm_lo"],
                                                              r["diameter_mm_hi"], scale_sigma_rel)
    row_kilograms(rows, scale_sigma_rel)
    out = size_figures(diameter)
    out["diameter_mm_lo"], out["diameter_mm_hi"] = with_scale(out["diameter_mm"], out["diameter_mm_lo"],
                                                              out["diameter_mm_hi"], scale_sigma_rel)
    out["scale_sigma_pct"] = 100.0 * scale_sigma_rel if np.isfinite(scale_sigma_rel) else None
    kg = np.array([[r["kg"], r["kg_lo"], r["kg_hi"]] for r in rows], float).reshape(-1, 3)
    out["kg"] = float(kg[:, 0].sum()) if len(kg) and np.isfinite(kg[:, 0]).all() else float("nan")
    out["apples_measured"] = int(np.isfinite(diameter).sum())
    out["apples_far_out"] = int(far.sum())
    return out


def far_out(diameter: np.ndarray) -> np.ndarray:
    """Which diameters lie beyond Tukey's far-out fences of the flight's measured ones (3 interquartile ranges past
    the quartiles): fits that failed (an apple of 1.3 m on a heavy tuning flight made the flight's mean apple 1.44 kg,
    seven times its rows'), left out of every size and mass."""
    d = np.asarray(diameter, float)
    ok = np.isfinite(d) & (d > 0)
    if ok.sum() < 4:
        return np.zeros(len(d), bool)
    q1, q3 = np.percentile(d[ok], [25, 75])
    return ok & ((d < q1 - 3 * (q3 - q1)) | (d > q3 + 3 * (q3 - q1)))


def with_scale(value: float, lo: float, hi: float, sigma_rel: float, power: int = 1) -> tuple[float, float]:
    """A 90 % interval (lo, hi) about ``value`` widened by the map scale's relative 1-sigma raised to ``power`` (1 a
    length, 3 a mass): each side's relative half-width and the scale's added in quadrature. Unchanged where the scale's
    uncertainty is not known."""
    value, lo, hi = float(value), float(lo), float(hi)
    if not (np.isfinite(sigma_rel) and np.isfinite(value) and value > 0):
        return lo, hi
    s = Z90 * power * float(sigma_rel)
    return (value * (1.0 - float(np.hypot((value - lo) / value, s))),
            value * (1.0 + float(np.hypot((hi - value) / value, s))))


def row_kilograms(rows: list[dict], scale_sigma_rel: float = float("nan")) -> None:
    """Each row's load in kilograms, with its interval (kg, kg_lo, kg_hi): its load times the mean mass of its
    measured apples (``apple_kg``; rows read back from rows.csv carry it as text), the interval widened by the map
    scale's uncertainty (``scale_sigma_rel``, cubed with the mass)."""
    for r in rows:
        m = float(r.get("apple_kg") or "nan")
        kg = float(r["load"]) * m
        lo, hi = with_scale(kg, float(r["load_lo"]) * m, float(r["load_hi"]) * m, scale_sigma_rel, power=3)
        r.update(kg=kg, kg_lo=lo, kg_hi=hi)
