"""python -m export SUBCOMMAND: train the apple detector, export it to ONNX, score it (needs the `export` extra).

  train     train the torchvision Faster R-CNN from scratch (ADD256 + simulated crops), checkpointed
  pack      a simulated flight's frames and truth boxes in one .npz, for training where the video cannot go
  onnx      export a checkpoint to ONNX (dynamic height and width, native resolution) with its metadata
  quantize  8-bit static quantization of an exported float32 model (faster on CPUs), calibrated on training data
  evaluate  AP@0.5 and P/R/F1 on the ADD256 test split and a held-out simulated flight, via onnxruntime
"""

import argparse
import logging
from pathlib import Path

from pomar import cli
from pomar.apple_scale import SCALE_HELP, scale_argument
from pomar.countable import MIN_VISIBLE
from pomar.settings import add_options


def train_arguments(p: argparse.ArgumentParser):
    from export.settings import TRAIN_FIELDS, TrainSettings

    add_options(p, TrainSettings(), TRAIN_FIELDS)


def pack_arguments(p: argparse.ArgumentParser):
    from export.settings import PackSettings, fields_of

    p.add_argument("flight", type=Path, help="a simulated flight folder (video and truth/detections.csv)")
    add_options(p, PackSettings(), fields_of(PackSettings))


def onnx_arguments(p: argparse.ArgumentParser):
    from export.settings import OnnxSettings, fields_of

    p.add_argument("checkpoint", type=Path, help="a checkpoint of python -m export train (best.pt / last.pt, or a "
                                                 "folder of fp16 parts)")
    add_options(p, OnnxSettings(), fields_of(OnnxSettings))


def quantize_arguments(p: argparse.ArgumentParser):
    from export.settings import QuantizeSettings, fields_of

    p.add_argument("model", type=Path, help="a float32 ONNX model of python -m export onnx (not --fp16)")
    add_options(p, QuantizeSettings(), fields_of(QuantizeSettings))


def evaluate_arguments(p: argparse.ArgumentParser):
    from export.settings import EvaluateSettings, fields_of

    add_options(p, EvaluateSettings(), fields_of(EvaluateSettings))
    # the truth's visibility is pomar.countable's, and the detector scale's option pomar.apple_scale's
    p.add_argument("--min-visible", type=float, default=MIN_VISIBLE,
                   help="simulated apples at least this visible are truth; less visible ones are ignored")
    p.add_argument("--detector-scale", type=scale_argument, default="auto",
                   help="simulated frames: " + SCALE_HELP + " (ADD256's patches go at their own size)")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m export", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", title="subcommands")
    t = sub.add_parser("train", help="train the detector")
    o = sub.add_parser("onnx", help="export a checkpoint to ONNX")
    q = sub.add_parser("quantize", help="8-bit static quantization of an exported model")
    e = sub.add_parser("evaluate", help="score an ONNX model through the onboard detector")
    k = sub.add_parser("pack", help="pack a simulated flight's frames and boxes into one .npz")
    train_arguments(t)
    pack_arguments(k)
    onnx_arguments(o)
    quantize_arguments(q)
    evaluate_arguments(e)
    args = p.parse_args(argv)
    if args.cmd is None:
        p.print_help()
        return 2
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(levelname)s %(name)s: %(message)s", datefmt="%H:%M:%S")
    # Imported only now: torch is needed by train and onnx, not by --help, quantize nor evaluate.
    if args.cmd == "train":
        from export.train import run
    elif args.cmd == "onnx":
        from export.onnx_export import run
    elif args.cmd == "pack":
        from export.data import run_pack as run
    elif args.cmd == "quantize":
        from export.quantize import run
    else:
        from export.evaluate import run
    return cli.run(run, args)


if __name__ == "__main__":
    cli.exit_with(main)
