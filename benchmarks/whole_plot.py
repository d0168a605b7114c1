"""Whole-plot flights (serpentine passes): apples counted twice, counts and per-row counts against the truth, F1,
and the ground's time per frame on each pass, with registration across passes and cross-pass identity, and without
them (the baseline).

    .venv/bin/python -m sim flight --config sim/configs/whole-plot.toml --out out/sim/whole-plot
    .venv/bin/python benchmarks/whole_plot.py out/sim/whole-plot [more flights] [--journals J ...] [--out DIR]

Each flight is replayed lock-step three times: as is; with ``--no-revisit`` (registration matches each keyframe only
against the previous ones); and with ``--no-revisit --no-cross-pass`` as well (the association merges an apple
only within its window of recent apples: the behaviour before issue 16). Without journals each replay runs both
processes (``python -m ground replay``, the shipped detector, about 1 s a frame here); with ``--journals`` (one per
flight, in order: the journal.bin of an earlier replay of it) the recorded stream is played instead and no detector
runs. ``--ground-args`` passes more options to every replay, for example the count's checks off with the journal
of a truth-detection replay (``--detector truth-replay``): what the ground does with perfect detections. Time
nothing else meanwhile (2 cores).
"""

from __future__ import annotations

import argparse
import json
import shlex
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


MODES = (("revisit+x-pass", []), ("x-pass only", ["--no-revisit"]), ("baseline", ["--no-revisit", "--no-cross-pass"]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("flights", nargs="+", type=Path)
    ap.add_argument("--journals", nargs="+", type=Path, help="a recorded stream per flight, in order (no detector runs)")
    ap.add_argument("--modes", nargs="+", choices=[m for m, _ in MODES], default=[m for m, _ in MODES])
    ap.add_argument("--ground-args", default="", help="more options for every replay, one string "
                    "(e.g. '--min-view-ratio 0 --min-parallax-deg 0')")
    ap.add_argument("--out", type=Path, default=Path("out/bench/whole-plot"))
    a = ap.parse_args(argv)
    if a.journals and len(a.journals) != len(a.flights):
        ap.error("give one journal per flight")
    lines, row_lines = [], []
    for n, path in enumerate(a.flights):
        flight = FlightDir(path)
        passes = pass_of_frames(flight)
        source = ["--recorded", str(a.journals[n]), "--speed", "0"] if a.journals else []
        for mode, extra in MODES:
            if mode not in a.modes:
                continue
            out = a.out / path.name / mode.replace("+", "-").replace(" ", "-")
            print(f"{path.name}: replay ({mode}) ...", file=sys.stderr, flush=True)
            subprocess.run([sys.executable, "-m", "ground", "replay", str(path), "--out", str(out), "--quiet"] + source
                           + extra + shlex.split(a.ground_args), check=True, stdout=subprocess.DEVNULL)
            rep = json.loads((out / "report.json").read_text())
            ev, reg = rep["evaluation"], rep["registration"]
            rows = [r for r in ev["rows"] if r["truth_visible"] >= 30]
            row_err = [100.0 * (r["count"] - r["truth_visible"]) / r["truth_visible"] for r in rows]
            spf = seconds_per_frame_by_pass(rep, passes)
            lines.append(f"| {path.name} | {mode} | {ev['count']} | {ev['truth_count']} | {ev['count_error_pct']:+.1f} | "
                         f"{ev.get('duplicates', 0)} | {max(np.abs(row_err)) if row_err else float('nan'):.1f} | "
                         f"{ev['f1']:.3f} | {ev['median_error_m'] * 100:.1f} | {reg.get('revisits', 0)} / "
                         f"{reg.get('reanchored', 0)} / {reg.get('rejoined', 0)} | "
                         f"{rep['association']['stats'].get('merged_across_passes', 0)} | {rep['wall_seconds']:.0f} | "
                         + " ".join(f"{x:.2f}" for x in spf) + " |")
            row_lines.append(f"{path.name}, {mode}: rows (count / visible) "
                             + ", ".join(f"{r['row']}: {r['count']}/{r['truth_visible']}" for r in ev["rows"]))
    if a.ground_args:
        print(f"every replay with: {a.ground_args}")
    print("| flight | mode | count | visible | error % | counted twice | worst row % (30+) | F1 | median error cm | "
          "revisits / re-anchored / re-joined | merged across passes | wall s | ground s/frame by pass |")
    print("|" + " --- |" * 13)
    print("\n".join(lines))
    print("\n" + "\n".join(row_lines))
    return 0


if __name__ == "__main__":
    sys.exit(main())
