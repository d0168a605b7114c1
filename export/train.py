"""Train the apple detector on real apples (ADD256, AppleBBCH76) and crops of simulated flights, checkpointed.

    python -m export train --out out/export/mv2 [--backbone mobilenet_v2] [--add256 DIR] [--applebbch76 DIR]
                           [--sim-flight DIR|PACK.npz ...] [--val-flight DIR|PACK.npz ...] [--epochs N] [--resume]
                           [--init CKPT]   # a second cycle from trained weights (a .pt or a folder of fp16 parts)
                           [--device auto|cpu|cuda] [--amp] [--fit-minutes M]

A new run of a pretrained backbone (``mobilenet_v2``, ``efficientnet_lite0``) starts from its ImageNet weights,
checked by hash (``export.pretrained``); the others start from random weights.

The same command trains on a GPU where one is present (``--device auto``) and on the CPU otherwise; ``--amp``
runs the forward pass in bfloat16 (mixed precision; no loss scaling needed). Augmentation runs in
``--workers`` loader processes, so a GPU is not left waiting on one CPU core.

Each epoch is ADD256's training patches (the official split without its held-back photos), ``--bbch-tiles``
AppleBBCH76 tiles of its training photos, and ``--sim-crops`` random crops of the simulated flights' frames, augmented
(scale, crops, flips, 90° rotations, colour, white balance, exposure, blur, noise, JPEG). The learning rate
warms up, then follows a cosine to the last iteration. ``last.pt`` is written every
``--checkpoint-every`` iterations and at each epoch's end (atomically), so a killed run resumes
where it stopped with ``--resume``. After each epoch the validation sets are scored (AP@0.5): ADD256's held-back
photos, AppleBBCH76's held-out photos and the ``--val-flight``s; their mean (``val_ap50``) keeps the best epoch as
``best.pt``. ADD256's test split is never scored here: ``export evaluate`` scores it once, at the end.
"""

from __future__ import annotations

import json
import logging
import math
import os
import time
from pathlib import Path

import cv2
import numpy as np
import torch

from export.data import Augment, load_add256, load_applebbch76, load_sim_frames, validation_sets
from export.metrics import evaluate_detections
from export.model import is_pretrained, load_checkpoint, make
from export.pretrained import weights_path
from export.settings import TRAIN_FIELDS, TrainSettings
from pomar.cli import InputError
from pomar.settings import from_options

log = logging.getLogger(__name__)


def to_tensor(img: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(img)).permute(2, 0, 1).float().div_(255.0)


def target(boxes: np.ndarray) -> dict:
    b = torch.from_numpy(np.asarray(boxes, np.float32).reshape(-1, 4))
    return {"boxes": b, "labels": torch.ones(len(b), dtype=torch.int64)}


class EpochPlan:
    """The (deterministic from seed and epoch) list of training items of one epoch: every ADD256 patch, ``bbch_tiles``
    AppleBBCH76 tiles drawn without replacement and ``sim_crops`` crops of simulated frames."""

    def __init__(self, n_add256: int, n_sim_frames: int, sim_crops: int, seed: int, n_bbch: int = 0,
                 bbch_tiles: int = 0):
        self.n_add, self.n_sim, self.sim_crops, self.seed = n_add256, n_sim_frames, sim_crops if n_sim_frames else 0, seed
        self.n_bbch, self.bbch_tiles = n_bbch, min(bbch_tiles, n_bbch)

    def __len__(self):
        return self.n_add + self.sim_crops + self.bbch_tiles

    def items(self, epoch: int) -> list[tuple[str, int]]:
        rng = np.random.default_rng([self.seed, epoch])
        items = [("add256", i) for i in range(self.n_add)]
        items += [("sim", int(i)) for i in rng.integers(0, max(self.n_sim, 1), self.sim_crops)]
        if self.bbch_tiles:  # drawn after the simulated crops, so that a plan without AppleBBCH76 stays as it was
            items += [("bbch", int(i)) for i in rng.choice(self.n_bbch, self.bbch_tiles, replace=False)]
        return [items[i] for i in rng.permutation(len(items))]


def lr_at(it: int, total: int, base: float, warmup: int = 300, final: float = 0.02) -> float:
    if it < warmup:
        return base * (0.001 + 0.999 * it / warmup)
    t = (it - warmup) / max(total - warmup, 1)
    return base * (final + (1 - final) * 0.5 * (1 + math.cos(math.pi * min(t, 1.0))))


class TrainingError(InputError, RuntimeError):
    """A training run that cannot start as asked (e.g. ``--device cuda`` without CUDA); the message says why."""


def pick_device(name: str = "auto") -> torch.device:
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name == "cuda" and not torch.cuda.is_available():
        raise TrainingError("--device cuda: this machine's torch sees no CUDA device (use --device cpu or auto)")
    return torch.device(name)


class EpochItems(torch.utils.data.Dataset):
    """One epoch's augmented training items, each from its own seed (seed, epoch, position): the same on a resume,
    whatever the number of loader processes."""

    def __init__(self, items, add, sim, seed: int, epoch: int, add256_scale, bbch=()):
        self.items, self.add, self.sim, self.seed, self.epoch, self.add256_scale = items, add, sim, seed, epoch, add256_scale
        self.bbch = bbch

    def __len__(self):
        return len(self.items)

    def __getitem__(self, k):
        kind, i = self.items[k]
        aug = Augment(rng=np.random.default_rng([self.seed, self.epoch, k]))
        if kind == "add256":
            img, b = aug(self.add[i].image, self.add[i].boxes, scale=self.add256_scale)
        elif kind == "bbch":  # resized by its curators to ADD256's apple size: the same scales
            img, b = aug(self.bbch[i].image, self.bbch[i].boxes, scale=self.add256_scale)
        else:
            img, b = aug(self.sim[i].image, self.sim[i].boxes, scale=(0.8, 1.25))
        return to_tensor(img), target(b)


def collate(batch):
    return tuple(zip(*batch))


@torch.no_grad()
def predict(model, samples, device=torch.device("cpu"), amp: bool = False) -> list[tuple[np.ndarray, np.ndarray]]:
    """(boxes, scores) of ``model`` on each sample's whole image."""
    was_training = model.training
    model.eval()
    preds = []
    for s in samples:
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=amp):
            out = model([to_tensor(s.image).to(device)])[0]
        preds.append((out["boxes"].float().cpu().numpy(), out["scores"].float().cpu().numpy()))
    model.train(was_training)
    return preds


def score_samples(model, samples, score_thresh: float = 0.5, device=torch.device("cpu"), amp: bool = False) -> dict:
    """AP@0.5 and P/R/F1 at ``score_thresh`` on samples (their ignore boxes neither count nor cost)."""
    return evaluate_detections(predict(model, samples, device, amp), [(s.boxes, s.ignore) for s in samples], score_thresh)


def score_validation(model, sets: dict, device=torch.device("cpu"), amp: bool = False) -> dict:
    """Each validation set's AP@0.5 and P/R/F1, and their mean AP (``val_ap50``), which picks the best epoch."""
    m = {k: score_samples(model, v, device=device, amp=amp) for k, v in sets.items()}
    out = {"val_ap50": round(float(np.mean([x["ap50"] for x in m.values()])), 4) if m else 0.0}
    out.update(m)
    return out


def save_atomic(obj, path: Path):
    tmp = path.with_suffix(".tmp")
    torch.save(obj, tmp)
    os.replace(tmp, path)


#: ``--fit-minutes``: iterations timed before the epochs are set, and the share of the time given to iterations
#: (the rest: the per-epoch test scoring and checkpoints).
FIT_AFTER, FIT_SHARE = 60, 0.85


def train(settings: TrainSettings, log_every: int = 10) -> list[dict]:
    """Train as ``settings`` say; the per-epoch ADD256 test scores."""
    s = settings
    out, add256, sim_flights, backbone, fpn_channels = s.out, s.add256, s.sim_flight, s.backbone, s.fpn_channels
    epochs, batch, lr, sim_crops, seed, threads = s.epochs, s.batch, s.lr, s.sim_crops, s.seed, s.threads
    checkpoint_every, resume, max_minutes, init, add256_scale = (s.checkpoint_every, s.resume, s.max_minutes, s.init,
                                                                 tuple(s.add256_scale))
    device, amp, workers, fit_minutes = s.device, s.amp, s.workers, s.fit_minutes
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    dev = pick_device(device)
    if workers is None:
        workers = min(4, max((os.cpu_count() or 1) - 1, 0)) if dev.type == "cuda" else 0
    if threads or dev.type == "cuda":
        torch.set_num_threads(threads or 2)
    if workers:
        # Loader processes each use one core (torch sees to its own threads there). OpenCV's is set here, before
        # the fork: cv2.setNumThreads inside a forked worker hangs.
        cv2.setNumThreads(1)
    torch.manual_seed(seed)
    fresh = not (resume and (out / "last.pt").is_file()) and init is None
    if fresh and is_pretrained(backbone):
        weights_path(backbone)  # missing or different ImageNet weights stop the run before the data is read
    add = load_add256(add256, "training")
    bbch = load_applebbch76(s.applebbch76, "training") if s.bbch_tiles else []
    sim = [x for f in sim_flights for x in load_sim_frames(f, s.min_visible)]
    val = validation_sets(add256, s.applebbch76, s.val_flight, bool(s.bbch_tiles))
    log.info("data: %d ADD256 patches, %d AppleBBCH76 tiles (%d/epoch), %d simulated frames (%d crops/epoch); "
             "validation: %s; %s%s, %d loader processes", len(add), len(bbch), min(s.bbch_tiles, len(bbch)), len(sim),
             sim_crops if sim else 0, ", ".join(f"{k} {len(v)}" for k, v in val.items()), dev,
             " bfloat16 autocast" if amp else "", workers)
    plan = EpochPlan(len(add), len(sim), sim_crops, seed, len(bbch), s.bbch_tiles)
    per_epoch = math.ceil(len(plan) / batch)
    total = epochs * per_epoch
    config = dict(backbone=backbone, fpn_channels=fpn_channels, head_width=s.head_width)
    last = out / "last.pt"
    if resume and last.is_file():
        model, ckpt = load_checkpoint(last)
        opt = torch.optim.SGD(model.parameters(), lr=lr, momentum=0.9, weight_decay=1e-4)
        opt.load_state_dict(ckpt["optimizer"])
        it, history, best = ckpt["iteration"], ckpt["history"], ckpt["best_ap50"]
        torch.set_rng_state(ckpt["torch_rng"])
        log.info("resumed %s at iteration %d/%d", last, it, total)
    elif init is not None:
        model, ckpt = load_checkpoint(init)
        config = ckpt["config"]
        log.info("initialised from %s (%s, trained %d iterations)", init, config, ckpt["iteration"])
        opt = torch.optim.SGD(model.parameters(), lr=lr, momentum=0.9, weight_decay=1e-4)
        it, history, best = 0, [], -1.0
    else:
        model = make(config, imagenet=is_pretrained(backbone))
        if is_pretrained(backbone):
            log.info("%s: ImageNet weights, checked", backbone)
        opt = torch.optim.SGD(model.parameters(), lr=lr, momentum=0.9, weight_decay=1e-4)
        it, history, best = 0, [], -1.0
    model.to(dev)
    for state in opt.state.values():  # a resumed optimiser's momenta go where the weights are
        for k, v in state.items():
            if torch.is_tensor(v):
                state[k] = v.to(dev)
    run_info = dict(backbone=backbone, fpn_channels=fpn_channels, head_width=s.head_width, epochs=epochs, batch=batch,
                    lr=lr, sim_crops=sim_crops, seed=seed, sim_flights=[str(f) for f in sim_flights],
                    add256_train=len(add), applebbch76_train=len(bbch), bbch_tiles=plan.bbch_tiles,
                    sim_frames=len(sim), iterations=total, validation={k: len(v) for k, v in val.items()},
                    imagenet=is_pretrained(config["backbone"]),
                    init=str(init) if init is not None else None, add256_scale=list(add256_scale),
                    min_visible=s.min_visible)

    def checkpoint(path):
        save_atomic({"config": config, "model": model.state_dict(), "optimizer": opt.state_dict(), "iteration": it,
                     "history": history, "best_ap50": best, "torch_rng": torch.get_rng_state(), "run": run_info}, path)

    model.train()
    t0, it0 = time.time(), it
    smooth = None
    stop = False
    while it < total and not stop:
        epoch, pos = divmod(it, per_epoch)
        items = EpochItems(plan.items(epoch), add, sim, seed, epoch, add256_scale, bbch)
        rest = torch.utils.data.Subset(items, range(pos * batch, len(items)))
        loader = torch.utils.data.DataLoader(rest, batch_size=batch, num_workers=workers, collate_fn=collate,
                                             pin_memory=dev.type == "cuda")
        for imgs, tgts in loader:
            imgs = [x.to(dev, non_blocking=True) for x in imgs]
            tgts = [{k: v.to(dev, non_blocking=True) for k, v in t.items()} for t in tgts]
            for g in opt.param_groups:
                g["lr"] = lr_at(it, total, lr)
            with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=amp):
                losses = model(imgs, tgts)
            loss = sum(v.float() for v in losses.values())
            if not torch.isfinite(loss):
                raise FloatingPointError(f"loss is {loss.item()} at iteration {it}; lower --lr")
            opt.zero_grad(set_to_none=True)
            loss.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), 10.0)
            opt.step()
            it += 1
            if it == it0 + FIT_AFTER // 2:
                t_fit = time.time()
            if fit_minutes and it == it0 + FIT_AFTER and not resume:
                # the epochs that fill the time asked for, from the rate of the second half of the first FIT_AFTER
                # iterations (past the start-up; the schedule is still warming up)
                rate = (time.time() - t_fit) / (FIT_AFTER - FIT_AFTER // 2)
                epochs = max(1, int((FIT_SHARE * fit_minutes * 60 - (time.time() - t0)) / rate / per_epoch))
                total = run_info["iterations"] = epochs * per_epoch
                run_info["epochs"] = epochs
                log.info("--fit-minutes %.1f: %.3f s/it, so %d epochs (%d iterations)", fit_minutes, rate, epochs, total)
            vals = {k: v.item() for k, v in losses.items()}
            smooth = vals if smooth is None else {k: 0.95 * smooth[k] + 0.05 * vals[k] for k in vals}
            if it % log_every == 0 or it == total:
                rate = (time.time() - t0) / max(it - it0, 1)
                log.info("epoch %d/%d it %d/%d loss %.3f (%s) lr %.4f %.3f s/it ETA %.1f min", epoch + 1, epochs, it, total,
                         sum(smooth.values()), " ".join(f"{k[5:]} {v:.3f}" for k, v in smooth.items()),
                         opt.param_groups[0]["lr"], rate, rate * (total - it) / 60)
            if it % checkpoint_every == 0:
                checkpoint(last)
            end_of_epoch = it % per_epoch == 0 or it == total
            if end_of_epoch:
                m = {"epoch": math.ceil(it / per_epoch), "iteration": it,
                     "minutes": round((time.time() - t0) / 60, 1), **score_validation(model, val, device=dev, amp=amp)}
                history.append(m)
                log.info("validation after epoch %d: AP50 %.3f (%s)", m["epoch"], m["val_ap50"],
                         ", ".join(f"{k} {m[k]['ap50']:.3f}" for k in val))
                if m["val_ap50"] > best:
                    best = m["val_ap50"]
                    checkpoint(out / "best.pt")
                checkpoint(last)
                (out / "history.json").write_text(json.dumps(history, indent=1))
            if max_minutes and (time.time() - t0) / 60 > max_minutes:
                checkpoint(last)
                log.warning("stopping after %.0f minutes (--max-minutes); resume with --resume", max_minutes)
                stop = True
            if stop or end_of_epoch or it >= total:
                break
    return history


def run(args) -> int:
    train(from_options(TrainSettings(), args, TRAIN_FIELDS))
    return 0
