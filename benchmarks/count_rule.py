"""Where a flight's count error comes from, and whether a rule learned from the count's candidates would do better
than today's checks (issue 40): read from replays already made, nothing replayed.

    python benchmarks/count_rule.py --replay out/bench/generalisation/g2b/tune-1 out/sim/tune-1 \\
        --replay out/bench/generalisation/g2b/tune-2 out/sim/gen/tune-2 ...

For each replay, every apple the count was chosen from (candidates.csv) is labelled against the truth on the map's
shape (ground.evaluation.scoring.label_candidates): countable, partial (a true apple the definition does not count)
or none. The table gives the countable apples the replay counted, those the checks left out, those no candidate
found (and the median of their countable views), and the partial and false apples counted: a count error is what is
left of these. ``misp``: candidates counted / left out that no apple lies within 0.10 m of but that lie on a real
apple's rays (placed off in depth; below the table, how many of those counted lie on an apple the definition does
not count, and how many on one another candidate also counts); ``on ray``: the countable apples no candidate found
that such a one lies on. Of the countable apples no candidate found, ``strong 3+`` had a detection scored at the count's confirm_score or more (a
box centre within the apple's radius, at least 2 px) in 3 or more of their countable views (the stream's
journal.bin): the ground lost or misplaced those (below the table: the angle their strong views meet at, from the
true cameras, and how many lie at the flight's ends); the detector, the rest. ``share``: the share of those apples'
countable views in which the detector found them so.

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

from ground.evaluation.scoring import detected, input_problem, label_candidates, stream_detections  # noqa: E402
from pomar.countable import MIN_VISIBLE  # noqa: E402
from pomar.flight import FlightDir  # noqa: E402

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


def strong_views(flight: FlightDir, journal: Path, apple_ids: np.ndarray, score: float) -> list[list[int]]:
    """Per apple (``apple_ids``): the frames of its countable views (at least MIN_VISIBLE visible) in which the stream
    carries a detection scored ``score`` or more whose box centre lies within the apple's radius (at least 2 px)."""
    from pomar.countable import visible

    d = flight.truth_detections()
    want = visible(d["visible_fraction"]) & np.isin(d["apple_id"], apple_ids)
    d = {k: np.asarray(d[k])[want] for k in ("frame", "apple_id", "u", "v", "r_px")}
    found = detected(d, stream_detections(journal, score))
    frames: dict[int, list[int]] = {int(a): [] for a in apple_ids}
    for f, a in zip(d["frame"][found], d["apple_id"][found]):
        frames[int(a)].append(int(f))
    return [frames[int(a)] for a in apple_ids]


def parallax_deg(R: np.ndarray, t: np.ndarray, X: np.ndarray, frames: list[int]) -> float:
    """The angle (deg) at the true apple ``X`` between the true camera centres (``R``, ``t``: the flight's truth poses)
    of the first and last of these frames."""
    u, v = (-R[f].T @ t[f] - X for f in (min(frames), max(frames)))
    return float(np.degrees(np.arccos(np.clip(u @ v / (np.linalg.norm(u) * np.linalg.norm(v)), -1.0, 1.0))))


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
        problem = input_problem(path, out, "candidates.csv", "missing (not a ground replay's output folder)")
        if problem:
            print(f"error: {problem}", file=sys.stderr)
            return 2
    if len(a.replay) < 3:
        print("error: --replay: give at least 3 (a rule is fitted on all but one)", file=sys.stderr)
        return 2
    data, partial = {}, []
    misp_rays = {"partial": 0, "countable": 0, "twice": 0}  # what the counted misplaced apples lie on
    lost_parallax, lost_at_ends = [], 0  # the countable apples detected strongly 3+ times that no candidate found
    found_parallax = []  # ... and those a candidate found
    from ground.apples.counting import CountingSettings

    confirm = CountingSettings().confirm_score
    print(f"{'flight':<14} {'countable':>9} {'counted':>7} {'checks':>6} {'unfound':>7} {'(views)':>7} {'on ray':>6} "
          f"{'strong 3+':>9} {'share':>5} {'partial':>7} {'misp':>9} {'false':>5} {'count':>5} {'err %':>6}")
    for out, path in a.replay:
        with open(out / "candidates.csv", newline="") as f:
            cands = list(csv.DictReader(f))
        lab = label_candidates(FlightDir(path), out)
        counted = np.array([c["left_out"] == "" for c in cands], bool)
        L, n = lab["label"], len(lab["countable"])
        unfound = lab["views"][~lab["found"]]
        fl, ids = FlightDir(path), lab["countable"][~lab["found"]]
        every = (strong_views(fl, out / "journal.bin", lab["countable"], confirm)
                 if (out / "journal.bin").is_file() else [[] for _ in lab["countable"]])
        views = [v for v, f in zip(every, lab["found"]) if not f]
        strong = np.array([len(v) for v in views], int)
        lost = strong >= 3
        share = strong.sum() / max(unfound.sum(), 1) if len(strong) else float("nan")
        n_frames = fl.meta().frame_count
        R, t = fl.truth_poses()
        ta = fl.truth_apples()
        where = {int(i): np.array([x, y, z]) for i, x, y, z in zip(ta["apple_id"], ta["x"], ta["y"], ta["z"])}
        for a, v in zip(ids, views):
            if len(v) >= 3:
                lost_parallax.append(parallax_deg(R, t, where[int(a)], v))
                lost_at_ends += min(v) < 0.1 * n_frames or max(v) > 0.9 * n_frames
        found_parallax += [parallax_deg(R, t, where[int(a)], v)
                           for a, v, f in zip(lab["countable"], every, lab["found"]) if f and len(v) >= 3]
        on_ray = int(np.isin(ids, lab["ray_apple"]).sum())
        print(f"{out.name:<14} {n:>9} {int((counted & (L == 'countable')).sum()):>7} "
              f"{int((~counted & (L == 'countable')).sum()):>6} {len(unfound):>7} "
              f"{float(np.median(unfound)) if len(unfound) else float('nan'):>7.0f} {on_ray:>6} {int(lost.sum()):>9} "
              f"{share:>5.2f} {int((counted & (L == 'partial')).sum()):>7} "
              f"{int((counted & (L == 'misplaced')).sum()):>4}/{int((~counted & (L == 'misplaced')).sum()):<4} "
              f"{int((counted & (L == 'none')).sum()):>5} {int(counted.sum()):>5} "
              f"{100.0 * (counted.sum() - n) / n:>+6.1f}",
              flush=True)
        data[out.name] = (features(cands), (L == "countable").astype(float), n, 100.0 * (counted.sum() - n) / n)
        partial += [(FlightDir(path), a) for a in lab["apple_id"][counted & (L == "partial")]]
        rays = lab["ray_apple"][counted & (L == "misplaced")]
        on_countable = np.isin(rays, lab["countable"])
        misp_rays["countable"] += int(on_countable.sum())
        misp_rays["partial"] += int((~on_countable).sum())
        misp_rays["twice"] += int(np.isin(rays, lab["apple_id"][counted]).sum())
    print(f"\nmisplaced and counted: {sum(misp_rays[k] for k in ('partial', 'countable'))}; on the rays of a partial "
          f"apple (one the definition does not count) {misp_rays['partial']}, of a countable one "
          f"{misp_rays['countable']}; of an apple another counted candidate matched too {misp_rays['twice']}")
    if lost_parallax:
        print(f"\ndetected strongly 3+ times, no candidate: {len(lost_parallax)}; their strong views meet at a median "
              f"{np.median(lost_parallax):.1f} deg (10th-90th percentile {np.percentile(lost_parallax, 10):.1f}-"
              f"{np.percentile(lost_parallax, 90):.1f}); {lost_at_ends} in the flight's first or last tenth; "
              f"those a candidate found, a median {np.median(found_parallax):.1f} deg")
    best, seen30 = [], []
    for flight, a in partial:  # how visible the partial apples counted are at best, and in how many frames 30 %
        d = flight.truth_detections()
        v = np.asarray(d["visible_fraction"], float)[np.asarray(d["apple_id"]) == a]
        best.append(v.max() if len(v) else np.nan)
        seen30.append(int((v >= 0.3).sum()))
    best = np.array(best)
    print(f"\npartial apples counted: {len(best)}; never {MIN_VISIBLE:.0%} visible: {int((best < MIN_VISIBLE).sum())}; "
          f"at best a median {np.nanmedian(best):.0%} visible; 30 % or more in a median {np.median(seen30):.0f} frames")
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
