"""The apple detector: torchvision Faster R-CNN with a ResNet FPN backbone, from scratch, for small fruit.

- Backbones: ``resnet50`` (the paper's), ``resnet18`` (lighter, for CPUs and companion computers) or
  ``mobilenet_v3_large`` (lightest), built without pretrained weights and with *trainable* BatchNorm
  (torchvision's frozen BatchNorm is only right for pretrained statistics).
- FPN levels P2..P5 plus a max-pool level; anchors of 8..128 px, one size per level: ADD256's apples
  are 8-34 px boxes, the simulated flights' 6-12 px.
- The transform keeps images at their native resolution (torchvision's resize to 800 px would be baked
  into the exported graph): the model sees frames as the camera gives them.
"""

from __future__ import annotations

from collections import OrderedDict

import torch
from torch import nn
from torchvision.models import mobilenet_v3_large, resnet18, resnet50
from torchvision.models.detection import FasterRCNN
from torchvision.models.detection.anchor_utils import AnchorGenerator
from torchvision.models.detection.backbone_utils import BackboneWithFPN
from torchvision.models.detection.transform import GeneralizedRCNNTransform
from torchvision.ops.feature_pyramid_network import LastLevelMaxPool

# name: (builder, the body's layers at strides 4, 8, 16 and 32, their channels)
BACKBONES = {
    "resnet18": (resnet18, ["layer1", "layer2", "layer3", "layer4"], [64, 128, 256, 512]),
    "resnet50": (resnet50, ["layer1", "layer2", "layer3", "layer4"], [256, 512, 1024, 2048]),
    "mobilenet_v3_large": (lambda **kw: mobilenet_v3_large(**kw).features, ["3", "6", "12", "16"], [24, 40, 112, 960]),
}
ANCHOR_SIZES = ((8,), (16,), (32,), (64,), (128,))
ASPECT_RATIOS = (0.5, 1.0, 2.0)


class NativeResolutionTransform(GeneralizedRCNNTransform):
    """Normalise and batch, but never resize: boxes come back in the input's own pixels."""

    def resize(self, image, target=None):
        return image, target


def build_model(backbone: str = "resnet18", fpn_channels: int = 128, detections_per_img: int = 300,
                score_thresh: float = 0.05, fast_train: bool = True) -> FasterRCNN:
    """A Faster R-CNN for apples (2 classes: background, apple), randomly initialised."""
    if backbone not in BACKBONES:
        raise ValueError(f"unknown backbone {backbone!r}; choose from {sorted(BACKBONES)}")
    builder, layers, in_channels = BACKBONES[backbone]
    body = builder(weights=None, norm_layer=nn.BatchNorm2d)
    fpn = BackboneWithFPN(body, OrderedDict((name, str(i)) for i, name in enumerate(layers)), in_channels,
                          fpn_channels, extra_blocks=LastLevelMaxPool())
    anchors = AnchorGenerator(ANCHOR_SIZES, (ASPECT_RATIOS,) * len(ANCHOR_SIZES))
    extra = dict(rpn_post_nms_top_n_train=500, box_batch_size_per_image=128) if fast_train else {}
    model = FasterRCNN(fpn, num_classes=2, rpn_anchor_generator=anchors, box_detections_per_img=detections_per_img,
                       box_score_thresh=score_thresh, **extra)
    t = model.transform
    model.transform = NativeResolutionTransform(t.min_size, t.max_size, t.image_mean, t.image_std,
                                                size_divisible=t.size_divisible)
    return model


def model_config(model: FasterRCNN) -> dict:
    """What rebuilds ``model`` (stored in checkpoints and the ONNX metadata)."""
    return dict(model._pomar_config) if hasattr(model, "_pomar_config") else {}


def make(config: dict) -> FasterRCNN:
    model = build_model(**config)
    model._pomar_config = dict(config)
    return model


def load_checkpoint(path, map_location="cpu") -> tuple[FasterRCNN, dict]:
    """A ``.pt`` of ``export train``, or a folder of fp16 parts (``export.parts``)."""
    from export.parts import is_parts, load_parts

    ckpt = load_parts(path) if is_parts(path) else torch.load(path, map_location=map_location, weights_only=False)
    model = make(ckpt["config"])
    model.load_state_dict(ckpt["model"])
    return model, ckpt
