"""A live node's frame indices, kept across restarts of the node within one flight.

    numbers = FrameNumbers(state_dir / "flight-drone.json")
    index = numbers(i, t_read)      # i: the frames read since this node started; t_read: when (unix s)
    numbers.save()                  # at the end (it also saves itself about once a second)

The ground drops a frame whose index it already passed (its association only moves forward), so a node restarted
mid-flight that numbered its frames from 0 again would have every frame dropped until it caught up with the frames of
before. A small JSON state (the last index given, when, and the rate the frames came at) lets a restarted node go on
from there: the frames missed while it was down are a gap in the indices, as the ground expects of a lost frame.
"""

from __future__ import annotations

import json
import logging
import os
import time
from pathlib import Path

from pomar.wire import MAX_FRAME

log = logging.getLogger(__name__)

#: A state older than this (s) is another flight's: a drone's battery does not last longer.
MAX_FLIGHT_S = 3600.0


def default_state_dir() -> Path:
    """Where a live node keeps its frame numbers by default: the user's cache ($XDG_CACHE_HOME, or ~/.cache)."""
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "pomar" / "onboard"


class FrameNumbers:
    SAVE_EVERY_S = 1.0

    def __init__(self, path: Path | None):
        self.path = Path(path) if path is not None else None
        self.base = 0
        self.resumed_from: int | None = None  # the last index of the run before, where this one goes on from it
        self._first = self._last = None  # (index, t_read) of the first and the last frame numbered by this run
        self._saved_at = 0.0
        self._before = self._read()

    def _read(self) -> dict | None:
        if self.path is None or not self.path.is_file():
            return None
        try:
            s = json.loads(self.path.read_text())
            return {k: float(s[k]) for k in ("last_index", "t_last", "rate_hz")}
        except (OSError, ValueError, KeyError, TypeError) as exc:
            log.warning("%s: not a frame-number state (%s): frames numbered from 0", self.path, exc)
            return None

    def __call__(self, i: int, t_read: float) -> int:
        if self._first is None:
            self._start(t_read)
        index = self.base + i
        self._first = self._first or (index, t_read)
        self._last = (index, t_read)
        if time.monotonic() - self._saved_at > self.SAVE_EVERY_S:
            self.save()
        return index

    def _start(self, t_read: float) -> None:
        b = self._before
        if b is None:
            return
        down = t_read - b["t_last"]
        if not 0 <= down <= MAX_FLIGHT_S:
            return  # another flight's state, or a clock that went back: from 0
        base = int(b["last_index"]) + 1 + int(round(down * b["rate_hz"]))
        if base >= MAX_FRAME:  # past the wire's bound: from 0
            return
        self.base, self.resumed_from = base, int(b["last_index"])
        log.warning("frames numbered from %d: this flight's node ran before (last frame %d, %.1f s ago; %s)", base,
                    self.resumed_from, down, self.path)

    def rate_hz(self) -> float:
        """The rate this run's frames came at (the run before's, until there are two)."""
        if self._first and self._last and self._last[1] > self._first[1]:
            return (self._last[0] - self._first[0]) / (self._last[1] - self._first[1])
        return self._before["rate_hz"] if self._before else 0.0

    def save(self) -> None:
        """Write the state (atomically); a state that cannot be written is warned about once and given up."""
        self._saved_at = time.monotonic()
        if self.path is None or self._last is None:
            return
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            tmp = self.path.with_name(self.path.name + ".tmp")
            tmp.write_text(json.dumps({"last_index": self._last[0], "t_last": self._last[1],
                                       "rate_hz": self.rate_hz()}))
            os.replace(tmp, self.path)
        except OSError as exc:
            log.warning("%s: the frame numbers cannot be kept (%s): a restarted node would number from 0",
                        self.path, exc.strerror or exc)
            self.path = None
