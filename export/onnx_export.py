"""Export a trained detector to ONNX: one RGB image of any height and width in, boxes and scores out.

    python -m export onnx out/export/resnet18/best.pt --out onboard/models/apple-detector.onnx --fp16

The graph takes ``image``: float32 (3, H, W), RGB in [0, 1], at native resolution (the model's
transform never resizes), and gives ``boxes`` (N, 4) x1 y1 x2 y2 in OpenCV pixels of that image and
``scores`` (N,). Exported with the legacy TorchScript-based exporter (``dynamo=False``), which handles
torchvision's detection ops. ``--fp16`` stores the weights as float16 with a Cast to float32 in
front of each (half the file, float32 arithmetic). The export checks torch against onnxruntime on the
float32 graph, on an image of a size other than the trace's, and refuses to write a model whose boxes
differ by more than 0.01 px (MobileNetV3's hard-swish rounds differently in onnxruntime: 0.003 px); with ``--fp16`` it then reports how the fp16 graph's boxes agree with the
float32 graph's. What the rounding costs in accuracy: ``python -m export evaluate`` on both files.
Metadata (input convention, threshold, training run, metrics) goes to the same name with ``.json``.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
import tempfile
from pathlib import Path

import numpy as np
import torch
from torch import nn

from export.model import load_checkpoint
from export.onnx_weights import weights_to_fp16

log = logging.getLogger(__name__)

TRACE_SIZE = (256, 320)  # (H, W) of the dummy input the graph is traced with


class SingleImage(nn.Module):
    """(3, H, W) tensor in, (boxes, scores) out: the ONNX graph's signature."""

    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, image):
        out = self.model([image])[0]
        return out["boxes"], out["scores"]


def fp16_agreement(boxes, scores, hboxes, hscores, score_thresh: float) -> dict:
    """How the fp16-weight graph's detections above ``score_thresh`` compare with the fp32 graph's:
    the share of fp32 boxes found again (IoU >= 0.9) and the largest coordinate change among those."""
    from export.metrics import iou

    a, b = boxes[scores >= score_thresh], hboxes[hscores >= score_thresh]
    if not len(a):
        return {"boxes": 0, "boxes_fp16": int(len(b))}
    m = iou(a, b) if len(b) else np.zeros((len(a), 0))
    found = m.max(1) >= 0.9 if len(b) else np.zeros(len(a), bool)
    j = m.argmax(1) if len(b) else np.zeros(len(a), int)
    diff = float(np.abs(a[found] - b[j[found]]).max()) if found.any() else float("nan")
    return {"boxes": int(len(a)), "boxes_fp16": int(len(b)), "found_again": round(float(found.mean()), 4),
            "max_box_diff_px": round(diff, 4)}


def parity_image(h: int, w: int, seed: int = 0) -> torch.Tensor:
    """A textured test image with apple-like red discs (so a model's scores are not all equal)."""
    rng = np.random.default_rng(seed)
    img = rng.uniform(0.2, 0.5, (3, h, w)).astype(np.float32)
    img[1] += 0.15
    yy, xx = np.mgrid[:h, :w]
    for _ in range(12):
        cx, cy, r = rng.uniform(0, w), rng.uniform(0, h), rng.uniform(4, 14)
        m = (xx - cx) ** 2 + (yy - cy) ** 2 < r * r
        img[0][m], img[1][m], img[2][m] = 0.8, 0.15, 0.1
    return torch.from_numpy(img)


def detection_set_difference(tb: np.ndarray, ts: np.ndarray, ob: np.ndarray, os_: np.ndarray) -> tuple[float, float]:
    """How far two detection sets are apart whatever their order (boxes of near-equal scores can come out in either
    order): the largest distance (px, in any coordinate) from a box of either set to the nearest box of the other,
    and the largest score difference between those nearest boxes."""
    if not len(tb):
        return 0.0, 0.0
    from scipy.spatial import cKDTree

    d1, j1 = cKDTree(ob).query(tb, p=np.inf)
    d2, j2 = cKDTree(tb).query(ob, p=np.inf)
    box = float(max(d1.max(), d2.max()))
    score = float(max(np.abs(ts - os_[j1]).max(), np.abs(os_ - ts[j2]).max()))
    return box, score


def export_onnx(model, path: Path, opset: int = 17, fp16: bool = False, check: torch.Tensor | None = None,
                metadata: dict | None = None, score_thresh: float = 0.5, max_box_diff_px: float = 1e-2) -> dict:
    """Write ``path`` (+ ``.json``) and return the parity report of torch vs onnxruntime."""
    import onnx
    import onnxruntime as ort

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    model.eval()
    wrapper = SingleImage(model).eval()
    dummy = parity_image(*TRACE_SIZE, seed=1)
    with tempfile.TemporaryDirectory() as tmp:
        raw = Path(tmp) / "model.onnx"
        torch.onnx.export(wrapper, (dummy,), str(raw), opset_version=opset, input_names=["image"],
                          output_names=["boxes", "scores"],
                          dynamic_axes={"image": {1: "height", 2: "width"}, "boxes": {0: "n"}, "scores": {0: "n"}},
                          dynamo=False)
        proto = onnx.load(str(raw))
    onnx.checker.check_model(proto)
    data = proto.SerializeToString()
    # Parity at a size other than the trace size.
    img = check if check is not None else parity_image(300, 420, seed=2)
    with torch.no_grad():
        tb, ts = (t.numpy() for t in wrapper(img))
    sess = ort.InferenceSession(data, providers=["CPUExecutionProvider"])
    ob, os_ = sess.run(None, {"image": img.numpy()})
    report = {"torch_boxes": int(len(tb)), "onnx_boxes": int(len(ob)), "image_hw": list(img.shape[1:])}
    if len(tb) != len(ob):
        report["max_box_diff_px"] = float("inf")
    else:
        report["max_box_diff_px"], report["max_score_diff"] = detection_set_difference(tb, ts, ob, os_)
    if report["max_box_diff_px"] > max_box_diff_px:
        raise RuntimeError(f"ONNX and torch disagree on {report}: not writing {path}")
    if fp16:
        proto = weights_to_fp16(proto)
        onnx.checker.check_model(proto)
        data = proto.SerializeToString()
        hb, hs = ort.InferenceSession(data, providers=["CPUExecutionProvider"]).run(None, {"image": img.numpy()})
        report["fp16"] = fp16_agreement(ob, os_, hb, hs, score_thresh)
    tmp_path = path.with_suffix(".onnx.tmp")
    tmp_path.write_bytes(data)
    os.replace(tmp_path, path)
    meta = {
        "format": "pomar-detector/1",
        "file": path.name,
        "sha256": hashlib.sha256(data).hexdigest(),
        "input": {"name": "image", "shape": ["3", "height", "width"], "dtype": "float32", "channels": "RGB",
                  "range": [0.0, 1.0], "resolution": "native (no resize inside the graph)"},
        "outputs": {"boxes": "float32 (N, 4) x1 y1 x2 y2", "scores": "float32 (N,) in [0, 1]"},
        "pixel_convention": "OpenCV: the top-left pixel's centre is (0, 0)",
        "score_thresh": score_thresh,
        "opset": opset,
        "weights": "float16 (cast to float32 in the graph)" if fp16 else "float32",
        "parity": report,
    }
    meta.update(metadata or {})
    path.with_suffix(".json").write_text(json.dumps(meta, indent=1) + "\n")
    log.info("wrote %s (%.1f MB) and its metadata; parity %s", path, len(data) / 1e6, report)
    return report


def run(args) -> int:
    model, ckpt = load_checkpoint(args.checkpoint)
    model.rpn._post_nms_top_n["testing"] = args.proposals
    check = None
    if args.check_image:
        from export.data import read_rgb

        check = torch.from_numpy(read_rgb(args.check_image).transpose(2, 0, 1).copy()).float() / 255
    meta = {"model": {**ckpt["config"], "proposals": args.proposals},
            "training": {**ckpt.get("run", {}), "iteration": ckpt["iteration"], "checkpoint": str(args.checkpoint)},
            "training_history": ckpt.get("history", [])}
    export_onnx(model, args.out, args.opset, args.fp16, check, meta, args.score_thresh)
    return 0
