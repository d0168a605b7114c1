"""python -m ground SUBCOMMAND: the ground side (association and its evaluation; the live node comes later)."""

from __future__ import annotations

import argparse
import json
import logging
import sys
from pathlib import Path


def _cmd_evaluate(args) -> int:
    from ground.association import AssociationParams
    from ground.evaluate import Perturbation, evaluate, format_table

    params = AssociationParams(k=args.k, tau_epipolar=args.tau_epipolar, tau_geom=args.tau_geom,
                               ransac_iterations=args.ransac_iterations, min_inliers=args.min_inliers,
                               max_paths=args.max_paths, merge_search_m=args.merge_search_m, seed=args.seed)
    pert = Perturbation(args.noise_px, args.miss, args.fp, args.dup, args.min_visible, args.seed)
    results = [evaluate(args.flight_dir, mode, params, pert, args.detections, args.poses, args.match_m,
                        baselines=(i == 0), truth_min_views=args.truth_min_views,
                        remove_pose_offset=args.remove_pose_offset) for i, mode in enumerate(args.mode)]
    print(format_table(results))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        out = results[0] if len(results) == 1 else {r["mode"]: r for r in results}
        Path(args.json).write_text(json.dumps(out, indent=2) + "\n")
    return 0


def _cmd_register(args) -> int:
    from ground.register_flight import register_flight
    from ground.registration import RegistrationSettings

    settings = RegistrationSettings(submodel_size=args.submodel_size, match_window=args.match_window,
                                    max_num_features=args.max_features)
    out = args.out or f"out/register/{Path(args.flight_dir).name}"
    res = register_flight(args.flight_dir, out, args.every, args.scale, settings, progress=not args.quiet,
                          frames_limit=args.frames)
    print(json.dumps(res, indent=2))
    print(f"poses for every frame: {out}/poses.csv; COLMAP text models (ENU): {out}/model/")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(res, indent=2) + "\n")
    return 0


def main(argv=None) -> int:
    from ground.evaluate import __doc__ as evaluate_doc

    p = argparse.ArgumentParser(prog="python -m ground", description=__doc__)
    sub = p.add_subparsers(dest="cmd", required=True)
    e = sub.add_parser("evaluate", help="run the association on a simulated flight and score it against the truth",
                       description=evaluate_doc,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    e.add_argument("flight_dir")
    e.add_argument("--detections", default="truth", help="'truth' or a CSV frame,u,v")
    e.add_argument("--poses", default="truth", help="'truth', 'telemetry' (GPS + gimbal only) or a CSV with truth/frames.csv's columns")
    e.add_argument("--noise-px", type=float, default=0.0)
    e.add_argument("--miss", type=float, default=0.0, help="probability a detection is missed")
    e.add_argument("--fp", type=float, default=0.0, help="false positives per frame (Poisson mean)")
    e.add_argument("--dup", type=float, default=0.0, help="probability a detection is duplicated")
    e.add_argument("--min-visible", type=float, default=0.5)
    e.add_argument("--mode", nargs="+", default=["windowed"], choices=["offline", "windowed"])
    e.add_argument("--k", type=int, default=5)
    e.add_argument("--tau-epipolar", type=float, default=4.0)
    e.add_argument("--tau-geom", type=float, default=3.0)
    e.add_argument("--ransac-iterations", type=int, default=50)
    e.add_argument("--min-inliers", type=int, default=3)
    e.add_argument("--max-paths", type=int, default=500, help="offline DFS bound per node")
    e.add_argument("--merge-search-m", type=float, default=1.0, help="merge duplicate apples (one apple seen twice) within this distance when their views agree; 0 = the paper as is")
    e.add_argument("--match-m", type=float, default=0.10)
    e.add_argument("--remove-pose-offset", action="store_true",
                   help="score the map's shape: subtract the poses' mean camera offset from truth (the GPS bias)")
    e.add_argument("--truth-min-views", type=int, default=3,
                   help="an apple is visible in the flight when seen (at least --min-visible) in this many frames")
    e.add_argument("--seed", type=int, default=0)
    e.add_argument("--json")
    e.set_defaults(func=_cmd_evaluate)
    r = sub.add_parser("register", help="register a flight's keyframes incrementally with pycolmap; ENU poses for every frame")
    r.add_argument("flight_dir")
    r.add_argument("--every", type=int, default=2, help="every Nth frame is a keyframe (as the onboard default)")
    r.add_argument("--scale", type=float, default=1.0, help="resize keyframes by this factor")
    r.add_argument("--submodel-size", type=int, default=60)
    r.add_argument("--match-window", type=int, default=8)
    r.add_argument("--max-features", type=int, default=4096)
    r.add_argument("--frames", type=int, help="only the first N frames")
    r.add_argument("--out")
    r.add_argument("--json")
    r.add_argument("--quiet", action="store_true")
    r.set_defaults(func=_cmd_register)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    from pomar.flight import FlightFormatError

    try:
        return args.func(args)
    except FlightFormatError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
