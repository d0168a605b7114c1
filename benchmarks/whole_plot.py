"""Whole-plot flights (serpentine passes): apples counted twice, counts and per-row counts against the truth, F1,
and the ground's time per frame on each pass, with cross-pass identity and without it (the baseline).

    .venv/bin/python -m sim flight --config sim/configs/whole-plot.toml --out out/sim/whole-plot
    .venv/bin/python benchmarks/whole_plot.py out/sim/whole-plot [more flights] [--out out/bench/whole-plot]

Each flight is replayed lock-step through both processes (`python -m ground replay`, the shipped detector) twice:
as is, and with ``--no-cross-pass``. Time nothing else meanwhile (2 cores).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from pomar.flight import FlightDir


def pass_of_frames(flight: FlightDir) -> np.ndarray:
    """Each frame's pass (0, 1, ...; -1 in a turn): the frames between changes of the along-row direction of travel."""
    cfg = json.loads((flight.path / "sim_config.json").read_text())
    az = np.radians(cfg["orchard"].get("row_azimuth_deg", 0.0))
    fr = flight.truth_frames()
    o = flight.origin()
    enu = o.to_enu(fr["lat"], fr["lon"], fr["alt"])
    # rows run along the orchard's y axis, turned by the azimuth (clockwise from north)
    along = enu[:, 0] * np.sin(az) + enu[:, 1] * np.cos(az)
    v = np.gradient(along) * float(flight.meta().fps)
    moving = np.abs(v) > 0.5 * np.median(np.abs(v))
    sign = np.sign(v) * moving
    out = np.full(len(v), -1)
    k = -1
    for i in range(len(v)):
        if sign[i] != 0 and (i == 0 or sign[i] != sign[i - 1]):
            k += 1
        if sign[i] != 0:
            out[i] = k
    return out


def seconds_per_frame_by_pass(rep: dict, passes: np.ndarray) -> list[float]:
    prog = np.array(rep["timings"].get("frames_mapped_by_wall_s") or [], float).reshape(-1, 2)
    out = []
    for k in range(passes.max() + 1):
        idx = np.nonzero(passes == k)[0]
        sel = (prog[:, 1] >= idx[0]) & (prog[:, 1] <= idx[-1]) if len(prog) else np.zeros(0, bool)
        if sel.sum() < 2:
            out.append(float("nan"))
            continue
        t, f = prog[sel, 0], prog[sel, 1]
        out.append(float((t[-1] - t[0]) / max(f[-1] - f[0], 1)))
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("flights", nargs="+", type=Path)
    ap.add_argument("--out", type=Path, default=Path("out/bench/whole-plot"))
    a = ap.parse_args(argv)
    lines = []
    for path in a.flights:
        flight = FlightDir(path)
        passes = pass_of_frames(flight)
        for mode, extra in (("cross-pass", []), ("baseline", ["--no-cross-pass"])):
            out = a.out / path.name / mode
            print(f"{path.name}: replay ({mode}) ...", file=sys.stderr, flush=True)
            subprocess.run([sys.executable, "-m", "ground", "replay", str(path), "--out", str(out), "--quiet"] + extra,
                           check=True, stdout=subprocess.DEVNULL)
            rep = json.loads((out / "report.json").read_text())
            ev = rep["evaluation"]
            rows = [r for r in ev["rows"] if r["truth_visible"] >= 30]
            row_err = [100.0 * (r["count"] - r["truth_visible"]) / r["truth_visible"] for r in rows]
            spf = seconds_per_frame_by_pass(rep, passes)
            lines.append(f"{path.name:<16} {mode:<11} {ev['count']:>6} {ev['truth_count']:>6} {ev['count_error_pct']:>+7.1f} "
                         f"{ev.get('duplicates', 0):>5} {max(np.abs(row_err)) if row_err else float('nan'):>8.1f} "
                         f"{ev['f1']:>6.3f} {rep['association']['stats'].get('merged_across_passes', 0):>6}  "
                         + " ".join(f"{x:.2f}" for x in spf))
            lines.append("    rows (count / visible): " + ", ".join(f"{r['row']}: {r['count']}/{r['truth_visible']}"
                                                            for r in ev["rows"]))
    print(f"{'flight':<16} {'mode':<11} {'count':>6} {'truth':>6} {'err %':>7} {'dups':>5} {'row err':>8} {'F1':>6} "
          f"{'x-pass':>6}  ground s/frame by pass")
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
