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


def test_a_hold_of_the_gaps_counts_the_links_wait_not_the_grounds_work(caplog):
    """A resumed ground holds the frames after a gap while the publisher's history comes: the time it spends working
    meanwhile does not count (on a slow laptop the history has as long to come), and when the hold runs out the log
    says how long it waited."""
    import logging

    a = Arrivals(max_wait_s=10.0)
    for f in (0, 1, 4, 5):  # frames 2 and 3 missing
        a.take(_frame(f))
    a.hold_gaps(0.3)

    def released():
        return [m.frame for m in a.release(lambda f: True, final=False, has_model=lambda: True)]

    assert released() == [0, 1]
    time.sleep(0.2)
    a.worked(0.5)  # the ground was busy: the hold is that much longer
    time.sleep(0.3)
    assert released() == []  # 0.5 s since the hold began, but only 0.2 s of it waiting
    with caplog.at_level(logging.INFO, logger="ground.link.arrivals"):
        time.sleep(0.4)
        assert released() == [4, 5]
    assert [m for m in caplog.messages if "frames 2-3 missing after 0.3 s of waiting for the publisher's history "
            "(and 0.5 s more while the ground worked)" in m]
    a.worked(5.0)  # no hold under way: nothing to lengthen
    a.take(_frame(7))
    assert released() == [7]
