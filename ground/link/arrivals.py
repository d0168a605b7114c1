"""Frames in order: the stream's frame and keyframe messages, de-duplicated, and handed on in frame index order; its
status messages, the newest kept, with the drone's restarts counted.

    arrivals = Arrivals()
    arrivals.take(msg)                          # a frame, keyframe or status message: any order, repeats allowed
    arrivals.fresh()                            # the frame messages taken since the last call (their telemetry)
    for frame, jpeg in arrivals.images(...):    # keyframe images in frame order, once they may go on
        ...
    for msg in arrivals.release(ready, ...):    # frame messages in index order, while ready(frame)
        ...

The two streams (frames, keyframes) do not keep each other's order. A frame that arrives after a later one was
released is late and dropped (the association only moves forward); missing frame indices are gaps.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from typing import Callable, Iterator

from pomar import wire

log = logging.getLogger(__name__)


class Arrivals:
    def __init__(self, max_wait_s: float = 5.0):
        #: Frames wait this long (s) for the keyframes after them (see stalled); a silence of half as long, no frame at
        #: all, is a link outage, after which the wait starts again.
        self.max_wait_s = max_wait_s
        self._last_frame_t = float("-inf")  # when the last frame message came (monotonic)
        self.pending: dict[int, wire.FrameMessage] = {}  # frames taken and not yet released
        self._fresh: list[wire.FrameMessage] = []  # frames taken since fresh() was last called
        self.keyframes: dict[int, bytes] = {}  # keyframe images waiting to go on
        self._kf_seen: set[int] = set()
        self.kf_awaited: set[int] = set()  # keyframes their frame messages announced that have not come yet
        self.counters = {"frames": 0, "keyframes": 0, "late_frames": 0, "gaps": 0, "missing_frames": 0,
                         "onboard_restarts": 0}
        self.status: wire.StatusMessage | None = None  # the drone's newest status
        self.frame_times: dict[int, float] = {}  # frame -> capture time
        self._late: list[int] = []  # the frames that came after a later one was released
        self.newest_t = float("-inf")  # the latest capture time of any frame received
        self._newest_frame = -1  # the highest frame index received
        self._arrived: dict[int, float] = {}  # frame -> when its message came (monotonic clock)
        self.t_first_frame: float | None = None  # when the first frame message came
        self.t_first_model: float | None = None  # when the first model was there (seen as a frame is released)
        self._last_kf_t = time.monotonic()  # when the last keyframe came, or the poses were last free again
        self._last_kf_capture = float("nan")  # capture time of the last keyframe's frame (or of the first frame)
        self._frames_since_kf: float | None = None  # when the first frame after the last keyframe came (monotonic)
        self._hold_gaps_until = 0.0  # until then (monotonic), a frame after a missing one waits for it
        self._hold = (0.0, 0.0, True)  # the hold asked (s), the time the ground's own work added to it (s), said
        self.released = -1  # the last frame released
        self.steps: deque[int] = deque(maxlen=20)  # frame-index steps between the last frames released
        self.gaps: list[tuple[int, int]] = []  # (first, last) frame indices missing between released frames
        self.frame_delays: list[float] = []  # per released frame: seconds from its message's arrival to its release
        self.frame_delays_mapped: list[float] = []  # ... of the frames that arrived once the first model existed

    def arrived_from(self, first: int = 0) -> int:
        """Frame messages taken (late ones too) of index ``first`` or more: what a sender that started at ``first``
        (a node restarted mid-flight) should have seen arrive."""
        if first <= 0:
            return self.counters["frames"] + self.counters["late_frames"]
        return sum(f >= first for f in self.frame_times) + sum(f >= first for f in self._late)

    # -- in
    def take(self, msg: wire.FrameMessage | wire.KeyframeMessage | wire.StatusMessage) -> None:
        if isinstance(msg, wire.KeyframeMessage):
            self._take_keyframe(msg)
            return
        if isinstance(msg, wire.StatusMessage):
            self._take_status(msg)
            return
        if msg.frame <= self.released or msg.frame in self.pending:
            if msg.frame <= self.released:
                self.counters["late_frames"] += 1
                self._late.append(msg.frame)
                log.warning("frame %d arrived after frame %d was processed: dropped", msg.frame, self.released)
            return
        self.pending[msg.frame] = msg
        self._fresh.append(msg)
        now = time.monotonic()
        if self._frames_since_kf is None or now - self._last_frame_t > self.max_wait_s / 2:
            self._frames_since_kf = now  # the first frame after a keyframe, or after an outage
        self._last_frame_t = now
        self.frame_times[msg.frame] = msg.t_capture
        self.newest_t = max(self.newest_t, msg.t_capture)
        self._newest_frame = max(self._newest_frame, msg.frame)
        self._arrived[msg.frame] = time.monotonic()
        if self.t_first_frame is None:
            self.t_first_frame = self._arrived[msg.frame]
        if self.counters["frames"] == 0 and not self._kf_seen:
            self._last_kf_t = time.monotonic()  # the wait for keyframes starts with the first frame
            self._last_kf_capture = msg.t_capture
        self.counters["frames"] += 1
        if msg.keyframe and msg.frame not in self._kf_seen:
            self.kf_awaited.add(msg.frame)

    def _take_keyframe(self, msg: wire.KeyframeMessage) -> None:
        if msg.frame in self._kf_seen:
            return
        self._kf_seen.add(msg.frame)
        self.kf_awaited.discard(msg.frame)
        self._last_kf_t = time.monotonic()
        self._frames_since_kf = None
        self._last_kf_capture = self.frame_times.get(msg.frame, self.newest_t)
        self.keyframes[msg.frame] = msg.jpeg
        self.counters["keyframes"] += 1

    def _take_status(self, msg: wire.StatusMessage) -> None:
        """The drone's newest status (an older one, from its history, changes nothing). A status that starts at
        another frame than the one before is a node started again mid-flight: said once per restart, and counted. So is
        the first status heard, where frames before the one it starts at came (sent by a node before it, whose statuses
        were lost: the link drops what it cannot carry)."""
        if self.status is not None and msg.t < self.status.t:
            return
        if (msg.first_frame != self.status.first_frame if self.status is not None
                else msg.first_frame > 0 and self.arrived_from(0) > self.arrived_from(msg.first_frame)):
            self.counters["onboard_restarts"] += 1
            log.warning("the drone's onboard node started again: it sends from frame %d on (frames not sent meanwhile "
                        "are gaps); the flight goes on", msg.first_frame)
        self.status = msg

    def fresh(self) -> list[wire.FrameMessage]:
        """The frame messages taken since the last call, in the order they came."""
        out, self._fresh = self._fresh, []
        return out

    def hold_gaps(self, seconds: float) -> None:
        """For the next ``seconds`` of waiting on the link, a frame after a missing one waits for it instead of leaving
        it to come late and be dropped: a resumed ground gets the frames it missed from the publisher's history while
        the live ones come too, in either order. The time the ground spends working meanwhile (:meth:`worked`) does not
        count: on a slow laptop the history has as long to come as on a fast one."""
        self._hold_gaps_until = time.monotonic() + seconds
        self._hold = (seconds, 0.0, False)

    def worked(self, seconds: float) -> None:
        """The ground spent ``seconds`` on a message: a hold of the gaps under way is that much longer."""
        if time.monotonic() < self._hold_gaps_until:
            self._hold_gaps_until += seconds
            self._hold = (self._hold[0], self._hold[1] + seconds, False)

    # -- out
    def images(self, final: bool, wait_for_announced: bool) -> Iterator[tuple[int, bytes]]:
        """The keyframe images in frame order, but never ahead of the frames: a frame needs the image after it. An
        image waits for its frame's message (the telemetry the mapper's georeferencing needs), unless a later
        frame's came (then it was lost). ``wait_for_announced`` (lock-step): an image also waits for the earlier
        keyframes announced by their frames' messages, so that the images go on in the same order whatever the
        link did."""
        wait_before = min(self.kf_awaited) if self.kf_awaited and wait_for_announced and not final else None
        for f in sorted(self.keyframes):
            if f not in self.frame_times and f > self._newest_frame and not final:
                break
            if wait_before is not None and f > wait_before:
                break
            yield f, self.keyframes.pop(f)

    def image_done(self) -> None:
        """The poses took an image: the wait for the next keyframe counts from now."""
        self._last_kf_t = time.monotonic()

    def stalled(self) -> bool:
        """No keyframe for max_wait_s while frames kept coming, and they went on for max_wait_s of flight past the last
        keyframe: the drone stopped sending keyframes. A slow onboard detector delays frames and keyframes alike and
        stalls nothing; nor does a link outage: the wait counts from when frames came again (after an outage both
        streams come back in a burst, in either order, and the frames must not leave without their images)."""
        now, wait = time.monotonic(), self.max_wait_s
        flown = self.newest_t - self._last_kf_capture
        return (now - self._last_kf_t > wait and not flown <= wait
                and self._frames_since_kf is not None and now - self._frames_since_kf > wait)

    def release(self, ready: Callable[[int], bool], final: bool,
                has_model: Callable[[], bool]) -> Iterator[wire.FrameMessage]:
        """The waiting frames in index order, each once ``ready(frame)`` says its pose can be decided (a frame before
        it may still come while hold_gaps holds). ``has_model()``: whether the map has its first model (the frame
        delays are also kept for the frames that came after it)."""
        while self.pending:
            f = min(self.pending)
            if not final and f > self.released + 1:
                if time.monotonic() < self._hold_gaps_until:
                    break
                asked, worked, said = self._hold
                if not said and asked:
                    self._hold = (asked, worked, True)
                    log.info("frames %d-%d missing after %.1f s of waiting for the publisher's history (and %.1f s more "
                             "while the ground worked): the frames after them go on", self.released + 1, f - 1, asked,
                             worked)
            if not ready(f):
                break
            msg = self.pending.pop(f)
            arrived = self._arrived.pop(f, None)
            if self.t_first_model is None and has_model():
                self.t_first_model = time.monotonic()
            if arrived is not None:
                self.frame_delays.append(time.monotonic() - arrived)
                if self.t_first_model is not None and arrived >= self.t_first_model:
                    self.frame_delays_mapped.append(self.frame_delays[-1])
            if self.released >= 0:
                self.steps.append(f - self.released)
            if f > self.released + 1 and self.released >= 0:
                self.gaps.append((self.released + 1, f - 1))
                self.counters["gaps"] += 1
                self.counters["missing_frames"] += f - 1 - self.released
            self.released = f
            yield msg

    def drop_images(self) -> None:
        """Told to stop: the images not yet tracked are dropped."""
        self.keyframes.clear()
