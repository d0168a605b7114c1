"""The paper's flight as a DJI user records it: a simulated 4K flight (sim/configs/paper-dji.toml: a Phantom 4 Pro's
lens, 12 m, 30 deg off nadir, along a row looking across the rows) given to the project only as its MP4 and an SRT,
through README's DJI command, against the same flight replayed from its .tlog.

    python benchmarks/dji_paper.py out/dji/paper-dji [--out out/dji]

Three replays, each scored against the flight's truth (the shape F1 at 0.10 m, the count against the apples at least
half visible in 3 frames, the georeference's scale error):
- ``tlog``: the flight directory itself (the .tlog's positions, gimbal and camera events);
- ``mavic3``: README's command with a Mavic 3 SRT (one subtitle a frame, 5 decimals, no attitudes);
- ``p4pro``: README's command with the Phantom 4 Pro's own SRT (one a second, 4 decimals: 11 m; the height above
  take-off to 0.01 m): GPS alone cannot scale this map, the heights above take-off against the floor it sees do.
Prints one table; nothing else should run meanwhile (the replays are timed).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

DJI = ["--camera", "phantom-4-pro", "--camera-tilt-deg", "60", "--camera-yaw-deg", "90"]


def replay(args: list[str], out: Path, scale: str | None = None) -> float:
    t0 = time.monotonic()
    extra = ["--detector-scale", scale] if scale else []
    r = subprocess.run([sys.executable, "-m", "ground", "replay", *args, *extra, "--out", str(out), "--quiet"],
                       capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"replay {' '.join(args)} failed:\n{r.stderr[-3000:]}")
    return time.monotonic() - t0


def main(argv=None) -> int:
    from ground.evaluation.scoring import evaluate_map
    from pomar.flight import FlightDir

    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("flight", help="the simulated flight (python -m sim flight --config sim/configs/paper-dji.toml)")
    p.add_argument("--out", default="out/dji")
    p.add_argument("--only", nargs="+", choices=["tlog", "mavic3", "p4pro"], default=["tlog", "mavic3", "p4pro"])
    p.add_argument("--detector-scale", help="one detector scale for every replay (default: each its own, from the "
                                            "apple size its log foresees: a log's height moves it a step)")
    a = p.parse_args(argv)
    flight, out = FlightDir(a.flight), Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = {}
    for name in a.only:
        res = out / name
        if name == "tlog":
            wall = replay([str(flight.path)], res, a.detector_scale)
        else:
            logs = out / f"{name}-srt"
            layout = {"mavic3": "mavic3", "p4pro": "p4p"}[name]
            r = subprocess.run([sys.executable, "-m", "sim", "logs", str(flight.path), "--out", str(logs), "--srt-layout",
                                layout, "--no-attitude"], capture_output=True, text=True)
            if r.returncode != 0:
                raise SystemExit(r.stderr)
            video = logs / "DJI_0001.MP4"
            shutil.copy(flight.video, video)
            (logs / "video.SRT").replace(logs / "DJI_0001.SRT")
            wall = replay(["--video", str(video), "--log", str(logs / "DJI_0001.SRT"), *DJI], res, a.detector_scale)
        ev = evaluate_map(flight, res)
        rep = json.loads((res / "report.json").read_text())
        g = ev.get("georeference_error", {})
        rows[name] = {"f1": ev["f1"], "count": ev["count"], "truth": ev["truth_count"],
                      "count_error_pct": ev["count_error_pct"], "scale_error_pct": g.get("scale_error_pct"),
                      "scale_from": rep["registration"].get("georeference_scale_from"), "wall_s": wall}
        print(f"{name}: {json.dumps(rows[name])}", file=sys.stderr)
    print(f"{'replay':8s} {'F1':>6s} {'count':>6s} {'truth':>6s} {'err %':>7s} {'scale %':>8s}  scaled by   wall s")
    for name, r in rows.items():
        print(f"{name:8s} {r['f1']:6.3f} {r['count']:6d} {r['truth']:6d} {r['count_error_pct']:+7.1f} "
              f"{r['scale_error_pct']:+8.2f}  {r['scale_from']:10s} {r['wall_s']:6.0f}")
    if "tlog" in rows:
        for name in ("mavic3", "p4pro"):
            if name in rows:
                print(f"{name} against tlog: F1 {rows[name]['f1'] - rows['tlog']['f1']:+.3f}, count error "
                      f"{rows[name]['count_error_pct'] - rows['tlog']['count_error_pct']:+.1f} points")
    (out / f"dji_paper{'-scale-' + a.detector_scale if a.detector_scale else ''}.json").write_text(
        json.dumps(rows, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
