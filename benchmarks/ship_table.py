"""Issue 70's gate: a candidate detector beside the shipped one, in one table, on what decides whether it ships.

    python benchmarks/ship_table.py --candidate out/export/cand/apple-detector.onnx \
        --flights out/yield/tune-1 out/yield/tune-2 out/yield/tune-3 out/yield/tune-4 replay_data/demo-flight \
        --yield-flights out/yield/tune-1 out/yield/tune-2 out/yield/tune-3 out/yield/tune-4 --out out/bench/ship

For each model (``--shipped``, default the shipped file, and ``--candidate``, each with its .json beside it):
- real photos: ``python -m export evaluate --model M`` (ADD256's test split and AppleBBCH76's held-out photos, at their
  own size, the model's own threshold);
- the map: ``benchmarks/generalisation.py FLIGHTS -- --model M`` (each flight replayed lock-step from pixels, its 3-D
  F1 and its count against the simulator's countable apples, reported beside, not a gate); a flight also given as a
  yield flight is scored on that replay (lock-step too, with its layout) rather than replayed twice;
- the count as growers use it: ``benchmarks/yield_flights.py YIELD_FLIGHTS --model M`` (each flight calibrated by 10
  hand-counted trees, exact counts): the median per-row load error over all rows, and the share of rows whose 90 %
  interval holds the true load.

Then the goals (issue 70, "Ship it when it beats today's model"), each with whether it holds. ``--reuse`` keeps what
an earlier run of the same --out already measured. Tuning flights only: evaluation flights are replayed once, at the
end, by hand.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "onboard" / "models" / "apple-detector.onnx"

#: The issue's gate: AppleBBCH76 held out, ADD256 test (both AP@0.5), F1 within this of today's on every flight, the
#: median row load error at most this many times today's, the rows' 90 % intervals holding this share.
BBCH_MIN, ADD256_MIN, F1_SLACK, ROW_ERROR_RATIO, COVER = 0.75, 0.759, 0.02, 1.1, (0.80, 0.95)


def run(cmd: list[str], log: Path) -> None:
    log.parent.mkdir(parents=True, exist_ok=True)
    print("$", " ".join(cmd), file=sys.stderr, flush=True)
    with open(log, "w") as f:
        r = subprocess.run(cmd, stdout=f, stderr=subprocess.STDOUT, cwd=ROOT)
    if r.returncode:
        raise SystemExit(f"{log}: the command failed (exit {r.returncode}); its output is there")


def measure(name: str, model: Path, flights: list[Path], yield_flights: list[Path], out: Path, reuse: bool,
            extra: list[str] = ()) -> dict:
    py = sys.executable
    here = out / name
    det = here / "detector.json"
    if not (reuse and det.is_file()):
        run([py, "-m", "export", "evaluate", "--model", str(model), "--json", str(det)], here / "detector.log")
    figs = {}
    ydir = here / "yield"
    if yield_flights:
        if not (reuse and all((ydir / f.name / "yield.json").is_file() for f in yield_flights)):
            run([py, "benchmarks/yield_flights.py", *map(str, yield_flights), "--out", str(ydir), "--model", str(model)]
                + (["--reuse"] if reuse else []) + (["--", *extra] if extra else []), here / "yield.log")
        figs = {f.name: json.loads((ydir / f.name / "yield.json").read_text()) for f in yield_flights}
    summary = out / name / "maps" / "summary.json"
    if flights and not (reuse and summary.is_file()):
        # a flight of both lists is scored on the yield workflow's own replay (lock-step, with its layout): one replay
        (here / "maps").mkdir(parents=True, exist_ok=True)
        for f in set(flights) & set(yield_flights):
            link = here / "maps" / f.name
            if not link.exists():
                link.symlink_to((ydir / f.name / "map").resolve())
        run([py, "benchmarks/generalisation.py", *map(str, flights), "--name", "maps", "--out", str(here), "--reuse",
             "--", "--model", str(model), *extra], here / "maps.log")
    d = json.loads(det.read_text())
    maps = [s for s in json.loads(summary.read_text()) if "f1" in s] if flights else []
    from ground.orchard.calibration import DEFAULT_MODEL

    rows = [r for f in figs.values() for r in f[DEFAULT_MODEL]["chosen"]["rows"]]
    return {"bbch": d.get("applebbch76_held_out", {}).get("ap50"), "add256": d["add256_test"]["ap50"],
            "bbch_f1": d.get("applebbch76_held_out", {}).get("f1"), "add256_f1": d["add256_test"]["f1"],
            "maps": {m["flight"]: m for m in maps},
            "row_error": float(np.median([abs(r["load_error"]) for r in rows])) if rows else None,
            "cover": float(np.mean([r["covered"] for r in rows])) if rows else None, "rows": len(rows)}


def table(a: dict, b: dict) -> tuple[list[str], bool]:
    """The table's lines (shipped ``a``, candidate ``b``) and whether every goal holds."""
    lines = [f"| {'':<44} | {'shipped':>9} | {'candidate':>9} | goal | holds |", f"| {'-' * 44} | ---: | ---: | --- | --- |"]
    ok = True

    def row(what, x, y, goal, holds):
        nonlocal ok
        ok &= bool(holds) if holds is not None else True
        f = (lambda v: "-" if v is None else f"{v:.3f}" if isinstance(v, float) else str(v))
        lines.append(f"| {what:<44} | {f(x):>9} | {f(y):>9} | {goal} | "
                     f"{'-' if holds is None else 'yes' if holds else '**no**'} |")

    row("AppleBBCH76 held-out AP@0.5", a["bbch"], b["bbch"], f">= {BBCH_MIN}",
        b["bbch"] is not None and b["bbch"] >= BBCH_MIN)
    row("ADD256 test AP@0.5", a["add256"], b["add256"], f">= {ADD256_MIN}", b["add256"] >= ADD256_MIN)
    row("AppleBBCH76 held-out F1 at the threshold", a["bbch_f1"], b["bbch_f1"], "reported", None)
    row("ADD256 test F1 at the threshold", a["add256_f1"], b["add256_f1"], "reported", None)
    for name in a["maps"]:
        x, y = a["maps"][name], b["maps"].get(name)
        row(f"3-D F1, {name}", x["f1"], y and y["f1"], f"within {F1_SLACK} of shipped",
            y is not None and y["f1"] >= x["f1"] - F1_SLACK)
        row(f"count vs countable apples, {name} (%)", x["count_error_pct"], y and y["count_error_pct"], "reported",
            None)
    if a["row_error"] is not None:
        row(f"median row load error ({a['rows']} rows, 10 trees counted)", a["row_error"], b["row_error"],
            f"<= {ROW_ERROR_RATIO} x shipped", b["row_error"] <= ROW_ERROR_RATIO * a["row_error"])
        row("rows' 90 % intervals holding the true load", a["cover"], b["cover"], f"{COVER[0]}-{COVER[1]}",
            COVER[0] <= b["cover"] <= COVER[1])
    return lines, ok


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--candidate", type=Path, required=True, help="the candidate ONNX (its .json beside it)")
    p.add_argument("--shipped", type=Path, default=SHIPPED, help="today's model (default: the shipped file)")
    p.add_argument("--flights", type=Path, nargs="*", default=[], help="flights whose 3-D F1 is compared")
    p.add_argument("--yield-flights", type=Path, nargs="*", default=[],
                   help="simulated flights with trees' truth for the yield workflow's comparison")
    p.add_argument("--out", type=Path, default=Path("out/bench/ship"))
    p.add_argument("--reuse", action="store_true", help="keep what an earlier run in --out measured")
    p.add_argument("--candidate-args", nargs="*", default=[],
                   help="ground replay arguments for the candidate's replays (its own count settings: "
                        "--candidate-args=--confirm-score=0.8)")
    p.add_argument("--only", choices=["shipped", "candidate"],
                   help="measure this model alone (the table comes from a later run with --reuse)")
    a = p.parse_args(argv)
    for m in (a.candidate, a.shipped):
        if not m.is_file() or not m.with_suffix(".json").is_file():
            p.error(f"{m}: needs the ONNX file and its .json beside it")
    res = {name: measure(name, m, a.flights, a.yield_flights, a.out, a.reuse, args)
           for name, m, args in (("shipped", a.shipped, []), ("candidate", a.candidate, a.candidate_args))
           if a.only in (None, name)}
    if a.only:
        return 0
    lines, ok = table(res["shipped"], res["candidate"])
    print(f"shipped {a.shipped}, candidate {a.candidate}")
    print("\n".join(lines))
    print("every goal holds: the candidate ships" if ok else "a goal does not hold: the candidate does not ship")
    (a.out / "table.json").write_text(json.dumps({**res, "ships": ok}, indent=1, default=float) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
