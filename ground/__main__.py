"""python -m ground SUBCOMMAND: the ground side of the system.

  replay    replay a recorded flight (default: the bundled one) through the onboard and ground nodes; with
            --recorded JOURNAL, a recorded stream played at --speed S into a ground
  play      publish a recorded stream (a ground's journal.bin) over zenoh at its capture-time pace
  run       the ground node: subscribe to a flight over zenoh, map its apples live, log to rerun
  register  register a flight's keyframes with pycolmap (files, no zenoh)
  evaluate  run the association on a simulated flight and score it against the truth
  batch     replay many flights at once on Dask (a local cluster, or --cluster), and one farm report
  layout, choose-trees, load, combine: the grower's commands on finished maps (ground/orchard/cli.py)
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys

from pomar import cli
from pomar.apple_scale import SCALE_HELP, scale_argument
from pathlib import Path


def _cmd_batch(args) -> int:
    from ground.batch import BatchSettings, connect, read_flights, run_batch
    from ground.farm import farm_report
    from pomar.settings import from_options

    jobs = read_flights(args.flights, args.flights_csv)  # every flight checked before any starts
    s = from_options(BatchSettings(), args, BATCH_FIELDS)
    client = connect(s)  # a cluster that does not answer stops the batch here
    out = Path(args.out)
    print(f"{len(jobs)} flights in {len({j.block for j in jobs})} blocks; on "
          f"{s.cluster or 'a local Dask cluster'}; outputs in {out}/", file=sys.stderr)
    report = run_batch(jobs, out, s, progress=lambda line: print(line, file=sys.stderr, flush=True), client=client)
    for f in report["flights"]:
        if f["status"] == "failed":
            print(f"  {f['name']}: failed after {f['attempts']} attempts: {f['error']}", file=sys.stderr)
    blocks: dict = {}
    for j in jobs:
        b = blocks.setdefault(j.block, {"folders": [], "flights": 0, "counts": j.sample_counts})
        b["flights"] += 1
        st = next(f for f in report["flights"] if f["name"] == j.name)["status"]
        if st in ("done", "skipped"):
            b["folders"].append(out / j.name)
    farm = farm_report(out, blocks)
    print(f"{report['done']} flights replayed, {report['skipped']} done before, {report['failed']} failed "
          f"({report['wall_s'] / 60:.1f} min); {out}/batch.json; the farm report in {farm['folder']}/ (rows.csv, "
          "trees.csv, blocks.csv, farm.parquet, farm.png)")
    return 1 if report["failed"] else 0


#: The batch's settings (ground.batch.BatchSettings) that are options.
BATCH_FIELDS = ["retries", "cpus_per_flight", "memory_per_flight_gb", "resume", "cluster"]


def _cmd_evaluate(args) -> int:
    from ground.apples.association import AssociationParams
    from ground.evaluation.evaluate import Perturbation, evaluate, format_table

    from dataclasses import replace

    from pomar.settings import from_options

    params = replace(from_options(AssociationParams(), args, EVALUATE_ASSOCIATION_FIELDS), seed=args.seed)
    pert = from_options(Perturbation(args.noise_px, args.miss, args.fp, args.dup, args.min_visible, args.seed), args,
                        ["pose_noise_deg", "pose_noise_m"])
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
    from ground.evaluation.register_flight import register_flight

    settings = _registration_settings(args, submodel_size=args.submodel_size)
    out = args.out or f"out/register/{Path(args.flight_dir).name}"
    res = register_flight(args.flight_dir, out, args.every, args.scale, settings, progress=not args.quiet,
                          frames_limit=args.frames)
    print(json.dumps(res, indent=2))
    print(f"poses for every frame: {out}/poses.csv; COLMAP text models (ENU): {out}/model/")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(res, indent=2) + "\n")
    return 0


def _settings(args):
    from dataclasses import replace

    from ground.pipeline import GroundSettings
    from pomar.settings import from_options

    g = GroundSettings()  # mapping "stream": the stream's profile
    return replace(from_options(g, args, GROUND_FIELDS),
                   association=from_options(g.association, args, ASSOCIATION_FIELDS),
                   registration=from_options(g.registration, args, REGISTRATION_FIELDS),
                   tracking=from_options(g.tracking, args, TRACKING_FIELDS),
                   counting=from_options(g.counting, args, COUNTING_FIELDS))


def _cmd_run(args) -> int:
    from ground.node import run_ground
    from pomar.transport import DEFAULT_ENDPOINT

    connect = args.connect or (None if args.listen or args.zenoh_config else [DEFAULT_ENDPOINT])
    report = run_ground(args.flight_id, args.out, connect=connect, listen=args.listen, zenoh_config=args.zenoh_config,
                        drone_ids=args.drone_id, settings=_settings(args), rrd=not args.no_rrd, serve=args.serve,
                        viewer=args.viewer, harvest=args.harvest, orchard=args.orchard,
                        sample_counts=args.sample_counts, idle_timeout_s=args.idle_timeout,
                        resume=not args.fresh, expected_frames=args.expected_frames, max_ahead_s=args.max_ahead_s)
    rows = ", ".join(f"row {r['row']}: {r['count']}" for r in report["rows"])
    print(f"{report['apples']} apples ({rows}); outputs in {args.out}/")
    failed, rescued = report.get("link", {}).get("outputs_write_failed"), report.get("link", {}).get("outputs_rescued_to")
    if failed:
        print(f"error: the map files could not be written to {args.out} ({failed})"
              + (f"; they are in {rescued}" if rescued else "; nor anywhere else"), file=sys.stderr)
        return 1
    return 0


def _cmd_play(args) -> int:
    from ground.link.player import PlayerError, load_recording, play
    from pomar import transport

    def write_summary(d):
        if args.summary:
            Path(args.summary).write_text(json.dumps(d, indent=2) + "\n")

    try:
        rec = load_recording(args.recording, args.flight_id)
    except PlayerError as exc:
        print(f"error: {exc}", file=sys.stderr)
        write_summary({"error": str(exc)})
        return 2
    for p in rec.problems:
        print(f"warning: {args.recording}: {p}", file=sys.stderr)
    session = transport.open_session(listen=args.listen or [transport.DEFAULT_ENDPOINT], connect=args.connect)
    pub = transport.FlightPublisher(session, rec.flight_id, rec.drone_id)
    if args.wait_for_ground > 0 and not pub.wait_for_subscriber(args.wait_for_ground):
        print(f"no ground subscribed within {args.wait_for_ground:g} s: playing anyway", file=sys.stderr)
    summary = play(rec, pub, args.speed)
    print(json.dumps(summary, indent=2))
    write_summary(summary)
    transport.linger_and_close(session, pub, args.linger)
    return 0


def _cmd_replay(args) -> int:
    from ground.evaluation.scoring import format_evaluation
    from ground.replay import BUNDLED, ReplayError, default_out, replay

    # a recorded stream without a flight directory is a flight of its own: the stream says what it is
    flight = args.flight_dir or (None if args.recorded else BUNDLED)
    # (its output folder then defaults to that of its flight id, which replay reads from the stream)
    name = Path(args.video).stem if args.video else Path(flight).name if flight else None
    out = Path(args.out) if args.out else default_out(name) if name else None
    if args.recorded and (args.video or args.log):
        print("error: --recorded plays a recorded stream: no --video or --log with it", file=sys.stderr)
        return 2
    if args.video:  # a flight built from the user's video, log and camera
        from pomar.assemble import assemble_flight, describe

        if args.flight_dir or not (args.log and args.camera):
            print("error: --video needs --log and --camera, and no flight directory", file=sys.stderr)
            return 2
        built = assemble_flight(args.video, args.log, args.camera, out / "flight")
        print(describe(built), file=sys.stderr)
        flight, args.log = built["flight_dir"], None  # the built flight names its log
    ground_args = _ground_argv(args)  # the stream says lock-step or live: the ground takes its profile from it
    if args.harvest:
        from ground.outputs.tables import read_harvest

        read_harvest(args.harvest)  # a file that does not read stops the replay before it starts
        ground_args += ["--harvest", str(Path(args.harvest).resolve())]
    if args.orchard or args.sample_counts:
        from ground.orchard.files import read_orchard_files

        # as the harvest: a layout or hand counts that do not read stop the replay before it starts
        read_orchard_files(args.orchard, args.sample_counts, args.load_model)
        for flag, path in (("--orchard", args.orchard), ("--sample-counts", args.sample_counts)):
            ground_args += [flag, str(Path(path).resolve())] if path else []
    try:
        rep = replay(flight, out, realtime=args.realtime, detector=args.detector, model=args.model,
                     keyframe_every=args.keyframe_every, keyframe_width=args.keyframe_width, every=args.every,
                     ground_args=ground_args, quiet=args.quiet,
                     onboard_args=(["--score-thresh", str(args.detector_score_thresh)] if args.detector_score_thresh else [])
                     + (["--log", args.log] if args.log else [])
                     + (["--camera-tilt-deg", str(args.camera_tilt_deg), "--camera-yaw-deg", str(args.camera_yaw_deg)]
                        if args.camera_tilt_deg is not None else [])
                     + ["--detector-scale", args.detector_scale],
                     recorded=args.recorded, speed=args.speed)
    except ReplayError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 1
    out = out or default_out(rep["flight_id"])
    print()
    print(f"flight {rep['flight_id']}: {rep['apples']} apples in {len(rep['rows'])} rows; "
          f"{rep['frames']['frames']} frames ({rep['frames']['registered']} registered, "
          f"{rep['frames'].get('tracked', 0)} tracked, {rep['frames']['interpolated']} interpolated, "
          f"{rep['frames'].get('apples', 0)} placed by apples, {rep['frames']['telemetry']} telemetry poses)")
    for r in rep["rows"]:
        load = r.get("load")
        print(f"  row {r['row']}: {r['count']} apples over {r['length_m']:.1f} m"
              + (f"; load {load:.0f} ({r['load_lo']:.0f}-{r['load_hi']:.0f}), {r['kg']:.0f} kg"
                 if load is not None and load == load else ""))  # NaN: no hand counts
    ob = rep.get("onboard", {})
    played = bool(rep.get("replay", {}).get("recorded"))
    print(f"wall {rep['wall_seconds']:.1f} s for a {rep['flight_seconds']:.1f} s flight: real-time factor "
          f"{rep['realtime_factor']:.2f}; peak memory: ground {rep['timings']['peak_rss_mb']:.0f} MB"
          + ("" if played else f", onboard {ob.get('peak_rss_mb', float('nan')):.0f} MB"))
    tm, fr = rep["timings"], rep["frames"]
    if tm.get("frame_delay_median_s") is not None:
        print(f"ground: frames mapped {tm['frame_delay_median_s']:.1f} s after they arrived (median; p95 "
              f"{tm['frame_delay_p95_s']:.1f} s, max {tm['frame_delay_max_s']:.1f} s); {fr['registered']} of "
              f"{fr['keyframes']} images registered as mapping keyframes, {fr.get('tracked', 0)} frames tracked, "
              f"{rep['tracking']['failed']} tracking failures")
    if ob and played:
        print(f"player: {ob['frames_processed']} frames of {ob['recording']} at {ob['speed']:g}x in {ob['seconds']:.1f} s "
              f"({ob['flight_seconds']:.1f} s of flight)")
    elif ob:
        print(f"onboard: {ob['frames_processed']} frames processed, {ob['frames_dropped']} dropped, detector "
              f"{ob['detector_latency_s']:.3f} s/frame, read-to-publish median {ob['read_to_publish_median_s']:.3f} s, "
              f"link {ob['link_bytes_per_s_at_video_fps'] / 1e6:.2f} MB/s at the video's frame rate")
    size = rep.get("apple_size") or {}
    if size.get("radius_px_median") is not None:
        print(f"apples reached the detector at a radius of {size['radius_px_median']:.1f} px (median)"
              + (f"; it finds them reliably from {size['min_supported_px']:.1f} px: {size['frames_below']} frames below"
                 if size.get("min_supported_px") else ""))
    if "evaluation" in rep:
        print("against the flight's truth:")
        print(format_evaluation(rep["evaluation"]))
    maps = Path(rep["out"])  # out, or where the ground put the map files when out's disk refused them
    print(f"map: {maps}/apples.csv, apples.geojson (open in any GIS, e.g. QGIS or geojson.io), apples.ply, rows.csv")
    print(f"rerun recording: {out}/flight.rrd  (open it with: rerun {out}/flight.rrd)")
    print(f"report: {maps}/report.json")
    if maps != Path(out):
        print(f"error: the map files could not be written to {out}; they are in {maps}", file=sys.stderr)
        return 1
    if rep.get("onboard_error"):
        print(f"error: the onboard node stopped early: {rep['onboard_error']} (the map holds the frames before)",
              file=sys.stderr)
        return 1
    return 0


#: The settings' fields that are options of `ground run` (and of `ground replay`, which hands them to it); each
#: option's name, default and help come from its field (pomar.settings).
ASSOCIATION_FIELDS = ["k", "tau_epipolar", "tau_geom", "min_inliers", "cross_pass", "merge_window", "max_merge_shift_m"]
REGISTRATION_FIELDS = ["max_num_features", "match_window", "sift", "init_frames", "sift_width", "upright", "revisit"]
TRACKING_FIELDS = ["min_share_to_go_on", "min_tracked_share", "max_points"]
COUNTING_FIELDS = ["confirm_score", "confirm_at_model_score", "confirm_views", "min_radius_ratio", "min_view_ratio", "min_parallax_deg"]
EVALUATE_ASSOCIATION_FIELDS = ["k", "tau_epipolar", "tau_geom", "ransac_iterations", "min_inliers", "max_paths",
                               "merge_search_m"]
GROUND_FIELDS = ["max_wait_s", "max_interp_gap", "mapping", "correction_every_s", "init_spacing_s", "min_score",
                 "tree_spacing_m", "load_model", "drift_sigma_s"]


def _registration_options(p, settings=None):
    """Registration's options, with ``settings``' values (a RegistrationSettings) as defaults."""
    from ground.poses.registration import RegistrationSettings
    from pomar.settings import add_options

    add_options(p, settings or RegistrationSettings(), REGISTRATION_FIELDS, prefix="registration: ")


def _registration_settings(args, **extra):
    from dataclasses import replace

    from ground.poses.registration import RegistrationSettings
    from pomar.settings import from_options

    return replace(from_options(RegistrationSettings(), args, REGISTRATION_FIELDS), **extra)


HARVEST_HELP = "CSV row,kg (rows numbered as in rows.csv): report the correlation of per-row counts with yield"
SAMPLE_COUNTS_HELP = ("the trees you counted by hand (CSV row,tree,apples, numbered as the --orchard layout numbers "
                      "them): trees.csv, rows.csv and report.json then give each tree's, row's and the flight's load "
                      "(every apple, seen or not) with a 90 %% interval")
ORCHARD_HELP = ("an orchard layout file (`ground layout` writes one from a finished map): rows.csv and trees.csv then "
                "use its rows' and trees' numbers, the same in every flight (default: the map's own numbering)")


def _ground_argv(args) -> list[str]:
    """The ground's options of a parsed command line as `ground run` arguments: every option _ground_options defines,
    so that none is accepted and then left behind."""
    p = argparse.ArgumentParser(add_help=False)
    _ground_options(p)
    out: list[str] = []
    for a in p._actions:
        if not a.option_strings:
            continue
        value = getattr(args, a.dest)
        if a.nargs == 0:  # a switch: --x or --no-x
            out += [a.option_strings[0] if value else a.option_strings[1]]
        else:
            out += [a.option_strings[0], str(value)]
    return out


def _ground_options(p):
    """`ground run`'s settings as options, GroundSettings' values their defaults (the profile, lock-step or live, is
    the stream's to say: --mapping stream)."""
    from ground.pipeline import GroundSettings
    from pomar.settings import add_options

    g = GroundSettings()
    add_options(p, g.association, ASSOCIATION_FIELDS, prefix="association: ")
    _registration_options(p, g.registration)
    add_options(p, g.tracking, TRACKING_FIELDS, prefix="tracking: ")
    add_options(p, g.counting, COUNTING_FIELDS, prefix="counting: ")
    add_options(p, g, GROUND_FIELDS)


def main(argv=None) -> int:
    from ground.apples.association import AssociationParams
    from ground.evaluation import scoring
    from pomar import countable
    from pomar.settings import add_options
    from ground.evaluation.evaluate import Perturbation, __doc__ as evaluate_doc
    from pomar.flight import id_argument

    p = argparse.ArgumentParser(prog="python -m ground", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = p.add_subparsers(dest="cmd", required=True)
    from ground.orchard.cli import add_orchard_commands

    add_orchard_commands(sub)
    from ground.batch import BatchSettings
    from pomar.settings import add_options

    b = sub.add_parser("batch", help="replay many flights at once on Dask (a local cluster, or --cluster ADDRESS), "
                                     "and one farm report", description=__import__("ground.batch", fromlist=["x"]).__doc__,
                       formatter_class=argparse.RawDescriptionHelpFormatter)
    b.add_argument("flights", nargs="*", help="flight directories (each its own block)")
    b.add_argument("--flights", dest="flights_csv", help="a flights CSV (block, flight or video+log+camera; optional "
                                                         "name, orchard, sample_counts, args)")
    b.add_argument("--out", required=True, help="the batch's folder: a folder per flight, batch.json, farm/")
    add_options(b, BatchSettings(), BATCH_FIELDS)
    b.set_defaults(func=_cmd_batch)
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
    add_options(e, Perturbation(), ["pose_noise_deg", "pose_noise_m"])
    e.add_argument("--min-visible", type=float, default=countable.MIN_VISIBLE,
                   help="the truth's apples counted: at least this visible (fraction)")
    e.add_argument("--mode", nargs="+", default=["windowed"], choices=["offline", "windowed"])
    add_options(e, AssociationParams(), EVALUATE_ASSOCIATION_FIELDS, prefix="association: ")
    e.add_argument("--match-m", type=float, default=scoring.MATCH_M, help="a predicted apple matches a true one within this (m)")
    e.add_argument("--remove-pose-offset", action="store_true",
                   help="score the map's shape: subtract the poses' mean camera offset from truth (the GPS bias)")
    e.add_argument("--truth-min-views", type=int, default=countable.MIN_VIEWS,
                   help="an apple is visible in the flight when seen (at least --min-visible) in this many frames")
    e.add_argument("--seed", type=int, default=0)
    e.add_argument("--json")
    e.set_defaults(func=_cmd_evaluate)
    rp = sub.add_parser("replay", help="replay a recorded flight through the onboard and ground nodes (zenoh on loopback)",
                        description=__import__("ground.replay", fromlist=["x"]).__doc__,
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    rp.add_argument("flight_dir", nargs="?", help="flight directory (default: the bundled replay_data/demo-flight; "
                                                  "with --recorded, none: the stream alone, nothing to score against)")
    rp.add_argument("--out", help="output folder (default out/replay/<flight>)")
    rp.add_argument("--realtime", action="store_true", help="frames at the video's rate, newest first (drops counted)")
    rp.add_argument("--detector", choices=["onnx", "truth-replay"], default="onnx")
    rp.add_argument("--model", help="ONNX model (default: the shipped one)")
    rp.add_argument("--detector-score-thresh", type=float,
                    help="the onboard node publishes detections scored at least this (default: its own, as on the "
                         "drone: the model's count publish score, pomar.countable.count_scores): weaker ones than the "
                         "confirm score extend tracks, the confirm score decides which apples count")
    rp.add_argument("--detector-scale", type=scale_argument, default="auto", help=SCALE_HELP)
    rp.add_argument("--keyframe-every", type=int,
                    help="every Nth processed frame also goes as a keyframe (default: the onboard node's, one "
                         "every 0.2 s of capture time)")
    rp.add_argument("--keyframe-width", type=int, default=960)
    rp.add_argument("--every", type=int, default=1, help="onboard processes every Nth frame")
    rp.add_argument("--quiet", action="store_true", help="no progress lines")
    rp.add_argument("--recorded", help="play this recorded stream (a ground's journal.bin; a flight directory given "
                                       "beside it gives the truth to score against) instead of running the onboard node")
    rp.add_argument("--speed", type=float, default=1.0,
                    help="with --recorded: S x the recording's capture-time pace (1 = real time, 0 = as fast as it goes)")
    rp.add_argument("--video", help="replay a video of your own: with --log and --camera, the flight is built from "
                                    "them (into OUT/flight; see pomar/assemble.py)")
    rp.add_argument("--camera", help="with --video: a camera.json or a built-in camera (phantom-4-pro, mavic-3, ...)")
    rp.add_argument("--log", help="the telemetry from this log (.tlog, DataFlash .bin, PX4 .ulg, DJI .SRT) instead of "
                                  "the flight directory's telemetry.tlog")
    from pomar.telemetry import mount_arguments

    rp.add_argument("--harvest", help=HARVEST_HELP)
    rp.add_argument("--orchard", help=ORCHARD_HELP)
    rp.add_argument("--sample-counts", help=SAMPLE_COUNTS_HELP)
    mount_arguments(rp)
    _ground_options(rp)
    rp.set_defaults(func=_cmd_replay)
    pl = sub.add_parser("play", help="publish a recorded stream (journal.bin) over zenoh at its capture-time pace",
                        description=__import__("ground.link.player", fromlist=["x"]).__doc__,
                        formatter_class=argparse.RawDescriptionHelpFormatter)
    pl.add_argument("recording", help="a ground's journal.bin")
    pl.add_argument("--speed", type=float, default=1.0, help="S x real time (0 = as fast as it goes)")
    pl.add_argument("--flight-id", type=id_argument("flight id"), help="refuse a recording of another flight")
    pl.add_argument("--listen", action="append", help="zenoh endpoint to listen on (default tcp/127.0.0.1:7447)")
    pl.add_argument("--connect", action="append", help="zenoh endpoint to connect to")
    pl.add_argument("--wait-for-ground", type=float, default=30.0,
                    help="wait up to this many seconds for a subscriber before the first message (0 = do not wait)")
    pl.add_argument("--linger", type=float, default=30.0, help="seconds to keep serving the history after the end")
    pl.add_argument("--summary", help="also write the play's summary (JSON) here")
    pl.set_defaults(func=_cmd_play)
    g = sub.add_parser("run", help="the ground node: subscribe to a flight over zenoh and map its apples live")
    g.add_argument("--flight-id", required=True, type=id_argument("flight id"))
    g.add_argument("--drone-id", action="append", type=id_argument("drone id"),
                   help="map this drone's messages (repeatable); others are counted and ignored (default: the first "
                        "drone heard)")
    g.add_argument("--out", default="out/ground", help="output folder: the map files, report.json, the journal (journal.bin) "
                                                     "and the recording (default out/ground)")
    g.add_argument("--connect", action="append", help="zenoh endpoint of the onboard node (default tcp/127.0.0.1:7447)")
    g.add_argument("--listen", action="append",
                   help="zenoh endpoint to listen on (default: none, the ground only connects; never every interface "
                        "unless given, e.g. tcp/0.0.0.0:7448)")
    g.add_argument("--zenoh-config", help="a zenoh JSON5 config file for real links: TLS and user/password "
                                          "authentication (docs/zenoh/)")
    g.add_argument("--max-ahead-s", type=float, default=60.0,
                   help="refuse frames more than this many seconds of video ahead of the newest one (plus the time "
                        "since it came)")
    g.add_argument("--no-rrd", action="store_true", help="no OUT/flight.rrd")
    g.add_argument("--serve", action="store_true", help="serve the rerun stream over gRPC for a viewer elsewhere")
    g.add_argument("--viewer", help="send the rerun stream to a running viewer at this URL")
    g.add_argument("--harvest", help=HARVEST_HELP)
    g.add_argument("--orchard", help=ORCHARD_HELP)
    g.add_argument("--sample-counts", help=SAMPLE_COUNTS_HELP)
    g.add_argument("--idle-timeout", type=float, default=60.0, help="finish after this long without a message (s; the ground's own work not counted)")
    g.add_argument("--fresh", action="store_true", help="ignore OUT/journal.bin (default: resume from it)")
    g.add_argument("--expected-frames", type=int, help="frames the flight will have, when known (progress ETA)")
    _ground_options(g)
    g.set_defaults(func=_cmd_run)
    r = sub.add_parser("register", help="register a flight's keyframes incrementally with pycolmap; ENU poses for every frame")
    r.add_argument("flight_dir")
    r.add_argument("--every", type=int, default=2, help="every Nth frame is a keyframe (as the onboard default)")
    r.add_argument("--scale", type=float, default=1.0, help="resize keyframes by this factor")
    r.add_argument("--submodel-size", type=int, default=60)
    _registration_options(r)
    r.add_argument("--frames", type=int, help="only the first N frames")
    r.add_argument("--out")
    r.add_argument("--json")
    r.add_argument("--quiet", action="store_true")
    r.set_defaults(func=_cmd_register)
    args = p.parse_args(argv)
    from pomar.shutdown import stop_on_sigterm

    stop_on_sigterm()
    logging.basicConfig(level=os.environ.get("POMAR_LOG_LEVEL", "INFO").upper(), format="%(asctime)s %(levelname)s %(name)s: %(message)s", datefmt="%H:%M:%S")
    return cli.run(args.func, args)


if __name__ == "__main__":
    # hard: what the command writes is written and closed by now (map files, report, recording, journal; the mapping
    # process is gone), so the interpreter's own teardown (zenoh's runtime, rerun, multiprocessing's finalisers) is
    # skipped. It took 1.8 s of the 5 s a stopped ground promises on a busy machine, and does nothing a user needs.
    cli.exit_with(main, hard=True)
