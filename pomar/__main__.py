"""python -m pomar SUBCOMMAND: the shared core's own tools, for a flight of your own before either node runs.

  flight   build a flight directory from a video, the drone's log (.tlog, DataFlash .bin, PX4 .ulg, DJI .SRT) and
           a camera (a camera.json or a built-in camera); the onboard node and the ground read it as any other
  cameras  list the built-in cameras, with the focal length in pixels each gives at a video width
  plan     a flight plan from the orchard's layout that films every tree from both sides, at the detector's apple
           size, for the drone and camera given (plan.json, coverage.csv)
  scale    the apple radius in pixels a camera foresees from a height and a tilt, and the scale that brings it to
           a detector's size (what the onboard node's --detector-scale auto does on each frame)
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from pomar import cli


def _cmd_flight(args) -> int:
    from pomar.assemble import assemble_flight, describe

    rep = assemble_flight(args.video, args.log, args.camera, args.out, flight_id=args.flight_id,
                          drone_id=args.drone_id, clock_offset_s=args.clock_offset_s)
    print(describe(rep))
    for problem in rep["problems"]:
        print(f"  problem: {problem}")
    if args.json:
        Path(args.json).write_text(json.dumps(rep, indent=2) + "\n")
    return 0


def _cmd_cameras(args) -> int:
    from pomar.assemble import CAMERAS, camera_for

    for name in sorted(CAMERAS):
        cam, _ = camera_for(name, args.width, round(args.width * 9 / 16))
        print(f"{name:14s} fx {cam.fx:7.1f} px at {args.width} px wide  {CAMERAS[name][2]}")
    return 0


def _cmd_scale(args) -> int:
    import numpy as np

    from pomar.apple_scale import ScalePolicy, envelope_height_m, expected_radius_px
    from pomar.assemble import camera_for

    target, min_px = args.model_radius_px, None
    if args.model:
        try:
            meta = json.loads(Path(args.model).read_text())
            target, min_px = meta.get("apple_radius_px"), meta.get("min_apple_radius_px")
        except json.JSONDecodeError as e:
            print(f"error: {args.model}: not a model's metadata (not valid JSON: {e})", file=sys.stderr)
            return 2
        if not target:
            print(f"error: {args.model}: no apple_radius_px in the model's metadata: it does not say its apple size",
                  file=sys.stderr)
            return 2
    cam, source = camera_for(args.camera, args.width, args.height or round(args.width * 9 / 16))
    r = float(np.asarray(expected_radius_px(cam.fx, args.height_m, 90.0 - args.tilt_deg)).reshape(-1)[0])
    print(f"camera {source}: fx {cam.fx:.1f} px")
    if not np.isfinite(r):
        print(f"{args.height_m:g} m is too near the canopy to foresee the apples' size: frames go at their own size")
        return 0
    print(f"apple radius foreseen at {args.height_m:g} m, camera {args.tilt_deg:g} deg below the horizon: {r:.2f} px")
    policy = ScalePolicy(target_px=target)
    scale = policy.scale(r)
    print(f"the onboard node's scale for a model of {target:g} px: {scale:.2f}")
    if min_px:
        own = envelope_height_m(cam.fx, 90.0 - args.tilt_deg, min_px, 1.0)
        top = envelope_height_m(cam.fx, 90.0 - args.tilt_deg, min_px, policy.max_scale)
        inside = r * scale >= min_px
        print(f"the apples reach the model at {r * scale:.1f} px; it finds them reliably from {min_px:g} px: "
              + ("inside its envelope" if inside else "OUTSIDE its envelope: it would miss most apples"))
        print(f"its envelope with this camera and tilt: up to {own:.1f} m above the take-off point with frames at their "
              f"own size, up to {top:.1f} m enlarged {policy.max_scale:g}x (lock-step; live, only as far as the "
              f"detector keeps the video's rate)")
    return 0


#: The shipped detector's metadata: the apple size a plan flies for.
SHIPPED_DETECTOR = Path(__file__).resolve().parents[1] / "onboard" / "models" / "apple-detector.json"
PLAN_OPTIONS = ["pitch_deg", "views", "blur_px", "shutter_s", "fps", "max_height_m", "rows", "boundary"]


def _cmd_plan(args) -> int:
    from pomar.assemble import camera_for
    from pomar.drones import load_drone
    from pomar.layout import read_layout
    from pomar.plan import PlanError, PlanSettings, make_plan, write_plan
    from pomar.settings import from_options

    layout = read_layout(args.orchard)
    drone = load_drone(args.drone)
    name = args.camera or drone.camera
    if Path(name).suffix.lower() == ".json":  # a camera.json: its own lens and video size
        from pomar.camera import Camera

        camera, source = Camera.load(name), name
    else:
        camera, source = camera_for(name, drone.video_width, drone.video_height)
    detector = cli.read_json(args.model, PlanError)
    if not isinstance(detector, dict) or not detector.get("apple_radius_px"):
        raise PlanError(f"{args.model}: no apple_radius_px in the detector's metadata: it does not say its apple size")
    try:
        plan = make_plan(layout, camera, drone, detector, from_options(PlanSettings(), args, PLAN_OPTIONS), name)
    except PlanError as e:
        raise PlanError(f"{args.orchard}: {e}") from None
    files = write_plan(plan, Path(args.out))
    d = plan.as_dict()
    print(f"{len(layout) if not plan.settings.rows else len(plan.settings.rows)} rows, {d['coverage']['trees']} trees;"
          f" {drone.name}, camera {source}")
    print(f"height {d['height_m']:.1f} m above the take-off point, {d['offset_m']:.1f} m to the side of each row, "
          f"gimbal {d['gimbal_pitch_deg']:.0f} deg; apples {d['apple_px']:.1f} px in radius (the detector's "
          f"{plan.detector['apple_radius_px']:g})")
    print(f"speed {d['speed_mps']:.2f} m/s (set by {d['speed_limited_by']}): {d['views_per_apple']:.0f} frames an apple,"
          f" {d['blur_px']:.2f} px of blur")
    for f in d["flights"]:
        print(f"flight {f['flight']}: rows {', '.join(map(str, f['rows']))}, {f['passes']} passes, "
              f"{f['minutes']:.1f} min")
    cov = d["coverage"]
    print(f"{d['batteries']} batteries, {d['minutes']:.1f} min in all; expected coverage {cov['mean']:.2f}, "
          f"{cov['trees_both_sides']} of {cov['trees']} trees from both sides")
    for line in plan.problems:
        print(f"  {line}")
    for t in plan.trees:
        if t["sides_seen"] < 2 and not plan.settings.boundary:
            print(f"  row {t['row']} tree {t['tree']}: seen from {t['sides_seen']} side(s) only "
                  f"(coverage {t['coverage']:.2f})")
    print("wrote " + ", ".join(str(f) for f in files))
    return 0


def _positive(value: str) -> float:
    v = float(value)
    if not v > 0:
        raise argparse.ArgumentTypeError(f"must be positive, not {value}")
    return v


def _pixels(value: str) -> int:
    try:
        v = int(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"a whole number of pixels, not {value!r}") from None
    if v <= 0:
        raise argparse.ArgumentTypeError(f"must be at least 1 pixel, not {value}")
    return v


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m pomar", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)

    f = sub.add_parser("flight", help="build a flight directory from a video, a log and a camera")
    f.add_argument("--video", required=True, help="the video file (MP4/MOV)")
    f.add_argument("--log", required=True, help="the drone's log: .tlog, DataFlash .bin, PX4 .ulg or DJI .SRT")
    f.add_argument("--camera", required=True,
                   help="a camera.json, or a built-in camera's name (python -m pomar cameras lists them)")
    f.add_argument("--out", required=True, help="the flight directory to write")
    f.add_argument("--flight-id", help="default: from the video's name")
    f.add_argument("--drone-id", default="drone-1")
    f.add_argument("--clock-offset-s", type=float, default=0.0,
                   help="the camera's clock minus the log's, where the log has no camera events to time the frames")
    f.add_argument("--json", help="write what was found (start time and how, camera, the log's problems) here")
    f.set_defaults(func=_cmd_flight)

    c = sub.add_parser("cameras", help="list the built-in cameras")
    c.add_argument("--width", type=_pixels, default=3840, help="the video's width in pixels (default 3840)")
    c.set_defaults(func=_cmd_cameras)

    s = sub.add_parser("scale", help="the apple size a camera foresees, and the detector scale for it")
    s.add_argument("--camera", required=True, help="a camera.json, or a built-in camera's name")
    s.add_argument("--width", type=_pixels, default=3840, help="the video's width in pixels (built-in cameras)")
    s.add_argument("--height", type=_pixels, help="the video's height in pixels (default: 16:9)")
    s.add_argument("--height-m", type=_positive, required=True, help="the camera's height above the ground (m)")
    s.add_argument("--tilt-deg", type=float, default=90.0, help="the camera's pitch below the horizon (90: nadir)")
    m = s.add_mutually_exclusive_group(required=True)
    m.add_argument("--model", help="a detector's metadata (JSON beside its .onnx, e.g. onboard/models/apple-detector.json)"
                                   ": the apple radius it works best at")
    m.add_argument("--model-radius-px", type=_positive, help="that radius, given by hand")
    s.set_defaults(func=_cmd_scale)

    pl = sub.add_parser("plan", help="a flight plan that films every tree of the rows from both sides")
    pl.add_argument("orchard", help="the orchard's layout (CSV: the format of ground's --orchard)")
    pl.add_argument("--drone", required=True,
                    help="a built-in drone (phantom-4-pro, mavic-3, generic-quad) or a JSON file of its figures")
    pl.add_argument("--camera", help="a camera.json (its lens and video size), or a built-in camera's name at the "
                                     "drone's video size (default: the drone's camera)")
    pl.add_argument("--model", default=str(SHIPPED_DETECTOR),
                    help="the detector's metadata: the apple size it works at (default: the shipped model's)")
    pl.add_argument("--out", required=True, help="the folder to write plan.json and coverage.csv to")
    from pomar.plan import PlanSettings
    from pomar.settings import add_options

    add_options(pl, PlanSettings(), PLAN_OPTIONS)
    pl.set_defaults(func=_cmd_plan)

    args = p.parse_args(argv)
    return cli.run(args.func, args)


if __name__ == "__main__":
    cli.exit_with(main)
