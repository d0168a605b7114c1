"""Detector latency: onnxruntime (what runs onboard) against torch, per frame, at 1280x720 and 1920x1080 (and 4K).

    python benchmarks/detector_latency.py [--model onboard/models/apple-detector.onnx]
                                          [--checkpoint out/export/resnet18/best.pt] [--repeats 5] [--json OUT]
                                          [--size 3840x2160 ...] [--scale 0.55 ...]

``--scale S`` also times the frame resized by S first, as the onboard node does to bring apples to the model's size
(``--detector-scale``; a 4K frame from 12 m goes at about 0.55).

Frames are real: the bundled flight's frame 80, resized to each size. onnxruntime runs through the
onboard detector class (tiling included: 1920x1080 is two tiles at the default tile size); torch
runs the checkpoint the model was exported from (needs the export extra; skipped without it).
Median of ``--repeats`` runs after one warm-up. Run it with nothing else on the machine.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np

from onboard.detector import OnnxDetector
from pomar.video import read_frame

ROOT = Path(__file__).resolve().parents[1]
SIZES = [(1280, 720), (1920, 1080)]


def median_time(fn, repeats: int) -> float:
    fn()
    ts = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return float(np.median(ts))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model")
    p.add_argument("--checkpoint", type=Path, default=ROOT / "out" / "export" / "resnet18" / "best.pt")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--threads", type=int, help="onnxruntime and torch threads (default: all cores)")
    p.add_argument("--json", type=Path)
    p.add_argument("--size", action="append", help="frame sizes WxH (default 1280x720 and 1920x1080)")
    p.add_argument("--scale", type=float, action="append", default=[], help="also time frames resized by this")
    args = p.parse_args(argv)
    sizes = [tuple(int(v) for v in s.split("x")) for s in args.size] if args.size else SIZES
    frame = read_frame(ROOT / "replay_data" / "demo-flight" / "video.mp4", 80)
    det = OnnxDetector(args.model, threads=args.threads)
    res = {"model": str(det.path), "providers": det.providers, "tile_size": det.tile_size, "sizes": {}}
    torch_model = None
    if args.checkpoint.is_file():
        try:
            import torch

            from export.model import load_checkpoint

            if args.threads:
                torch.set_num_threads(args.threads)
            torch_model = load_checkpoint(args.checkpoint)[0].eval()
        except ImportError:
            print("torch not installed: onnxruntime only")
    for w, h in sizes:
        img = cv2.resize(frame, (w, h), interpolation=cv2.INTER_LINEAR)
        r = {"onnxruntime_s": median_time(lambda: det.detect(0, img), args.repeats),
             "detections": int(len(det.detect(0, img)[0]))}
        for sc in args.scale:
            r[f"onnxruntime_scale_{sc:g}_s"] = t = median_time(lambda: det.detect(0, img, sc), args.repeats)
            print(f"{w}x{h} resized by {sc:g}: onnxruntime {t:.3f} s/frame")
        if torch_model is not None:
            x = torch.from_numpy(np.ascontiguousarray(img[..., ::-1].transpose(2, 0, 1))).float() / 255

            def run_torch():
                with torch.no_grad():
                    torch_model([x])

            r["torch_s"] = median_time(run_torch, args.repeats)
        res["sizes"][f"{w}x{h}"] = r
        print(f"{w}x{h}: onnxruntime {r['onnxruntime_s']:.3f} s/frame ({1 / r['onnxruntime_s']:.2f} fps)"
              + (f", torch {r['torch_s']:.3f} s/frame" if "torch_s" in r else "") + f", {r['detections']} detections")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(res, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
