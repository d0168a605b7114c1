"""ADD256's label ceiling (issue 40): the shipped model's highest-scoring false positives on the test split, drawn for a
person to judge, and the AP again with those judged unlabelled apples ignored.

    python benchmarks/label_ceiling.py [--top 48] [--out out/bench/label-ceiling]
    python benchmarks/label_ceiling.py --apples 0 3 7 ...      # the sheet's numbers judged apples nobody circled

A false positive is a detection (score >= 0.05, onnxruntime, patches at their own size) that matches no circled apple
at IoU 0.5. The ``--top`` highest-scoring ones go on ``sheet.png``, numbered, each a 64-px crop around its box (box in
yellow, circled apples in cyan) enlarged 3x. Judged by eye: an apple nobody circled, or not. With ``--apples``, those
boxes join the ignore set (neither found nor false) and AP@0.5 is scored again: how much of the gap to a perfect score
is the labels', not the model's. Accuracy only.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from export.data import add256_split, read_rgb  # noqa: E402
from export.metrics import evaluate_detections, iou  # noqa: E402
from onboard.detector import OnnxDetector  # noqa: E402

CROP, ZOOM = 64, 3


def false_positives(preds, truths, iou_thresh: float = 0.5) -> list[tuple[float, int, np.ndarray]]:
    """(score, image index, box) of every detection that matches no truth box, highest score first."""
    out = []
    for k, ((boxes, scores), truth) in enumerate(zip(preds, truths)):
        m = iou(boxes, truth).max(axis=1) if len(truth) and len(boxes) else np.zeros(len(boxes))
        out += [(float(s), k, b) for b, s, v in zip(boxes, scores, m) if v < iou_thresh]
    return sorted(out, key=lambda x: -x[0])


def sheet(fps, images, truths, top: int, cols: int = 8) -> np.ndarray:
    tiles = []
    for n, (s, k, b) in enumerate(fps[:top]):
        img = cv2.cvtColor(images[k], cv2.COLOR_RGB2BGR)
        cx, cy = (b[0] + b[2]) / 2, (b[1] + b[3]) / 2
        x0 = int(np.clip(cx - CROP / 2, 0, img.shape[1] - CROP))
        y0 = int(np.clip(cy - CROP / 2, 0, img.shape[0] - CROP))
        tile = cv2.resize(img[y0:y0 + CROP, x0:x0 + CROP], None, fx=ZOOM, fy=ZOOM, interpolation=cv2.INTER_NEAREST)
        for t in truths[k]:
            cv2.rectangle(tile, tuple(int(ZOOM * (v - o)) for v, o in zip(t[:2], (x0, y0))),
                          tuple(int(ZOOM * (v - o)) for v, o in zip(t[2:], (x0, y0))), (255, 255, 0), 1)
        cv2.rectangle(tile, (int(ZOOM * (b[0] - x0)), int(ZOOM * (b[1] - y0))),
                      (int(ZOOM * (b[2] - x0)), int(ZOOM * (b[3] - y0))), (0, 255, 255), 1)
        cv2.putText(tile, f"{n} {s:.2f}", (3, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (255, 255, 255), 1, cv2.LINE_AA)
        tiles.append(tile)
    while len(tiles) % cols:
        tiles.append(np.zeros_like(tiles[0]))
    return np.vstack([np.hstack(tiles[i:i + cols]) for i in range(0, len(tiles), cols)])


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", default=None, help="ONNX model (default: the shipped one)")
    p.add_argument("--add256", default=None)
    p.add_argument("--top", type=int, default=48)
    p.add_argument("--apples", type=int, nargs="*", default=None, help="the sheet's numbers judged unlabelled apples")
    p.add_argument("--out", type=Path, default=ROOT / "out" / "bench" / "label-ceiling")
    a = p.parse_args(argv)
    det = OnnxDetector(a.model)
    items = add256_split(a.add256, "test")
    images = [read_rgb(path) for path, _ in items]
    truths = [np.asarray(b, float).reshape(-1, 4) for _, b in items]
    preds = [det.detect_rgb(img, score_thresh=0.05) for img in images]
    fps = false_positives(preds, truths)
    a.out.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(a.out / "sheet.png"), sheet(fps, images, truths, a.top))
    base = evaluate_detections(preds, [(t, None) for t in truths], det.score_thresh)
    above = sum(s >= det.score_thresh for s, _, _ in fps)
    print(f"ADD256 test: {len(images)} patches, {sum(map(len, truths))} circled apples; AP@0.5 {base['ap50']:.3f}, "
          f"P {base['precision']:.3f}, R {base['recall']:.3f} at the operating threshold {det.score_thresh:g}")
    print(f"false positives: {len(fps)} from score 0.05, {above} at the operating threshold; the top {a.top} drawn on "
          f"{a.out / 'sheet.png'}")
    res = {"ap50": base["ap50"], "precision": base["precision"], "recall": base["recall"], "false_positives": len(fps),
           "false_positives_at_threshold": above}
    if a.apples is not None:
        ignore = [[] for _ in images]
        for n in a.apples:
            _, k, b = fps[n]
            ignore[k].append(b)
        again = evaluate_detections(preds, [(t, np.array(ig, float).reshape(-1, 4) if ig else None)
                                            for t, ig in zip(truths, ignore)], det.score_thresh)
        print(f"with the {len(a.apples)} judged unlabelled apples of the top {a.top} ignored: AP@0.5 "
              f"{again['ap50']:.3f}, P {again['precision']:.3f}, R {again['recall']:.3f}")
        res.update(judged_apples=list(a.apples), top=a.top, ap50_without_them=again["ap50"],
                   precision_without_them=again["precision"])
    (a.out / "ceiling.json").write_text(json.dumps(res, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
