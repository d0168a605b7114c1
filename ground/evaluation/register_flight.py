"""Register a whole flight from its files (no zenoh): keyframes -> incremental pycolmap -> ENU poses
for every frame, scored against the truth when the flight has one.

    python -m ground register FLIGHT_DIR [--every 2] [--scale 1.0] [--out DIR] [--json OUT]

Every frame gets a pose and its source: ``registered`` (a keyframe the model registered),
``interpolated`` (between two registered keyframes at most ``max_interp_gap`` frames apart: centre
linearly, rotation by slerp), or ``telemetry`` (GPS + gimbal alone). Each carries a rough 1-sigma
uncertainty (position m, rotation deg) the association can use to loosen its gates.
"""

from __future__ import annotations

import json
import logging
import time
from pathlib import Path

import cv2
import numpy as np
import pycolmap
from scipy.spatial.transform import Rotation, Slerp

from ground.evaluation.scoring import score_poses
from ground.poses.georeference import fit_similarity, georeference_poses
from ground.poses.telemetry_poses import frame_telemetry, telemetry_origin, telemetry_poses
from ground.poses.registration import IncrementalRegistrar, RegistrationSettings
from pomar import flight as ff
from pomar.camera import Camera
from pomar.flight import FlightDir
from pomar.rotations import camera_rotations, rotation_to_quat_wxyz
from pomar.video import iter_frames

log = logging.getLogger(__name__)

SOURCES = ("registered", "interpolated", "telemetry")


def register_flight(flight_dir, out_dir, every: int = 2, scale: float = 1.0, settings: RegistrationSettings | None = None,
                    max_interp_gap: int = 10, sigma_att_deg: float = 0.5, progress: bool = False,
                    frames_limit: int | None = None) -> dict:
    fl = FlightDir(flight_dir)
    meta, cam = fl.meta(), fl.camera()
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    kcam = Camera(int(round(cam.width * scale)), int(round(cam.height * scale)), cam.fx * scale, cam.fy * scale,
                  cam.cx * scale, cam.cy * scale)
    reg = IncrementalRegistrar(kcam, out / "work", settings, sigma_att_deg)
    n = meta.frame_count if frames_limit is None else min(frames_limit, meta.frame_count)
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=(n + every - 1) // every, unit="keyframe", desc="registering")
    # telemetry at every frame: the keyframes' priors (they place a sub-model when the chain breaks), then the
    # georeferencing and the fallback poses
    tf, s = frame_telemetry(fl)
    origin = telemetry_origin(fl, s)
    R_tel, t_tel, tel_flags = telemetry_poses(fl, origin, sample=s)
    prior_c, prior_R = -np.einsum("nji,nj->ni", R_tel, t_tel), R_tel
    prior_sig = np.where(np.isfinite(s["h_acc"]) & (s["h_acc"] > 0), s["h_acc"], 2.0)
    t0 = time.perf_counter()
    decoded = 0
    for i, img in iter_frames(fl.video):
        if i >= n:
            break
        decoded += 1
        if i % every:
            continue
        if scale != 1.0:
            img = cv2.resize(img, (kcam.width, kcam.height), interpolation=cv2.INTER_AREA)
        try:
            reg.add_keyframe(i, img, (prior_c[i], prior_R[i], float(prior_sig[i])))
        except Exception as exc:  # one keyframe that breaks the mapper must not stop the flight
            log.warning("keyframe %d failed to register: %s", i, exc)
            reg.failed.append(i)
        if bar:
            bar.update(1)
    if bar:
        bar.close()
    reg.close()
    seconds = time.perf_counter() - t0
    if decoded < n:
        log.error("%s: decoded %d of %d frames; the rest get telemetry poses", fl.video, decoded, n)

    P = reg.poses()  # model coordinates (first sub-model)
    kf = np.array(sorted(P))
    R = np.zeros((meta.frame_count, 3, 3))
    t = np.zeros((meta.frame_count, 3))
    source = np.full(meta.frame_count, "telemetry", dtype=object)
    sim = None
    if len(kf) >= 3:
        R_m = np.array([P[f][0] for f in kf])
        t_m = np.array([P[f][1] for f in kf])
        c_m = -np.einsum("nji,nj->ni", R_m, t_m)
        gps = origin.to_enu(s["lat"][kf], s["lon"][kf], s["alt"][kf])
        sig = np.where(np.isfinite(s["h_acc"][kf]) & (s["h_acc"][kf] > 0), s["h_acc"][kf], 2.0)
        good = np.isfinite(gps).all(1) & np.isfinite(s["q_gimbal"][kf]).all(1)
        R_axes = camera_rotations(s["q_gimbal"][kf], cam)
        fit = fit_similarity(c_m[good], gps[good], sig[good], R_m[good], R_axes[good], np.radians(sigma_att_deg))
        sim = fit.similarity
        R_e, t_e = georeference_poses(R_m, t_m, sim)
        R[kf], t[kf] = R_e, t_e
        source[kf] = "registered"
        # frames between registered keyframes: centre linearly, rotation by slerp
        C_e = -np.einsum("nji,nj->ni", R_e, t_e)
        slerp = Slerp(kf, Rotation.from_matrix(R_e))
        for f in range(meta.frame_count):
            if source[f] == "registered" or f < kf[0] or f > kf[-1]:
                continue
            k = np.searchsorted(kf, f)
            if kf[k] - kf[k - 1] > max_interp_gap:
                continue
            w = (f - kf[k - 1]) / (kf[k] - kf[k - 1])
            C = (1 - w) * C_e[k - 1] + w * C_e[k]
            R[f] = slerp([f]).as_matrix()[0]
            t[f] = -R[f] @ C
            source[f] = "interpolated"
    tel = source == "telemetry"
    R[tel], t[tel] = R_tel[tel], t_tel[tel]
    sigma_m = np.where(source == "registered", 0.01, np.where(source == "interpolated", 0.02,
                       np.where(np.isfinite(s["h_acc"]), s["h_acc"], 2.0)))
    sigma_deg = np.where(source == "telemetry", sigma_att_deg, 0.05)

    # outputs: poses.csv (truth/frames.csv columns + source + uncertainty), COLMAP text models
    q = rotation_to_quat_wxyz(Rotation.from_matrix(R))
    C = -np.einsum("nji,nj->ni", R, t)
    geo = origin.to_geodetic(C) if origin is not None else np.full((meta.frame_count, 3), np.nan)
    cols = ff.FRAMES_COLUMNS + ["source", "sigma_m", "sigma_deg", "flags"]
    ff.write_csv(out / "poses.csv", cols, {
        "frame": np.arange(meta.frame_count), "t_unix": tf, "qw": q[:, 0], "qx": q[:, 1], "qy": q[:, 2], "qz": q[:, 3],
        "tx": t[:, 0], "ty": t[:, 1], "tz": t[:, 2], "lat": geo[:, 0], "lon": geo[:, 1], "alt": geo[:, 2],
        "source": source, "sigma_m": sigma_m, "sigma_deg": sigma_deg, "flags": tel_flags,
    }, {"t_unix": ".6f", **{k: ".12f" for k in ("qw", "qx", "qy", "qz")}, **{k: ".7f" for k in ("tx", "ty", "tz")},
        "lat": ".10f", "lon": ".10f", "alt": ".6f", "sigma_m": ".4f", "sigma_deg": ".4f"})
    for k, sm in enumerate(reg.submodels):
        d = out / "model" / str(k)
        d.mkdir(parents=True, exist_ok=True)
        rec = pycolmap.Reconstruction(sm.reconstruction())
        if sim is not None:  # into ENU: first sub-model coordinates, then the georeferencing similarity
            to_first = sm.to_first
            S = (sim.scale * to_first.scale, sim.R @ to_first.R, sim.scale * sim.R @ to_first.t + sim.t)
            rec.transform(pycolmap.Sim3d(S[0], pycolmap.Rotation3d(S[1]), S[2]))
        rec.write_text(str(d))
    if sim is not None:
        (out / "georeference.json").write_text(json.dumps({"origin": origin.as_dict(), "scale": sim.scale,
                                                           "R": sim.R.tolist(), "t": sim.t.tolist()}, indent=2) + "\n")

    keyframes = (n + every - 1) // every
    result = {
        "flight": str(fl.path), "keyframes": keyframes, "registered": int(len(kf)),
        "registered_fraction": len(kf) / max(keyframes, 1), "submodels": len(reg.submodels), "rejoined": reg.rejoined,
        "revisits": reg.revisits, "reanchored": reg.reanchored,
        "sources": {src: int((source == src).sum()) for src in SOURCES},
        "seconds": seconds, "seconds_per_keyframe": float(np.mean(reg.seconds)) if reg.seconds else float("nan"),
        "seconds_per_keyframe_median": float(np.median(reg.seconds)) if reg.seconds else float("nan"),
        "seconds_per_keyframe_p95": float(np.percentile(reg.seconds, 95)) if reg.seconds else float("nan"),
        "keyframe_size": [kcam.width, kcam.height], "every": every,
        "stage_seconds_median": dict(zip(("features", "matching", "mapping"),
                                         np.median(np.array(reg.stage_seconds), axis=0).tolist())) if reg.stage_seconds else {},
        "seconds_per_keyframe_by_decile": [float(np.mean(x)) for x in np.array_split(np.array(reg.seconds), 10)] if len(reg.seconds) >= 10 else [],
    }
    if fl.has_truth:
        result.update(score_poses(fl, R, t, source, kf, SOURCES))
    (out / "report.json").write_text(json.dumps(result, indent=2) + "\n")
    return result


