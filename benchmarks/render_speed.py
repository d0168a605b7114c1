"""Simulator render time per frame (one process), at 1280x720 and 1920x1080 by default.

    python benchmarks/render_speed.py [--sizes 1280x720 1920x1080 3840x2160] [--frames 10]

Builds the demo orchard once, then renders frames along the demo flight's trajectory and prints
the median and p90 seconds per frame for each size (render only: no video encoding).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from pomar.camera import Camera
from sim import config
from sim.orchard import build_scene
from sim.render import Renderer
from sim.trajectory import build_trajectory, camera_poses

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--config", default=str(ROOT / "sim" / "configs" / "demo.toml"))
    ap.add_argument("--sizes", nargs="+", default=["1280x720", "1920x1080"])
    ap.add_argument("--frames", type=int, default=10)
    args = ap.parse_args()
    cfg = config.load(args.config)
    t0 = time.perf_counter()
    scene = build_scene(cfg)
    print(f"scene: {len(scene.pos)} splats, {len(scene.apples['apple_id'])} apples, built in {time.perf_counter() - t0:.1f} s")
    traj = build_trajectory(cfg)
    times = np.linspace(0, traj.duration, args.frames)
    for size in args.sizes:
        w, h = (int(x) for x in size.split("x"))
        cam = Camera.from_fov(w, h, cfg.camera.hfov_deg)
        R, t = camera_poses(traj.sample(times), cam.r_gimbal_from_camera)
        r = Renderer(scene, cam, cfg.render.ambient, cfg.render.sensor_noise)
        r.render(R[0], t[0], rng=np.random.default_rng(0))  # warm-up
        dt = []
        for i in range(len(times)):
            t1 = time.perf_counter()
            r.render(R[i], t[i], blur_px=(3.0, 0.5), rng=np.random.default_rng(i))
            dt.append(time.perf_counter() - t1)
        print(f"{size}: median {np.median(dt):.3f} s/frame, p90 {np.percentile(dt, 90):.3f} s/frame "
              f"({len(dt)} frames, one process)")


if __name__ == "__main__":
    main()
