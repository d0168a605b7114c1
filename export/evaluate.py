"""Score an ONNX detector through the onboard detector (what ships is what is scored); no torch needed.

    python -m export evaluate [--model FILE.onnx] [--sim-flight DIR] [--json OUT]

Datasets: the ADD256 test split (114 patches, 267 apples), AppleBBCH76's held-out photos (641 tiles of 51 photos,
at their own size, as ADD256's) where the dataset is found, and every ``--sim-every``-th frame of each
held-out simulated flight, where apples at least ``--min-visible`` visible are the truth and the
barely visible ones (5 % up to that) are ignored: found or not, they count neither way. Reports
COCO-style AP@0.5 and precision/recall/F1 at the operating threshold, per dataset, and the
detector's latency on those frames.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import numpy as np

from export.data import DataError, add256_split, applebbch76_split, load_sim_frames, read_rgb, yolo_boxes
from export.metrics import evaluate_detections
from pomar.cli import InputError
from pomar.countable import MIN_VISIBLE

log = logging.getLogger(__name__)


def score(detector, samples, score_thresh: float, progress_name: str) -> dict:
    preds, truths, times = [], [], []
    t_last = time.perf_counter()
    for i, (img, boxes, ignore, *scale) in enumerate(samples):
        t = time.perf_counter()
        # low threshold: AP needs the whole ranking
        b, s = detector.detect_rgb(img, score_thresh=0.05, scale=scale[0] if scale else 1.0)
        times.append(time.perf_counter() - t)
        preds.append((b, s))
        truths.append((boxes, ignore))
        if time.perf_counter() - t_last > 10:
            t_last = time.perf_counter()
            log.info("%s: %d images, %.2f s/image", progress_name, i + 1, float(np.mean(times)))
    m = evaluate_detections(preds, truths, score_thresh)
    m["seconds_per_image"] = round(float(np.mean(times)), 4) if times else None
    return m


def applebbch76_held_out(root):
    """(image, boxes, None) of AppleBBCH76's held-out tiles, or None where the dataset is not found (and not asked
    for: a folder given that is not one is an error)."""
    try:
        tiles = applebbch76_split(root, "held-out")
    except DataError:
        if root is not None:
            raise
        return None

    def items():
        for p in tiles:
            img = read_rgb(p)
            yield img, yolo_boxes(p.parent.parent / "labels" / f"{p.stem}.txt", img.shape[1], img.shape[0]), None
    return items()


def evaluate(model=None, add256=None, sim_flights=(), sim_every: int = 5, min_visible: float = MIN_VISIBLE,
             score_thresh: float | None = None, detector_scale: str = "auto", applebbch76=None,
             test: bool = True) -> dict:
    """Scores on ADD256's test split (its patches at their own size; not with ``test`` False), AppleBBCH76's held-out
    photos and simulated flights, whose frames are rescaled as the onboard node does (``detector_scale``: auto from
    each frame's telemetry, off, or a factor)."""
    from onboard.detector import OnnxDetector
    from pomar.apple_scale import flight_radius_px, policy_for
    from pomar.flight import FlightDir

    det = OnnxDetector(model)
    thresh = det.score_thresh if score_thresh is None else score_thresh
    policy = policy_for(det, detector_scale)
    out = {"model": str(det.path), "score_thresh": thresh, "detector_scale": detector_scale}
    if test:
        photos = ((read_rgb(p), b, None) for p, b in add256_split(add256, "test"))
        out["add256_test"] = score(det, photos, thresh, "ADD256 test")
    bbch = applebbch76_held_out(applebbch76)
    if bbch is not None:
        out["applebbch76_held_out"] = score(det, bbch, thresh, "AppleBBCH76 held out")
    for f in sim_flights:
        key = "sim" if f == sim_flights[0] else f"sim:{Path(f).name}"  # the first is the headline
        if str(f).endswith(".npz"):  # a pack of export pack: its frames and boxes as packed, at their own size
            frames = load_sim_frames(f, every=sim_every)
            scales = [1.0] * len(frames)
        else:
            frames = load_sim_frames(f, min_visible, every=sim_every)
            radius = flight_radius_px(FlightDir(f))
            scales = [policy.scale(float(radius[int(s.name.rsplit(":", 1)[1])])) for s in frames]
        out[key] = score(det, ((s.image, s.boxes, s.ignore, k) for s, k in zip(frames, scales)), thresh, key)
        out[key].update(flight=str(f), image_size=list(frames[0].image.shape[1::-1]) if frames else None,
                        scale_median=float(np.median(scales)) if scales else None)
    return out


def print_table(res: dict):
    print(f"model {res['model']}  (score threshold {res['score_thresh']})")
    print(f"{'dataset':<21}{'images':>7}{'apples':>8}{'AP50':>7}{'P':>7}{'R':>7}{'F1':>7}{'s/img':>8}{'partial':>9}")
    for k, m in res.items():
        if isinstance(m, dict):
            partial = f"{m['ignored_found']:>9.3f}" if "ignored_found" in m else f"{'-':>9}"
            print(f"{k:<21}{m['images']:>7}{m['apples']:>8}{m['ap50']:>7.3f}{m['precision']:>7.3f}"
                  f"{m['recall']:>7.3f}{m['f1']:>7.3f}{m['seconds_per_image']:>8.3f}{partial}")
    if any(isinstance(m, dict) and "ignored_found" in m for m in res.values()):
        print("partial: the share of the apples less visible than the definition asks (the ignored ones) that a "
              "detection at the threshold finds")


#: The operating thresholds tried.
THRESHOLDS = np.round(np.arange(0.3, 0.96, 0.05), 2)


def choose_threshold(model, samples, name: str) -> float:
    """The operating threshold: the best F1 over ``samples`` (image, boxes, ignore), on a 0.05 grid."""
    from export.metrics import best_f1_threshold
    from onboard.detector import OnnxDetector

    det = OnnxDetector(model)
    preds, truths = [], []
    for img, boxes, ignore in samples:
        preds.append(det.detect_rgb(img, score_thresh=0.05))
        truths.append((boxes, ignore))
    t = best_f1_threshold(preds, truths, THRESHOLDS)
    log.info("operating threshold %.2f: the best F1 on %d images of %s", t, len(preds), name)
    return t


def choose_threshold_on_sets(model, sets: dict[str, list]) -> tuple[float, dict]:
    """The operating threshold of best mean F1 over the validation ``sets`` (export.data.validation_sets), each image
    at its own size, and each set's F1 at it."""
    from onboard.detector import OnnxDetector

    det = OnnxDetector(model)
    runs = {}
    for name, samples in sets.items():
        preds = [det.detect_rgb(s.image, score_thresh=0.05) for s in samples]
        runs[name] = (preds, [(s.boxes, s.ignore) for s in samples])
        log.info("%s: %d images detected", name, len(samples))
    f1 = {float(t): {k: evaluate_detections(p, tr, float(t))["f1"] for k, (p, tr) in runs.items()} for t in THRESHOLDS}
    best = max(f1, key=lambda t: float(np.mean(list(f1[t].values()))))
    log.info("operating threshold %.2f: the best mean F1 (%.3f) over %s", best, np.mean(list(f1[best].values())),
             ", ".join(f"{k} {v:.3f}" for k, v in f1[best].items()))
    return best, f1[best]


def validation_samples(args):
    """The images the threshold is chosen on, and their name: a held-out simulated flight, or ADD256
    training patches (a fixed sample)."""
    if args.val_flight:
        frames = load_sim_frames(args.val_flight, args.min_visible, every=args.sim_every)
        return ((s.image, s.boxes, s.ignore) for s in frames), str(args.val_flight)
    items = add256_split(args.add256, "training")
    items = [items[i] for i in np.random.default_rng(0).permutation(len(items))[:args.val_add256]]
    return ((read_rgb(p), b, None) for p, b in items), f"{len(items)} ADD256 training patches"


def run(args) -> int:
    thresh, chosen_on = args.score_thresh, None
    if args.val_flight and args.val_add256 or args.val_sets and args.val_add256:
        raise InputError("--val-add256 chooses the threshold alone: not with --val-flight nor --val-sets")
    if args.val_sets:
        from export.data import find_applebbch76, validation_sets

        try:
            bbch = find_applebbch76(args.applebbch76)
        except DataError:
            if args.applebbch76 is not None:
                raise
            bbch = None
        sets = validation_sets(args.add256, bbch, [args.val_flight] if args.val_flight else [], bbch is not None)
        thresh, f1 = choose_threshold_on_sets(args.model, sets)
        chosen_on = "the best mean F1 over " + ", ".join(f"{k} ({len(sets[k])} images, F1 {v:.3f})"
                                                         for k, v in f1.items())
    elif args.val_flight or args.val_add256:
        samples, chosen_on = validation_samples(args)
        thresh = choose_threshold(args.model, samples, chosen_on)
    res = evaluate(args.model, args.add256, args.sim_flight, args.sim_every, args.min_visible, thresh,
                   args.detector_scale, args.applebbch76, args.test)
    if chosen_on:
        res["score_thresh_chosen_on"] = chosen_on
    print_table(res)
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(res, indent=1) + "\n")
    if args.write_metadata:
        meta_path = Path(res["model"]).with_suffix(".json")
        meta = json.loads(meta_path.read_text())
        meta["metrics"] = {k: v for k, v in res.items() if isinstance(v, dict)}
        meta["score_thresh"] = res["score_thresh"]
        if "score_thresh_chosen_on" in res:
            meta["score_thresh_chosen_on"] = res["score_thresh_chosen_on"]
        meta_path.write_text(json.dumps(meta, indent=1) + "\n")
        print(f"metrics stored in {meta_path}")
    return 0
