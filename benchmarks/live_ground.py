"""The ground alone, live (issue 15): a flight's recorded stream (a ground's journal.bin) played over zenoh into a
ground in its own process, lock-step (``--speed 0``: mapping inline, the reference) and at S x its capture-time
pace (mapping in its own process), with one table of how long frames waited and what the map scored.

    python benchmarks/live_ground.py FLIGHT_DIR JOURNAL [--speeds 0 1 3] [--name N] [--json FILE] [-- GROUND ARGS]

Record the journal first with a lock-step replay of the flight (the onboard detector runs there, not here):
    python -m ground replay FLIGHT_DIR --out out/replay/F   # -> out/replay/F/journal.bin
Take the timings with nothing else running: the player and the ground share the machine's cores.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from ground.replay import replay


def row(rep: dict, speed: float) -> dict:
    tm, ev, fr = rep["timings"], rep.get("evaluation", {}), rep["frames"]
    shares = rep["pose_shares"]
    return {"speed": speed, "wall_s": rep["wall_seconds"], "flight_s": rep["flight_seconds"],
            "delay_median_s": tm["frame_delay_median_s"], "delay_p95_s": tm["frame_delay_p95_s"],
            "delay_p95_after_first_model_s": tm.get("frame_delay_p95_s_after_first_model"),
            "first_model_after_s": tm.get("first_model_after_s"),
            "f1": ev.get("f1"), "count": rep["apples"], "count_error_pct": ev.get("count_error_pct"),
            "registered": shares["registered"], "tracked": shares["tracked"], "interpolated": shares["interpolated"],
            "telemetry": shares["telemetry"], "mapping_keyframes": rep["registration"]["keyframes_processed"],
            "tracking_failed": rep["tracking"]["failed"], "frames": fr["frames"],
            "peak_rss_mb": tm["peak_rss_mb"], "mapping_peak_rss_mb": tm.get("mapping_peak_rss_mb"),
            "mapping_s_per_keyframe": rep["registration"]["seconds_per_keyframe_median"]}


def num(v, fmt: str) -> str:
    """A figure, or a dash where there is none (0 is a figure)."""
    return "–" if v is None else format(v, fmt)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("flight_dir", help="the flight (its truth scores the map)")
    ap.add_argument("journal", help="its recorded stream")
    ap.add_argument("--speeds", type=float, nargs="+", default=[0.0, 1.0, 3.0])
    ap.add_argument("--name", default=None, help="outputs under out/bench/live/NAME (default: the flight's name)")
    ap.add_argument("--json", help="also write the rows here")
    argv = sys.argv[1:]
    cut = argv.index("--") if "--" in argv else len(argv)
    args = ap.parse_args(argv[:cut])
    ground_args = argv[cut + 1:]  # after --: passed on to the ground node
    name = args.name or Path(args.flight_dir).name
    rows = []
    for s in args.speeds:
        print(f"playing {args.journal} at {'lock-step' if s == 0 else f'{s:g}x'} ...", flush=True)
        rep = replay(args.flight_dir, Path("out/bench/live") / name / f"speed-{s:g}", recorded=args.journal, speed=s,
                     quiet=True, ground_args=ground_args)
        rows.append(row(rep, s))
    ref = rows[0] if rows[0]["speed"] == 0 else None
    print(f"\n{name}: the ground alone, its recorded stream played (nothing else running?)")
    print("| speed | wall s | delay median / p95 s | first model after s | p95 s of frames after it | F1 | count (error) | "
          "poses reg/track/interp/telem | mapping keyframes | tracking failed | peak MB ground + mapper |")
    print("| --- | ---: | ---: | ---: | ---: | ---: | ---: | --- | ---: | ---: | ---: |")
    for r in rows:
        d = "" if ref is None or r is ref or r["f1"] is None else f" ({r['f1'] - ref['f1']:+.3f})"
        speed = "lock-step" if r["speed"] == 0 else f"{r['speed']:g}x"
        print(f"| {speed} | {r['wall_s']:.1f} | "
              f"{r['delay_median_s']:.2f} / {r['delay_p95_s']:.2f} | {num(r['first_model_after_s'], '.2f')} | "
              f"{num(r['delay_p95_after_first_model_s'], '.2f')} | {num(r['f1'], '.3f')}{d} | "
              f"{r['count']} ({num(r['count_error_pct'], '+.1f')} %) | "
              f"{r['registered']:.2f}/{r['tracked']:.2f}/{r['interpolated']:.2f}/{r['telemetry']:.2f} | "
              f"{r['mapping_keyframes']} | {r['tracking_failed']} | {r['peak_rss_mb']:.0f} + "
              f"{num(r['mapping_peak_rss_mb'], '.0f')} |")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(rows, indent=2) + "\n")


if __name__ == "__main__":
    main()
