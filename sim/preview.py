"""Look at a flight directory: a text summary, and a frame with the truth apples drawn."""

from __future__ import annotations

from collections import Counter
from pathlib import Path

import numpy as np

from pomar.countable import MIN_VISIBLE, visible
from pomar.flight import FlightDir
from pomar.telemetry import read_log


def flight_info(flight_dir) -> str:
    from pomar.video import count_frames

    fd = FlightDir(flight_dir)
    meta, cam = fd.meta(), fd.camera()
    lines = [
        f"flight {meta.flight_id} (drone {meta.drone_id}) in {fd.path}",
        f"  video: {meta.frame_count} frames at {meta.fps:g} fps ({meta.frame_count / meta.fps:.1f} s), "
        f"{meta.width}x{meta.height}; {count_frames(fd.video)} decode from {fd.video.name} "
        f"({fd.video.stat().st_size / 1e6:.1f} MB)",
        f"  camera: {cam.model} fx={cam.fx:.1f} fy={cam.fy:.1f} cx={cam.cx:.1f} cy={cam.cy:.1f} "
        f"(HFOV {np.degrees(2 * np.arctan(cam.width / 2 / cam.fx)):.1f} deg)",
    ]
    # the flight's log in whatever format it is (an assembled flight names its own), read by the one reader
    tl = read_log(fd.telemetry_log)
    lines.append(f"  telemetry ({tl.format}, {fd.telemetry_log.name}): {sum(tl.counts.values())} records: "
                 + ", ".join(f"{k} {v}" for k, v in sorted(tl.counts.items())))
    lines += [f"  problem: {p}" for p in tl.problems]
    if fd.has_truth:
        a, d, o = fd.truth_apples(), fd.truth_detections(), fd.origin()
        seen = np.unique(d["apple_id"])
        half = np.unique(d["apple_id"][visible(d["visible_fraction"])])
        lines.append(f"  truth: origin {o.lat:.6f}, {o.lon:.6f}, {o.alt:.1f} m; {len(a['apple_id'])} apples in "
                     f"{len(np.unique(a['row']))} rows; {len(seen)} seen in the video, {len(half)} at least half visible "
                     f"in some frame; {len(d['frame'])} apple observations ({len(d['frame']) / meta.frame_count:.1f} per frame)")
        rows = a["row"][np.isin(a["apple_id"], half)]
        per_row = Counter(rows.tolist())
        lines.append("  half-visible apples per row: " + ", ".join(f"row {r}: {c}" for r, c in sorted(per_row.items())))
    return "\n".join(lines)


def draw_truth(flight_dir, frame: int, out_png, min_visible: float = MIN_VISIBLE) -> Path:
    import cv2

    from pomar.video import read_frame

    fd = FlightDir(flight_dir)
    img = read_frame(fd.video, frame)
    if fd.has_truth:
        d = fd.truth_detections()
        sel = d["frame"] == frame
        for u, v, r, vf in zip(d["u"][sel], d["v"][sel], d["r_px"][sel], d["visible_fraction"][sel]):
            colour = (0, 255, 0) if vf >= min_visible else (160, 160, 160)
            cv2.circle(img, (int(round(u)), int(round(v))), int(round(r + 4)), colour, 1, cv2.LINE_AA)
    out = Path(out_png)
    out.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out), img)
    return out
