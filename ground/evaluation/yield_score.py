"""The yield of a simulated flight's map scored against its truth (issue 59): the loads, intervals, sizes and
kilograms the ground wrote (trees.csv, rows.csv; mapped with the layout of ``python -m sim layout``, so that its rows
and trees are the truth's) against every tree's full load and every apple's diameter and mass.

- trees: the error of each tree not counted by hand, and the correlation (r) of the estimated with the true loads;
- rows: each row's load error (relative), whether its interval holds the true load, the interval's half-width
  (relative to the load);
- size: each row's median diameter against the truth's (all the row's apples), beside the error of one constant
  median (the map's own over all its apples) for every row; each row's kilograms against the truth's mass;
- the oracle: the seen share each tree truly had (its countable apples over its load, from the truth) for the
  estimate to use in the coverage's place (``oracle_trees``).
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from pomar.countable import countable_ids


def _records(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def truth_of(flight) -> dict:
    """The flight's truth for the yield: each tree's load and mass, each row's apples' diameters (m) and mass."""
    t = flight.truth_trees()
    a = flight.truth_apples(trees=True)
    trees = {(int(r), int(k)): (int(n), float(m)) for r, k, n, m in zip(t["row"], t["tree"], t["apples"], t["mass_kg"])}
    rows = {}
    for r in np.unique(a["row"].astype(int)):
        sel = a["row"].astype(int) == r
        rows[int(r)] = {"diameters_m": 2.0 * a["radius_m"][sel], "load": int(sel.sum()),
                        "kg": float(a["mass_kg"][sel].sum())}
    return {"trees": trees, "rows": rows}


def seen_share(flight) -> dict[tuple[int, int], float]:
    """Each tree's true seen share: its countable apples (pomar.countable, from the truth detections) over its load."""
    a = flight.truth_apples(trees=True)
    d = flight.truth_detections()
    seen = set(countable_ids(d["apple_id"], d["visible_fraction"]).tolist())
    tree_of = {int(i): (int(r), int(k)) for i, r, k in zip(a["apple_id"], a["row"], a["tree"])}
    n_seen: dict[tuple[int, int], int] = {}
    for i in seen:
        if int(i) in tree_of:
            n_seen[tree_of[int(i)]] = n_seen.get(tree_of[int(i)], 0) + 1
    return {k: n_seen.get(k, 0) / n for k, (n, _) in truth_of(flight)["trees"].items() if n > 0}


def oracle_trees(trees: list[dict], share: dict[tuple[int, int], float]) -> list[dict]:
    """The map's trees with each one's true seen share in its coverage's place (the oracle of issue 59's goals: the
    same estimate, with the coverage model, given what the camera truly saw of each tree)."""
    return [{**t, "coverage": share.get((int(t["row"]), int(t["tree"])), 0.0)} for t in trees]


def read_map(out_dir) -> tuple[list[dict], list[dict]]:
    """A finished map's trees.csv and rows.csv as records (text values)."""
    return _records(Path(out_dir) / "trees.csv"), _records(Path(out_dir) / "rows.csv")


def _value(x) -> float:
    return float("nan") if x in (None, "") else float(x)


def score_yield(trees: list[dict], rows: list[dict], truth: dict) -> dict:
    """The figures above for a map's trees and rows (records as trees.csv and rows.csv give them, with loads from hand
    counts) against ``truth`` (:func:`truth_of`)."""
    est, true = [], []
    for t in trees:
        key = (int(t["row"]), int(t["tree"]))
        if key in truth["trees"] and not np.isfinite(_value(t["hand_count"])) and np.isfinite(_value(t["load"])):
            est.append(float(t["load"]))
            true.append(truth["trees"][key][0])
    est, true = np.array(est), np.array(true, float)
    per_row = []
    measured = [_value(r.get("diameter_mm")) for r in rows]
    measured = [m for m in measured if np.isfinite(m)]
    constant = float(np.median(measured)) if measured else float("nan")
    for r in rows:
        tr = truth["rows"].get(int(r["row"]))
        if tr is None or not np.isfinite(_value(r.get("load"))):
            continue
        load, lo, hi = _value(r["load"]), _value(r["load_lo"]), _value(r["load_hi"])
        true_mm = float(np.median(tr["diameters_m"]) * 1000.0)
        d_mm, kg = _value(r.get("diameter_mm")), _value(r.get("kg"))
        per_row.append({"row": int(r["row"]), "load": load, "true_load": tr["load"],
                        "load_error": (load - tr["load"]) / tr["load"], "covered": bool(lo <= tr["load"] <= hi),
                        "half_width": (hi - lo) / 2.0 / max(load, 1.0),
                        "diameter_mm": d_mm, "true_diameter_mm": true_mm, "diameter_error_mm": d_mm - true_mm,
                        "constant_error_mm": constant - true_mm,
                        "kg": kg, "true_kg": tr["kg"], "kg_error": (kg - tr["kg"]) / tr["kg"]})
    return {"trees": {"n": int(len(est)), "r": float(np.corrcoef(est, true)[0, 1]) if len(est) >= 3 else None,
                      "median_abs_error": float(np.median(np.abs(est - true))) if len(est) else None},
            "rows": per_row,
            # the flight's total over the rows scored: the sum of their loads against the sum of their true loads
            "total_error": (sum(r["load"] for r in per_row) / sum(r["true_load"] for r in per_row) - 1.0
                            if per_row else None),
            "row_load_error_median": float(np.median([abs(r["load_error"]) for r in per_row])) if per_row else None,
            "coverage": float(np.mean([r["covered"] for r in per_row])) if per_row else None,
            "half_width_median": float(np.median([r["half_width"] for r in per_row])) if per_row else None}
