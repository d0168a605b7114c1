"""Counts across flights (issues 17, 40): replay simulated flights through both processes and print one table of F1,
count error, per-row count error, per-tree correlation and the count against the load (per-row count against each
row's true total, hidden apples included: Pearson r and the coefficient of variation of count / total) against each
flight's truth; with ``--pair A B``, a repeat pair's per-row ratios of count to countable apples.

    for n in tune-1 tune-2; do .venv/bin/python -m sim flight --config sim/configs/generalise/$n.toml \
        --out out/sim/gen/$n; done
    .venv/bin/python benchmarks/generalisation.py out/sim/gen/tune-1 out/sim/gen/tune-2 [--name NAME] [-- REPLAY ARGS]

Tune on the tuning flights (tune-*); the evaluation flights (eval-*) are replayed once, at the end. Each flight is
replayed lock-step (`python -m ground replay`, the shipped detector, arguments after ``--`` passed on) into
out/bench/generalisation/NAME/FLIGHT; ``--rescore`` scores outputs already there again, ``--reuse`` replays only the
flights not replayed there yet. Per-row errors count rows
with at least 30 visible apples; per-tree correlation is over 1-m bins along those rows (ground/evaluation/evaluate.py).
Accuracy only: the replays' times depend on what else runs.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

from pomar.flight import FlightDir


def setting(flight: FlightDir) -> str:
    """The flight's varied settings, in one short line."""
    p = flight.path / "sim_config.json"
    if not p.is_file():
        return ""
    c = json.loads(p.read_text())
    f, cam, o = c["flight"], c["camera"], c["orchard"]
    look = "+" if f["passes"][0]["look"] > 0 else "-"
    return (f"{cam['height']}p {f['altitude_m']:g}m {f['speed_mps']:g}m/s {f['fps']:g}fps tilt{f['tilt_deg']:g} "
            f"look{look} az{o['row_azimuth_deg']:g} blur{c['render']['exposure_s'] * 1e3:g}ms "
            f"gps{c['telemetry']['gps_noise_m']:g}")


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = argv[argv.index("--") + 1:] if "--" in argv else []
    argv = argv[:argv.index("--")] if "--" in argv else argv
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("flights", nargs="+", type=Path)
    ap.add_argument("--name", default="default", help="the run's name (its output folder)")
    ap.add_argument("--out", type=Path, default=Path("out/bench/generalisation"))
    ap.add_argument("--rescore", action="store_true", help="score the replays already in the output folder again")
    ap.add_argument("--reuse", action="store_true",
                    help="replay only the flights whose output folder holds no finished replay (report.json)")
    ap.add_argument("--pair", nargs=2, action="append", default=[], metavar=("A", "B"),
                    help="two of the flights (folder names) that fly the same orchard: a repeat pair")
    a = ap.parse_args(argv)
    from ground.evaluation.scoring import evaluate_map, repeat_pair

    rows_out, summary = [], []
    for path in a.flights:
        flight = FlightDir(path)
        out = a.out / a.name / path.name
        if not (a.rescore or a.reuse and (out / "report.json").is_file()):
            print(f"{path.name}: replay ...", file=sys.stderr, flush=True)
            subprocess.run([sys.executable, "-m", "ground", "replay", str(path), "--out", str(out), "--quiet"] + extra,
                           check=True, stdout=subprocess.DEVNULL)
        ev = evaluate_map(flight, out)
        onboard = json.loads((out / "onboard.json").read_text()) if (out / "onboard.json").is_file() else {}
        big = [r for r in ev["rows"] if r["truth_visible"] >= 30]
        row_err = ", ".join(f"{r['count_error_pct']:+.0f}" for r in big)
        scale = (onboard.get("detector_scale") or {}).get("median", float("nan"))
        tr, load = ev["trees"], ev["load"]
        rows_out.append(f"{path.name:<14} {ev['f1']:>6.3f} {ev['count']:>6} {ev['truth_count']:>6} "
                        f"{ev['count_error_pct']:>+7.1f} {ev['worst_row_error_pct']:>8.1f}  {tr['r']:>6.3f} "
                        f"{load['r']:>6.3f} {load['cv']:>5.3f} {scale:>6.2f}  [{row_err}]  {setting(flight)}")
        summary.append({"flight": path.name, "f1": ev["f1"], "count": ev["count"], "truth_count": ev["truth_count"],
                        "count_error_pct": ev["count_error_pct"], "worst_row_error_pct": ev["worst_row_error_pct"],
                        "rows": ev["rows"], "trees": tr, "load": load, "detector_scale": scale, "replay_args": extra})
    print(f"run {a.name}" + (f" (replay {' '.join(extra)})" if extra else ""))
    print(f"{'flight':<14} {'F1':>6} {'count':>6} {'truth':>6} {'err %':>7} {'worst row':>8}  {'tree r':>6} "
          f"{'load r':>6} {'cv':>5} {'scale':>6}  [row errors %, rows of 30+]  setting")
    print("\n".join(rows_out))
    by_name = {s["flight"]: s for s in summary}
    for fa, fb in a.pair:
        pr = repeat_pair(by_name[fa]["rows"], by_name[fb]["rows"])
        rows = ", ".join(f"row {r['row']}: {r['ratio_a']:.2f}/{r['ratio_b']:.2f}" for r in pr["rows"])
        print(f"repeat pair {fa} / {fb}: worst |ratio difference| {pr['worst']:.3f} over {len(pr['rows'])} rows "
              f"(count / countable apples: {rows})")
        summary.append({"pair": [fa, fb], **pr})
    flights = [s for s in summary if "f1" in s]
    f1 = np.array([s["f1"] for s in flights])
    print(f"mean F1 {f1.mean():.3f}; worst |count error| {max(abs(s['count_error_pct']) for s in flights):.1f} %")
    (a.out / a.name).mkdir(parents=True, exist_ok=True)
    (a.out / a.name / "summary.json").write_text(json.dumps(summary, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
