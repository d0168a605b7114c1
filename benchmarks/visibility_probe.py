"""Does the detector know how visible an apple is, beyond its score? A linear probe on its own box features.

    python benchmarks/visibility_probe.py out/sim/outage-flight:3 out/sim/tune-1:2 out/sim/gen/eval-6:4 \\
        out/sim/gen/tune-2:3 [--checkpoint export/checkpoint] [--cache out/bench/visibility-probe]

Each FLIGHT:EVERY is a simulated flight, run every EVERY-th frame through the kept torch checkpoint at the scale the
onboard node gives the frame (pomar.apple_scale). For each detection scored 0.3 or more it keeps the box head's
features (256 for the shipped MobileNetV2's head, 1024 for a ResNet-18's) and the visible share of the truth apple it
lies on (0 where none). Then, leaving each flight out in turn, two logistic rules are fitted on the others'
detections to tell apples at least MIN_VISIBLE visible
(pomar.countable) from the rest: on the score alone (a threshold), and on the box features with the score (what a
visibility head on the shipped features could learn). Each is judged on the flight left out, against the score at
the count's confirm_score:
- the share of the apples in a frame flagged, by visible band, the share at which half are flagged and the width
  of the ramp (from a quarter to three quarters flagged): the definition is a step at MIN_VISIBLE;
- per apple: those flagged in at least MIN_VIEWS sampled frames against those at least MIN_VISIBLE visible in as
  many (sampled frames, so not the count's definition, but the same for every rule).
Needs the export extra (torch). Accuracy only; features are cached per flight (``--cache``).
"""

from __future__ import annotations

import argparse
import hashlib
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(ROOT / "benchmarks"))

from detector_visibility import EDGES, band_shares, crossing  # noqa: E402

from ground.apples.counting import CountingSettings  # noqa: E402
from ground.evaluation.scoring import input_problem, on_apple  # noqa: E402
from pomar.countable import MIN_VIEWS, MIN_VISIBLE  # noqa: E402
from pomar.flight import FlightDir  # noqa: E402

MIN_SCORE = 0.3  # detections kept for the probe: well below the count's threshold


def flight_features(flight: FlightDir, every: int, model, target_px: float) -> dict[str, np.ndarray]:
    """Per detection of ``model`` (a torch Faster R-CNN) on every ``every``-th frame: box-head features, score and
    the visible share of the truth apple it lies on; per truth apple-frame: its apple, visible share and the index of
    the nearest detection on it (-1: none)."""
    import torch

    from onboard.detector import boxes_before_resize, resized
    from pomar.apple_scale import ScalePolicy, flight_radius_px
    from pomar.video import iter_frames

    policy = ScalePolicy(target_px)
    radius = flight_radius_px(flight)
    td = {k: np.asarray(v) for k, v in flight.truth_detections().items()}
    det = {k: [] for k in ("feat", "score", "vis")}
    apple = {k: [] for k in ("apple", "vis", "det")}
    n, t0, todo = 0, time.monotonic(), len(range(0, len(radius), every))
    for idx, bgr in iter_frames(flight.video):
        if idx % every:
            continue
        s = policy.scale(float(radius[idx]))
        rgb = np.ascontiguousarray(bgr[..., ::-1])
        if s != 1.0:  # as the onboard node gives the detector the frame
            rgb, factors = resized(rgb, s)
        with torch.no_grad():
            images, _ = model.transform([torch.from_numpy(rgb).permute(2, 0, 1).float() / 255])
            feats = model.backbone(images.tensors)
            proposals, _ = model.rpn(images, feats)
            out = model.roi_heads(feats, proposals, images.image_sizes)[0][0]
            keep = out["scores"] >= MIN_SCORE
            boxes, scores = out["boxes"][keep], out["scores"][keep]
            f = model.roi_heads.box_head(model.roi_heads.box_roi_pool(feats, [boxes], images.image_sizes))
        b = boxes.numpy()
        b = (boxes_before_resize(b, factors) if s != 1.0 else b).astype(float)  # in the full frame's pixels
        cx, cy = (b[:, 0] + b[:, 2]) / 2, (b[:, 1] + b[:, 3]) / 2
        rows = np.flatnonzero(td["frame"] == idx)
        # detections x the frame's truth apples: each detection the visible share of its nearest apple where it lies on it,
        # each apple the nearest detection on it
        d = np.hypot(cx[:, None] - td["u"][rows][None], cy[:, None] - td["v"][rows][None])
        on = on_apple(d, td["r_px"][rows][None])
        vis = np.zeros(len(b))
        if len(rows) and len(b):
            j = d.argmin(1)
            hit = on[np.arange(len(b)), j]
            vis[hit] = td["visible_fraction"][rows][j[hit]]
            nearest = np.where(on, d, np.inf).argmin(0)
            found = np.where(on.any(0), n + nearest, -1)
        else:
            found = np.full(len(rows), -1)
        apple["apple"].extend(td["apple_id"][rows])
        apple["vis"].extend(td["visible_fraction"][rows])
        apple["det"].extend(found)
        det["feat"].append(f.numpy().astype(np.float16))
        det["score"].append(scores.numpy())
        det["vis"].append(vis)
        n += len(b)
        done = len(det["score"])
        rate = done / (time.monotonic() - t0)
        print(f"\r{flight.path.name}: {done}/{todo} frames, {rate:.2f} frames/s, ETA {(todo - done) / rate:.0f} s",
              end="", file=sys.stderr, flush=True)
    print(file=sys.stderr)
    return {**{k: np.concatenate(v) for k, v in det.items()}, **{"t_" + k: np.asarray(v) for k, v in apple.items()}}


def logistic(X: np.ndarray, y: np.ndarray, l2: float):
    """A logistic rule fitted on standardised ``X`` (L-BFGS, L2 penalty ``l2``): a function of new rows to P(y)."""
    import torch

    X = X.astype(np.float64)
    mu, sd = X.mean(0), X.std(0) + 1e-6
    Xt, yt = torch.from_numpy((X - mu) / sd), torch.from_numpy(y.astype(np.float64))
    lin = torch.nn.Linear(X.shape[1], 1, dtype=torch.float64)
    torch.nn.init.zeros_(lin.weight)  # from zero, not at random: the same rule every run
    torch.nn.init.zeros_(lin.bias)
    opt = torch.optim.LBFGS(lin.parameters(), max_iter=500, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        loss = torch.nn.functional.binary_cross_entropy_with_logits(lin(Xt)[:, 0], yt) + l2 * (lin.weight ** 2).sum()
        loss.backward()
        return loss

    opt.step(closure)
    return lambda Z: torch.sigmoid(lin(torch.from_numpy((Z.astype(np.float64) - mu) / sd))[:, 0]).detach().numpy()


def inputs(z, with_features: bool) -> np.ndarray:
    s = np.clip(z["score"].astype(float), 1e-4, 1 - 1e-4)
    logit = np.log(s / (1 - s))[:, None]
    return np.hstack([z["feat"].astype(np.float32), logit] if with_features else [logit]).astype(np.float32)


def judge(z, good: np.ndarray) -> tuple[np.ndarray, float, float, float]:
    """(share flagged per visible band, half at, ramp width, apples flagged / apples countable in sampled frames)."""
    i, vis, ids = z["t_det"], z["t_vis"], z["t_apple"]
    flag = (i >= 0) & good[np.maximum(i, 0)]
    share = band_shares(vis, flag)
    _, n_flag = np.unique(ids[flag], return_counts=True)
    _, n_vis = np.unique(ids[vis >= MIN_VISIBLE], return_counts=True)
    return (share, crossing(share, 0.5), crossing(share, 0.75) - crossing(share, 0.25),
            (n_flag >= MIN_VIEWS).sum() / max((n_vis >= MIN_VIEWS).sum(), 1))


def flight_spec(text: str) -> tuple[Path, int]:
    path, _, every = text.rpartition(":") if ":" in text else (text, "", "1")
    try:
        return Path(path), max(1, int(every))
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text}: give FLIGHT or FLIGHT:EVERY (a whole number)") from None


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("flights", nargs="+", type=flight_spec, metavar="FLIGHT[:EVERY]",
                    help="simulated flights (at least two), each run every EVERY-th frame (default 1)")
    ap.add_argument("--checkpoint", type=Path, default=ROOT / "export" / "checkpoint",
                    help="the torch checkpoint (default: the shipped model's, export/checkpoint); frames are scaled "
                         "to the shipped model's apple size (its metadata's apple_radius_px)")
    ap.add_argument("--cache", type=Path, default=ROOT / "out" / "bench" / "visibility-probe",
                    help="folder of each flight's features (NAME-PATHHASH-eEVERY.npz), reused when there")
    ap.add_argument("--l2", type=float, default=1e-2, help="the probe's L2 penalty (standardised features)")
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    a = ap.parse_args(argv)
    if len(a.flights) < 2:
        ap.error("give at least two flights: each is judged by rules fitted on the others")
    for path, _ in a.flights:
        if problem := input_problem(path):
            print(f"error: {problem}", file=sys.stderr)
            return 2
    data = {}
    model = None
    names = [p.name for p, _ in a.flights]
    for path, every in a.flights:
        # a flight's name, or its folder's too where two flights share a name
        name = path.name if names.count(path.name) == 1 else f"{path.parent.name}/{path.name}"
        key = hashlib.sha1(str(path.resolve()).encode()).hexdigest()[:8]
        cache = a.cache / f"{path.name}-{key}-e{every}.npz"
        if cache.is_file():
            data[name] = dict(np.load(cache))
            continue
        if model is None:
            import torch

            from export.model import load_checkpoint
            from onboard.detector import default_model_path, read_metadata

            if a.threads:
                torch.set_num_threads(a.threads)
            model = load_checkpoint(a.checkpoint)[0].eval()
            target = read_metadata(default_model_path()).get("apple_radius_px")
            print(f"checkpoint {a.checkpoint}, frames scaled to apples of {target} px", file=sys.stderr)
        data[name] = flight_features(FlightDir(path), every, model, float(target))
        cache.parent.mkdir(parents=True, exist_ok=True)
        np.savez(cache, **data[name])
    confirm = CountingSettings.confirm_score
    bands = [f"{lo:.2f}" for lo in EDGES[:-1]]
    print(f"share of the apples in a frame flagged, by visible share (from); the rules fitted on the other flights")
    print(f"{'flight, rule':<40}" + "".join(f"{b:>6}" for b in bands) + f"{'half':>7}{'width':>7}"
          f"{'apples':>8}")
    for held, z in data.items():
        rest = [d for n, d in data.items() if n != held]
        y = np.concatenate([d["vis"] >= MIN_VISIBLE for d in rest])
        rules = {f"score >= {confirm}": z["score"] >= confirm}
        for feats in (False, True):
            p = logistic(np.concatenate([inputs(d, feats) for d in rest]), y, a.l2)
            if feats:
                rules["features + score, fitted"] = p(inputs(z, feats)) >= 0.5
            else:  # on the score alone the rule is a threshold: name it
                grid = np.linspace(MIN_SCORE, 0.9999, 20000)
                at = grid[np.argmax(p(inputs({"score": grid}, False)) >= 0.5)]
                rules[f"score >= {at:.3f}, fitted"] = z["score"] >= at
        for name, good in rules.items():
            share, half, width, ratio = judge(z, good)
            print(f"{held + ', ' + name:<40}" + "".join(f"{s:>6.2f}" for s in share)
                  + f"{half:>7.2f}{width:>7.2f}{ratio:>8.2f}")
    print(f"half: the visible share at which half are flagged (the definition: {MIN_VISIBLE}); width: from a quarter "
          f"to three quarters flagged; apples: flagged in {MIN_VIEWS}+ sampled frames / {MIN_VISIBLE}+ visible in as many")
    return 0


if __name__ == "__main__":
    sys.exit(main())
