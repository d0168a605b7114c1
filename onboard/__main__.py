"""python -m onboard SUBCOMMAND: the drone's companion-computer node.

  run         replay a flight directory through the node: frames + telemetry -> detector -> zenoh
  live        a camera or stream + a live MAVLink link -> detector -> zenoh
  telemetry   read any supported log (.tlog, DataFlash .bin, PX4 .ulg, DJI .SRT): its streams, clock, gaps and
              problems (--json OUT for a summary file), and with --flight each frame's sample
"""

from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

from onboard.detector import TILE_SIZE
from onboard.node import NodeSettings
from onboard.numbering import default_state_dir
from pomar import cli
from pomar.countable import PUBLISH_BELOW, PUBLISH_SCORE, count_scores
from pomar.settings import add_options
from pomar.telemetry import mount_arguments

DEFAULT_ENDPOINT = "tcp/127.0.0.1:7447"


def _cmd_telemetry(args) -> int:
    import numpy as np

    import json
    from pathlib import Path

    from pomar.flight import FlightDir
    from pomar.telemetry import Flags, TelemetryError, read_log

    if Path(args.log).is_dir():
        raise TelemetryError(f"{args.log}: is a directory; give the log file (e.g. {Path(args.log) / 'telemetry.tlog'})")
    tl = read_log(args.log, max_gap_s=args.max_gap_s)
    print(tl.summary())
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(tl.summary_dict(), indent=2) + "\n")
    if args.flight:
        meta = FlightDir(args.flight).meta()
        t, flags = tl.frame_times(meta.frame_count, meta.video_start_utc, meta.fps, args.clock_offset_s)
        s = tl.at(t, args.camera_tilt_deg, args.camera_yaw_deg)
        flags = flags | s["flags"]
        print(f"frames: {meta.frame_count}, {int((flags & Flags.incomplete() == 0).sum())} with complete telemetry "
              f"(a position, the camera's attitude and a GPS fix), {int((flags == 0).sum())} with no flag")
        for f in Flags:
            n = int((flags & f).astype(bool).sum())
            if n:
                print(f"  {f.name:<18} {n} frames")
        if args.show:
            for i in np.linspace(0, meta.frame_count - 1, min(args.show, meta.frame_count)).astype(int):
                print(f"  frame {i:>5} t={t[i]:.3f} lat={s['lat'][i]:.7f} lon={s['lon'][i]:.7f} alt={s['alt'][i]:.2f} "
                      f"q_gimbal={np.round(s['q_gimbal'][i], 4).tolist()} flags={Flags(int(flags[i]))!r}")
    return 0


def _cmd_run(args) -> int:
    import json
    from pathlib import Path

    from onboard.node import NodeSettings, OnboardNode

    def write_summary(summary: dict) -> None:
        if args.summary:
            Path(args.summary).write_text(json.dumps(summary, indent=2) + "\n")

    from pomar.settings import from_options

    settings = from_options(NodeSettings(), args, RUN_FIELDS + LINK_FIELDS + SCALE_FIELDS + MOUNT_FIELDS)
    if args.video:
        if not (args.log and args.camera):
            print("error: --video needs --log and --camera", file=sys.stderr)
            return 2
        if args.flight_dir:
            print("error: give a flight directory or --video/--log/--camera, not both", file=sys.stderr)
            return 2
        from pomar.assemble import assemble_flight, describe

        rep = assemble_flight(args.video, args.log, args.camera, args.flight_out or f"out/flights/{Path(args.video).stem}",
                              flight_id=args.flight_id, clock_offset_s=args.clock_offset_s)
        print(describe(rep), file=sys.stderr)
        args.flight_dir = rep["flight_dir"]
    elif not args.flight_dir:
        print("error: give a flight directory, or --video, --log and --camera", file=sys.stderr)
        return 2
    try:
        # every input is read and cross-checked before anything is published or any port is opened
        node = OnboardNode(args.flight_dir, None, None, settings)
        meta = node.check_inputs()[0]
        node.detector = _detector(args, args.flight_dir)
    except Exception as exc:
        print(f"error: {exc}", file=sys.stderr)
        write_summary({"error": str(exc)})
        return 2
    session, pub = _publisher(args, meta.flight_id, meta.drone_id)
    node.pub = pub
    _wait_for_ground(pub, args.wait_for_ground if args.wait_for_ground is not None else 0.0 if args.realtime else 30.0)
    try:
        summary = node.run()
        print(json.dumps(summary, indent=2))
        write_summary(summary)
        code = 0
    except Exception as exc:
        print(f"error: {exc}", file=sys.stderr)
        write_summary({**getattr(exc, "summary", {}), "error": str(exc)})
        code = 1
    from pomar.transport import linger_and_close

    linger_and_close(session, pub, args.linger)
    return code


def _publisher(args, flight_id: str, drone_id: str):
    """The zenoh session (listening on the default endpoint unless told otherwise) and the flight's publisher."""
    from pomar import transport

    listen = None if args.zenoh_config else (args.listen or [transport.DEFAULT_ENDPOINT])
    session = transport.open_session(listen=listen, connect=args.connect, config_file=args.zenoh_config)
    return session, transport.FlightPublisher(session, flight_id, drone_id)


def _detector(args, flight_dir=None):
    if args.detector == "onnx":
        from onboard.detector import OnnxDetector

        det = OnnxDetector(args.model, providers=args.providers, score_thresh=args.score_thresh,
                           tile_size=args.tile_size, threads=args.threads)
        if args.score_thresh is None:  # the publish score the model's JSON gives, or follows from its operating score
            det.score_thresh = count_scores(det.meta)[1]
        return det
    from onboard.replay_detector import TruthReplayDetector

    if flight_dir is None:
        raise cli.InputError("--detector truth-replay needs a simulated flight (--truth-flight DIR)")
    return TruthReplayDetector(flight_dir)


def _wait_for_ground(pub, seconds: float) -> None:
    """Hold the first frame until a ground subscribes (at most ``seconds``): a ground that joins as the first
    samples go out can miss them (zenoh's history recovers only after the first sample a subscriber gets)."""
    if seconds > 0 and not pub.wait_for_subscriber(seconds):
        print(f"no ground subscribed within {seconds:g} s: publishing anyway", file=sys.stderr)


def _cmd_live(args) -> int:
    import json

    from onboard.live import run_live
    from onboard.node import KeyframePolicy
    from onboard.telemetry import LiveTelemetry
    from pomar.camera import Camera

    detector = _detector(args, args.truth_flight)
    camera = Camera.load(args.camera_json).to_dict()
    telemetry = LiveTelemetry(args.mavlink, max_gap_s=args.max_gap_s)
    session, pub = _publisher(args, args.flight_id, args.drone_id)
    _wait_for_ground(pub, args.wait_for_ground)
    try:
        summary = run_live(args.camera, telemetry, camera, args.flight_id, args.drone_id, pub, detector,
                           KeyframePolicy(args.keyframe_every, args.keyframe_every_s, args.keyframe_every_m),
                           args.keyframe_width, args.jpeg_quality, args.clock_offset_s, play_fps=args.play_fps,
                           max_frames=args.max_frames, duration_s=args.duration, detector_scale=args.detector_scale,
                           state_dir=args.state_dir)
        print(json.dumps(summary, indent=2))
        if summary["error"]:
            print(f"error: {summary['error']}", file=sys.stderr)
    finally:
        telemetry.close()
        from pomar.transport import linger_and_close

        linger_and_close(session, pub, args.linger)
    return 1 if summary["error"] else 0


def _detector_options(r):
    r.add_argument("--model", help="ONNX model (default: $POMAR_DETECTOR, else the shipped onboard/models/apple-detector.onnx)")
    r.add_argument("--providers", nargs="+", help="onnxruntime execution providers, in order of preference "
                   "(default CPUExecutionProvider; e.g. CUDAExecutionProvider TensorrtExecutionProvider)")
    r.add_argument("--score-thresh", type=float, help="publish the detections scored at least this (default: the "
                   "model JSON's count.publish_score, chosen on tuning flights; for a model without one "
                   f"{PUBLISH_SCORE}, pomar.countable.PUBLISH_SCORE, or {PUBLISH_BELOW} under the model's operating "
                   "score where that is lower: weaker than the count's confirm score, they extend tracks)")
    r.add_argument("--tile-size", type=int, default=TILE_SIZE, help="frames with a side larger than this (px, after "
                   "--detector-scale) are cut into as few tiles as cover them")
    r.add_argument("--threads", type=int, help="onnxruntime intra-op threads")
    add_options(r, NodeSettings(), SCALE_FIELDS)


#: The node's settings (onboard.node.NodeSettings) that are options; each option's name, default and help come from
#: its field (pomar.settings). The camera's mount comes from pomar.telemetry.mount_arguments, shared with the ground.
RUN_FIELDS = ["realtime", "every", "camera_started_at", "log", "clock_offset_s"]
LINK_FIELDS = ["keyframe_every", "keyframe_every_s", "keyframe_every_m", "keyframe_width", "jpeg_quality"]
SCALE_FIELDS = ["detector_scale"]
MOUNT_FIELDS = ["camera_tilt_deg", "camera_yaw_deg"]


def _link_options(r):
    add_options(r, NodeSettings(), LINK_FIELDS)
    r.add_argument("--listen", action="append", help=f"zenoh endpoint to listen on (default {DEFAULT_ENDPOINT})")
    r.add_argument("--connect", action="append", help="zenoh endpoint to connect to")
    r.add_argument("--zenoh-config", help="a zenoh JSON5 config file for real links")
    r.add_argument("--linger", type=float, default=10.0, help="seconds to keep serving history after the end")


def main(argv=None) -> int:
    from pomar.flight import id_argument

    p = argparse.ArgumentParser(prog="python -m onboard", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", help="replay a flight directory through the node and publish it over zenoh")
    r.add_argument("flight_dir", nargs="?", help="a flight directory (docs/flight-format.md); or give --video, "
                                                  "--log and --camera")
    r.add_argument("--video", help="a video file (MP4/MOV): the flight is built from it, --log and --camera "
                                   "(frame rate and count from the container; see pomar/assemble.py)")
    r.add_argument("--camera", help="with --video: a camera.json, or a built-in camera (phantom-4-pro, mavic-3, "
                                    "mavic-2-pro, air-2s, mini-2, mini-3-pro, phantom-4-rtk)")
    r.add_argument("--flight-id", type=id_argument("flight id"), help="with --video: the flight's id (default: the "
                                                                      "video's name)")
    r.add_argument("--flight-out", help="with --video: where the built flight directory goes (default "
                                        "out/flights/<video name>)")
    r.add_argument("--detector", choices=["onnx", "truth-replay"], default="onnx",
                   help="onnx (the shipped model, default) or truth-replay (a diagnostic stand-in that replays "
                        "truth/detections.csv)")
    _detector_options(r)
    add_options(r, NodeSettings(), RUN_FIELDS)
    mount_arguments(r)
    _link_options(r)
    r.add_argument("--wait-for-ground", type=float, default=None,
                   help="wait up to this many seconds for a ground to subscribe before the first frame (0 = do not "
                        "wait; default 30 lock-step, 0 with --realtime)")
    r.add_argument("--summary", help="also write the run's summary (JSON) here")
    r.set_defaults(func=_cmd_run)
    lv = sub.add_parser("live", help="a camera or stream + a live MAVLink link -> detector -> zenoh")
    lv.add_argument("--camera", required=True, help="OpenCV camera index, stream URL or video file")
    lv.add_argument("--mavlink", default="udpin:127.0.0.1:14550", help="pymavlink connection string (udpin:..., serial)")
    lv.add_argument("--camera-json", required=True, help="the camera's intrinsics (camera.json, COLMAP convention)")
    lv.add_argument("--flight-id", required=True, type=id_argument("flight id"))
    lv.add_argument("--drone-id", default="drone-1", type=id_argument("drone id"))
    lv.add_argument("--detector", choices=["onnx", "truth-replay"], default="onnx")
    lv.add_argument("--truth-flight", help="for --detector truth-replay: the simulated flight whose truth to replay")
    _detector_options(lv)
    _link_options(lv)
    add_options(lv, NodeSettings(), ["clock_offset_s"])
    lv.add_argument("--max-gap-s", type=float, default=1.0, help="telemetry gaps longer than this flag frames")
    lv.add_argument("--play-fps", type=float, help="play a video file at this rate (a camera sets its own)")
    lv.add_argument("--state-dir", type=Path, default=default_state_dir(),
                    help="where the frame numbers are kept, so that a node restarted mid-flight goes on from them "
                         "(default: %(default)s)")
    lv.add_argument("--max-frames", type=int, help="stop after this many processed frames")
    lv.add_argument("--duration", type=float, help="stop after this many seconds")
    lv.add_argument("--wait-for-ground", type=float, default=0.0,
                    help="wait up to this many seconds for a ground to subscribe before the first frame (0 = do not "
                         "wait: a drone flies whether or not a ground listens)")
    lv.set_defaults(func=_cmd_live)
    t = sub.add_parser("telemetry", help="read a log (.tlog, .bin, .ulg, .SRT): streams, clock, gaps, problems, and "
                                         "each frame's sample")
    t.add_argument("log", help="the telemetry log; its format is taken from its first bytes")
    t.add_argument("--json", help="write a summary here: format, positions, lat_range, lon_range, span_s, attitudes, "
                                  "gimbal_attitudes, camera_events, problems, ...")
    t.add_argument("--flight", help="flight directory: sample the telemetry at its frames")
    add_options(t, NodeSettings(), ["clock_offset_s"])
    t.add_argument("--max-gap-s", type=float, default=1.0)
    mount_arguments(t)
    t.add_argument("--show", type=int, default=0, help="print this many frames' samples")
    t.set_defaults(func=_cmd_telemetry)
    args = p.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    return cli.run(args.func, args)


if __name__ == "__main__":
    cli.exit_with(main)
