"""python -m onboard SUBCOMMAND: the drone's companion-computer node.

The node itself (video + MAVLink -> detector -> zenoh) lands with the Onboard issue; today:
  telemetry   read a .tlog and report its streams, gaps and, with --flight, each frame's sample
"""

from __future__ import annotations

import argparse
import logging
import sys


def _cmd_telemetry(args) -> int:
    import numpy as np

    from onboard.telemetry import Flags, read_tlog
    from pomar.flight import FlightDir

    tl = read_tlog(args.tlog, max_gap_s=args.max_gap_s)
    print(tl.summary())
    if args.flight:
        meta = FlightDir(args.flight).meta()
        t, flags = tl.frame_times(meta.frame_count, meta.video_start_utc, meta.fps, args.clock_offset_s)
        s = tl.at(t)
        flags = flags | s["flags"]
        print(f"frames: {meta.frame_count}, {int((flags == 0).sum())} with complete telemetry")
        for f in Flags:
            n = int((flags & f).astype(bool).sum())
            if n:
                print(f"  {f.name:<18} {n} frames")
        if args.show:
            for i in np.linspace(0, meta.frame_count - 1, min(args.show, meta.frame_count)).astype(int):
                print(f"  frame {i:>5} t={t[i]:.3f} lat={s['lat'][i]:.7f} lon={s['lon'][i]:.7f} alt={s['alt'][i]:.2f} "
                      f"q_gimbal={np.round(s['q_gimbal'][i], 4).tolist()} flags={Flags(int(flags[i]))!r}")
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m onboard", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    t = sub.add_parser("telemetry", help="read a .tlog: streams, rates, gaps, and each frame's sample")
    t.add_argument("tlog")
    t.add_argument("--flight", help="flight directory: sample the telemetry at its frames")
    t.add_argument("--clock-offset-s", type=float, default=0.0, help="camera clock minus autopilot clock")
    t.add_argument("--max-gap-s", type=float, default=1.0)
    t.add_argument("--show", type=int, default=0, help="print this many frames' samples")
    t.set_defaults(func=_cmd_telemetry)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    from onboard.telemetry import TelemetryError
    from pomar.flight import FlightFormatError

    try:
        return args.func(args)
    except (TelemetryError, FlightFormatError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
