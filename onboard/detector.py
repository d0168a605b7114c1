"""The apple detector onboard: the exported Faster R-CNN run by onnxruntime (no torch).

    det = OnnxDetector()                      # the shipped model, CPU
    boxes, scores = det.detect(frame_index, bgr_image)

Boxes are ``x1, y1, x2, y2`` in OpenCV's pixel convention (the top-left pixel's centre is (0, 0)),
so an apple's centre is ``((x1 + x2) / 2, (y1 + y2) / 2)``; scores are in [0, 1] and only those at
least the model's operating threshold (its metadata, or ``score_thresh``) are returned.

Frames with a side larger than ``tile_size`` (``TILE_SIZE``) are cut into as few tiles as cover them, overlapping by
``overlap`` px. Each tile keeps the detections whose centre falls in its own share of the overlap (so an apple cut by
a tile border is reported by the tile that sees it whole, once), then a non-maximum suppression merges what is left.

The model file ships with a metadata file of the same name and ``.json`` suffix: input convention,
operating threshold, training data and metrics (see ``models/README.md``).
"""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

import numpy as np

from pomar import wire
from pomar.cli import InputError

log = logging.getLogger(__name__)

#: the largest side (px) run in one call: a 720p frame at x1.4 (1792 px) goes whole, the paper's 4K at x0.55 (2112 px)
#: as two tiles of 1104 px; a call's fixed costs (the proposals, the box head) are paid once per tile, an overlap twice
TILE_SIZE = 2048

MODEL_ENV = "POMAR_DETECTOR"
DEFAULT_MODEL = Path(__file__).resolve().parent / "models" / "apple-detector.onnx"


def resized(rgb: np.ndarray, scale: float) -> tuple[np.ndarray, np.ndarray]:
    """An image resized by ``scale`` as the detector is given it (pomar.apple_scale), and the factors (x, y, x, y)
    its width and height were resized by, for :func:`boxes_before_resize`."""
    import cv2

    h, w = rgb.shape[:2]
    size = (max(1, round(w * scale)), max(1, round(h * scale)))
    small = cv2.resize(rgb, size, interpolation=cv2.INTER_AREA if scale < 1 else cv2.INTER_LINEAR)
    return small, np.array([size[0] / w, size[1] / h, size[0] / w, size[1] / h], np.float32)


def boxes_before_resize(boxes: np.ndarray, factors: np.ndarray) -> np.ndarray:
    """Boxes found in a :func:`resized` image, in the original image's pixels. OpenCV's resize maps pixel centres:
    x_small = (x + 0.5) * s - 0.5."""
    return ((np.asarray(boxes, np.float32) + 0.5) / factors - 0.5).astype(np.float32)


class ModelError(InputError, RuntimeError):
    """A model file that is missing, corrupt or not one of ours; the message names the file."""


def default_model_path() -> Path:
    return Path(os.environ.get(MODEL_ENV) or DEFAULT_MODEL)


def read_metadata(model_path: Path) -> dict:
    meta_path = Path(model_path).with_suffix(".json")
    if not meta_path.is_file():
        raise ModelError(f"{meta_path}: the model's metadata file is missing (it ships next to {Path(model_path).name})")
    try:
        meta = json.loads(meta_path.read_text())
    except json.JSONDecodeError as e:
        raise ModelError(f"{meta_path}: not valid JSON ({e})") from None
    if meta.get("format") != "pomar-detector/1":
        raise ModelError(f"{meta_path}: not a pomar detector metadata file (format {meta.get('format')!r})")
    return meta


def nms(boxes: np.ndarray, scores: np.ndarray, iou_thresh: float) -> np.ndarray:
    """Indices kept by greedy non-maximum suppression, best score first."""
    import cv2

    if not len(boxes):
        return np.zeros(0, np.int64)
    xywh = np.column_stack([boxes[:, :2], boxes[:, 2:] - boxes[:, :2]]).astype(np.float32)
    keep = cv2.dnn.NMSBoxes(xywh.tolist(), scores.astype(np.float32).tolist(), 0.0, iou_thresh)
    return np.asarray(keep, np.int64).reshape(-1)


def tiles(width: int, height: int, size: int, overlap: int):
    """(x0, y0, x1, y1, own_x0, own_y0, own_x1, own_y1) per tile: the tile, and the area whose apples it owns."""
    def spans(n):
        if n <= size:
            return [(0, n)]
        # as few tiles as cover it, each as small as lets neighbours overlap by `overlap` (a tile of `size` each
        # would overlap by up to size - overlap px, and that area is computed twice)
        count = int(np.ceil((n - overlap) / (size - overlap)))
        tile = int(np.ceil((n + (count - 1) * overlap) / count))
        starts = np.linspace(0, n - tile, count).round().astype(int)
        return [(int(s), int(s) + tile) for s in starts]

    xs, ys = spans(width), spans(height)

    def owned(sp, i, n):
        lo = 0 if i == 0 else (sp[i - 1][1] + sp[i][0]) / 2
        hi = n if i == len(sp) - 1 else (sp[i][1] + sp[i + 1][0]) / 2
        return lo, hi

    for j, (y0, y1) in enumerate(ys):
        for i, (x0, x1) in enumerate(xs):
            ox0, ox1 = owned(xs, i, width)
            oy0, oy1 = owned(ys, j, height)
            yield x0, y0, x1, y1, ox0, oy0, ox1, oy1


class OnnxDetector:
    """Detect apples in frames of any size with the ONNX model (onnxruntime)."""

    name = "onnx"

    def __init__(self, model_path: str | os.PathLike | None = None, providers: list[str] | None = None,
                 score_thresh: float | None = None, tile_size: int = TILE_SIZE, overlap: int = 96,
                 nms_iou: float = 0.5, threads: int | None = None):
        import onnxruntime as ort

        self.path = Path(model_path) if model_path else default_model_path()
        if not self.path.is_file():
            raise ModelError(f"{self.path}: model file not found (set ${MODEL_ENV} or pass the path)")
        self.meta = read_metadata(self.path)
        opts = ort.SessionOptions()
        opts.log_severity_level = 3
        if threads:
            opts.intra_op_num_threads = threads
        # idle threads sleep instead of spinning between operators: the node shares its cores (video decoding, the
        # link, a ground in a replay), and spinning threads took CPU time that the other work needed
        opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
        available = ort.get_available_providers()
        wanted = providers or ["CPUExecutionProvider"]
        use = [p for p in wanted if p in available]
        if not use:
            raise ModelError(f"none of the execution providers {wanted} is available here ({available})")
        try:
            self.session = ort.InferenceSession(str(self.path), opts, providers=use)
        except Exception as e:  # onnxruntime raises its own exception types for bad files
            raise ModelError(f"{self.path}: onnxruntime cannot load it ({type(e).__name__}: {e})") from None
        self.providers = self.session.get_providers()
        self.input_name = self.session.get_inputs()[0].name
        self.score_thresh = float(score_thresh if score_thresh is not None else self.meta.get("score_thresh", 0.5))
        self.tile_size, self.overlap, self.nms_iou = int(tile_size), int(overlap), float(nms_iou)
        #: the apple radius (px) the model detects best, where the optical axis meets the canopy (its metadata;
        #: None: the model does not say, and frames go at their own size)
        self.apple_radius_px = self.meta.get("apple_radius_px")
        #: the smallest apple radius (px, as the model sees it) it finds reliably: its envelope (None: not said)
        self.min_apple_radius_px = self.meta.get("min_apple_radius_px")
        #: how its boxes answer an apple's size: (slope, intercept px) of box half-size against the true radius, as the
        #: model sees them (benchmarks/box_response.py; None: not said)
        r = self.meta.get("box_response")
        try:  # the limits the camera message that carries it checks (pomar.wire)
            self.box_response = None if r is None else wire.box_response_of([r["slope"], r["intercept_px"]],
                                                                             "box_response")
        except (KeyError, TypeError, wire.WireError) as exc:
            why = exc if isinstance(exc, wire.WireError) else \
                f'box_response must be {{"slope": number, "intercept_px": number}}, got {r!r:.60}'
            raise ModelError(f"{Path(self.path).with_suffix('.json')}: {why}") from None
        if self.overlap * 2 >= self.tile_size:
            raise ValueError("overlap must be less than half the tile size")

    def _run(self, rgb: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        x = np.ascontiguousarray(rgb.transpose(2, 0, 1), dtype=np.float32) / 255.0
        boxes, scores = self.session.run(None, {self.input_name: x})[:2]
        return boxes.reshape(-1, 4).astype(np.float32), scores.reshape(-1).astype(np.float32)

    def detect_rgb(self, rgb: np.ndarray, score_thresh: float | None = None,
                   scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """(boxes (N, 4), scores (N,)) of an RGB uint8 image, scores at least ``score_thresh``. With ``scale`` != 1
        the image is resized by it first (apples at the model's size, see pomar.apple_scale); the boxes are in the
        given image's pixels either way."""
        if rgb.ndim != 3 or rgb.shape[2] != 3:
            raise ValueError(f"expected an HxWx3 image, got shape {rgb.shape}")
        if scale != 1.0:
            small, factors = resized(rgb, scale)
            boxes, scores = self.detect_rgb(small, score_thresh)
            return boxes_before_resize(boxes, factors), scores
        thresh = self.score_thresh if score_thresh is None else score_thresh
        h, w = rgb.shape[:2]
        all_b, all_s = [], []
        parts = list(tiles(w, h, self.tile_size, self.overlap))
        for x0, y0, x1, y1, ox0, oy0, ox1, oy1 in parts:
            b, s = self._run(rgb[y0:y1, x0:x1])
            keep = s >= thresh
            b, s = b[keep] + np.array([x0, y0, x0, y0], np.float32), s[keep]
            if len(parts) > 1:
                cx, cy = (b[:, 0] + b[:, 2]) / 2, (b[:, 1] + b[:, 3]) / 2
                own = (cx >= ox0 - 0.5) & (cx < ox1 - 0.5) & (cy >= oy0 - 0.5) & (cy < oy1 - 0.5)
                b, s = b[own], s[own]
            all_b.append(b)
            all_s.append(s)
        boxes = np.concatenate(all_b) if all_b else np.zeros((0, 4), np.float32)
        scores = np.concatenate(all_s) if all_s else np.zeros(0, np.float32)
        if len(parts) > 1 and len(boxes):
            keep = nms(boxes, scores, self.nms_iou)
            boxes, scores = boxes[keep], scores[keep]
        order = np.argsort(-scores, kind="stable")
        return boxes[order], scores[order]

    def detect(self, frame: int, image: np.ndarray, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """Same call as the other onboard detectors: a frame index and its BGR image (OpenCV's order)."""
        return self.detect_rgb(np.ascontiguousarray(image[..., ::-1]), scale=scale)
