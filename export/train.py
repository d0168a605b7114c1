"""Train the apple detector on real apples (ADD256, AppleBBCH76) and crops of simulated flights, checkpointed.

    python -m export train --out out/export/mv2 [--backbone mobilenet_v2] [--add256 DIR] [--applebbch76 DIR]
                           [--sim-flight DIR|PACK.npz ...] [--val-flight DIR|PACK.npz ...] [--epochs N] [--resume]
                           [--init CKPT]   # a second cycle from trained weights (a .pt or a folder of fp16 parts)
                           [--threads N] [--freeze-stages K] [--rpn-fg-iou IOU] [--keep FOLDER] [--stop-after N]
                           [--device auto|cpu|cuda] [--amp] [--fit-minutes M]

A new run of a pretrained backbone (``mobilenet_v2``, ``efficientnet_lite0``) starts from its ImageNet weights,
checked by hash (``export.pretrained``); the others start from random weights.

The same command trains on a GPU where one is present (``--device auto``) and on the CPU otherwise; ``--amp``
runs the forward pass in bfloat16 (mixed precision; no loss scaling needed). Augmentation runs in
``--workers`` loader processes, so a GPU is not left waiting on one CPU core.

Each epoch is ADD256's training patches (the official split without its held-back photos), ``--bbch-tiles``
AppleBBCH76 tiles of its training photos, and ``--sim-crops`` random crops of the simulated flights' frames, augmented
(scale, crops, flips, 90° rotations, colour, white balance, exposure, blur, noise, JPEG). The learning rate
warms up, then follows a cosine to the last iteration.

A run stops and goes on bit for bit (on the same number of ``--threads``): ``last.pt`` (atomically, every
``--checkpoint-every`` iterations and at each epoch's end) holds the weights, the optimiser, the RNG, the iteration
(hence the epoch, its order and each item's augmentation, all drawn from the seed) and the run's settings, which
``--resume`` takes back. ``--keep FOLDER`` writes the same state as parts after each epoch and at a stop: the folder
committed to the repository, from which ``--resume`` goes on on another machine. Ctrl-C or SIGTERM stops at the next
iteration, checkpointed. The log gives iterations a second, the ETA, each epoch's validation and the CPU-hours.

After each epoch the validation sets are scored (AP@0.5): ADD256's held-back
photos, AppleBBCH76's held-out photos and the ``--val-flight``s; their mean (``val_ap50``) keeps the best epoch as
``best.pt``. ADD256's test split is never scored here: ``export evaluate`` scores it once, at the end.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import math
import os
import signal
import threading
import time
from pathlib import Path

import cv2
import numpy as np
import torch
from torchvision.models.detection._utils import Matcher

from export.data import Augment, load_add256, load_applebbch76, load_sim_frames, validation_sets
from export.metrics import evaluate_detections
from export.model import (freeze_stages, is_pretrained, load_checkpoint, make, model_config, rebuilt, widen_pyramid,
                          with_square_anchors)
from export.parts import is_state, save_state, state_manifest
from export.pretrained import weights_path
from export.settings import TRAIN_FIELDS, TrainSettings
from pomar.cli import InputError
from pomar.settings import from_options

log = logging.getLogger(__name__)


def to_tensor(img: np.ndarray) -> torch.Tensor:
    return torch.from_numpy(np.ascontiguousarray(img)).permute(2, 0, 1).float().div_(255.0)


def target(boxes: np.ndarray, ignore: np.ndarray | None = None) -> dict:
    b = torch.from_numpy(np.asarray(boxes, np.float32).reshape(-1, 4))
    t = {"boxes": b, "labels": torch.ones(len(b), dtype=torch.int64)}
    if ignore is not None:  # export.model's heads leave the anchors and proposals on these out of their losses
        t["ignore"] = torch.from_numpy(np.asarray(ignore, np.float32).reshape(-1, 4))
    return t


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

    def __init__(self, items, add, sim, seed: int, epoch: int, add256_scale, bbch=(), bbch_scale=None,
                 sim_ignore: bool = False):
        self.items, self.add, self.sim, self.seed, self.epoch, self.add256_scale = items, add, sim, seed, epoch, add256_scale
        self.bbch, self.bbch_scale, self.sim_ignore = bbch, bbch_scale or add256_scale, sim_ignore

    def __len__(self):
        return len(self.items)

    def __getitem__(self, k):
        kind, i = self.items[k]
        aug = Augment(rng=np.random.default_rng([self.seed, self.epoch, k]))
        if kind == "add256":
            img, b = aug(self.add[i].image, self.add[i].boxes, scale=self.add256_scale)
        elif kind == "bbch":  # resized by its curators to ADD256's apple size: the same scales unless told
            img, b = aug(self.bbch[i].image, self.bbch[i].boxes, scale=self.bbch_scale)
        elif self.sim_ignore:
            img, b, ig = aug(self.sim[i].image, self.sim[i].boxes, scale=(0.8, 1.25), ignore=self.sim[i].ignore)
            return to_tensor(img), target(b, ig)
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

#: The RPN's anchors below this IoU with every apple are background (torchvision's)
RPN_BG_IOU = 0.3

#: The settings that make a run what it is: a resumed run takes them from its checkpoint, and refuses an option that
#: asks for another value (the others, such as the paths to the data, the threads or the device, may change).
RUN_FIELDS = ("backbone", "fpn_channels", "head_width", "epochs", "batch", "lr", "sim_crops", "bbch_tiles", "seed",
              "min_visible", "add256_scale", "freeze_stages", "bbch_scale", "ignore_from", "rpn_fg_iou")


def _plain(v):
    return list(v) if isinstance(v, tuple) else v


def run_settings(s: TrainSettings, ckpt: dict, path) -> TrainSettings:
    """``s`` with the run-defining settings of the checkpoint it resumes; an option given for another value of one of
    them: TrainingError naming the checkpoint."""
    stored = ckpt.get("settings") or {k: v for k, v in (ckpt.get("run") or {}).items() if k in RUN_FIELDS}
    default = TrainSettings()
    for k in RUN_FIELDS:
        if k not in stored:
            continue
        given, want = _plain(getattr(s, k)), _plain(stored[k])
        if given != want and given != _plain(getattr(default, k)):
            opt = "--" + k.replace("_", "-")
            raise TrainingError(f"{path}: this run trains with {opt} {want}, not {given}: resume it without {opt}, or "
                                f"start a new run in another --out")
    return dataclasses.replace(s, **{k: tuple(v) if k in ("add256_scale", "bbch_scale") and v else v
                                     for k, v in stored.items()
                                     if k in RUN_FIELDS})


def latest_checkpoint(out: Path, keep: Path | None) -> Path | None:
    """Where a resumed run goes on from: ``out/last.pt`` or the kept state, whichever is further on (a torn
    ``last.pt`` counts as not there)."""
    found = []
    if (out / "last.pt").is_file():
        try:
            found.append((torch.load(out / "last.pt", map_location="cpu", weights_only=False)["iteration"], 1,
                          out / "last.pt"))
        except Exception:  # torn or of another kind: load_checkpoint names it where nothing else is there
            found.append((-1, 1, out / "last.pt"))
    if keep is not None and is_state(keep):
        found.append((state_manifest(keep)["iteration"], 0, Path(keep)))
    return max(found)[2] if found else None


def data_fingerprint(*sets) -> str:
    """A hash of the training data's pixels and boxes: a resume on other data (another render, another copy) is not
    bit for bit, and says so."""
    h = hashlib.sha256()
    for samples in sets:
        for x in samples:
            h.update(np.ascontiguousarray(x.image).tobytes())
            h.update(np.asarray(x.boxes, np.float32).tobytes())
    return h.hexdigest()[:16]


class StopRequest:
    """SIGINT or SIGTERM asks the run to stop at the next iteration, checkpointed; a second one stops it at once."""

    def __init__(self):
        self.signal = None
        self.old = {}

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            self.old = {sig: signal.signal(sig, self.handle) for sig in (signal.SIGINT, signal.SIGTERM)}
        return self

    def handle(self, signum, frame):
        if self.signal is not None:
            raise KeyboardInterrupt
        self.signal = signum
        log.warning("%s: stopping after this iteration, checkpointed (again to stop at once)",
                    signal.Signals(signum).name)

    def __exit__(self, *exc):
        for sig, h in self.old.items():
            signal.signal(sig, h)


def train(settings: TrainSettings, log_every: int = 10) -> list[dict]:
    """Train as ``settings`` say (a resumed run: as its checkpoint says); the per-epoch validation scores."""
    s = settings
    out = Path(s.out)
    out.mkdir(parents=True, exist_ok=True)
    dev = pick_device(s.device)
    source = latest_checkpoint(out, s.keep) if s.resume else None
    if source is not None:
        model, ckpt = load_checkpoint(source)
        s = run_settings(s, ckpt, source)
    elif s.init is not None:
        model, ckpt = load_checkpoint(s.init)
    elif s.widen_fpn is not None:
        raise TrainingError(f"--widen-fpn {s.widen_fpn}: it widens an --init model's pyramid; give --init")
    if s.roi_context is not None and not 1 <= s.roi_context <= 4:
        raise TrainingError(f"--roi-context {s.roi_context}: give a factor from 1 (the box itself) to 4")
    if s.anchor_scales is not None and not 1 <= s.anchor_scales <= 4:
        raise TrainingError(f"--anchor-scales {s.anchor_scales}: give 1 to 4 square sizes per level")
    if not RPN_BG_IOU < s.rpn_fg_iou <= 1:
        raise TrainingError(f"--rpn-fg-iou {s.rpn_fg_iou}: give an IoU above the RPN's background one ({RPN_BG_IOU}) "
                            f"and at most 1")
    if s.freeze_stages and not is_pretrained(s.backbone) and source is None and s.init is None:
        raise TrainingError(f"--freeze-stages {s.freeze_stages}: {s.backbone} starts from random weights, which "
                            f"freezing would keep random (pretrained: mobilenet_v2, efficientnet_lite0)")
    epochs, batch, lr, sim_crops, seed = s.epochs, s.batch, s.lr, s.sim_crops, s.seed
    add256_scale, workers = tuple(s.add256_scale), s.workers
    bbch_scale = tuple(s.bbch_scale) if s.bbch_scale else None
    if workers is None:
        workers = min(4, max((os.cpu_count() or 1) - 1, 0)) if dev.type == "cuda" else 0
    threads = s.threads or (2 if dev.type == "cuda" else os.cpu_count() or 1)
    torch.set_num_threads(threads)
    if workers:
        # Loader processes each use one core (torch sees to its own threads there). OpenCV's is set here, before
        # the fork: cv2.setNumThreads inside a forked worker hangs.
        cv2.setNumThreads(1)
    torch.manual_seed(seed)
    if source is None and s.init is None and is_pretrained(s.backbone):
        weights_path(s.backbone)  # missing or different ImageNet weights stop the run before the data is read
    add = load_add256(s.add256, "training")
    bbch = load_applebbch76(s.applebbch76, "training") if s.bbch_tiles else []
    if s.ignore_from is not None and not 0 < s.ignore_from < s.min_visible:
        raise TrainingError(f"--ignore-from {s.ignore_from}: give a visible fraction between 0 and --min-visible "
                            f"({s.min_visible})")
    sim = [x for f in s.sim_flight
           for x in (load_sim_frames(f, s.min_visible, min_ignore=s.ignore_from) if s.ignore_from is not None
                     else load_sim_frames(f, s.min_visible))]
    val = validation_sets(s.add256, s.applebbch76, s.val_flight, bool(s.bbch_tiles))
    fingerprint = data_fingerprint(add, bbch, sim)
    log.info("data: %d ADD256 patches, %d AppleBBCH76 tiles (%d/epoch), %d simulated frames (%d crops/epoch); "
             "validation: %s; %s%s, %d threads, %d loader processes", len(add), len(bbch), min(s.bbch_tiles, len(bbch)),
             len(sim), sim_crops if sim else 0, ", ".join(f"{k} {len(v)}" for k, v in val.items()), dev,
             " bfloat16 autocast" if s.amp else "", threads, workers)
    plan = EpochPlan(len(add), len(sim), sim_crops, seed, len(bbch), s.bbch_tiles)
    per_epoch = math.ceil(len(plan) / batch)
    total = epochs * per_epoch
    config = dict(backbone=s.backbone, fpn_channels=s.fpn_channels, head_width=s.head_width)
    if s.roi_context is not None:
        config["roi_context"] = s.roi_context
    if s.anchor_scales:
        config["anchor_scales"] = s.anchor_scales
    if source is not None:
        config = ckpt["config"]
        it, history, best = ckpt["iteration"], ckpt["history"], ckpt["best_ap50"]
        cpu_s, wall_s = ckpt.get("cpu_s", 0.0), ckpt.get("wall_s", 0.0)
        if ckpt.get("data") not in (None, fingerprint):
            log.warning("%s was trained on other data (fingerprint %s, here %s): the resume is not bit for bit",
                        source, ckpt["data"], fingerprint)
        for k, now in (("threads", threads), ("device", dev.type), ("amp", s.amp)):
            if ckpt.get("where", {}).get(k, now) != now:
                log.warning("%s ran with %s %s, this with %s: the resume is not bit for bit", source, k,
                            ckpt["where"][k], now)
    elif s.init is not None:
        config = ckpt["config"]
        log.info("initialised from %s (%s, trained %d iterations)", s.init, config, ckpt["iteration"])
        if s.widen_fpn is not None:
            try:
                model = widen_pyramid(model, s.widen_fpn)
            except ValueError as e:
                raise TrainingError(f"--widen-fpn {s.widen_fpn}: {e}") from None
            config = model_config(model)
            log.info("its pyramid widened to %d channels, the new ones silent", s.widen_fpn)
        if s.roi_context is not None and s.roi_context != config.get("roi_context", 1.0):
            config = dict(config, roi_context=s.roi_context)
            model = rebuilt(model, config)
            log.info("its box head now pools %.2f times each box", s.roi_context)
        if s.anchor_scales and s.anchor_scales != config.get("anchor_scales", 0):
            try:
                model = with_square_anchors(model, s.anchor_scales)
            except ValueError as e:
                raise TrainingError(f"--anchor-scales {s.anchor_scales}: {e}") from None
            config = model_config(model)
            log.info("its anchors now %d square sizes per level, each starting as its square anchor",
                     s.anchor_scales)
        it, history, best, cpu_s, wall_s = 0, [], -1.0, 0.0, 0.0
    else:
        model = make(config, imagenet=is_pretrained(s.backbone))
        if is_pretrained(s.backbone):
            log.info("%s: ImageNet weights, checked", s.backbone)
        it, history, best, cpu_s, wall_s = 0, [], -1.0, 0.0, 0.0
    if s.rpn_fg_iou != model.rpn.proposal_matcher.high_threshold:  # training only: the network is the same
        model.rpn.proposal_matcher = Matcher(s.rpn_fg_iou, RPN_BG_IOU, allow_low_quality_matches=True)
        log.info("the RPN trains its anchors as apples from IoU %.2f", s.rpn_fg_iou)
    frozen = freeze_stages(model, s.freeze_stages)
    if frozen:
        log.info("the stem and the first %d pyramid stage(s) stay as they are: %d parameters", s.freeze_stages, frozen)
    opt = torch.optim.SGD(model.parameters(), lr=lr, momentum=0.9, weight_decay=1e-4)
    if source is not None:
        opt.load_state_dict(ckpt["optimizer"])
        torch.set_rng_state(ckpt["torch_rng"])
        if it >= total:
            log.info("%s is finished (iteration %d of %d, %d epochs), %.2f CPU-hours: nothing left to train", source,
                     it, total, epochs, cpu_s / 3600)
        else:
            log.info("resumed %s at iteration %d/%d (epoch %d of %d), %.2f CPU-hours so far", source, it, total,
                     it // per_epoch + 1, epochs, cpu_s / 3600)
    model.to(dev)
    for state in opt.state.values():  # a resumed optimiser's momenta go where the weights are
        for k, v in state.items():
            if torch.is_tensor(v):
                state[k] = v.to(dev)
    run_info = dict(backbone=config["backbone"], fpn_channels=config["fpn_channels"],
                    head_width=config.get("head_width"), epochs=epochs, batch=batch, lr=lr, sim_crops=sim_crops,
                    seed=seed, sim_flights=[str(f) for f in s.sim_flight], add256_train=len(add),
                    applebbch76_train=len(bbch), bbch_tiles=plan.bbch_tiles, sim_frames=len(sim), iterations=total,
                    validation={k: len(v) for k, v in val.items()}, imagenet=is_pretrained(config["backbone"]),
                    init=str(s.init) if s.init is not None else None, add256_scale=list(add256_scale),
                    min_visible=s.min_visible, freeze_stages=s.freeze_stages,
                    bbch_scale=list(bbch_scale) if bbch_scale else None, ignore_from=s.ignore_from,
                    widen_fpn=s.widen_fpn, roi_context=config.get("roi_context", 1.0),
                    anchor_scales=config.get("anchor_scales", 0), rpn_fg_iou=s.rpn_fg_iou)
    if source is not None:  # where the run began, not this call's --init and --widen-fpn
        run_info["init"] = (ckpt.get("run") or {}).get("init")
        run_info["widen_fpn"] = (ckpt.get("run") or {}).get("widen_fpn")
    run_settings_now = {k: _plain(getattr(s, k)) for k in RUN_FIELDS}
    where = dict(threads=threads, device=dev.type, amp=s.amp)
    c0, w0 = time.process_time(), time.time()

    def save(*, keep: bool = False, best_too: bool = False):
        """last.pt (and best.pt, and the kept state where asked): the CPU time is this process's threads', added up
        over every call of the run."""
        ck = {"config": config, "model": model.state_dict(), "optimizer": opt.state_dict(), "iteration": it,
              "history": history, "best_ap50": best, "torch_rng": torch.get_rng_state(), "run": run_info,
              "settings": dict(run_settings_now, epochs=epochs), "data": fingerprint, "where": where,
              "cpu_s": cpu_s + time.process_time() - c0, "wall_s": wall_s + time.time() - w0}
        save_atomic(ck, out / "last.pt")
        if best_too:
            save_atomic(ck, out / "best.pt")
        if keep and s.keep is not None:
            n = save_state(ck, s.keep)
            log.info("kept the training state in %s (%.1f MB, iteration %d)", s.keep, n / 1e6, it)

    model.train()
    t0, it0 = time.time(), it
    smooth = None
    stopping = None
    with StopRequest() as request:
        while it < total and stopping is None:
            epoch, pos = divmod(it, per_epoch)
            items = EpochItems(plan.items(epoch), add, sim, seed, epoch, add256_scale, bbch, bbch_scale,
                               sim_ignore=s.ignore_from is not None)
            rest = torch.utils.data.Subset(items, range(pos * batch, len(items)))
            # its own generator: a loader drawing its seed from torch's would shift the RNG on every resume
            loader = torch.utils.data.DataLoader(rest, batch_size=batch, num_workers=workers, collate_fn=collate,
                                                 pin_memory=dev.type == "cuda", generator=torch.Generator())
            for imgs, tgts in loader:
                imgs = [x.to(dev, non_blocking=True) for x in imgs]
                tgts = [{k: v.to(dev, non_blocking=True) for k, v in t.items()} for t in tgts]
                for g in opt.param_groups:
                    g["lr"] = lr_at(it, total, lr)
                with torch.autocast(dev.type, dtype=torch.bfloat16, enabled=s.amp):
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
                if s.fit_minutes and it == it0 + FIT_AFTER and source is None:
                    # the epochs that fill the time asked for, from the rate of the second half of the first FIT_AFTER
                    # iterations (past the start-up; the schedule is still warming up)
                    rate = (time.time() - t_fit) / (FIT_AFTER - FIT_AFTER // 2)
                    epochs = max(1, int((FIT_SHARE * s.fit_minutes * 60 - (time.time() - t0)) / rate / per_epoch))
                    total = run_info["iterations"] = epochs * per_epoch
                    run_info["epochs"] = epochs
                    log.info("--fit-minutes %.1f: %.3f s/it, so %d epochs (%d iterations)", s.fit_minutes, rate, epochs,
                             total)
                vals = {k: v.item() for k, v in losses.items()}
                smooth = vals if smooth is None else {k: 0.95 * smooth[k] + 0.05 * vals[k] for k in vals}
                if it % log_every == 0 or it == total:
                    rate = max(it - it0, 1) / max(time.time() - t0, 1e-9)
                    log.info("epoch %d/%d it %d/%d loss %.3f (%s) lr %.4f %.2f it/s ETA %s", epoch + 1, epochs, it, total,
                             sum(smooth.values()), " ".join(f"{k[5:]} {v:.3f}" for k, v in smooth.items()),
                             opt.param_groups[0]["lr"], rate, _eta((total - it) / rate))
                end_of_epoch = it % per_epoch == 0 or it == total
                if end_of_epoch and (math.ceil(it / per_epoch) % s.validate_every and it < total):
                    log.info("epoch %d done; %.2f CPU-hours", it // per_epoch, (cpu_s + time.process_time() - c0) / 3600)
                    save(keep=True)  # an epoch's end without validation (--validate-every)
                elif end_of_epoch:
                    m = {"epoch": math.ceil(it / per_epoch), "iteration": it,
                         "minutes": round((time.time() - t0) / 60, 1),
                         **score_validation(model, val, device=dev, amp=s.amp)}
                    m["cpu_hours"] = round((cpu_s + time.process_time() - c0) / 3600, 3)
                    history.append(m)
                    log.info("validation after epoch %d: AP50 %.3f (%s); %.2f CPU-hours", m["epoch"], m["val_ap50"],
                             ", ".join(f"{k} {m[k]['ap50']:.3f}" for k in val), m["cpu_hours"])
                    improved = m["val_ap50"] > best
                    best = max(best, m["val_ap50"])
                    save(keep=True, best_too=improved)
                    (out / "history.json").write_text(json.dumps(history, indent=1))
                elif it % s.checkpoint_every == 0:
                    save()
                if s.max_minutes and (time.time() - t0) / 60 > s.max_minutes:
                    stopping = f"after {s.max_minutes:g} minutes (--max-minutes)"
                elif s.stop_after and it - it0 >= s.stop_after:
                    stopping = f"after {s.stop_after} iterations (--stop-after)"
                elif request.signal is not None:
                    stopping = f"on {signal.Signals(request.signal).name}"
                if stopping is not None and it < total and not end_of_epoch:
                    save(keep=True)
                if stopping is not None or end_of_epoch or it >= total:
                    break
    if stopping is not None and it < total:
        log.warning("stopped %s at iteration %d/%d; go on with --resume", stopping, it, total)
    return history


def _eta(seconds: float) -> str:
    return f"{seconds / 60:.1f} min" if seconds < 5400 else f"{seconds / 3600:.1f} h"


def run(args) -> int:
    train(from_options(TrainSettings(), args, TRAIN_FIELDS))
    return 0
