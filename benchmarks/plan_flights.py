"""Issue 72's goals: a flight plan against a one-pass flight over the same held-out orchard, each replayed with the
orchard's layout and calibrated by 10 hand-counted trees (exact counts), with the shipped detector.

    python benchmarks/plan_flights.py sim/configs/plan-eval/a.toml sim/configs/plan-eval/b.toml \
        sim/configs/plan-eval/c.toml --drone generic-quad --out out/bench/plan-eval [--reuse]

For each orchard config: its layout (``sim layout``), the plan on it (``pomar plan``, the config's camera, its frame
rate), each of the plan's flights rendered (``sim flight --plan --plan-flight N``) and replayed with the layout, their
maps combined (``ground combine``; one flight: its map); the config's own flight (one pass) rendered and replayed the
same way. Then, for both: the mean tree coverage and the trees seen from both sides, the per-row count against the
row's true load (r), and the loads from the 10 trees ``ground choose-trees`` names (their true counts): the median
per-row load error, the rows' 90 % intervals' share holding the true load and their median half-width. Beside them
the plan's stated time against its videos' length, and its planned apple radius at the detector against what the
onboard node reports for each flight (``report.json`` ``apple_size``). The goals printed with whether each holds.
Held-out orchards: replayed once, at the end; nothing is tuned on them. Accuracy only.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from benchmarks.yield_flights import estimate_and_score, numeric  # noqa: E402
from ground.evaluation.yield_score import read_map, truth_of  # noqa: E402
from ground.orchard.calibration import DEFAULT_MODEL  # noqa: E402
from ground.orchard.choose import choose_trees  # noqa: E402
from pomar.flight import FlightDir  # noqa: E402
from sim.counts import sample_counts  # noqa: E402

#: Issue 72's goals: coverage, per-row r, the load error against the one pass's, the interval width against its.
COVERAGE_MIN, ROW_R_MIN, ERROR_RATIO, WIDTH_RATIO, HOLD, TIME_TOL, PX_TOL = 0.9, 0.97, 0.5, 0.5, (0.8, 0.95), 0.1, 0.1


def run(cmd: list, reuse_if: Path | None = None, reuse: bool = False) -> None:
    if reuse and reuse_if is not None and reuse_if.exists():
        return
    r = subprocess.run([sys.executable, "-m", *map(str, cmd)], capture_output=True, text=True, cwd=ROOT)
    if r.returncode:
        raise SystemExit(f"{' '.join(map(str, cmd[:3]))}: failed: {r.stderr.strip().splitlines()[-1:]}")


def judge(map_dir: Path, fd: FlightDir, k: int = 10) -> dict:
    """A map's coverage, per-row r against the true loads, and its loads from k trees counted exactly."""
    trees, rows = read_map(map_dir)
    trees = numeric(trees)
    truth = truth_of(fd)
    cov = np.array([t["coverage"] for t in trees], float)
    counts = {int(r["row"]): float(r["count"]) for r in rows}
    common = sorted(set(counts) & set(truth["rows"]))
    r_rows = float(np.corrcoef([counts[r] for r in common], [truth["rows"][r]["load"] for r in common])[0, 1]) \
        if len(common) >= 3 else float("nan")
    chosen = choose_trees(trees, k, DEFAULT_MODEL)
    got = sample_counts(fd, [(t["row"], t["tree"]) for t in chosen])
    samples = {(c["row"], c["tree"]): c["apples"] for c in got}
    score = estimate_and_score(trees, rows, samples, DEFAULT_MODEL, truth)
    rws = score["rows"]
    return {"coverage": float(np.nanmean(cov)), "both_sides": int(sum(t.get("sides_seen") == "2" for t in trees)),
            "trees": len(trees), "row_r": r_rows, "row_error": score["row_load_error_median"],
            "hold": float(np.mean([x["covered"] for x in rws])) if rws else float("nan"),
            "half_width": float(np.median([x["half_width"] for x in rws])) if rws else float("nan"), "rows": len(rws)}


def orchard(cfg: Path, out: Path, drone: str, reuse: bool) -> dict:
    out.mkdir(parents=True, exist_ok=True)
    layout = out / "orchard.csv"
    run(["sim", "layout", "--config", cfg, "--out", layout], layout, reuse)
    one = out / "one-pass"
    run(["sim", "flight", "--config", cfg, "--out", one, "--quiet"], one / "flight.json", reuse)
    meta = FlightDir(one).meta()
    camera = one / "camera.json"
    run(["pomar", "plan", layout, "--drone", drone, "--camera", camera, "--fps", f"{meta.fps:g}", "--out",
         out / "plan"], out / "plan" / "plan.json", reuse)
    plan = json.loads((out / "plan" / "plan.json").read_text())
    maps, video_s, px = [], [], []
    for n in range(1, len(plan["flights"]) + 1):
        f = out / f"flight-{n}"
        run(["sim", "flight", "--config", cfg, "--plan", out / "plan" / "plan.json", "--plan-flight", n, "--out", f,
             "--quiet"], f / "flight.json", reuse)
        m = FlightDir(f).meta()
        video_s.append(m.frame_count / m.fps)
        run(["ground", "replay", f, "--orchard", layout, "--out", out / f"map-{n}", "--quiet"],
            out / f"map-{n}" / "trees.csv", reuse)
        maps.append(out / f"map-{n}")
        px.append(((json.loads((out / f"map-{n}" / "report.json").read_text()).get("apple_size") or {})
                   .get("radius_px_median")))
    combined = maps[0]
    if len(maps) > 1:
        combined = out / "combined"
        run(["ground", "combine", *maps, "--out", combined], combined / "trees.csv", reuse)
    run(["ground", "replay", one, "--orchard", layout, "--out", out / "one-pass-map", "--quiet"],
        out / "one-pass-map" / "trees.csv", reuse)
    fd = FlightDir(one)
    planned_s = sum(plan["minutes"]) * 60 if isinstance(plan["minutes"], list) else plan["minutes"] * 60
    return {"orchard": cfg.stem, "plan": judge(combined, fd), "one_pass": judge(out / "one-pass-map", fd),
            "flights": len(maps), "planned_s": planned_s, "video_s": float(sum(video_s)),
            "planned_px": plan["apple_px"], "onboard_px": px}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("configs", nargs="+", type=Path)
    p.add_argument("--drone", default="generic-quad")
    p.add_argument("--out", type=Path, default=Path("out/bench/plan-eval"))
    p.add_argument("--reuse", action="store_true", help="keep what an earlier run of the same --out made")
    a = p.parse_args(argv)
    res = [orchard(c, a.out / c.stem, a.drone, a.reuse) for c in a.configs]
    print(f"{'orchard':<8} {'flight':<9} {'cover':>6} {'both':>7} {'row r':>6} {'row err':>8} {'hold':>5} "
          f"{'half-w':>7}")
    for r in res:
        for k in ("plan", "one_pass"):
            j = r[k]
            print(f"{r['orchard']:<8} {k:<9} {j['coverage']:>6.2f} {j['both_sides']:>3}/{j['trees']:<3} "
                  f"{j['row_r']:>6.3f} {j['row_error']:>8.3f} {j['hold']:>5.2f} {j['half_width']:>7.3f}")
        print(f"{'':<8} plan {r['flights']} flights: stated {r['planned_s']:.0f} s, videos {r['video_s']:.0f} s; "
              f"apple radius planned {r['planned_px']:.2f} px, onboard {r['onboard_px']}")
    goals = []
    for r in res:
        pl, one = r["plan"], r["one_pass"]
        holds = [x for x in r["onboard_px"] if x is not None]
        goals += [(f"{r['orchard']}: every tree from both sides", pl["both_sides"] == pl["trees"]),
                  (f"{r['orchard']}: mean tree coverage >= {COVERAGE_MIN}", pl["coverage"] >= COVERAGE_MIN),
                  (f"{r['orchard']}: per-row count vs load r >= {ROW_R_MIN}", pl["row_r"] >= ROW_R_MIN),
                  (f"{r['orchard']}: row load error <= {ERROR_RATIO} x one pass's",
                   pl["row_error"] <= ERROR_RATIO * one["row_error"]),
                  (f"{r['orchard']}: intervals <= {WIDTH_RATIO} x as wide, holding {HOLD}",
                   pl["half_width"] <= WIDTH_RATIO * one["half_width"]),
                  (f"{r['orchard']}: video within {TIME_TOL:.0%} of the plan's time",
                   abs(r["video_s"] / r["planned_s"] - 1) <= TIME_TOL),
                  (f"{r['orchard']}: planned apple size within {PX_TOL:.0%} of the onboard's",
                   bool(holds) and all(abs(r["planned_px"] / x - 1) <= PX_TOL for x in holds))]
    hold = np.mean([x for r in res for x in [r["plan"]["hold"]]])
    goals.append((f"plans' intervals hold {HOLD[0]}-{HOLD[1]} (pooled {hold:.2f})", HOLD[0] <= hold <= HOLD[1]))
    for g, ok in goals:
        print(f"  {'yes' if ok else 'NO ':<4} {g}")
    (a.out / "summary.json").write_text(json.dumps(res, indent=1, default=float) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
