"""Where a detector hits and misses on real photos (issue 70, the model card's pictures): AppleBBCH76's held-out tiles
(the real-photo check's handful: every 16th, never trained on) through the ONNX file at its own threshold, each
apple's box drawn green where a detection finds it (IoU 0.5), blue where none does, and red a detection that finds no
labelled apple. The tiles of best and worst F1 go side by side on one sheet.

    python benchmarks/detector_pictures.py [--model FILE.onnx] [--tiles 3] [--out out/bench/detector-pictures.jpg]

Accuracy only; prints each tile's F1 and counts.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from export.data import applebbch76_split, read_rgb, yolo_boxes  # noqa: E402
from export.metrics import iou  # noqa: E402
from onboard.detector import OnnxDetector  # noqa: E402

#: The real-photo check's handful (tests/test_detector.py): every 16th held-out tile.
EVERY = 16
GREEN, BLUE, RED = (0, 200, 0), (255, 140, 0), (0, 0, 255)  # BGR


def matched(boxes: np.ndarray, truth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(each detection found an apple, each apple was found): greedy by the given order, IoU 0.5."""
    hit, found = np.zeros(len(boxes), bool), np.zeros(len(truth), bool)
    m = iou(np.asarray(boxes, float).reshape(-1, 4), truth)
    for i in range(len(boxes)):
        if len(truth):
            cand = np.where(~found, m[i], -1.0)
            j = int(np.argmax(cand))
            if cand[j] >= 0.5:
                found[j] = hit[i] = True
    return hit, found


def draw(img: np.ndarray, boxes, hit, truth, found, title: str, size: int = 420) -> np.ndarray:
    out = cv2.cvtColor(img, cv2.COLOR_RGB2BGR)
    for b, ok in zip(truth, found):
        cv2.rectangle(out, (int(b[0]), int(b[1])), (int(b[2]), int(b[3])), GREEN if ok else BLUE, 2)
    for b, ok in zip(boxes, hit):
        if not ok:
            cv2.rectangle(out, (int(b[0]), int(b[1])), (int(b[2]), int(b[3])), RED, 2)
    k = size / max(out.shape[:2])
    out = cv2.resize(out, (int(out.shape[1] * k), int(out.shape[0] * k)), interpolation=cv2.INTER_AREA)
    canvas = np.full((size + 24, size, 3), 255, np.uint8)
    canvas[24:24 + out.shape[0], :out.shape[1]] = out
    cv2.putText(canvas, title, (4, 17), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    return canvas


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", default=None, help="ONNX model (default: the shipped one)")
    p.add_argument("--applebbch76", default=None)
    p.add_argument("--tiles", type=int, default=3, help="tiles of best and of worst F1 on the sheet")
    p.add_argument("--out", type=Path, default=ROOT / "out" / "bench" / "detector-pictures.jpg")
    a = p.parse_args(argv)
    det = OnnxDetector(a.model)
    runs = []
    for path in applebbch76_split(a.applebbch76, "held-out")[::EVERY]:
        img = read_rgb(path)
        truth = yolo_boxes(path.parent.parent / "labels" / f"{path.stem}.txt", img.shape[1], img.shape[0])
        boxes, _ = det.detect_rgb(img)  # the model's own threshold, best first
        hit, found = matched(boxes, truth)
        tp = int(found.sum())
        f1 = 2 * tp / max(len(boxes) + len(truth), 1)
        runs.append((f1, path, img, boxes, hit, truth, found))
        print(f"{path.name}: F1 {f1:.2f}, {tp} of {len(truth)} apples found, {int((~hit).sum())} false", flush=True)
    runs = [r for r in runs if len(r[5])]
    runs.sort(key=lambda r: r[0])
    pick = runs[-a.tiles:][::-1] + runs[:a.tiles]
    panels = [draw(img, b, h, t, f, f"{path.stem}: F1 {f1:.2f}, {int(f.sum())}/{len(t)} found, {int((~h).sum())} false")
              for f1, path, img, b, h, t, f in pick]
    rows = [np.hstack(panels[i:i + a.tiles]) for i in range(0, len(panels), a.tiles)]
    a.out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(a.out), np.vstack(rows), [cv2.IMWRITE_JPEG_QUALITY, 70])
    print(f"{a.out}: the {a.tiles} tiles of best F1 (top) and of worst (bottom) of {len(runs)}, model "
          f"{det.path.name} at its threshold {det.score_thresh}; green found, blue missed, red false")
    return 0


if __name__ == "__main__":
    sys.exit(main())
