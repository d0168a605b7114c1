"""python -m export SUBCOMMAND: train the apple detector, export it to ONNX, score it (needs the `export` extra).

  train     train the torchvision Faster R-CNN from scratch (ADD256 + simulated crops), checkpointed
  pack      a simulated flight's frames and truth boxes in one .npz, for training where the video cannot go
  onnx      export a checkpoint to ONNX (dynamic height and width, native resolution) with its metadata
  quantize  8-bit static quantization of an exported float32 model (faster on CPUs), calibrated on training data
  evaluate  AP@0.5 and P/R/F1 on the ADD256 test split and a held-out simulated flight, via onnxruntime
"""

import argparse
import logging
import sys
from pathlib import Path

from pomar.apple_scale import SCALE_HELP, scale_argument
from pomar.countable import MIN_VISIBLE


def train_arguments(p: argparse.ArgumentParser):
    p.add_argument("--out", type=Path, default=Path("out/export/resnet18"), help="run folder (checkpoints, history)")
    p.add_argument("--add256", help="ADD256 folder (default: $POMAR_ADD256, then the workplace's shared copy)")
    p.add_argument("--sim-flight", action="append", default=[], type=Path,
                   help="simulated flight folder(s) to crop training patches from (repeatable)")
    p.add_argument("--backbone", default="resnet18", choices=["resnet18", "resnet50", "mobilenet_v3_large"])
    p.add_argument("--fpn-channels", type=int, default=128)
    p.add_argument("--epochs", type=int, default=8)
    p.add_argument("--batch", type=int, default=4)
    p.add_argument("--lr", type=float, default=0.01)
    p.add_argument("--sim-crops", type=int, default=400, help="simulated crops per epoch")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=int, help="torch CPU threads")
    p.add_argument("--checkpoint-every", type=int, default=100)
    p.add_argument("--max-minutes", type=float, help="stop (checkpointed, resumable) after this long")
    p.add_argument("--resume", action="store_true", help="continue from OUT/last.pt")
    p.add_argument("--init", type=Path, metavar="CKPT",
                   help="start from this checkpoint's weights with a fresh optimiser and schedule (a second cycle)")
    p.add_argument("--add256-scale", type=float, nargs=2, default=(0.45, 1.3), metavar=("LO", "HI"),
                   help="random scale range of ADD256 patches (default 0.45 1.3: down to the simulated flights' "
                        "apple sizes; 0.8 1.25 to train for ADD256-like imagery alone)")
    p.add_argument("--device", default="auto", choices=["auto", "cpu", "cuda"],
                   help="where to train (auto: the GPU if torch sees one, else the CPU)")
    p.add_argument("--amp", action="store_true", help="mixed precision: the forward pass in bfloat16")
    p.add_argument("--workers", type=int, help="augmentation processes (default: 0 on the CPU, up to 4 beside a GPU)")
    p.add_argument("--fit-minutes", type=float, metavar="M",
                   help="set the epochs so that the whole schedule takes about M minutes, from the first iterations' rate")


def pack_arguments(p: argparse.ArgumentParser):
    p.add_argument("flight", type=Path, help="a simulated flight folder (video and truth/detections.csv)")
    p.add_argument("--out", type=Path, required=True, help=".npz to write")
    p.add_argument("--every", type=int, default=1, help="keep every N-th frame")
    p.add_argument("--limit", type=int, help="at most this many frames")
    p.add_argument("--quality", type=int, default=95, help="JPEG quality of the packed frames")





def onnx_arguments(p: argparse.ArgumentParser):
    p.add_argument("checkpoint", type=Path, help="a checkpoint of python -m export train (best.pt / last.pt, or a folder of fp16 parts)")
    p.add_argument("--out", type=Path, default=Path("out/export/apple-detector.onnx"), help="ONNX file to write "
                   "(its metadata goes next to it, same name with .json)")
    p.add_argument("--opset", type=int, default=17)
    p.add_argument("--fp16", action="store_true", help="store weights as float16 (computation stays float32)")
    p.add_argument("--score-thresh", type=float, default=0.5, help="operating score threshold written in the metadata")
    p.add_argument("--proposals", type=int, default=300,
                   help="region proposals kept per image at inference (torchvision's default 1000 spends a fifth of "
                        "a 1280x720 frame's time in the box head; 300 scores the same here)")
    p.add_argument("--check-image", type=Path, help="an image to compare torch and onnxruntime on (default: synthetic)")


def quantize_arguments(p: argparse.ArgumentParser):
    p.add_argument("model", type=Path, help="a float32 ONNX model of python -m export onnx (not --fp16)")
    p.add_argument("--out", type=Path, default=Path("out/export/int8/apple-detector.onnx"),
                   help="int8 ONNX file to write (its metadata goes next to it)")
    p.add_argument("--fp16", action="store_true", help="store the weights left in float32 as float16 (smaller file)")
    p.add_argument("--ops", default="Conv", help="operator types to quantize, comma-separated (Conv; Conv,Gemm)")
    p.add_argument("--add256", help="ADD256 folder (default: $POMAR_ADD256, then the workplace's shared copy)")
    p.add_argument("--add256-images", type=int, default=24, help="ADD256 training patches to calibrate on")
    p.add_argument("--sim-flight", type=Path, action="append", default=[],
                   help="simulated training flight(s) to calibrate on (repeatable)")
    p.add_argument("--sim-frames", type=int, default=8, help="frames per simulated flight to calibrate on")
    p.add_argument("--seed", type=int, default=0)


def evaluate_arguments(p: argparse.ArgumentParser):
    p.add_argument("--model", type=Path, help="ONNX model (default: the shipped one)")
    p.add_argument("--add256", help="ADD256 folder (default: $POMAR_ADD256, then the workplace's shared copy)")
    p.add_argument("--sim-flight", type=Path, action="append", default=[],
                   help="held-out simulated flight(s) to score on (every --sim-every-th frame), or packs of export "
                        "pack (.npz: their boxes as packed, frames at their own size)")
    p.add_argument("--sim-every", type=int, default=5)
    p.add_argument("--min-visible", type=float, default=MIN_VISIBLE,
                   help="simulated apples at least this visible are truth; less visible ones are ignored")
    p.add_argument("--score-thresh", type=float, help="operating threshold (default: the model's metadata)")
    p.add_argument("--val-flight", type=Path, help="choose the operating threshold as the best F1 on this simulated "
                   "flight (held out from training and from the scored flights)")
    p.add_argument("--val-add256", type=int, metavar="N", help="choose the operating threshold as the best F1 on N "
                   "ADD256 *training* patches instead (for a model meant for ADD256-like imagery; never the test split)")
    p.add_argument("--detector-scale", type=scale_argument, default="auto",
                   help="simulated frames: " + SCALE_HELP + " (ADD256's patches go at their own size)")
    p.add_argument("--json", type=Path, help="write the metrics here")
    p.add_argument("--write-metadata", action="store_true",
                   help="also store the metrics (and the score threshold used) in the model's metadata file")


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
    return run(args)


if __name__ == "__main__":
    sys.exit(main())
