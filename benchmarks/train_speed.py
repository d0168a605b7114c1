"""What a training iteration of the detector costs on this CPU, by recipe: frozen early stages, threads.

    python benchmarks/train_speed.py [--freeze 0 1 2] [--threads 2] [--iterations 12] [--rounds 2]

Each variant trains ``export.model``'s network (MobileNetV2-FPN from its ImageNet weights, the committed run's
widths) on the same batch of four 256x256 crops of the bundled flight, with the run's SGD; the variants take turns
for ``--rounds`` rounds, so that their ratios hold whatever else the machine does. Prints the median seconds per
iteration of each (after two warm-up iterations) and its speed against the first variant: ratios in one run, not
times, unless nothing else ran.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import torch  # noqa: E402

from export.data import Augment, load_sim_frames  # noqa: E402
from export.model import freeze_stages, make  # noqa: E402
from export.train import collate, target, to_tensor  # noqa: E402

BUNDLED = Path(__file__).resolve().parents[1] / "replay_data" / "demo-flight"


def batch_of(n: int = 4, seed: int = 0):
    frames = load_sim_frames(BUNDLED, every=30)
    aug = Augment(rng=np.random.default_rng(seed))
    items = []
    while len(items) < n:
        img, b = aug(frames[len(items) % len(frames)].image, frames[len(items) % len(frames)].boxes, scale=(0.8, 1.25))
        if len(b):
            items.append((to_tensor(img), target(b)))
    return collate(items)


def seconds_per_iteration(freeze: int, imgs, tgts, iterations: int, backbone: str, fpn: int, head: int) -> float:
    torch.manual_seed(0)
    model = make(dict(backbone=backbone, fpn_channels=fpn, head_width=head), imagenet=True)
    freeze_stages(model, freeze)
    model.train()
    opt = torch.optim.SGD(model.parameters(), lr=0.001, momentum=0.9, weight_decay=1e-4)
    times = []
    for _ in range(iterations + 2):
        t = time.perf_counter()
        loss = sum(model(list(imgs), list(tgts)).values())
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        times.append(time.perf_counter() - t)
    return float(np.median(times[2:]))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--freeze", type=int, nargs="+", default=[0, 1, 2], help="--freeze-stages values to compare")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--iterations", type=int, default=12)
    p.add_argument("--rounds", type=int, default=2)
    p.add_argument("--backbone", default="mobilenet_v2")
    p.add_argument("--fpn-channels", type=int, default=48)
    p.add_argument("--head-width", type=int, default=256)
    a = p.parse_args(argv)
    torch.set_num_threads(a.threads)
    imgs, tgts = batch_of()
    got: dict[int, list[float]] = {f: [] for f in a.freeze}
    for r in range(a.rounds):
        for f in a.freeze:
            got[f].append(seconds_per_iteration(f, imgs, tgts, a.iterations, a.backbone, a.fpn_channels, a.head_width))
            print(f"round {r + 1}: freeze {f}: {got[f][-1]:.3f} s/it", flush=True)
    base = min(got[a.freeze[0]])
    print(f"{a.backbone}, fpn {a.fpn_channels}, head {a.head_width}, batch of 4 crops of 256 px, {a.threads} threads; "
          f"best round of {a.rounds}:")
    for f in a.freeze:
        print(f"  --freeze-stages {f}: {min(got[f]):.3f} s/it, {base / min(got[f]):.2f}x the speed of "
              f"--freeze-stages {a.freeze[0]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
