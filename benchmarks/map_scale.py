"""The map's scale against the truth, with its stated uncertainty (issue 75), on the scale's evaluation flights.

    python benchmarks/map_scale.py [--flights sim/configs/scale/flights.csv] [--only eval-1 eval-2]
                                   [--out out/bench/map-scale] [--reuse] [-- REPLAY ARGS]

Each flight of the CSV (config, log) is rendered where missing (out/sim/scale/NAME), its log written as the CSV says
(``tlog`` and ``tlog-px4``: the flight's own telemetry.tlog; ``dataflash`` and ``ulog``: ``sim logs``' telemetry.bin
and telemetry.ulg; ``srt-p4p``,
``srt-mavic3``: ``sim logs --srt-layout``'s video.SRT with the video and camera.json), and replayed lock-step with the
truth's layout (``--orchard``, numbered as the truth). Printed per flight: the map's scale error (the similarity that
takes its cameras onto the truth's, ground/evaluation/scoring.py), the 1-sigma report.json states
(``registration.georeference_scale``), the error in sigmas, each source's weight; and the rows' median diameter and
mean apple mass against the truth's (median over rows of |error|), which the scale carries (a mass its cube). Then
how many flights lie within 2 sigma, and the largest |error|. Evaluation flights: replay them once, at the end.
Accuracy only.
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from ground.evaluation.scoring import evaluate_map  # noqa: E402
from ground.evaluation.yield_score import truth_of  # noqa: E402
from pomar.flight import FlightDir  # noqa: E402
from pomar.fruit import apple_mass_kg  # noqa: E402
from pomar.layout import write_layout  # noqa: E402
from sim.layout import truth_layout  # noqa: E402


def sh(cmd: list[str]) -> None:
    r = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
    if r.returncode:
        raise SystemExit(f"{' '.join(cmd)}: failed: {r.stderr.strip().splitlines()[-1:]}")


def replay(flight: Path, log: str, out: Path, extra: list[str]) -> None:
    py = sys.executable
    layout = out.parent / f"{flight.name}-orchard.csv"
    write_layout(truth_layout(FlightDir(flight)), layout)
    args = [py, "-m", "ground", "replay", "--out", str(out), "--orchard", str(layout), "--quiet", *extra]
    if log in ("tlog", "tlog-px4"):
        sh(args + [str(flight)])
        return
    logs = out.parent / f"{flight.name}-logs"
    sh([py, "-m", "sim", "logs", str(flight), "--out", str(logs)]
       + (["--srt-layout", log.split("-", 1)[1]] if log.startswith("srt-") else []))
    what = logs / {"dataflash": "telemetry.bin", "ulog": "telemetry.ulg"}.get(log, "video.SRT")
    sh(args + ["--video", str(flight / "video.mp4"), "--log", str(what), "--camera", str(flight / "camera.json")])


def sizes(flight: FlightDir, out: Path) -> tuple[float, float]:
    """The median over rows of |median diameter error| (mm) and of |mean apple mass error| (%), rows measured."""
    truth = truth_of(flight)["rows"]
    d_err, m_err = [], []
    with open(out / "rows.csv", newline="") as f:
        for r in csv.DictReader(f):
            t = truth.get(int(r["row"]))
            d = float(r["diameter_mm"] or "nan")
            if t is None or not np.isfinite(d):
                continue
            d_err.append(abs(d - 1000 * float(np.median(t["diameters_m"]))))
            m_true = float(apple_mass_kg(t["diameters_m"]).mean())
            m_err.append(abs(100 * (float(r["apple_kg"]) / m_true - 1)))
    return (float(np.median(d_err)) if d_err else float("nan"), float(np.median(m_err)) if m_err else float("nan"))


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    extra = argv[argv.index("--") + 1:] if "--" in argv else []
    argv = argv[:argv.index("--")] if "--" in argv else argv
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--flights", type=Path, default=ROOT / "sim" / "configs" / "scale" / "flights.csv")
    p.add_argument("--only", nargs="*", help="these flights of the CSV (names without .toml)")
    p.add_argument("--out", type=Path, default=ROOT / "out" / "bench" / "map-scale")
    p.add_argument("--reuse", action="store_true", help="keep renders and replays already there")
    a = p.parse_args(argv)
    with open(a.flights, newline="") as f:
        todo = [r for r in csv.DictReader(f) if not a.only or Path(r["config"]).stem in a.only]
    rows = []
    print(f"{'flight':<10} {'log':<11} {'GPS m':>5} {'passes':<10} {'err %':>6} {'sigma %':>7} {'z':>5}  "
          f"{'diam mm':>7} {'mass %':>6}  sources (weight)")
    for r in todo:
        name = Path(r["config"]).stem
        flight = ROOT / "out" / "sim" / "scale" / name
        if not (flight / "video.mp4").is_file():
            sh([sys.executable, "-m", "sim", "flight", "--config", str(a.flights.parent / r["config"]), "--out",
                str(flight)])
        out = a.out / name
        if not (a.reuse and (out / "report.json").is_file()):
            replay(flight, r["log"], out, extra)
        fd = FlightDir(flight)
        ev = evaluate_map(fd, out)
        err = ev["georeference_error"]["scale_error_pct"]
        sc = json.loads((out / "report.json").read_text())["registration"].get("georeference_scale") or {}
        sigma = float(sc.get("sigma_pct") or "nan")
        d_mm, m_pct = sizes(fd, out)
        src = ", ".join(f"{s['name']} {s['scale'] / sc['scale'] * 100 - 100:+.1f} % ± {s['sigma_pct']:.1f} "
                        f"({s['weight']:.2f})" for s in sc.get("sources", []))
        rows.append({"flight": name, "log": r["log"], "gps_m": float(r["gps_noise_m"]), "error_pct": err,
                     "sigma_pct": sigma, "diameter_error_mm": d_mm, "mass_error_pct": m_pct, "scale": sc})
        print(f"{name:<10} {r['log']:<11} {r['gps_noise_m']:>5} {r['passes']:<10} {err:>+6.2f} {sigma:>7.2f} "
              f"{err / sigma:>5.2f}  {d_mm:>7.1f} {m_pct:>6.1f}  {src}", flush=True)
    if rows:
        z = np.array([abs(x["error_pct"]) / x["sigma_pct"] for x in rows])
        print(f"within 2 sigma: {int((z <= 2).sum())} of {len(rows)}; largest |error| "
              f"{max(abs(x['error_pct']) for x in rows):.2f} %; within 1.5 %: "
              f"{sum(abs(x['error_pct']) <= 1.5 for x in rows)} of {len(rows)}")
        a.out.mkdir(parents=True, exist_ok=True)
        (a.out / "summary.json").write_text(json.dumps(rows, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
