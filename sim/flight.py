"""Render a whole simulated flight into a replay flight directory (see docs/flight-format.md)."""

from __future__ import annotations

import json
import logging
import multiprocessing as mp
import os
import time
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from pomar import flight as ff
from pomar.camera import Camera
from pomar.geo import Origin
from pomar.rotations import rotation_to_quat_wxyz
from sim.config import SimConfig, parse_utc
from sim.orchard import build_scene
from sim.render import Renderer
from sim.telemetry import write_tlog
from sim.trajectory import build_trajectory, camera_poses, smooth_noise

log = logging.getLogger(__name__)

_WORKER: dict = {}  # per-process render state (set before forking the pool)


def _render_one(i: int):
    w = _WORKER
    img, truth = w["renderer"].render(
        w["R"][i], w["t"][i], gain=float(w["gain"][i]), blur_px=tuple(w["blur"][i]),
        rng=np.random.default_rng([w["seed"], 3, i]),
    )
    return i, img, truth


def _blur_vectors(cam: Camera, traj, frame_times, exposure_s, r_gimbal_from_camera, mount_err):
    """Image motion (px) during the exposure of each frame, of the scene point on the optical axis."""
    if exposure_s <= 0:
        return np.zeros((len(frame_times), 2))
    out = []
    R0, t0 = camera_poses(traj.sample(frame_times), r_gimbal_from_camera, mount_err)
    R1, t1 = camera_poses(traj.sample(frame_times + exposure_s), r_gimbal_from_camera, mount_err)
    for i in range(len(frame_times)):
        c = -R0[i].T @ t0[i]
        axis = R0[i].T @ np.array([0, 0, 1.0])
        depth = (c[2] - 2.0) / max(-axis[2], 0.1)  # scene point about canopy height
        x = c + depth * axis
        (uv0, _), (uv1, _) = cam.project(x[None], R0[i], t0[i]), cam.project(x[None], R1[i], t1[i])
        out.append(uv1[0] - uv0[0])
    return np.array(out)


def simulate_flight(cfg: SimConfig, out_dir: str | Path, jobs: int | None = None, progress: bool = True,
                    config_text: str | None = None, command: str | None = None) -> dict:
    """Render cfg into out_dir; returns a summary dict (frames, apples, timings)."""
    import imageio_ffmpeg

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / ff.TRUTH).mkdir(exist_ok=True)
    t_start = time.perf_counter()
    origin = Origin(cfg.origin.lat, cfg.origin.lon, cfg.origin.alt)
    cam = Camera.from_fov(cfg.camera.width, cfg.camera.height, cfg.camera.hfov_deg)
    rng = np.random.default_rng([cfg.seed, 4])
    mount_err = Rotation.from_rotvec(rng.normal(size=3) / np.sqrt(3) * np.radians(cfg.camera.mount_error_deg))

    log.info("building orchard (seed %d)", cfg.seed)
    scene = build_scene(cfg)
    traj = build_trajectory(cfg)
    fps = cfg.flight.fps
    n_frames = int(np.floor(traj.duration * fps)) + 1
    start_unix = parse_utc(cfg.flight.start_utc)
    tf = np.arange(n_frames) / fps
    sample = traj.sample(tf)
    R, t = camera_poses(sample, cam.r_gimbal_from_camera, mount_err)
    gain = np.exp(smooth_noise(np.random.default_rng([cfg.seed, 5]), n_frames, 4.0, cfg.render.exposure_wobble, rate_hz=fps))
    blur = _blur_vectors(cam, traj, tf, cfg.render.exposure_s, cam.r_gimbal_from_camera, mount_err)
    t_setup = time.perf_counter() - t_start

    _WORKER.update(renderer=Renderer(scene, cam, cfg.render.ambient, cfg.render.sensor_noise),
                   R=R, t=t, gain=gain, blur=blur, seed=cfg.seed)
    jobs = max(1, min(jobs or os.cpu_count() or 1, n_frames))
    writer = imageio_ffmpeg.write_frames(
        str(out / ff.VIDEO), (cam.width, cam.height), fps=fps, codec="libx264", pix_fmt_in="bgr24",
        quality=None, macro_block_size=2, ffmpeg_log_level="error",
        output_params=["-crf", str(cfg.render.video_crf), "-preset", "medium", "-g", str(int(max(1, 2 * fps)))],
    )
    writer.send(None)
    det = {c: [] for c in ff.DETECTIONS_COLUMNS}
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=n_frames, unit="frame", desc="rendering", smoothing=0.1)
    t_render = time.perf_counter()
    pool = mp.get_context("fork").Pool(jobs) if jobs > 1 else None
    try:
        results = pool.imap(_render_one, range(n_frames)) if pool else map(_render_one, range(n_frames))
        for i, img, truth in results:
            writer.send(np.ascontiguousarray(img))
            k = len(truth.apple_index)
            det["frame"].append(np.full(k, i))
            det["apple_id"].append(scene.apples["apple_id"][truth.apple_index])
            det["u"].append(truth.uv[:, 0])
            det["v"].append(truth.uv[:, 1])
            det["r_px"].append(truth.r_px)
            det["visible_fraction"].append(truth.visible_fraction)
            if bar:
                bar.update(1)
            elif i % 50 == 0:
                log.info("rendered %d/%d frames", i + 1, n_frames)
    finally:
        if pool:
            pool.terminate()
        writer.close()
        if bar:
            bar.close()
        _WORKER.clear()
    render_s = time.perf_counter() - t_render

    # truth
    a = scene.apples
    geo = origin.to_geodetic(a["xyz"])
    ff.write_csv(out / ff.TRUTH / "apples.csv", ff.APPLES_COLUMNS + ff.APPLE_TREE_COLUMNS, {
        "apple_id": a["apple_id"], "row": a["row"], "variety": a["variety"],
        "x": a["xyz"][:, 0], "y": a["xyz"][:, 1], "z": a["xyz"][:, 2],
        "lat": geo[:, 0], "lon": geo[:, 1], "alt": geo[:, 2], "radius_m": a["radius_m"],
        "tree": a["tree"], "mass_kg": a["mass_kg"],
    }, {"x": ".6f", "y": ".6f", "z": ".6f", "lat": ".10f", "lon": ".10f", "alt": ".6f", "radius_m": ".6f",
        "mass_kg": ".5f"})
    tr = scene.trees
    tgeo = origin.to_geodetic(tr["xyz"])
    ff.write_csv(out / ff.TRUTH / "trees.csv", ff.TREES_COLUMNS, {
        "row": tr["row"], "tree": tr["tree"], "x": tr["xyz"][:, 0], "y": tr["xyz"][:, 1], "z": tr["xyz"][:, 2],
        "lat": tgeo[:, 0], "lon": tgeo[:, 1], "apples": tr["apples"], "mass_kg": tr["mass_kg"],
    }, {"x": ".4f", "y": ".4f", "z": ".4f", "lat": ".10f", "lon": ".10f", "mass_kg": ".4f"})
    q = rotation_to_quat_wxyz(Rotation.from_matrix(R))
    cgeo = origin.to_geodetic(sample["centre"])
    ff.write_csv(out / ff.TRUTH / "frames.csv", ff.FRAMES_COLUMNS, {
        "frame": np.arange(n_frames), "t_unix": start_unix + tf,
        "qw": q[:, 0], "qx": q[:, 1], "qy": q[:, 2], "qz": q[:, 3], "tx": t[:, 0], "ty": t[:, 1], "tz": t[:, 2],
        "lat": cgeo[:, 0], "lon": cgeo[:, 1], "alt": cgeo[:, 2],
    }, {"t_unix": ".6f", **{k: ".12f" for k in ("qw", "qx", "qy", "qz")}, **{k: ".7f" for k in ("tx", "ty", "tz")},
        "lat": ".10f", "lon": ".10f", "alt": ".6f"})
    cols = {c: np.concatenate(v) if v else np.array([]) for c, v in det.items()}
    ff.write_csv(out / ff.TRUTH / "detections.csv", ff.DETECTIONS_COLUMNS, cols,
                 {"u": ".3f", "v": ".3f", "r_px": ".3f", "visible_fraction": ".3f"})
    (out / ff.TRUTH / "origin.json").write_text(json.dumps(origin.as_dict(), indent=2) + "\n")

    counts = write_tlog(cfg, traj, origin, start_unix, n_frames, out / ff.TLOG)
    cam.save(out / ff.CAMERA)
    meta = ff.FlightMeta(cfg.flight_id, cfg.drone_id, start_unix + cfg.telemetry.clock_offset_s, fps, n_frames,
                         cam.width, cam.height, {
                             "simulated": True, "seed": cfg.seed, "capture_message": cfg.telemetry.capture_message,
                             "generator": command or "python -m sim flight",
                         })
    (out / ff.FLIGHT).write_text(json.dumps(meta.to_dict(), indent=2) + "\n")
    (out / "sim_config.json").write_text(json.dumps(cfg.to_dict(), indent=2) + "\n")
    if config_text is not None:
        (out / "sim_config.toml").write_text(config_text)

    seen = np.unique(cols["apple_id"]) if len(cols["apple_id"]) else np.array([])
    vis = cols["visible_fraction"]
    summary = {
        "out": str(out), "frames": n_frames, "duration_s": round(traj.duration, 3), "apples_total": int(len(a["apple_id"])),
        "apples_seen": int(len(seen)),
        "apples_seen_half_visible": int(len(np.unique(cols["apple_id"][vis >= 0.5]))) if len(vis) else 0,
        "detections": int(len(vis)), "video_bytes": (out / ff.VIDEO).stat().st_size, "tlog_messages": counts,
        "setup_s": round(t_setup, 2), "render_s": round(render_s, 2), "jobs": jobs,
        "render_s_per_frame_wall": round(render_s / n_frames, 4),
    }
    log.info("flight written: %s", summary)
    return summary


def rewrite_telemetry(flight_dir: str | Path, out_dir: str | Path, **telemetry) -> dict:
    """A copy of a simulated flight whose .tlog is written again with other telemetry settings.

    The video, camera and truth are the same flight's (linked, not copied); only the autopilot's view
    changes, e.g. an RTK receiver (``gps_noise_m=0.02``) in place of a plain GPS, to separate what the
    images can give from what the GPS allows.
    """
    src, out = Path(flight_dir), Path(out_dir)
    cfg_path = src / "sim_config.json"
    if not cfg_path.is_file():
        raise ff.FlightFormatError(f"{cfg_path}: missing; only a simulated flight's telemetry can be written again")
    from sim import config as sc

    data = json.loads(cfg_path.read_text())
    known = list(sc.Telemetry.__dataclass_fields__)  # a flight rendered before a field was added lacks it
    for key, value in telemetry.items():
        if key not in known:
            raise sc.ConfigError(f"telemetry.{key}: unknown (known: {', '.join(known)})")
        data["telemetry"][key] = value
    cfg = sc.from_dict(data, str(cfg_path))
    meta = json.loads((src / ff.FLIGHT).read_text())
    out.mkdir(parents=True, exist_ok=True)
    for name in (ff.VIDEO, ff.TRUTH):
        link = out / name
        if link.is_symlink() or link.exists():
            if not link.is_symlink():
                raise FileExistsError(f"{link}: exists and is not a link; choose an empty --out")
            link.unlink()
        link.symlink_to((src / name).resolve())
    (out / ff.CAMERA).write_text((src / ff.CAMERA).read_text())
    origin = Origin(cfg.origin.lat, cfg.origin.lon, cfg.origin.alt)
    counts = write_tlog(cfg, build_trajectory(cfg), origin, parse_utc(cfg.flight.start_utc), int(meta["frame_count"]),
                        out / ff.TLOG)
    meta["telemetry_rewritten_from"] = str(src)
    (out / ff.FLIGHT).write_text(json.dumps(meta, indent=2) + "\n")
    (out / "sim_config.json").write_text(json.dumps(cfg.to_dict(), indent=2) + "\n")
    log.info("telemetry of %s written again into %s (%s)", src, out, telemetry)
    return {"out": str(out), "telemetry": cfg.to_dict()["telemetry"], "tlog_messages": counts}
