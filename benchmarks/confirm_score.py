"""The count's scores for a detector (issue 70): which publish score (the drone's) and confirm score (the ground's)
give the best maps on tuning flights, measured from one detector run a flight.

    python benchmarks/confirm_score.py out/yield/tune-1 out/yield/tune-2 --model CANDIDATE.onnx \
        --publish 0.5 0.6 0.7 --confirm 0.6 0.7 0.8 0.9 --out out/bench/confirm

Each flight is replayed once lock-step with the drone publishing from the lowest ``--publish`` score (``ground replay
--detector-score-thresh``); then the ground alone runs again from that replay's journal for each pair (publish P,
confirm C >= P: ``ground replay FLIGHT --recorded JOURNAL --speed 0 --min-score P --confirm-score C
--no-confirm-at-model-score``), as a drone
publishing from P would have given it. Prints each pair's F1 and count error (against the simulator's countable
apples) per flight, their mean F1 and the root mean square of the count errors. Tuning flights only.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np


def replay(args: list[str], out: Path, reuse: bool) -> dict:
    report = out / "report.json"
    if not (reuse and report.is_file()):
        r = subprocess.run([sys.executable, "-m", "ground", "replay", *args, "--out", str(out), "--quiet"],
                           capture_output=True, text=True)
        if r.returncode:
            raise SystemExit(f"{out}: the replay failed: {r.stderr.strip().splitlines()[-1:]}")
    ev = json.loads(report.read_text()).get("evaluation") or {}
    if "f1" not in ev:
        raise SystemExit(f"{report}: no evaluation (a simulated flight with its truth is needed)")
    return ev


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("flights", nargs="+", type=Path, help="simulated tuning flights (with truth/)")
    p.add_argument("--model", type=Path, help="the ONNX detector (default: the shipped one)")
    p.add_argument("--publish", type=float, nargs="+", default=[0.5, 0.6, 0.7])
    p.add_argument("--confirm", type=float, nargs="+", default=[0.6, 0.7, 0.8, 0.9])
    p.add_argument("--out", type=Path, default=Path("out/bench/confirm"))
    p.add_argument("--reuse", action="store_true", help="keep replays an earlier run of the same --out made")
    a = p.parse_args(argv)
    model = ["--model", str(a.model)] if a.model else []
    low = min(a.publish)
    pairs = [(pub, c) for pub in sorted(a.publish) for c in sorted(a.confirm) if c >= pub]
    got: dict[tuple[float, float], list[dict]] = {pc: [] for pc in pairs}
    for f in a.flights:
        base = a.out / f.name / "base"
        replay([str(f), *model, "--detector-score-thresh", str(low)], base, a.reuse)
        for pub, c in pairs:
            ev = replay([str(f), "--recorded", str(base / "journal.bin"), "--speed", "0", "--min-score", str(pub),
                         "--confirm-score", str(c), "--no-confirm-at-model-score"],
                        a.out / f.name / f"p{pub:g}-c{c:g}", a.reuse)
            got[(pub, c)].append(ev)
            print(f"{f.name}: publish {pub:g}, confirm {c:g}: F1 {ev['f1']:.3f}, count {ev['count']} for "
                  f"{ev['truth_count']} ({ev['count_error_pct']:+.1f} %)", flush=True)
    print(f"\n{'publish':>7} {'confirm':>7} {'mean F1':>7} {'rms count err %':>15}  per flight (F1, count error %)")
    for (pub, c), evs in got.items():
        rms = float(np.sqrt(np.mean([e["count_error_pct"] ** 2 for e in evs])))
        each = ", ".join(f"{f.name} {e['f1']:.3f} {e['count_error_pct']:+.1f}" for f, e in zip(a.flights, evs))
        print(f"{pub:>7g} {c:>7g} {np.mean([e['f1'] for e in evs]):>7.3f} {rms:>15.1f}  {each}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
