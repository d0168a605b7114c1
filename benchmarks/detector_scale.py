"""The detector's AP@0.5 against the scale frames are resized by before detection (issue 17), on simulated flights
and on ADD256's test split: where the model works best, and what the telemetry foresees for each flight.

    .venv/bin/python benchmarks/detector_scale.py out/sim/gen/tune-1 [more flights] [--add256]
        [--scales 0.5 0.75 1 1.25] [--every 8] [--model FILE.onnx] [--by-size] [--bands]

For each flight it prints the apple radius the telemetry foresees (pomar.apple_scale, median over frames), the
truth's median radius (apples at least half visible), and AP, precision, recall and F1 at each scale; with
``--add256``, the same for ADD256's test patches (radius about 6-13 px). With ``--bands``, also a scale per image
row instead of one per frame: each row at the scale that brings its own foreseen apple radius
(pomar.apple_scale.row_radius_px) to the model's, among ``--scales``. Accuracy only.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

from export.data import add256_split, load_sim_frames, read_rgb
from export.metrics import evaluate_detections, iou
from ground.evaluation.scoring import input_problem
from onboard.detector import OnnxDetector
from pomar.apple_scale import flight_radius_px, flight_telemetry, row_radius_px
from pomar.countable import visible
from pomar.flight import FlightDir


def sweep(det, samples, scales, name: str) -> None:
    for sc in scales:
        preds, truths = [], []
        for img, boxes, ignore in samples:
            preds.append(det.detect_rgb(img, score_thresh=0.05, scale=sc))
            truths.append((boxes, ignore))
        m = evaluate_detections(preds, truths, det.score_thresh)
        print(f"  {name:<16} scale {sc:>5.2f}: AP {m['ap50']:.3f}  P {m['precision']:.3f}  R {m['recall']:.3f}  "
              f"F1 {m['f1']:.3f}", flush=True)


def band_sweep(det, samples, row_radii, scales, name: str) -> None:
    """AP when each image row is detected at its own scale: the frame is detected at every scale in ``scales``, and a
    detection is kept from the scale nearest what its centre's row asks for (the model's radius over the row's)."""
    S = np.asarray(sorted(scales), float)
    detected = [[det.detect_rgb(img, score_thresh=0.05, scale=float(sc)) for sc in S] for img, _, _ in samples]
    for target in (det.apple_radius_px * 0.9, det.apple_radius_px, det.apple_radius_px * 1.1):
        preds, truths = [], []
        for (_, boxes, ignore), r_rows, per_scale in zip(samples, row_radii, detected):
            want = np.clip(target / np.where(np.isfinite(r_rows), r_rows, target), S[0], S[-1])
            row_scale = np.abs(S[None] - want[:, None]).argmin(1)  # index into S, per image row
            kept_b, kept_s = [], []
            for k, (b, sco) in enumerate(per_scale):
                rows = np.clip(((b[:, 1] + b[:, 3]) / 2).round().astype(int), 0, len(r_rows) - 1)
                keep = row_scale[rows] == k
                kept_b.append(b[keep])
                kept_s.append(sco[keep])
            preds.append((np.concatenate(kept_b), np.concatenate(kept_s)))
            truths.append((boxes, ignore))
        m = evaluate_detections(preds, truths, det.score_thresh)
        print(f"  {name:<16} bands to {target:.2f} px: AP {m['ap50']:.3f}  P {m['precision']:.3f}  R {m['recall']:.3f}"
              f"  F1 {m['f1']:.3f}  (row scales {S[row_scale].min():.2f}-{S[row_scale].max():.2f} in the last frame)",
              flush=True)


def recall_by_size(det, samples, scale: float, name: str, edges=(0, 3, 4, 5, 6, 8, 12, 99)) -> None:
    """Recall at the operating threshold of truth apples by their radius (px) as the model sees them (x scale): a
    truth box counts as found when a detection overlaps it at IoU 0.5 or more."""
    found, radius = [], []
    for img, boxes, _ in samples:
        b, _ = det.detect_rgb(img, scale=scale)
        if len(boxes):
            hit = (iou(np.asarray(boxes, float), b).max(1) >= 0.5) if len(b) else np.zeros(len(boxes), bool)
            found.append(hit)
            radius.append((boxes[:, 2] - boxes[:, 0]) / 2 * scale)
    found, radius = np.concatenate(found), np.concatenate(radius)
    cells = []
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = (radius >= lo) & (radius < hi)
        if sel.any():
            cells.append(f"{lo}-{hi} px: {found[sel].mean():.2f} ({int(sel.sum())})")
    print(f"  {name:<16} scale {scale:>5.2f}: recall by radius as the model sees it: " + "; ".join(cells), flush=True)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("flights", nargs="*", type=Path)
    p.add_argument("--add256", action="store_true", help="also ADD256's test split")
    p.add_argument("--scales", type=float, nargs="+", default=[0.5, 0.75, 1.0, 1.25])
    p.add_argument("--every", type=int, default=8, help="every Nth frame of each flight")
    p.add_argument("--model")
    p.add_argument("--by-size", action="store_true", help="also recall by apple radius, at each scale")
    p.add_argument("--bands", action="store_true", help="also a scale per image row, from the telemetry")
    a = p.parse_args(argv)
    for f in a.flights:  # every flight checked before the first one takes minutes
        problem = input_problem(f)
        if problem:
            print(f"error: {problem}", file=sys.stderr)
            return 2
    det = OnnxDetector(a.model)
    print(f"model {det.path.name}: apple_radius_px {det.apple_radius_px}, threshold {det.score_thresh}")
    for f in a.flights:
        flight = FlightDir(f)
        d = flight.truth_detections()
        truth_r = float(np.median(d["r_px"][visible(d["visible_fraction"])]))
        foreseen = float(np.nanmedian(flight_radius_px(flight)))
        print(f"{f.name}: {flight.camera().width}x{flight.camera().height}, apple radius foreseen {foreseen:.2f} px, "
              f"truth median {truth_r:.2f} px" + (f"; auto scale {det.apple_radius_px / foreseen:.2f}"
                                                  if det.apple_radius_px else ""))
        samples = load_sim_frames(f, 0.5, every=a.every)
        frames = [(s.image, s.boxes, s.ignore) for s in samples]
        sweep(det, frames, a.scales, f.name)
        if a.bands and det.apple_radius_px:
            cam, tel = flight.camera(), flight_telemetry(flight)
            idx = [int(s.name.rsplit(":", 1)[1]) for s in samples]
            band_sweep(det, frames, [row_radius_px(cam, tel["height"][i], tel["q_gimbal"][i]) for i in idx], a.scales,
                       f.name)
        if a.by_size:
            for sc in a.scales:
                recall_by_size(det, frames, sc, f.name)
    if a.add256:
        test = [(read_rgb(pth), b, None) for pth, b in add256_split(None, "test")]
        print(f"ADD256 test: {len(test)} patches")
        sweep(det, test, a.scales, "ADD256 test")
        if a.by_size:
            for sc in a.scales:
                recall_by_size(det, test, sc, "ADD256 test")
    return 0


if __name__ == "__main__":
    sys.exit(main())
