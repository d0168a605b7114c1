"""Quantize an exported detector to 8-bit integers (onnxruntime static quantization), for CPUs.

    python -m export quantize onboard/models/apple-detector.onnx --out out/export/int8/apple-detector.onnx

The convolutions with their ReLU6 (Clip), the pyramid's Resize and MaxPool (and, with ``--ops ...,Gemm``, the box
head's fully connected layers) get int8 weights, per output channel, and uint8 activations whose ranges are calibrated
on training data only:
ADD256 training patches and frames of a simulated training flight (never the scored test split nor the
held-out flights). The graph is QDQ: onnxruntime fuses each QuantizeLinear/DequantizeLinear pair with
its Conv into an integer kernel (VNNI on recent x86). The float model's metadata is copied with the
quantization recorded in it; score it again with ``python -m export evaluate --model`` before shipping.
"""

from __future__ import annotations

import json
import logging
import os
import tempfile
from pathlib import Path

import numpy as np

from pomar.cli import InputError

log = logging.getLogger(__name__)


class QuantizeError(InputError, ValueError):
    """A model or calibration input that cannot be quantized; the message names the file."""


def calibration_images(add256=None, sim_flights=(), add256_count: int = 24, sim_count: int = 8, seed: int = 0):
    """RGB uint8 images to calibrate on: ``add256_count`` ADD256 *training* patches and ``sim_count``
    frames spread over each simulated flight's video."""
    import cv2

    from export.data import add256_split, read_rgb

    rng = np.random.default_rng(seed)
    images = []
    if add256_count:
        train = add256_split(add256, "training")
        for i in sorted(rng.choice(len(train), min(add256_count, len(train)), replace=False)):
            images.append(read_rgb(train[i][0]))
    for flight in sim_flights:
        video = Path(flight) / "video.mp4"
        cap = cv2.VideoCapture(str(video))
        n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        if n <= 0:
            raise QuantizeError(f"{video}: no frames to calibrate on")
        for i in np.linspace(0, n - 1, sim_count).round().astype(int):
            cap.set(cv2.CAP_PROP_POS_FRAMES, int(i))
            ok, bgr = cap.read()
            if not ok:
                raise QuantizeError(f"{video}: cannot read frame {i}")
            images.append(cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB))
        cap.release()
    if not images:
        raise QuantizeError("no calibration images: give ADD256 or a simulated flight")
    return images


def float_model_metadata(model_path) -> dict:
    """The metadata of the float32 export at ``model_path``; QuantizeError naming the file if it is missing,
    already quantized, or an fp16 export (checked before any calibration image is read)."""
    from onboard.detector import read_metadata

    model_path = Path(model_path)
    if not model_path.is_file():
        raise QuantizeError(f"{model_path}: model file not found")
    meta = read_metadata(model_path)
    if "quantization" in meta:
        raise QuantizeError(f"{model_path}: already quantized (from {meta['quantization'].get('from')}); quantize the "
                         "float32 export")
    if "float16" in str(meta.get("weights", "")):
        # the fp16 file casts its weights to float32 inside the graph: the quantizer sees no weight initialisers
        raise QuantizeError(f"{model_path}: quantize a float32 export (python -m export onnx without --fp16)")
    return meta


def quantize(model_path, out_path, images, ops=("Conv", "Clip", "Resize", "MaxPool"), fp16: bool = False) -> dict:
    """Write the int8 model ``out_path`` (+ its ``.json`` metadata) calibrated on ``images`` (RGB uint8);
    ``fp16``: the weights left in float32 (the box head's, when only Conv is quantized) are stored as
    float16 with a Cast back, as ``python -m export onnx --fp16`` does."""
    from onnxruntime.quantization import (CalibrationDataReader, CalibrationMethod, QuantFormat, QuantType,
                                          quantize_static)
    from onnxruntime.quantization.shape_inference import quant_pre_process

    model_path, out_path = Path(model_path), Path(out_path)
    meta = float_model_metadata(model_path)
    input_name = meta["input"]["name"]

    class Reader(CalibrationDataReader):
        def __init__(self):
            self._it = iter(images)
            self.seen = 0

        def get_next(self):
            img = next(self._it, None)
            if img is None:
                return None
            self.seen += 1
            if self.seen % 8 == 0:
                log.info("calibrating: %d/%d images", self.seen, len(images))
            return {input_name: np.ascontiguousarray(img.transpose(2, 0, 1), np.float32) / 255.0}

    out_path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        pre = Path(tmp) / "pre.onnx"
        quant_pre_process(str(model_path), str(pre), skip_symbolic_shape=True)
        staged = Path(tmp) / "int8.onnx"
        quantize_static(str(pre), str(staged), Reader(), quant_format=QuantFormat.QDQ, op_types_to_quantize=list(ops),
                        per_channel=True, activation_type=QuantType.QUInt8, weight_type=QuantType.QInt8,
                        calibrate_method=CalibrationMethod.MinMax)
        if fp16:
            import onnx

            from export.onnx_weights import weights_to_fp16

            proto = weights_to_fp16(onnx.load(str(staged)))
            onnx.checker.check_model(proto)
            data = proto.SerializeToString()
        else:
            data = staged.read_bytes()
    import hashlib

    tmp_out = out_path.with_suffix(".onnx.tmp")
    tmp_out.write_bytes(data)
    os.replace(tmp_out, out_path)
    meta.update(file=out_path.name, sha256=hashlib.sha256(data).hexdigest(),
                weights=f"int8 per channel, uint8 activations (static QDQ quantization of {', '.join(ops)}; "
                        f"other weights {'float16, cast to float32 in the graph' if fp16 else 'float32'})",
                quantization={"from": model_path.name, "from_sha256": meta.get("sha256"), "ops": list(ops),
                              "calibration_images": len(images), "method": "MinMax"})
    meta.pop("metrics", None)  # the float model's scores are not this model's: score it again
    out_path.with_suffix(".json").write_text(json.dumps(meta, indent=1) + "\n")
    log.info("wrote %s (%.1f MB) and its metadata", out_path, len(data) / 1e6)
    return meta


def run(args) -> int:
    float_model_metadata(args.model)  # a wrong model is refused before the images are read
    images = calibration_images(args.add256, args.sim_flight, args.add256_images, args.sim_frames, args.seed)
    quantize(args.model, args.out, images, tuple(args.ops.split(",")), args.fp16)
    return 0
