"""The detector's training settings, declared once: ``python -m export train``'s options are built from them.

No torch here, so that every subcommand's ``--help`` runs without it.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from pomar.countable import MIN_VISIBLE

#: The backbones ``export.model`` builds (mobilenet_v2 and efficientnet_lite0 from ImageNet weights).
BACKBONE_NAMES = ["mobilenet_v2", "efficientnet_lite0", "resnet18", "resnet50", "mobilenet_v3_large"]


@dataclass
class TrainSettings:
    #: Run folder (checkpoints, history).
    out: Path = Path("out/export/resnet18")
    #: ADD256 folder (default: $POMAR_ADD256, then the workplace's shared copy).
    add256: str | None = None
    #: AppleBBCH76 folder (default: $POMAR_APPLEBBCH76, then the workplace's shared copy); its held-out photos are
    #: never trained on.
    applebbch76: str | None = None
    #: AppleBBCH76 training tiles drawn per epoch (0: AppleBBCH76 not used, neither to train nor to validate).
    bbch_tiles: int = 600
    #: Simulated flight folders, or packs of export pack (.npz), to crop training patches from (repeatable).
    sim_flight: list[Path] = field(default_factory=list, metadata={"action": "append", "type": Path})
    #: Held-out simulated flights or packs to validate on after each epoch, every 5th frame at its own size
    #: (repeatable).
    val_flight: list[Path] = field(default_factory=list, metadata={"action": "append", "type": Path})
    #: The Faster R-CNN's backbone.
    backbone: str = field(default="mobilenet_v2", metadata={"choices": BACKBONE_NAMES})
    #: Channels of the feature pyramid's levels (the RPN's and the pyramid's cost on the finest level).
    fpn_channels: int = 48
    #: Width of the box head's two fully connected layers.
    head_width: int = 256
    #: Epochs: each the ADD256 training split plus sim_crops simulated crops.
    epochs: int = 8
    #: Images per iteration.
    batch: int = 4
    #: Peak learning rate (SGD, warm-up then cosine).
    lr: float = 0.01
    #: Simulated crops per epoch.
    sim_crops: int = 400
    #: Seed of the epochs' order and augmentation.
    seed: int = 0
    #: Torch CPU threads (default: every core; 2 beside a GPU). A run resumes bit for bit on the same number.
    threads: int | None = field(default=None, metadata={"type": int})
    #: Pyramid stages (strides 4, 8, 16, 32), and the stem before them, kept at their ImageNet weights (a pretrained
    #: backbone only): 1 makes an iteration about a fifth cheaper on the CPU.
    freeze_stages: int = 0
    #: Iterations between checkpoints (last.pt), besides each epoch's end.
    checkpoint_every: int = 100
    #: Score the validation sets after every this many epochs, and after the last (on this CPU they cost about half
    #: an epoch's iterations); the training is the same whatever it is.
    validate_every: int = 1
    #: Stop (checkpointed, resumable) after this many minutes.
    max_minutes: float | None = field(default=None, metadata={"type": float})
    #: Stop (checkpointed, resumable) after this many iterations of this call.
    stop_after: int | None = field(default=None, metadata={"type": int, "metavar": "N"})
    #: Continue from OUT/last.pt, or from --keep's state where that is further on; the run's own settings are used.
    resume: bool = False
    #: Also keep the run's exact state in this folder after each epoch and at a stop (float32 weights, optimiser, RNG,
    #: position; parts of at most 15 MB): the folder to commit, so that another machine goes on from it.
    keep: Path | None = field(default=None, metadata={"type": Path, "metavar": "FOLDER"})
    #: Start from this checkpoint's weights (a .pt, or a folder of fp16 parts) with a fresh optimiser and schedule.
    init: Path | None = field(default=None, metadata={"type": Path, "metavar": "CKPT"})
    #: With --init: widen its pyramid to this many channels first, the new ones silent until trained, so that the run
    #: starts from what the init computes (more room for small apples).
    widen_fpn: int | None = field(default=None, metadata={"type": int, "metavar": "CHANNELS"})
    #: The box head pools a region this many times each proposal's box (1: the box itself), so that a small apple is
    #: judged with the leaves around it; with --init, the init's weights carry over to the new pooling.
    roi_context: float | None = field(default=None, metadata={"type": float, "metavar": "FACTOR"})
    #: Anchors: this many square sizes per pyramid level, each 2^(1/N) times the last (unset: one size at three
    #: aspect ratios), so that every apple size has an anchor it overlaps well; with --init, each starts as the
    #: init's square anchor.
    anchor_scales: int | None = field(default=None, metadata={"type": int, "metavar": "N"})
    #: The RPN trains an anchor as an apple from this IoU with one (torchvision's 0.7): a small apple overlaps the
    #: anchors of a 4-px grid by less, and at 0.7 most keep only their one best anchor (the rule for every apple).
    rpn_fg_iou: float = field(default=0.7, metadata={"type": float, "metavar": "IOU"})
    #: Simulated apples at least this visible are boxes to find, the rest background (default: the definition's,
    #: pomar.countable.MIN_VISIBLE; another for a study). Flight folders only: a pack keeps the labels it was packed with.
    min_visible: float = MIN_VISIBLE
    #: Simulated apples from this visible fraction up to --min-visible are neither apples nor background in training
    #: (the anchors and proposals on them are left out of the losses), as the barely visible ones cost nothing in
    #: validation; unset: they are background. Flight folders only.
    ignore_from: float | None = field(default=None, metadata={"type": float, "metavar": "FRACTION"})
    #: Random scale range of ADD256 patches (0.45 1.3: down to the simulated flights' apple sizes; 0.8 1.25 to train
    #: for ADD256-like imagery alone).
    add256_scale: tuple[float, float] = field(default=(0.45, 1.3), metadata={"nargs": 2, "type": float,
                                                                             "metavar": ("LO", "HI")})
    #: Random scale range of AppleBBCH76 tiles (default: --add256-scale's; its apples are resized to ADD256's size).
    bbch_scale: tuple[float, float] | None = field(default=None, metadata={"nargs": 2, "type": float,
                                                                          "metavar": ("LO", "HI")})
    #: Where to train (auto: the GPU if torch sees one, else the CPU).
    device: str = field(default="auto", metadata={"choices": ["auto", "cpu", "cuda"]})
    #: Mixed precision: the forward pass in bfloat16.
    amp: bool = False
    #: Augmentation processes (default: 0 on the CPU, up to 4 beside a GPU).
    workers: int | None = field(default=None, metadata={"type": int})
    #: Set the epochs so that the whole schedule takes about this many minutes, from the first iterations' rate.
    fit_minutes: float | None = field(default=None, metadata={"type": float, "metavar": "M"})


TRAIN_FIELDS = [f for f in TrainSettings.__dataclass_fields__]


@dataclass
class OnnxSettings:
    """``python -m export onnx CHECKPOINT``'s settings."""

    #: ONNX file to write (its metadata goes next to it, same name with .json).
    out: Path = Path("out/export/apple-detector.onnx")
    #: ONNX opset.
    opset: int = 17
    #: Store the weights as float16 (the computation stays float32).
    fp16: bool = False
    #: Operating score threshold written in the metadata.
    score_thresh: float = 0.5
    #: Region proposals kept per image at inference (torchvision's 1000 spent a fifth of a 1280x720 frame's time in the
    #: box head; 300 score the same here).
    proposals: int = 300
    #: An image to compare torch and onnxruntime on (default: synthetic).
    check_image: Path | None = field(default=None, metadata={"type": Path})


@dataclass
class QuantizeSettings:
    """``python -m export quantize MODEL``'s settings."""

    #: The int8 ONNX file to write (its metadata goes next to it).
    out: Path = Path("out/export/int8/apple-detector.onnx")
    #: Store the weights left in float32 as float16 (a smaller file).
    fp16: bool = False
    #: Operator types to quantize, comma-separated. Clip (MobileNet's ReLU6) fuses into the convolutions: without it
    #: an untrained MobileNetV2-FPN spent more time in (de)quantizing than in them (0.53 s against 0.31 s at
    #: 1792x1008, one core); Resize and MaxPool cost nothing; Add (the residuals, the pyramid's sums) lost half the AP.
    ops: str = "Conv,Clip,Resize,MaxPool"
    #: ADD256 folder (default: $POMAR_ADD256, then the workplace's shared copy).
    add256: str | None = None
    #: ADD256 training patches to calibrate on.
    add256_images: int = 24
    #: Simulated training flights to calibrate on (repeatable).
    sim_flight: list[Path] = field(default_factory=list, metadata={"action": "append", "type": Path})
    #: Frames per simulated flight to calibrate on.
    sim_frames: int = 8
    #: Seed of the calibration sample.
    seed: int = 0


@dataclass
class EvaluateSettings:
    """``python -m export evaluate``'s settings (the detector scale's option is ``pomar.apple_scale``'s)."""

    #: ONNX model (default: the shipped one).
    model: Path | None = field(default=None, metadata={"type": Path})
    #: ADD256 folder (default: $POMAR_ADD256, then the workplace's shared copy).
    add256: str | None = None
    #: AppleBBCH76 folder whose held-out photos are scored too (default: $POMAR_APPLEBBCH76, then the workplace's
    #: shared copy; none there: not scored).
    applebbch76: str | None = None
    #: Held-out simulated flights to score on (every sim_every-th frame), or packs of export pack (.npz: their boxes
    #: as packed, frames at their own size).
    sim_flight: list[Path] = field(default_factory=list, metadata={"action": "append", "type": Path})
    #: Score every this many frames of a flight.
    sim_every: int = 5
    #: Operating threshold (default: the model's metadata).
    score_thresh: float | None = field(default=None, metadata={"type": float})
    #: Choose the operating threshold as the best F1 on this simulated flight (held out from training and scoring).
    val_flight: Path | None = field(default=None, metadata={"type": Path})
    #: Choose the operating threshold as the best mean F1 over the sets models are chosen on: ADD256's held-back
    #: photos, AppleBBCH76's held-out photos (where found) and --val-flight's frames (if given).
    val_sets: bool = False
    #: Choose the operating threshold as the best F1 on N ADD256 training patches instead (never the test split).
    val_add256: int | None = field(default=None, metadata={"type": int, "metavar": "N"})
    #: Score ADD256's test split too: once per shipped model (--no-test while candidates are compared).
    test: bool = True
    #: Write the metrics here.
    json: Path | None = field(default=None, metadata={"type": Path})
    #: Also store the metrics (and the score threshold used) in the model's metadata file.
    write_metadata: bool = False


@dataclass
class PackSettings:
    """``python -m export pack FLIGHT``'s settings."""

    #: The .npz to write.
    out: Path | None = field(default=None, metadata={"type": Path, "required": True})
    #: Keep every this many frames.
    every: int = 1
    #: At most this many frames.
    limit: int | None = field(default=None, metadata={"type": int})
    #: JPEG quality of the packed frames.
    quality: int = 95


def fields_of(cls) -> list[str]:
    return list(cls.__dataclass_fields__)
