"""The same simulated flight replayed from each telemetry format: its .tlog, an ArduPilot DataFlash .bin and a DJI
.SRT (written by ``python -m sim logs``), each lock-step through both processes and scored against the truth.

    .venv/bin/python benchmarks/log_formats.py replay_data/demo-flight [more flights] [--out out/bench/log-formats]

Prints one line per flight and format: F1, count error, and the F1 difference from the .tlog's. Each replay takes
about as long as `make demo` (95 s for the bundled flight on 2 cores); time nothing else meanwhile.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from pomar.flight import FlightDir
from sim.logs import write_dataflash, write_srt


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("flights", nargs="+", type=Path, help="simulated flight directories (with truth/)")
    ap.add_argument("--out", type=Path, default=Path("out/bench/log-formats"))
    a = ap.parse_args(argv)
    rows = []
    for path in a.flights:
        fd = FlightDir(path)
        meta = fd.meta()
        logs = a.out / path.name / "logs"
        logs.mkdir(parents=True, exist_ok=True)
        write_dataflash(fd.tlog, logs / "telemetry.bin")
        write_srt(fd.tlog, meta.frame_count, meta.fps, meta.video_start_utc, logs / "video.SRT")
        base = None
        for fmt, log in (("tlog", None), ("dataflash", logs / "telemetry.bin"), ("srt", logs / "video.SRT")):
            t0 = time.monotonic()
            print(f"{path.name}: replaying from its {fmt} ...", file=sys.stderr, flush=True)
            out = a.out / path.name / fmt
            # the command line, as `make demo` runs it (its defaults), plus the log
            cmd = [sys.executable, "-m", "ground", "replay", str(path), "--out", str(out), "--quiet"]
            subprocess.run(cmd + (["--log", str(log)] if log else []), check=True, stdout=subprocess.DEVNULL)
            rep = json.loads((out / "report.json").read_text())
            ev = rep.get("evaluation", {})
            base = ev.get("f1") if fmt == "tlog" else base
            rows.append((path.name, fmt, ev.get("f1"), ev.get("count_error_pct"), rep["frames"]["frames"],
                         time.monotonic() - t0, ev.get("f1") - base if base is not None and ev.get("f1") is not None else None))
    print(f"{'flight':<20} {'format':<10} {'F1':>6} {'count %':>8} {'frames':>7} {'wall s':>7} {'F1 - tlog':>10}")
    for name, fmt, f1, cerr, frames, wall, d in rows:
        print(f"{name:<20} {fmt:<10} {f1:>6.3f} {cerr:>+8.1f} {frames:>7d} {wall:>7.0f} {d:>+10.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
