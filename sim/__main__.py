"""python -m sim {flight,info,show,telemetry,logs}: render synthetic orchard flights and look at them."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path

from pomar import cli
from pomar.countable import MIN_VISIBLE


def _cmd_flight(args) -> int:
    from sim import config as sc
    from sim.flight import simulate_flight

    if args.config:
        text = Path(args.config).read_text() if Path(args.config).exists() else None
        cfg = sc.load(args.config)
    else:
        text, cfg = None, sc.SimConfig()
    if args.seed is not None:
        cfg.seed = args.seed
    if args.plan:
        from sim.plan import fly_plan, read_plan

        cfg = fly_plan(cfg, read_plan(args.plan), args.plan_flight, args.plan)
    command = "python -m sim flight " + " ".join(sys.argv[2:])
    summary = simulate_flight(cfg, args.out, jobs=args.jobs, progress=not args.quiet, config_text=text, command=command)
    print(json.dumps(summary, indent=2))
    return 0


def _cmd_info(args) -> int:
    from sim.preview import flight_info

    print(flight_info(args.flight_dir))
    return 0


def _cmd_show(args) -> int:
    from sim.preview import draw_truth

    out = draw_truth(args.flight_dir, args.frame, args.out, args.min_visible)
    print(f"wrote {out} (frame {args.frame} with the truth apples circled: green = at least "
          f"{args.min_visible:.0%} visible, grey = less)")
    return 0


def _cmd_telemetry(args) -> int:
    from sim.flight import rewrite_telemetry

    changes = {k: v for k, v in (("gps_noise_m", args.gps_noise_m), ("gps_alt_noise_m", args.gps_alt_noise_m),
                                 ("attitude_noise_deg", args.attitude_noise_deg),
                                 ("gimbal_noise_deg", args.gimbal_noise_deg), ("height_source", args.height_source))
               if v is not None}
    print(json.dumps(rewrite_telemetry(args.flight_dir, args.out, **changes), indent=2))
    return 0


def _cmd_logs(args) -> int:
    from pathlib import Path

    import numpy as np

    from pomar.flight import FlightDir
    from sim.config import rendered_config
    from sim.logs import write_dataflash, write_srt, write_ulog

    fd = FlightDir(args.flight_dir)
    meta = fd.meta()
    out = Path(args.out or fd.path)
    out.mkdir(parents=True, exist_ok=True)
    counts = write_dataflash(fd.tlog, out / "telemetry.bin")
    ucounts = write_ulog(fd.tlog, out / "telemetry.ulg")
    truth = None
    # the height above take-off as a DJI barometer gives it: the truth's, drifting a little; where the tlog's height is
    # already the barometer's (height_source baro), that one: one drone, one barometer, whichever log records it
    if fd.has_truth and rendered_config(fd.path).telemetry.height_source != "baro":
        fr = fd.truth_frames()
        truth = (np.asarray(fr["t_unix"], float), np.asarray(fr["alt"], float) - fd.origin().alt)
    n = write_srt(fd.tlog, meta.frame_count, meta.fps, meta.video_start_utc, out / "video.SRT",
                  layout=args.srt_layout, attitude=not args.no_attitude, truth_heights=truth,
                  seed=int(meta.extra.get("seed", 0)))
    print(f"wrote {out / 'telemetry.bin'} ({', '.join(f'{k} {v}' for k, v in counts.items())}), "
          f"{out / 'telemetry.ulg'} ({', '.join(f'{k} {v}' for k, v in ucounts.items())}) and "
          f"{out / 'video.SRT'} ({n} subtitles)")
    return 0


def _cmd_counts(args) -> int:
    from pomar.flight import FlightDir
    from pomar.sample_counts import write_sample_counts
    from sim.counts import parse_tree, sample_counts

    trees = [parse_tree(t) for t in args.trees] if args.trees else None
    rows = sample_counts(FlightDir(args.flight_dir), trees, args.random or 0, args.seed, args.count_error_cv)
    write_sample_counts(rows, args.out)
    print(f"wrote {args.out}: {len(rows)} trees, {sum(r['apples'] for r in rows)} apples counted")
    return 0


def _cmd_layout(args) -> int:
    from pomar.flight import FlightDir
    from pomar.layout import read_layout, write_layout
    from sim.layout import truth_layout

    if (args.flight_dir is None) == (args.config is None):
        raise cli.InputError("sim layout: give a rendered flight's folder, or --config (the orchard before a flight)")
    if args.config:
        from sim import config as sc
        from sim.layout import config_layout

        rows = config_layout(sc.load(args.config))
    else:
        rows = truth_layout(FlightDir(args.flight_dir))
    write_layout(rows, args.out)
    read_layout(args.out)  # what it wrote reads back
    print(f"wrote {args.out}: {len(rows)} rows, numbered as the truth numbers them")
    return 0


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m sim", description=__doc__)
    sub = p.add_subparsers(dest="cmd", required=True)
    f = sub.add_parser("flight", help="render a synthetic orchard flight with ground truth")
    f.add_argument("--config", help="TOML config (see sim/configs/); defaults for every missing key")
    f.add_argument("--out", required=True, help="output flight directory")
    f.add_argument("--seed", type=int, help="override the config's seed")
    f.add_argument("--jobs", type=int, help="render processes (default: all cores)")
    f.add_argument("--quiet", action="store_true", help="no progress bar")
    f.add_argument("--plan", help="fly this plan (plan.json of python -m pomar plan, made on the orchard's layout) "
                                  "instead of the config's passes: its lines, height, speed and gimbal pitch")
    f.add_argument("--plan-flight", type=int, default=1, help="which of the plan's flights (batteries); default 1")
    f.set_defaults(func=_cmd_flight)
    i = sub.add_parser("info", help="print what a flight directory holds")
    i.add_argument("flight_dir")
    i.set_defaults(func=_cmd_info)
    s = sub.add_parser("show", help="write a PNG of one frame with the truth apples drawn")
    s.add_argument("flight_dir")
    s.add_argument("--frame", type=int, default=0)
    s.add_argument("--out", default="out/frame.png")
    s.add_argument("--min-visible", type=float, default=MIN_VISIBLE)
    s.set_defaults(func=_cmd_show)
    t = sub.add_parser("telemetry", help="write a simulated flight's .tlog again with other telemetry settings "
                                         "(e.g. RTK-grade GPS); video and truth are linked, not copied")
    t.add_argument("flight_dir")
    t.add_argument("--out", required=True, help="new flight directory")
    t.add_argument("--gps-noise-m", type=float, help="horizontal GPS error sigma (m); RTK is about 0.02")
    t.add_argument("--gps-alt-noise-m", type=float, help="vertical GPS error sigma (m)")
    t.add_argument("--attitude-noise-deg", type=float)
    t.add_argument("--gimbal-noise-deg", type=float)
    t.add_argument("--height-source", choices=("gps", "baro"), help="where the autopilot's EKF takes its height from: "
                   "the GPS's vertical error, or a barometer's drift (ArduPilot's default)")
    t.set_defaults(func=_cmd_telemetry)
    lg = sub.add_parser("logs", help="write the flight's telemetry as other drones log it, beside its .tlog: an "
                                     "ArduPilot DataFlash telemetry.bin and a DJI video.SRT (one subtitle a frame)")
    lg.add_argument("flight_dir")
    lg.add_argument("--out", help="folder for the three files (default: the flight directory)")
    from sim.logs import SRT_LAYOUTS

    lg.add_argument("--srt-layout", choices=sorted(SRT_LAYOUTS), default="mavic3",
                    help="the DJI layout of video.SRT: " + "; ".join(f"{k}, {v[3]}" for k, v in SRT_LAYOUTS.items()))
    lg.add_argument("--no-attitude", action="store_true",
                    help="no attitude fields in video.SRT (most DJI drones write none)")
    lg.set_defaults(func=_cmd_logs)
    c = sub.add_parser("counts", help="write the hand counts of a few trees a grower would make (row,tree,apples), "
                                      "from the truth's full loads")
    c.add_argument("flight_dir")
    c.add_argument("--out", required=True, help="the sample-count CSV to write")
    pick = c.add_mutually_exclusive_group(required=True)
    pick.add_argument("--trees", nargs="+", metavar="ROW:TREE", help="these trees (rows and trees numbered from 1)")
    pick.add_argument("--random", type=int, metavar="K", help="K trees drawn at random (--seed)")
    c.add_argument("--seed", type=int, default=0)
    c.add_argument("--count-error-cv", type=float, default=0.0,
                   help="a human's counting error: each count times a normal factor of mean 1 and this CV")
    c.set_defaults(func=_cmd_counts)
    lo = sub.add_parser("layout", help="write the orchard layout file a grower would have (rows' ends, tree spacing), "
                                       "fitted to the truth's trees and numbered as they are")
    lo.add_argument("flight_dir", nargs="?", help="a rendered flight's folder")
    lo.add_argument("--config", help="or a config: its orchard's layout before any flight (to plan the flight on)")
    lo.add_argument("--out", required=True, help="the orchard layout CSV to write")
    lo.set_defaults(func=_cmd_layout)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    return cli.run(args.func, args)


if __name__ == "__main__":
    cli.exit_with(main)
