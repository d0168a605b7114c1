"""The ground's memory against flight length: replays a flight (lock-step, truth-replay detector, so that only
the ground's work is measured) and prints its resident memory at each minute of flight mapped, and its peak.

    python benchmarks/ground_memory.py out/sim/long-flight [--out out/bench/memory] [--json FILE] [--no-rrd]

Render the five-minute flight first: python -m sim flight --config sim/configs/long-flight.toml --out out/sim/long-flight
The ground samples its resident memory (/proc/self/statm) every second, from a thread; report.json keeps the
samples (frames mapped, MB) under timings.rss_mb_by_frames_mapped.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from ground.replay import replay
from pomar.flight import FlightDir


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("flight_dir")
    ap.add_argument("--out", help="replay output (default out/bench/memory/<flight>)")
    ap.add_argument("--json", help="also write the figures here")
    ap.add_argument("--every-s", type=float, default=60.0, help="rows of the table: one per this many flight seconds")
    ap.add_argument("--no-rrd", action="store_true", help="without the rerun recording (what it costs in memory)")
    args = ap.parse_args()
    flight = FlightDir(args.flight_dir)
    meta = flight.meta()
    out = Path(args.out or f"out/bench/memory/{flight.path.name}")
    rep = replay(flight.path, out, detector="truth-replay", keyframe_every=2, keyframe_width=0, quiet=False,
                 rrd=not args.no_rrd)
    samples = np.array(rep["timings"]["rss_mb_by_frames_mapped"], float).reshape(-1, 2)
    print(f"\n{flight.path}: {meta.frame_count} frames, {meta.frame_count / meta.fps:.0f} s of flight, "
          f"{meta.width}x{meta.height} at {meta.fps:g} fps; {rep['apples']} apples; wall {rep['wall_seconds']:.0f} s")
    print(f"{'flight s':>9}{'frames':>8}{'RSS MB':>9}")
    rows, last = [], -1
    for t in np.arange(0, meta.frame_count / meta.fps + 1e-9, args.every_s)[1:].tolist() + [meta.frame_count / meta.fps]:
        k = int(np.searchsorted(samples[:, 0], t * meta.fps, side="right")) - 1
        if k > last:  # the last sample up to this much flight mapped
            last = k
            rows.append({"flight_s": float(samples[k, 0] / meta.fps), "frames": int(samples[k, 0]),
                         "rss_mb": float(samples[k, 1])})
            print(f"{rows[-1]['flight_s']:>9.0f}{rows[-1]['frames']:>8}{rows[-1]['rss_mb']:>9.0f}")
    half = samples[samples[:, 0] >= samples[-1, 0] / 2]
    growth = float(np.polyfit(half[:, 0] / meta.fps / 60, half[:, 1], 1)[0]) if len(half) >= 3 else float("nan")
    res = {"flight": str(flight.path), "flight_seconds": meta.frame_count / meta.fps, "table": rows,
           "peak_rss_mb": rep["timings"]["peak_rss_mb"], "growth_mb_per_min_second_half": growth,
           "submodels": rep["registration"]["submodels"], "registered": rep["frames"]["registered"]}
    print(f"peak {res['peak_rss_mb']:.0f} MB; over the flight's second half the resident memory grows "
          f"{growth:+.1f} MB per minute of flight; {res['submodels']} sub-models")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(res, indent=2) + "\n")


if __name__ == "__main__":
    main()
