"""Train the detector candidates on equal terms (same data, same schedule), score them on the validation sets, and
keep the chosen one's checkpoint. On the GPU machine or on this CPU.

    python -m export pack out/sim/detector-train --out gpu/detector-train.npz --quality 80     # on this machine
    python -m export pack out/sim/detector-val --out gpu/detector-val.npz --every 5 --quality 90
    python -m export pack out/sim/tune-1 --out gpu/heldout-720p.npz --every 20 --limit 12
    python -m export pack out/sim/paper-4k-small --out gpu/heldout-4k.npz --every 5 --limit 6 --quality 85
    (gpu/add256: ADD256's training patches and training.json; gpu/applebbch76: its images/ and labels/;
     gpu/weights: the ImageNet files of export.pretrained, found through $POMAR_WEIGHTS)
    PYTHONPATH=. python3 benchmarks/detector_candidates.py --data gpu --out $OUT --minutes 6   # on the GPU machine
    .venv/bin/python benchmarks/detector_candidates.py --data gpu --out out/bench/candidates --device cpu --epochs 6

The candidates (``CANDIDATES``): Faster R-CNN on MobileNetV2 and EfficientNet-Lite0, from ImageNet, and today's
ResNet-18 from scratch, each with its own pyramid and box head widths. Each runs ``python -m export train`` with the
same data and schedule: ``--epochs N`` (the same iterations for all), or ``--minutes M`` (``--fit-minutes``: the same
time; all at once on a GPU). Then each one's last checkpoint (not its best epoch) is scored anew on the same validation sets
(ADD256's held-back photos, AppleBBCH76's held-out photos, the held-out simulated frames at their own size); ADD256's
test split is left for the end. ``candidates.json`` holds the figures; the chosen model's weights come back as fp16
parts (``export.parts``) under ``OUT/<backbone>/``, with each run's log under ``OUT/logs``. Everything under OUT stays
within what a device run returns (8 files, 60 MB).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from export.settings import TrainSettings

#: backbone: its own pyramid channels and box head width (today's ResNet-18 as shipped)
CANDIDATES = {"mobilenet_v2": (48, 256), "efficientnet_lite0": (48, 256), "resnet18": (128, 1024)}
HELDOUT = {"sim_720p": "heldout-720p.npz", "sim_4k": "heldout-4k.npz"}
#: What a device run brings back: files and bytes under OUT.
MAX_FILES, MAX_BYTES = 8, 60_000_000


def train_command(bb: str, data: Path, runs: Path, a, minutes: float) -> list[str]:
    fpn, head = CANDIDATES[bb]
    schedule = ["--epochs", str(a.epochs)] if a.epochs else ["--fit-minutes", str(minutes), "--max-minutes",
                                                             str(minutes * 1.15)]
    bbch = ["--applebbch76", str(data / "applebbch76")] if (data / "applebbch76").is_dir() else ["--bbch-tiles", "0"]
    val = ["--val-flight", str(data / "detector-val.npz")] if (data / "detector-val.npz").is_file() else []
    return [sys.executable, "-m", "export", "train", "--out", str(runs / bb), "--add256", str(data / "add256"), *bbch,
            "--sim-flight", str(data / "detector-train.npz"), *val, "--backbone", bb, "--fpn-channels", str(fpn),
            "--head-width", str(head), "--device", a.device, *(["--amp"] if a.amp else []), "--batch", str(a.batch),
            "--lr", str(a.lr), "--sim-crops", str(a.sim_crops), *schedule, "--workers", str(a.workers),
            "--checkpoint-every", "500", "--seed", str(a.seed), "--add256-scale", *map(str, a.add256_scale)]


def evaluation_sets(data: Path) -> dict[str, list]:
    """The sets every candidate is scored on, loaded once: export.train's validation sets (as its runs name them) and
    the held-out packs. Scored anew for each, so that no candidate is judged on a set its run saw in another state."""
    from export.data import load_sim_frames
    from export.data import validation_sets

    bbch = data / "applebbch76"
    val = [data / "detector-val.npz"] if (data / "detector-val.npz").is_file() else []
    sets = validation_sets(data / "add256", bbch if bbch.is_dir() else None, val, bbch.is_dir())
    sets.update({name: load_sim_frames(data / pack) for name, pack in HELDOUT.items() if (data / pack).is_file()})
    return sets


def score(bb: str, runs: Path, sets: dict[str, list], device: str) -> dict:
    import torch

    from export.model import load_checkpoint
    from export.train import pick_device, score_samples

    last = runs / bb / "last.pt"
    if not last.is_file():
        return {"backbone": bb, "error": "no checkpoint (see its log)"}
    model, ckpt = load_checkpoint(last)
    dev = pick_device(device)
    model.to(dev)
    out = {"backbone": bb, "parameters_m": round(sum(p.numel() for p in model.parameters()) / 1e6, 2),
           "iterations": ckpt["iteration"], "epochs": ckpt["run"]["epochs"], "history": ckpt["history"]}
    for name, samples in sets.items():
        out[name] = score_samples(model, samples, device=dev)
    out["ckpt"] = ckpt
    del model
    if dev.type == "cuda":
        torch.cuda.empty_cache()
    return out


def mean_ap(r: dict) -> float:
    """The mean AP@0.5 over the validation sets and the held-out packs (never a test split)."""
    aps = [v["ap50"] for k, v in r.items() if isinstance(v, dict) and "ap50" in v]
    return sum(aps) / len(aps) if aps else -1.0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--data", type=Path, required=True)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--runs", type=Path, default=Path("/tmp/pomar-candidates"), help="checkpoints (not brought back)")
    p.add_argument("--minutes", type=float, default=6.0, help="training time of each candidate (all at once)")
    p.add_argument("--epochs", type=int, help="train each candidate this many epochs instead of --minutes")
    p.add_argument("--device", default="cuda")
    p.add_argument("--amp", action=argparse.BooleanOptionalAction, default=True)
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--lr", type=float, default=0.02)
    p.add_argument("--sim-crops", type=int, default=1500)
    p.add_argument("--workers", type=int, default=4)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--add256-scale", type=float, nargs=2, default=TrainSettings.add256_scale, metavar=("LO", "HI"),
                   help="random scale range of ADD256 patches (export train's --add256-scale)")
    p.add_argument("--only", nargs="*", default=list(CANDIDATES), choices=list(CANDIDATES))
    p.add_argument("--one-at-a-time", action="store_true", help="train the candidates one after another, each for "
                   "MINUTES / their number, instead of all at once")
    a = p.parse_args(argv)
    a.out.mkdir(parents=True, exist_ok=True)
    (a.out / "logs").mkdir(exist_ok=True)
    t0 = time.time()
    procs = {}
    groups = [[bb] for bb in a.only] if a.one_at_a_time or a.epochs else [a.only]
    minutes = a.minutes / len(groups)
    for group in groups:
        t_group = time.time()
        for bb in group:
            log = open(a.out / "logs" / f"{bb}.log", "w")
            procs[bb] = subprocess.Popen(train_command(bb, a.data, a.runs, a, minutes), stdout=log,
                                         stderr=subprocess.STDOUT)
        deadline = t_group + minutes * 60 * 1.3 + 60
        while any(procs[bb].poll() is None for bb in group) and (a.epochs or time.time() < deadline):
            time.sleep(2)
        for bb in group:
            if procs[bb].poll() is None:
                procs[bb].terminate()
                procs[bb].wait(30)
    print(f"trained in {(time.time() - t0) / 60:.1f} min: " + ", ".join(f"{b} rc {pr.returncode}" for b, pr in procs.items()),
          flush=True)
    results, ckpts = [], {}
    sets = evaluation_sets(a.data)
    for bb in a.only:
        r = score(bb, a.runs, sets, a.device)
        ckpts[bb] = r.pop("ckpt", None)
        results.append(r)
        print(json.dumps({k: v for k, v in r.items() if k != "history"}), flush=True)
        (a.out / "candidates.json").write_text(json.dumps({"candidates": results}, indent=1))
    # Keep the best mean AP among the candidates whose parts fit beside the logs and this table.
    from export.parts import PART_BYTES, save_parts

    used_files = len(a.only) + 1
    chosen = None
    for r in sorted(results, key=mean_ap, reverse=True):
        ck = ckpts.get(r["backbone"])
        if ck is None:
            continue
        size = 2 * sum(v.numel() for v in ck["model"].values() if v.is_floating_point()) + 1_000_000
        files = -(-size // PART_BYTES) + 1
        if used_files + files <= MAX_FILES and size <= MAX_BYTES:
            save_parts(ck, a.out / r["backbone"])
            chosen = r["backbone"]
            break
        r["not_kept"] = f"its fp16 weights ({size / 1e6:.0f} MB, {files} files) do not fit through a device run's return"
    summary = {"candidates": results, "chosen": chosen, "rule": "highest mean AP@0.5 over the validation sets and the "
               "held-out simulated frames, among checkpoints that can be kept",
               "minutes": round((time.time() - t0) / 60, 1)}
    (a.out / "candidates.json").write_text(json.dumps(summary, indent=1))
    print(f"chosen: {chosen}; {summary['minutes']} min in all", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
