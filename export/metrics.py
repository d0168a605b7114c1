"""Detection metrics: COCO-style AP at IoU 0.5 and precision/recall/F1 at a score threshold (numpy only).

Truth boxes may come with *ignore* boxes (apples mostly hidden by leaves in simulated frames): a
detection that matches one is neither a true nor a false positive, as COCO treats its crowd regions.
"""

from __future__ import annotations

import numpy as np


def iou(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """IoU matrix (len(a), len(b)) of x1 y1 x2 y2 boxes."""
    a = np.asarray(a, np.float64).reshape(-1, 4)
    b = np.asarray(b, np.float64).reshape(-1, 4)
    lt = np.maximum(a[:, None, :2], b[None, :, :2])
    rb = np.minimum(a[:, None, 2:], b[None, :, 2:])
    inter = np.prod((rb - lt).clip(0), axis=2)
    area_a = np.prod(a[:, 2:] - a[:, :2], axis=1)
    area_b = np.prod(b[:, 2:] - b[:, :2], axis=1)
    return inter / np.maximum(area_a[:, None] + area_b[None, :] - inter, 1e-12)


def match_image(boxes, scores, truth, ignore=None, iou_thresh: float = 0.5):
    """Greedy matching by descending score. Returns (scores, is_tp) of the detections not ignored."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)
    scores = np.asarray(scores, np.float64).reshape(-1)
    order = np.argsort(-scores, kind="stable")
    boxes, scores = boxes[order], scores[order]
    m = iou(boxes, truth)
    taken = np.zeros(len(truth), bool)
    tp = np.zeros(len(boxes), bool)
    keep = np.ones(len(boxes), bool)
    ig = iou(boxes, ignore) if ignore is not None and len(ignore) else None
    for i in range(len(boxes)):
        if len(truth):
            cand = np.where(~taken, m[i], -1.0)
            j = int(np.argmax(cand))
            if cand[j] >= iou_thresh:
                taken[j] = True
                tp[i] = True
                continue
        if ig is not None and ig[i].max() >= iou_thresh:
            keep[i] = False
    return scores[keep], tp[keep]


def ignored_found(boxes, scores, truth, ignore, score_thresh: float, iou_thresh: float = 0.5) -> int:
    """How many ignore boxes (apples less visible than the definition asks) a detection at ``score_thresh`` or more
    finds (IoU ``iou_thresh``) that matched no truth box: the partial apples a detector finds at its operating point."""
    if ignore is None or not len(ignore):
        return 0
    keep = np.asarray(scores, np.float64).reshape(-1) >= score_thresh
    boxes = np.asarray(boxes, np.float64).reshape(-1, 4)[keep]
    truth = np.asarray(truth, np.float64).reshape(-1, 4)
    if len(truth) and len(boxes):
        boxes = boxes[iou(boxes, truth).max(1) < iou_thresh]  # those that found a countable apple do not count here
    if not len(boxes):
        return 0
    return int((iou(np.asarray(ignore, np.float64).reshape(-1, 4), boxes).max(1) >= iou_thresh).sum())


def evaluate_detections(predictions, truths, score_thresh: float, iou_thresh: float = 0.5) -> dict:
    """``predictions``: [(boxes, scores)]; ``truths``: [(boxes, ignore_boxes_or_None)] per image. With ignore boxes,
    ``ignored_found`` is the share of them a detection at ``score_thresh`` finds (:func:`ignored_found`)."""
    all_s, all_tp = [], []
    n_truth = n_ignore = n_ignore_found = 0
    tp_at = fp_at = 0
    for (boxes, scores), (truth, ignore) in zip(predictions, truths, strict=True):
        truth = np.asarray(truth, np.float64).reshape(-1, 4)
        n_truth += len(truth)
        s, tp = match_image(boxes, scores, truth, ignore, iou_thresh)
        all_s.append(s)
        all_tp.append(tp)
        # Precision/recall at the operating threshold: match only what passes it.
        keep = np.asarray(scores) >= score_thresh
        s2, tp2 = match_image(np.asarray(boxes).reshape(-1, 4)[keep], np.asarray(scores)[keep], truth, ignore, iou_thresh)
        tp_at += int(tp2.sum())
        fp_at += int((~tp2).sum())
        if ignore is not None:
            n_ignore += len(np.asarray(ignore).reshape(-1, 4))
            n_ignore_found += ignored_found(boxes, scores, truth, ignore, score_thresh, iou_thresh)
    s = np.concatenate(all_s) if all_s else np.zeros(0)
    tp = np.concatenate(all_tp) if all_tp else np.zeros(0, bool)
    ap = average_precision(s, tp, n_truth)
    precision = tp_at / max(tp_at + fp_at, 1)
    recall = tp_at / max(n_truth, 1)
    f1 = 2 * precision * recall / max(precision + recall, 1e-12)
    return {"ap50": round(ap, 4), "precision": round(precision, 4), "recall": round(recall, 4), "f1": round(f1, 4),
            "images": len(truths), "apples": n_truth, "score_thresh": score_thresh,
            **({"ignored": n_ignore, "ignored_found": round(n_ignore_found / n_ignore, 4)} if n_ignore else {})}


def average_precision(scores: np.ndarray, tp: np.ndarray, n_truth: int) -> float:
    """COCO's 101-point interpolated AP."""
    if n_truth == 0:
        return float("nan")
    order = np.argsort(-scores, kind="stable")
    tp = tp[order]
    ctp = np.cumsum(tp)
    cfp = np.cumsum(~tp)
    recall = ctp / n_truth
    precision = ctp / np.maximum(ctp + cfp, 1)
    # Precision envelope (monotone non-increasing from the right).
    precision = np.maximum.accumulate(precision[::-1])[::-1] if len(precision) else precision
    pts = np.linspace(0, 1, 101)
    idx = np.searchsorted(recall, pts, side="left")
    vals = np.where(idx < len(precision), precision[np.minimum(idx, max(len(precision) - 1, 0))] if len(precision) else 0, 0.0)
    return float(np.mean(vals))


def best_f1_threshold(predictions, truths, candidates=np.linspace(0.3, 0.95, 14)) -> float:
    """The score threshold of best F1 among ``candidates`` (for choosing the operating point on held-out data)."""
    best = max(candidates, key=lambda t: evaluate_detections(predictions, truths, float(t))["f1"])
    return float(best)
