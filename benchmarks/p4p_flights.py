"""Issue 62: does a Phantom 4 Pro's SRT (one subtitle a second, 4 decimals, ``H`` above take-off, no attitudes) map a
flight as well as a Mavic 3's SRT (one a frame, 5 decimals) of the same flight? Each simulated flight is replayed
through README's DJI command with both layouts (benchmarks/dji_paper.py's replays), and scored against its truth.

    python benchmarks/p4p_flights.py out/p4p/tune-1 out/p4p/tune-2 [--out out/p4p/runs]
    python benchmarks/p4p_flights.py out/p4p/tune-1 --ground-only      # the ground again, from each run's journal

The first run of a flight replays both nodes (the detector on 4K frames: minutes); ``--ground-only`` replays the
ground alone from the journal the first run recorded (the same frame messages, so a change on the ground is measured
without the detector), lock-step. Prints one line per flight and layout (F1, count, duplicates, scale error, frames
without a pose, pose sources) and the issue's goals for the flight: F1 within 0.03 of the Mavic 3's, no more apples
counted twice, the map's scale within 2 %, every frame posed. Tuning flights (sim/configs/p4p/tune-*.toml) are for
working on it; the evaluation flights (eval-*) are replayed once, at the end.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

LAYOUTS = {"mavic3": "mavic3", "p4pro": "p4p"}
#: The issue's goals: the Phantom 4 Pro layout within this F1 of the Mavic 3's, its scale error within this (%).
F1_WITHIN = 0.03
SCALE_WITHIN_PCT = 2.0


def ground_only(run: Path, out: Path) -> None:
    """The ground alone, lock-step, from the journal ``run`` recorded (the stream alone says the flight: the DJI
    command named it after its video; it is scored here, against the simulated flight)."""
    r = subprocess.run([sys.executable, "-m", "ground", "replay", "--recorded", str(run / "journal.bin"),
                        "--speed", "0", "--out", str(out), "--quiet"], capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"ground replay of {run / 'journal.bin'} failed:\n{r.stderr[-3000:]}")


def scores(flight: Path, res: Path) -> dict:
    from ground.evaluation.scoring import evaluate_map
    from pomar.flight import FlightDir

    ev = evaluate_map(FlightDir(flight), res)
    rep = json.loads((res / "report.json").read_text())
    fr = rep["frames"]
    return {"f1": ev["f1"], "count": ev["count"], "truth": ev["truth_count"], "count_error_pct": ev["count_error_pct"],
            "duplicates": ev["duplicates"], "scale_error_pct": ev.get("georeference_error", {}).get("scale_error_pct"),
            "scale_from": rep["registration"].get("georeference_scale_from"),
            "frames": fr["frames"], "without_pose": fr["frames_without_pose"],
            "sources": {k: fr.get(k, 0) for k in ("registered", "tracked", "interpolated", "extrapolated", "apples",
                                                  "telemetry")},
            "registered_keyframes": rep["registration"].get("registered"),
            "failed_keyframes": rep["registration"].get("failed"), "submodels": rep["registration"].get("submodels"),
            "above_sea_level": rep.get("map", {}).get("above_sea_level")}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("flights", nargs="+", type=Path, help="simulated flights (python -m sim flight --config "
                                                         "sim/configs/p4p/tune-1.toml ...)")
    p.add_argument("--out", type=Path, default=Path("out/p4p/runs"))
    p.add_argument("--ground-only", action="store_true", help="replay the ground alone from each run's journal "
                                                              "(the first run's, under OUT/<flight>/<layout>)")
    p.add_argument("--tag", default="ground", help="with --ground-only: the folder name of these replays")
    a = p.parse_args(argv)
    table = {}
    for flight in a.flights:
        base = a.out / flight.name
        if not a.ground_only:
            r = subprocess.run([sys.executable, "benchmarks/dji_paper.py", str(flight), "--out", str(base), "--only",
                                *LAYOUTS], capture_output=True, text=True)
            if r.returncode != 0:
                raise SystemExit(r.stderr[-3000:])
        for name in LAYOUTS:
            res = base / name
            if a.ground_only:
                res = base / f"{name}-{a.tag}"
                ground_only(base / name, res)
            table[(flight.name, name)] = s = scores(flight, res)
            print(f"{flight.name:10s} {name:7s} F1 {s['f1']:.3f} count {s['count']:4d}/{s['truth']:4d} "
                  f"({s['count_error_pct']:+5.1f} %) dup {s['duplicates']:3d} scale {s['scale_error_pct']:+6.2f} % "
                  f"({s['scale_from']}) unposed {s['without_pose']} keyframes {s['registered_keyframes']}+"
                  f"{s['failed_keyframes']} failed, {s['submodels']} sub-model(s) {s['sources']}", flush=True)
        m, q = table[(flight.name, "mavic3")], table[(flight.name, "p4pro")]
        goals = {"f1": q["f1"] >= m["f1"] - F1_WITHIN, "duplicates": q["duplicates"] <= m["duplicates"],
                 "scale": abs(q["scale_error_pct"]) <= SCALE_WITHIN_PCT, "every_frame_posed": q["without_pose"] == 0}
        print(f"{flight.name:10s} goals: F1 {q['f1'] - m['f1']:+.3f} {'ok' if goals['f1'] else 'FAIL'}, duplicates "
              f"{q['duplicates']} vs {m['duplicates']} {'ok' if goals['duplicates'] else 'FAIL'}, scale "
              f"{q['scale_error_pct']:+.2f} % {'ok' if goals['scale'] else 'FAIL'}, every frame posed "
              f"{'ok' if goals['every_frame_posed'] else 'FAIL'}", flush=True)
        table[(flight.name, "goals")] = goals
    a.out.mkdir(parents=True, exist_ok=True)
    name = "p4p_flights" + (f"-{a.tag}" if a.ground_only else "") + ".json"
    (a.out / name).write_text(json.dumps({f"{k[0]}/{k[1]}": v for k, v in table.items()}, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
