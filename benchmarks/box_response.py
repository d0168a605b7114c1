"""How the detector's boxes answer an apple's size (issue 59's fruit sizes): each detection of a replay matched to the
apple it lies on (its centre within the truth's radius), its box's half-size against the apple's true radius, both in
the pixels the detector saw (the frame's detector scale), by the apple's true radius and by its visible share; and the
line box = slope x radius + intercept through the wholly seen ones (visible share above 0.9), with its margin in the
detector's pixels, and with it in the frame's own pixels (box = slope x radius + frame intercept x scale: the margin
of a box is the frame's blur, which the detector sees shrunk on a 4K frame it takes at 0.65 and grown on a 720p one it
takes at 1.4).

    python benchmarks/box_response.py out/yield/tune-1 out/yield/runs/tune-1/map out/yield/tune-2 out/yield/runs/tune-2/map
    python benchmarks/box_response.py ... --write onboard/models/apple-detector.json   # the model's box_response

Arguments come in pairs: a simulated flight and the folder of its replay (whose journal.bin holds the detections the
drone sent). A slope under 1 means the boxes pull sizes towards a middle one: small apples read large, large ones
small, and a row's fruit size reads by how far it was from the camera, not only by its fruit. ``--write`` stores the
wholly seen line in the model's metadata (``box_response``): the drone sends it, and the ground takes its fruit sizes
back through it (ground/apples/counting.py). Measure it again for every model shipped, on tuning flights of each
resolution. The frame-margin line is printed for comparison only: it evens the flights out, but on the tuning flights
and the spent fourth evaluation set its rows' diameters came out no better, and 0.7 mm worse on the latter
(docs/benchmarks.md, twenty-first session), so no model carries it.

Beside it: the line through the views the ground sizes each apple from (its largest tenth by size), and the fruit-size
estimate over the true size (median over apples) under no line, the wholly seen one and that one, by flight and by the
apple's radius in the detector's pixels: how far the estimate still depends on the flight (its light, its frames) and on
the range.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from ground.link.journal import read_journal  # noqa: E402
from pomar import wire  # noqa: E402
from pomar.flight import FlightDir  # noqa: E402

#: Detections scored at least this are matched (the onboard node's publishing threshold is lower).
SCORE = 0.5
#: Apples at least this visible are "wholly seen" for the line.
WHOLE = 0.9
#: Apples with fewer matched views are left out of the estimator's line (the ground sizes an apple it has confirmed).
MIN_VIEWS = 5


def matched_boxes(flight: Path, replay: Path) -> np.ndarray:
    """(n, 5): per detection on an apple, the apple's true radius and the box's half-size (detector px), the apple's
    visible share, its id (made unique across flights by the caller) and the frame's detector scale."""
    from scipy.spatial import cKDTree

    d = FlightDir(flight).truth_detections()
    frame = np.asarray(d["frame"]).astype(int)
    out = []
    for payload in read_journal(replay / "journal.bin"):
        m = wire.decode(payload)
        if not isinstance(m, wire.FrameMessage):
            continue
        b = np.asarray(m.boxes, float).reshape(-1, 4)[np.asarray(m.scores, float).reshape(-1) >= SCORE]
        sel = frame == m.frame
        if not sel.any() or not len(b):
            continue
        s = float(m.scale or 1.0)
        u, v, r, vis, ids = (np.asarray(d[k], float)[sel] for k in ("u", "v", "r_px", "visible_fraction", "apple_id"))
        dist, k = cKDTree(np.c_[u, v]).query(np.c_[(b[:, 0] + b[:, 2]) / 2, (b[:, 1] + b[:, 3]) / 2])
        on = dist < r[k]
        half = (b[:, 2] - b[:, 0] + b[:, 3] - b[:, 1]) / 4
        out.append(np.c_[r[k[on]] * s, half[on] * s, vis[k[on]], ids[k[on]], np.full(int(on.sum()), s)])
    return np.concatenate(out) if out else np.zeros((0, 5))


def by_apple(a: np.ndarray, min_views: int = MIN_VIEWS) -> list[np.ndarray]:
    """The rows of ``a`` (matched_boxes') of each apple with ``min_views`` views or more (the ground sizes an apple it
    has confirmed)."""
    order = np.argsort(a[:, 3], kind="stable")
    return [idx for idx in np.split(order, np.nonzero(np.diff(a[order, 3]))[0] + 1) if len(idx) >= min_views]


def top_tenth(a: np.ndarray, idx: np.ndarray, slope: float, icpt: float,
              frame_icpt: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Of one apple's views (rows ``idx``), the largest tenth by size, each box taken back through the line as
    ground/apples/counting.py does (ranking by the size over the true radius in the detector's pixels is its ranking
    by size in metres): (those rows, their sizes over the true radius)."""
    size = np.maximum(a[idx, 1] - icpt - frame_icpt * a[idx, 4], 0.0) / slope / a[idx, 0]
    top = np.argsort(size)[-max(1, len(idx) // 10):]
    return idx[top], size[top]


def estimator_line(a: np.ndarray, slope: float, icpt: float, rounds: int = 5) -> tuple[float, float, int]:
    """The line through the views the ground sizes apples from (each apple's top tenth), refitted until the views it
    picks stay: what the fruit-size estimate answers, where the wholly seen boxes' line is what one box answers (a
    tenth picked by size also picks the boxes that came out large)."""
    groups = by_apple(a)
    top = np.zeros(0, int)
    for _ in range(rounds):
        top = np.concatenate([top_tenth(a, g, slope, icpt)[0] for g in groups]) if groups else np.zeros(0, int)
        if len(top) < 10:
            break
        slope, icpt = np.polyfit(a[top, 0], a[top, 1], 1)
    return float(slope), float(icpt), int(len(top))


def estimate_ratio(a: np.ndarray, slope: float, icpt: float, frame_icpt: float = 0.0) -> float:
    """The median over apples of the size estimate (the median of its top tenth) over the true size, under a line."""
    out = [np.median(top_tenth(a, g, slope, icpt, frame_icpt)[1]) for g in by_apple(a)]
    return float(np.median(out)) if out else float("nan")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("pairs", nargs="+", help="FLIGHT REPLAY_OUT [FLIGHT REPLAY_OUT ...]")
    p.add_argument("--write", metavar="MODEL_JSON", help="store the line as this model metadata's box_response")
    args = p.parse_args(argv)
    if len(args.pairs) % 2:
        p.error("give each flight with its replay's folder (pairs)")
    flights = [(Path(f), Path(o)) for f, o in zip(args.pairs[::2], args.pairs[1::2])]
    parts = [matched_boxes(f, o) for f, o in flights]
    for k, part in enumerate(parts):
        part[:, 3] += k * 10_000_000  # apple ids unique across flights
    a = np.concatenate(parts)
    if not len(a):
        print("no detection lies on an apple")
        return 1
    print(f"{len(a)} detections on apples; box half-size over the true radius (detector px), median:")
    print(f"{'true radius px':>15} {'n':>6} {'box / r':>8} {'wholly seen':>12}")
    for lo in range(1, 12):
        s = (a[:, 0] >= lo) & (a[:, 0] < lo + 1)
        w = s & (a[:, 2] > WHOLE)
        if s.sum() >= 10:
            print(f"{f'{lo}-{lo + 1}':>15} {int(s.sum()):>6} {np.median(a[s, 1] / a[s, 0]):>8.3f} "
                  f"{np.median(a[w, 1] / a[w, 0]) if w.sum() >= 5 else float('nan'):>12.3f}")
    print(f"{'visible share':>15} {'n':>6} {'box / r':>8}")
    for lo, hi in ((0.0, 0.3), (0.3, 0.5), (0.5, 0.7), (0.7, 0.9), (0.9, 1.01)):
        s = (a[:, 2] >= lo) & (a[:, 2] < hi)
        if s.sum():
            print(f"{f'{lo:.1f}-{min(hi, 1.0):.1f}':>15} {int(s.sum()):>6} {np.median(a[s, 1] / a[s, 0]):>8.3f}")
    w = a[:, 2] > WHOLE
    if w.sum() < 10:
        print("too few wholly seen apples for a line")
        return 1
    slope, icpt = np.polyfit(a[w, 0], a[w, 1], 1)
    print(f"wholly seen (visible > {WHOLE}, n {int(w.sum())}): box = {slope:.3f} x radius + {icpt:.3f} px "
          f"(rms {np.sqrt(np.mean((slope * a[w, 0] + icpt - a[w, 1]) ** 2)):.3f})")
    (f_slope, f_icpt), *_ = np.linalg.lstsq(np.c_[a[w, 0], a[w, 4]], a[w, 1], rcond=None)
    print(f"the same, its margin in the frame's pixels: box = {f_slope:.3f} x radius + {f_icpt:.3f} px x scale "
          f"(rms {np.sqrt(np.mean((f_slope * a[w, 0] + f_icpt * a[w, 4] - a[w, 1]) ** 2)):.3f})")
    e_slope, e_icpt, n_top = estimator_line(a, slope, icpt)
    print(f"the views the ground sizes apples from (each apple's largest tenth, {n_top} views): box = {e_slope:.3f} x "
          f"radius + {e_icpt:.3f} px")
    lines = {"identity": (1.0, 0.0, 0.0), "wholly seen": (slope, icpt, 0.0), "frame margin": (f_slope, 0.0, f_icpt),
             "estimator": (e_slope, e_icpt, 0.0)}
    print("the fruit-size estimate over the true size (median over apples), by flight and by the apple's median radius:")
    print(f"{'':>22}" + "".join(f"{k:>13}" for k in lines))
    for (f, _), part in zip(flights, parts):
        print(f"{f.name:>22}" + "".join(f"{estimate_ratio(part, *ln):>13.3f}" for ln in lines.values()))
    px = {int(a[g[0], 3]): float(np.median(a[g, 0])) for g in by_apple(a, 1)}
    for lo in range(2, 10):
        keep = np.isin(a[:, 3], [i for i, r in px.items() if lo <= r < lo + 1])
        if np.unique(a[keep, 3]).size >= 10:
            print(f"{f'{lo}-{lo + 1} px':>22}" + "".join(f"{estimate_ratio(a[keep], *ln):>13.3f}" for ln in lines.values()))
    if args.write:
        meta = json.loads(Path(args.write).read_text())
        meta["box_response"] = {"slope": round(float(slope), 3), "intercept_px": round(float(icpt), 3),
                                "measured": f"benchmarks/box_response.py, {int(w.sum())} boxes of wholly seen "
                                            f"apples on {', '.join(f.name for f, _ in flights)}"}
        Path(args.write).write_text(json.dumps(meta, indent=1) + "\n")
        print(f"written to {args.write}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
