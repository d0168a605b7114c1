"""Where the ground's time goes, by stage and by pass: a flight's recorded stream fed to the ground pipeline in this
one process, lock-step with mapping inline (no zenoh, no rerun), timing each stage per frame over each pass of a
whole-plot flight (the whole flight as one pass where the flight has no simulated passes).

    python benchmarks/ground_stages.py FLIGHT_DIR JOURNAL

Stages: association, pose corrections, poses (tracking and mapping together), of which KLT tracking, and the
mapper's SIFT extraction, matching (the recent keyframes and earlier passes' of the same place) and registration
(incremental mapping, bundle adjustment, re-anchoring). Take it with nothing else running.
"""

from __future__ import annotations

import argparse
import logging
import tempfile
import time
from pathlib import Path

import numpy as np

from ground.link.journal import read_journal
from ground.pipeline import GroundPipeline, GroundSettings
from pomar import wire
from pomar.flight import FlightDir

STAGES = ("wall", "association", "corrections", "poses", "tracking", "sift", "matching", "registration")


def stage_seconds(pipe: GroundPipeline) -> list[float]:
    """The pipeline's cumulative seconds in each stage (STAGES but wall), and the keyframes mapped so far."""
    poses = pipe.poses
    st = np.zeros(3)
    stages = poses.mapper.registrar.stage_seconds if poses is not None else []
    if stages:
        st = np.asarray(stages, float).reshape(-1, 3).sum(0)
    return [pipe.seconds["association"], pipe.seconds["corrections"], pipe.seconds["poses"],
            poses.tracking.seconds["tracking"] if poses is not None else 0.0, *st.tolist(), len(stages)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("flight_dir")
    ap.add_argument("journal", help="its recorded stream (a ground's journal.bin)")
    args = ap.parse_args()
    logging.basicConfig(level=logging.WARNING)
    flight = FlightDir(args.flight_dir)
    if (flight.path / "sim_config.json").exists():
        from whole_plot import pass_of_frames  # noqa: E402  (benchmarks/ is this script's own folder)

        passes = pass_of_frames(flight)
    else:
        passes = np.zeros(flight.meta().frame_count, int)
    msgs = [wire.decode(p) for p in read_journal(Path(args.journal))]
    snap = []  # per frame message: frame, then STAGES' cumulative seconds
    with tempfile.TemporaryDirectory() as work:
        pipe = GroundPipeline(Path(work), GroundSettings(mapping="inline"))
        t0 = time.perf_counter()
        for i, m in enumerate(msgs):
            pipe.take(m)
            if isinstance(m, wire.FrameMessage):
                snap.append([m.frame, time.perf_counter() - t0, *stage_seconds(pipe)])
            if i % 200 == 0:
                print(f"  {i}/{len(msgs)} messages, {time.perf_counter() - t0:.0f} s", flush=True)
        pipe.finish()
    S = np.array(snap)
    print(f"\n{flight.path}: seconds per frame, by pass (the turns left out)")
    print("| pass | frames | keyframes mapped | " + " | ".join(STAGES) + " |")
    print("| ---: | ---: | ---: | " + " | ".join("---:" for _ in STAGES) + " |")
    frames = S[:, 0].astype(int).clip(0, len(passes) - 1)
    for k in sorted(set(passes[frames].tolist()) - {-1}):
        idx = np.nonzero(passes[frames] == k)[0]
        if len(idx) < 2:
            continue
        # from the pass's first frame message to its last: what each stage took meanwhile, per frame
        d = (S[idx[-1], 1:-1] - S[idx[0], 1:-1]) / (idx[-1] - idx[0])
        kf = int(S[idx[-1], -1] - S[idx[0], -1])
        print(f"| {k} | {len(idx)} | {kf} | " + " | ".join(f"{v:.3f}" for v in d) + " |")


if __name__ == "__main__":
    main()
