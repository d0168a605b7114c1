"""Detector latency: onnxruntime (what runs onboard) against torch, per frame, at 1280x720 and 1920x1080 (and 4K).

    python benchmarks/detector_latency.py [--model onboard/models/apple-detector.onnx --model OTHER.onnx ...]
                                          [--checkpoint out/export/resnet18/best.pt] [--repeats 5] [--json OUT]
                                          [--size 3840x2160 ...] [--scale 1.4 ...] [--own-scale]

``--scale S`` also times the frame resized by S first, as the onboard node does to bring apples to the model's size
(``--detector-scale``; a 4K frame from 12 m goes at about 0.55, the bundled flight's 720p at about 1.4 for today's
model). ``--own-scale`` also times each model at its own scale: the bundled flight's median apple brought to that
model's ``apple_radius_px``, as ``--detector-scale auto`` would (the 4K size at the paper's 12 m takes the same ratio).
Several ``--model``s are timed in one run, one after another on each frame, so that their ratios hold whatever
else the machine does.

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
BUNDLED = ROOT / "replay_data" / "demo-flight"
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
    p.add_argument("--model", action="append", help="an ONNX model (repeatable; default: the shipped one)")
    p.add_argument("--checkpoint", type=Path, default=ROOT / "out" / "export" / "resnet18" / "best.pt")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--threads", type=int, help="onnxruntime and torch threads (default: all cores)")
    p.add_argument("--json", type=Path)
    p.add_argument("--size", action="append", help="frame sizes WxH (default 1280x720 and 1920x1080)")
    p.add_argument("--scale", type=float, action="append", default=[], help="also time frames resized by this")
    p.add_argument("--tile-size", type=int, help="frames larger than this are tiled (default: the detector's)")
    p.add_argument("--own-scale", action="store_true", help="also time each model at its own scale on the bundled "
                   "flight (its apple_radius_px over the flight's median apple radius)")
    args = p.parse_args(argv)
    if args.model and len(args.model) > 1:
        return compare(args)
    sizes = [tuple(int(v) for v in s.split("x")) for s in args.size] if args.size else SIZES
    frame = read_frame(ROOT / "replay_data" / "demo-flight" / "video.mp4", 80)
    det = OnnxDetector(args.model[0] if args.model else None, threads=args.threads,
                       **({"tile_size": args.tile_size} if args.tile_size else {}))
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
        for sc in args.scale + ([own_scale(det)] if args.own_scale else []):
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


def own_scale(det) -> float:
    """The scale ``--detector-scale auto`` gives the bundled flight's median frame for ``det``'s apple size."""
    from pomar.apple_scale import flight_radius_px, policy_for
    from pomar.flight import FlightDir

    return round(policy_for(det, "auto").scale(float(np.median(flight_radius_px(FlightDir(BUNDLED))))), 3)


def _short(path: Path) -> str:
    """A model's path, relative to the repository where it lies inside it."""
    try:
        return str(Path(path).resolve().relative_to(ROOT))
    except ValueError:
        return str(path)


def compare(args) -> int:
    """Several models in one run: each size and scale timed for every model in turn, medians, and each model's time
    as a ratio of the first model's."""
    sizes = [tuple(int(v) for v in s.split("x")) for s in args.size] if args.size else SIZES
    frame = read_frame(BUNDLED / "video.mp4", 80)
    dets = [OnnxDetector(m, threads=args.threads, **({"tile_size": args.tile_size} if args.tile_size else {}))
            for m in args.model]
    res = {"models": [str(d.path) for d in dets], "threads": args.threads, "tile_size": dets[0].tile_size, "rows": []}
    for w, h in sizes:
        img = cv2.resize(frame, (w, h), interpolation=cv2.INTER_LINEAR)
        scales = [(f"x{sc:g}", [sc] * len(dets)) for sc in args.scale]
        if args.own_scale:
            scales.append(("own", [own_scale(d) for d in dets]))
        for label, per_model in scales or [("x1", [1.0] * len(dets))]:
            times = [[] for _ in dets]
            for d, sc in zip(dets, per_model):
                d.detect(0, img, sc)  # warm-up
            for _ in range(args.repeats):  # interleaved, so that a busy moment falls on every model alike
                for k, (d, sc) in enumerate(zip(dets, per_model)):
                    t = time.perf_counter()
                    d.detect(0, img, sc)
                    times[k].append(time.perf_counter() - t)
            med = [float(np.median(t)) for t in times]
            for d, sc, t in zip(dets, per_model, med):
                row = {"size": f"{w}x{h}", "scale": label, "model": d.path.name, "model_path": str(d.path),
                       "factor": sc, "seconds": round(t, 4), "speedup_vs_first": round(med[0] / t, 2)}
                res["rows"].append(row)
                print(f"{w}x{h} {label:>6} (x{sc:.3g}) {_short(d.path)}: {t:.3f} s/frame, "
                      f"{med[0] / t:.2f} times the first model's speed", flush=True)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(res, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
