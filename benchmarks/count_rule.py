"""Where a flight's count error comes from, and whether a rule learned from the count's candidates would do better
than today's checks (issue 40): read from replays already made, nothing replayed.

    python benchmarks/count_rule.py --replay out/bench/generalisation/g2b/tune-1 out/sim/tune-1 \\
        --replay out/bench/generalisation/g2b/tune-2 out/sim/gen/tune-2 ...

For each replay, every apple the count was chosen from (candidates.csv) is labelled against the truth on the map's
shape (ground.evaluation.scoring.label_candidates): countable, partial (a true apple the definition does not count)
or none. The table gives the countable apples the replay counted, those the checks left out, those no candidate
found (and the median of their countable views), and the partial and false apples counted: a count error is what is
left of these.

Then a logistic rule on the candidates' features (share of the expected views detected, strong views among them,
strong views per expected view, radius against the flight's median, strong views, the parallax check), with a
threshold chosen to give the least squared count error, is fitted on all flights but one and applied to the one left
out, for every flight: its count errors beside the checks'. Tuning flights only. Accuracy only.
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ground.evaluation.scoring import label_candidates  # noqa: E402
from pomar.flight import FlightDir, FlightFormatError  # noqa: E402

FEATURES = ["share of expected views", "strong / views", "strong / expected", "radius / median", "log strong",
            "narrow"]


def features(cands: list[dict]) -> np.ndarray:
    """One row per candidate: a constant, then FEATURES."""
    def col(k):
        return np.array([float(c[k]) if c[k] not in ("", "nan") else np.nan for c in cands], float)

    obs, strong, expected, radius = col("observations"), col("strong_views"), col("expected_views"), col("radius_m")
    expected = np.where(np.isfinite(expected) & (expected > 0), expected, obs)  # not computed: as if all were seen
    rr = radius / np.nanmedian(radius) if np.isfinite(radius).any() else np.ones(len(cands))
    rr = np.where(np.isfinite(rr), rr, 1.0)
    narrow = np.array([c["left_out"] == "narrow" for c in cands], float)
    return np.column_stack([np.ones(len(cands)), np.clip(obs / np.maximum(expected, 1), 0, 1.5),
                            strong / np.maximum(obs, 1), np.clip(strong / np.maximum(expected, 1), 0, 1.5),
                            np.minimum(rr, 1.5), np.log(np.maximum(strong, 1)), narrow])


def fit_logistic(X: np.ndarray, y: np.ndarray, l2: float = 1e-2, iterations: int = 50) -> np.ndarray:
    """Weights of a logistic regression (Newton's method, a little L2 for flights whose classes separate)."""
    w = np.zeros(X.shape[1])
    for _ in range(iterations):
        p = 1.0 / (1.0 + np.exp(-X @ w))
        g = X.T @ (p - y) + l2 * w
        H = (X * (p * (1 - p))[:, None]).T @ X + l2 * np.eye(len(w))
        w -= np.linalg.solve(H, g)
    return w


def count_error(X: np.ndarray, truth: int, w: np.ndarray, t: float) -> float:
    return 100.0 * (int((1.0 / (1.0 + np.exp(-X @ w)) > t).sum()) - truth) / truth


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--replay", nargs=2, action="append", required=True, type=Path, metavar=("REPLAY", "FLIGHT"),
                    help="a replay's output folder and the simulated flight it replayed (at least 3)")
    a = ap.parse_args(argv)
    for out, path in a.replay:  # every input checked before any work: one line naming what is wrong
        try:
            FlightDir(path).meta()
        except FlightFormatError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        if not (out / "candidates.csv").is_file():
            print(f"error: {out / 'candidates.csv'}: missing (not a ground replay's output folder)", file=sys.stderr)
            return 2
    if len(a.replay) < 3:
        print("error: --replay: give at least 3 (a rule is fitted on all but one)", file=sys.stderr)
        return 2
    data = {}
    print(f"{'flight':<14} {'countable':>9} {'counted':>7} {'checks':>6} {'unfound':>7} {'(views)':>7} "
          f"{'partial':>7} {'false':>5} {'count':>5} {'err %':>6}")
    for out, path in a.replay:
        with open(out / "candidates.csv", newline="") as f:
            cands = list(csv.DictReader(f))
        lab = label_candidates(FlightDir(path), out)
        counted = np.array([c["left_out"] == "" for c in cands], bool)
        L, n = lab["label"], len(lab["countable"])
        unfound = lab["views"][~lab["found"]]
        print(f"{out.name:<14} {n:>9} {int((counted & (L == 'countable')).sum()):>7} "
              f"{int((~counted & (L == 'countable')).sum()):>6} {len(unfound):>7} "
              f"{float(np.median(unfound)) if len(unfound) else float('nan'):>7.0f} "
              f"{int((counted & (L == 'partial')).sum()):>7} {int((counted & (L == 'none')).sum()):>5} "
              f"{int(counted.sum()):>5} {100.0 * (counted.sum() - n) / n:>+6.1f}", flush=True)
        data[out.name] = (features(cands), (L == "countable").astype(float), n, 100.0 * (counted.sum() - n) / n)
    print(f"\nleave one flight out: a logistic rule on {', '.join(FEATURES)}")
    print(f"{'flight':<14} {'checks %':>8} {'rule %':>7} {'threshold':>9}")
    thresholds = np.linspace(0.05, 0.95, 91)
    errs = []
    for held in data:
        rest = [k for k in data if k != held]
        w = fit_logistic(np.vstack([data[k][0] for k in rest]), np.concatenate([data[k][1] for k in rest]))
        t = min(thresholds, key=lambda t: np.mean([count_error(data[k][0], data[k][2], w, t) ** 2 for k in rest]))
        e = count_error(data[held][0], data[held][2], w, t)
        errs.append((data[held][3], e))
        print(f"{held:<14} {data[held][3]:>+8.1f} {e:>+7.1f} {t:>9.2f}")
    e = np.array(errs)
    print(f"{'rms':<14} {np.sqrt((e[:, 0] ** 2).mean()):>8.1f} {np.sqrt((e[:, 1] ** 2).mean()):>7.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
