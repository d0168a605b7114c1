"""Georeference a COLMAP model of a flight with its own telemetry and score the poses in ENU.

    python benchmarks/sfm_batch.py replay_data/demo-flight --work out/sfm      # makes out/sfm/sparse/0
    python benchmarks/georeference.py replay_data/demo-flight --model out/sfm/sparse/0

Fits the model-to-ENU similarity two ways, GPS positions only (weighted Umeyama) and GPS positions
plus the telemetry's camera axes (attitude x gimbal x mount), and prints for each: camera position
error (median, p95) and rotation error (median) against truth/frames.csv in ENU, and the median
reprojection error of the true apples through the georeferenced P_i minus through the true P_i.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pycolmap
from scipy.spatial.transform import Rotation

from ground.poses.georeference import fit_similarity, georeference_poses
from ground.poses.telemetry_poses import frame_telemetry
from pomar.rotations import camera_rotations
from ground.evaluation.scoring import apple_reprojection_errors
from pomar.flight import FlightDir


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("flight_dir")
    ap.add_argument("--model", default="out/sfm/sparse/0")
    ap.add_argument("--sigma-att-deg", type=float, default=0.5)
    ap.add_argument("--json")
    args = ap.parse_args()
    fl = FlightDir(args.flight_dir)
    meta, cam, origin = fl.meta(), fl.camera(), fl.origin()
    rec = pycolmap.Reconstruction(args.model)
    frames, R_m, t_m = [], [], []
    for im in rec.images.values():
        if im.has_pose:
            frames.append(int(Path(im.name).stem))
            m = im.cam_from_world().matrix()
            R_m.append(m[:, :3])
            t_m.append(m[:, 3])
    order = np.argsort(frames)
    frames, R_m, t_m = np.array(frames)[order], np.array(R_m)[order], np.array(t_m)[order]
    c_m = -np.einsum("nji,nj->ni", R_m, t_m)

    _, s = frame_telemetry(fl)
    s = {k: v[frames] for k, v in s.items()}
    gps = origin.to_enu(s["lat"], s["lon"], s["alt"])
    sigma = np.where(np.isfinite(s["h_acc"]) & (s["h_acc"] > 0), s["h_acc"], 2.0)
    R_tel = camera_rotations(s["q_gimbal"], cam)

    R_true_all, t_true_all = fl.truth_poses()
    R_true, t_true = R_true_all[frames], t_true_all[frames]
    C_true = -np.einsum("nji,nj->ni", R_true, t_true)
    out = {"registered_frames": len(frames), "frames": meta.frame_count}
    for name, fit in (("gps_only", fit_similarity(c_m, gps, sigma)),
                      ("gps_and_axes", fit_similarity(c_m, gps, sigma, R_m, R_tel, np.radians(args.sigma_att_deg)))):
        R_e, t_e = georeference_poses(R_m, t_m, fit.similarity)
        C_e = -np.einsum("nji,nj->ni", R_e, t_e)
        pos = np.linalg.norm(C_e - C_true, axis=1)
        rot = np.degrees(np.linalg.norm(Rotation.from_matrix(np.einsum("nij,nkj->nik", R_e, R_true)).as_rotvec(), axis=1))
        R_all, t_all = R_true_all.copy(), t_true_all.copy()
        R_all[frames], t_all[frames] = R_e, t_e
        reproj = apple_reprojection_errors(fl, R_all, t_all, R_true_all, t_true_all, frames=frames)
        out[name] = {"position_error_median_m": float(np.median(pos)), "position_error_p95_m": float(np.percentile(pos, 95)),
                     "rotation_error_median_deg": float(np.median(rot)), "rotation_error_p95_deg": float(np.percentile(rot, 95)),
                     "apple_reprojection_error_median_px": float(np.median(reproj)), "scale": fit.similarity.scale,
                     "gps_residual_rms_m": fit.position_rms_m, "axis_residual_rms_deg": fit.axis_rms_deg}
        r = out[name]
        print(f"{name:<13} position error median {r['position_error_median_m']:.3f} m (p95 {r['position_error_p95_m']:.3f}), "
              f"rotation error median {r['rotation_error_median_deg']:.3f} deg (p95 {r['rotation_error_p95_deg']:.3f}), "
              f"true apples reproject {r['apple_reprojection_error_median_px']:.2f} px median from the true P_i")
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=2) + "\n")


if __name__ == "__main__":
    main()
