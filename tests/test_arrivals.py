"""Frames in order (ground.link.arrivals): when frames may leave without the keyframes after them."""

from __future__ import annotations

import time
from types import SimpleNamespace

from ground.link.arrivals import Arrivals
from pomar import wire


def _frame(f: int, keyframe: bool = False):
    return SimpleNamespace(frame=f, t_capture=1000.0 + 0.1 * f, keyframe=keyframe)


def _keyframe(f: int):
    return wire.KeyframeMessage("flight", "drone", f, b"")


def test_frames_that_come_back_after_a_link_outage_wait_for_their_keyframes():
    """After an outage both streams come back in a burst, in either order: the frames that come first wait
    max_wait_s for their keyframes (before, they left at once with telemetry poses: a live ground's map fell to F1
    0.01 after an 8-s cut of the link, benchmarks/faults.py --only link-lost-8). Keyframes that never come stall the
    frames as before."""
    wait = 0.3
    a = Arrivals(max_wait_s=wait)
    for f in range(10):
        a.take(_frame(f, keyframe=f % 2 == 0))
        if f % 2 == 0:
            a.take(_keyframe(f))
    assert not a.stalled()
    time.sleep(1.5 * wait)  # the outage: nothing comes
    for f in range(10, 100):  # 9 s of flight past the last keyframe, all at once
        a.take(_frame(f, keyframe=f % 2 == 0))
    assert not a.stalled()
    time.sleep(1.5 * wait)  # no keyframe came with them: the drone stopped sending them
    assert a.stalled()
    a.take(_keyframe(10))
    assert not a.stalled()


def test_a_restarted_node_is_counted_from_the_frames_when_the_statuses_before_it_were_lost(tmp_path):
    """The link may drop statuses: the first one heard can be a restarted node's. Frames before the one it starts at
    came from a node before it, so it counts as a restart; one that starts at the first frame heard does not."""
    from ground.pipeline import GroundPipeline

    def pipe_with(frames):
        pipe = GroundPipeline(tmp_path)
        for f in frames:
            pipe.arrivals.take(_frame(f))
        return pipe

    pipe = pipe_with([*range(10), *range(12, 20)])
    pipe.feed(wire.StatusMessage("flight", "drone", time.time(), 8, 8, state="finished", first_frame=12))
    assert pipe.counters["onboard_restarts"] == 1
    pipe.feed(wire.StatusMessage("flight", "drone", time.time() + 1, 8, 8, state="finished", first_frame=12))
    assert pipe.counters["onboard_restarts"] == 1  # the same node again
    late_ground = pipe_with(range(12, 20))  # nothing came before the node's first frame
    late_ground.feed(wire.StatusMessage("flight", "drone", time.time(), 8, 8, first_frame=12))
    assert late_ground.counters["onboard_restarts"] == 0
