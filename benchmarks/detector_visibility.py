"""How visible an apple must be for the detector to find it at the count's score.

    python benchmarks/detector_visibility.py --replay out/bench/generalisation/np0/tune-1 out/sim/tune-1 \\
        --replay out/bench/generalisation/np0/tune-2 out/sim/gen/tune-2 ...
    python benchmarks/detector_visibility.py --flight out/sim/tune-1 --flight out/sim/gen/tune-2 [--model M.onnx]

For every apple in every frame of each simulated flight (its truth detections, with the share of the apple not hidden),
whether a detection scored at the count's confirm_score or more has its box centre within the apple's radius
(ground.evaluation.scoring.detected): the detections the ground received (``--replay``: the replay's journal.bin,
nothing run), or a model's (``--flight``: an ONNX model run on every ``--every``-th frame, scaled as the onboard node
scales them; to judge a candidate before it ships). The table
gives the share found per band of visibility, over all flights and per flight, and the visibility at which half are
found: the threshold the detector applies in effect, to set beside the definition's MIN_VISIBLE (pomar.countable).
Accuracy only.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ground.apples.counting import CountingSettings  # noqa: E402
from ground.evaluation.scoring import box_centres, found_by_visibility, input_problem, stream_detections  # noqa: E402
from pomar.countable import IGNORE_ABOVE, MIN_VISIBLE  # noqa: E402
from pomar.flight import FlightDir  # noqa: E402

EDGES = [IGNORE_ABOVE, 0.2, 0.3, 0.4, MIN_VISIBLE, 0.6, 0.7, 0.8, 0.9, 1.0 + 1e-9]


def model_detections(flight: FlightDir, det, scaling, score: float, every: int) -> dict[int, np.ndarray]:
    """Per every ``every``-th frame of the flight, the box centres of ``det``'s detections (an
    onboard.detector.OnnxDetector) scored ``score`` or more, at the scale ``scaling`` (pomar.apple_scale) gives it."""
    from pomar.apple_scale import flight_radius_px
    from pomar.video import iter_frames

    radius = flight_radius_px(flight)
    centres = {}
    for idx, bgr in iter_frames(flight.video):
        if idx % every:
            continue
        centres[idx] = box_centres(*det.detect(idx, bgr, scale=scaling.scale(float(radius[idx]))), score)
    return centres


def band_shares(vis: np.ndarray, found: np.ndarray, min_count: int = 20) -> np.ndarray:
    """The share found in each band of EDGES (NaN where the band holds fewer than ``min_count`` apples)."""
    return np.array([found[(vis >= lo) & (vis < hi)].mean() if ((vis >= lo) & (vis < hi)).sum() >= min_count
                     else np.nan for lo, hi in zip(EDGES[:-1], EDGES[1:])])


def crossing(share: np.ndarray, level: float = 0.5) -> float:
    """The visibility at which the shares per band (:func:`band_shares`) cross ``level`` (linear between the bands'
    middles); NaN if never."""
    mids = np.array([(lo + min(hi, 1.0)) / 2 for lo, hi in zip(EDGES[:-1], EDGES[1:])])
    ok = np.isfinite(share)
    mids, share = mids[ok], share[ok]
    for x0, y0, x1, y1 in zip(mids, share, mids[1:], share[1:]):
        if y0 < level <= y1:
            return float(x0 + (level - y0) * (x1 - x0) / (y1 - y0))
    return float("nan")


def half_found(vis: np.ndarray, found: np.ndarray) -> float:
    """The visibility at which the share found crosses one half (linear between the bands' middles); NaN if never."""
    return crossing(band_shares(vis, found))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--replay", nargs=2, action="append", metavar=("REPLAY", "FLIGHT"), default=[], type=Path,
                    help="a replay folder (its journal.bin) and the simulated flight it replayed (repeatable)")
    ap.add_argument("--flight", action="append", default=[], type=Path,
                    help="a simulated flight to run --model on instead (repeatable)")
    ap.add_argument("--model", type=Path, default=None, help="with --flight: the ONNX model (default: the shipped one)")
    ap.add_argument("--every", type=int, default=5, help="with --flight: every this many frames")
    ap.add_argument("--score", type=float, default=CountingSettings.confirm_score,
                    help="the score a detection needs (default: the count's confirm_score)")
    a = ap.parse_args(argv)
    if not a.replay and not a.flight:
        ap.error("give --replay REPLAY FLIGHT or --flight FLIGHT")
    # every input checked before any work: one line naming what is wrong
    for problem in [input_problem(p) for p in a.flight] + [input_problem(p, out, "journal.bin", "no recorded stream "
                                                                         "there") for out, p in a.replay]:
        if problem:
            print(f"error: {problem}", file=sys.stderr)
            return 2
    per = {}
    for out, path in a.replay:
        per[path.name] = found_by_visibility(FlightDir(path), stream_detections(out / "journal.bin", a.score))
        print(f"{path.name}: {len(per[path.name][0])} apples in frames read", file=sys.stderr, flush=True)
    if a.flight:
        from onboard.detector import OnnxDetector
        from pomar.apple_scale import policy_for

        det = OnnxDetector(a.model)
        scaling = policy_for(det, "auto")
        print(f"model {det.path}", flush=True)
        for path in a.flight:
            flight = FlightDir(path)
            per[path.name] = found_by_visibility(flight, model_detections(flight, det, scaling, a.score, a.every))
            print(f"{path.name}: {len(per[path.name][0])} apples in frames run", file=sys.stderr, flush=True)
    allv = np.concatenate([v for v, _ in per.values()])
    allf = np.concatenate([f for _, f in per.values()])
    bands = [f"{lo:.2f}-{min(hi, 1.0):.2f}" for lo, hi in zip(EDGES[:-1], EDGES[1:])]
    print(f"share of the apples in a frame found at score >= {a.score} (apples in the band), by visible share")
    print(f"{'flight':<14}" + "".join(f"{b:>13}" for b in bands) + f"{'half at':>9}")
    for name, (v, f) in [*per.items(), ("all", (allv, allf))]:
        cells = []
        for lo, hi in zip(EDGES[:-1], EDGES[1:]):
            sel = (v >= lo) & (v < hi)
            cells.append(f"{f[sel].mean():>6.2f} ({sel.sum():>4})" if sel.any() else f"{'-':>13}")
        print(f"{name:<14}" + "".join(f"{c:>13}" for c in cells) + f"{half_found(v, f):>9.2f}")
    print(f"the definition: an apple counts in a frame at {MIN_VISIBLE} visible (pomar.countable.MIN_VISIBLE)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
