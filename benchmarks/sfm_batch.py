"""Batch COLMAP (pycolmap) on a flight's video: does structure-from-motion register its frames?

    python benchmarks/sfm_batch.py replay_data/demo-flight [--work out/sfm] [--every 1]

Decodes the video, extracts SIFT (pycolmap, CPU), matches sequentially (overlap 10,
quadratic_overlap off), runs incremental mapping, then aligns the registered camera centres to
truth/frames.csv with a similarity and prints: SIFT keypoints per frame, registered fraction,
centre error after alignment (median, p95, max), and the time of each stage.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from pomar.align import umeyama
from pomar.flight import FlightDir
from pomar.video import iter_frames


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("flight_dir")
    ap.add_argument("--work", default="out/sfm")
    ap.add_argument("--every", type=int, default=1, help="use every Nth frame")
    ap.add_argument("--overlap", type=int, default=10)
    ap.add_argument("--first-octave", type=int, default=-1)
    ap.add_argument("--json")
    args = ap.parse_args()

    fd = FlightDir(args.flight_dir)
    cam = fd.camera()
    work = Path(args.work)
    if work.exists():
        shutil.rmtree(work)
    images = work / "images"
    images.mkdir(parents=True)
    t0 = time.perf_counter()
    names = []
    for i, img in iter_frames(fd.video):
        if i % args.every == 0:
            name = f"{i:06d}.png"
            cv2.imwrite(str(images / name), img)
            names.append(name)
    t_decode = time.perf_counter() - t0

    db = work / "database.db"
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = cam.model
    reader.camera_params = ",".join(str(p) for p in cam.params())
    ext = pycolmap.FeatureExtractionOptions()
    ext.sift.first_octave = args.first_octave
    t0 = time.perf_counter()
    pycolmap.extract_features(db, images, camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                              extraction_options=ext, device=pycolmap.Device.cpu)
    t_extract = time.perf_counter() - t0
    with pycolmap.Database.open(db) as database:
        kps = [database.read_keypoints(im.image_id).shape[0] for im in database.read_all_images()]

    pairing = pycolmap.SequentialPairingOptions()
    pairing.overlap = args.overlap
    pairing.quadratic_overlap = False
    t0 = time.perf_counter()
    pycolmap.match_sequential(db, pairing_options=pairing, device=pycolmap.Device.cpu)
    t_match = time.perf_counter() - t0

    opts = pycolmap.IncrementalPipelineOptions()
    opts.ba_refine_focal_length = False
    opts.ba_refine_principal_point = False
    opts.ba_refine_extra_params = False
    t0 = time.perf_counter()
    recs = pycolmap.incremental_mapping(db, images, work / "sparse", options=opts)
    t_map = time.perf_counter() - t0
    rec = max(recs.values(), key=lambda r: r.num_reg_images()) if recs else None

    R_true, t_true = fd.truth_poses() if fd.has_truth else (None, None)
    result = {
        "frames": len(names), "sift_keypoints_per_frame_median": float(np.median(kps)),
        "sift_keypoints_per_frame_min": int(np.min(kps)), "models": len(recs),
        "registered": rec.num_reg_images() if rec else 0,
        "seconds": {"decode": round(t_decode, 1), "extract": round(t_extract, 1), "match": round(t_match, 1),
                    "map": round(t_map, 1)},
    }
    result["registered_fraction"] = result["registered"] / len(names)
    if rec is not None and R_true is not None:
        est, tru = [], []
        for im in rec.images.values():
            if not im.has_pose:
                continue
            f = int(Path(im.name).stem)
            est.append(im.projection_center())
            tru.append(-R_true[f].T @ t_true[f])
        est, tru = np.array(est), np.array(tru)
        sim = umeyama(est, tru)
        err = np.linalg.norm(sim.apply(est) - tru, axis=1)
        result.update(centre_error_median_m=float(np.median(err)), centre_error_p95_m=float(np.percentile(err, 95)),
                      centre_error_max_m=float(err.max()), points3d=rec.num_points3D(),
                      mean_reprojection_error_px=rec.compute_mean_reprojection_error())
    print(json.dumps(result, indent=2))
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2) + "\n")


if __name__ == "__main__":
    main()
