"""Run a command beside CPU hogs, as on a busy laptop or a shared CI runner: ``make test-busy`` runs the suite so.

    python tests/busy.py [--hogs 2] -- COMMAND ...

Each hog is a Python process spinning on one core; they are stopped by PID when the command ends, whatever way it
ends. The exit status is the command's.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--hogs", type=int, default=2, help="CPU hogs beside the command")
    p.add_argument("command", nargs=argparse.REMAINDER, help="the command (after --)")
    a = p.parse_args(argv)
    cmd = a.command[1:] if a.command[:1] == ["--"] else a.command
    if not cmd:
        p.error("no command given")
    hogs = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(a.hogs)]
    print(f"busy: {a.hogs} CPU hogs (pids {', '.join(str(h.pid) for h in hogs)}) beside: {' '.join(cmd)}", flush=True)
    t0 = time.monotonic()
    try:
        code = subprocess.call(cmd)
    except KeyboardInterrupt:
        code = 130
    finally:
        for h in hogs:
            h.kill()
            h.wait()
    print(f"busy: the command ended with {code} after {(time.monotonic() - t0) / 60:.1f} min; hogs stopped", flush=True)
    return code


if __name__ == "__main__":
    raise SystemExit(main())
