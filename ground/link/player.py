"""Play a recorded stream (a ground's ``journal.bin``) over zenoh again, at its own pace: no detector runs.

    python -m ground play out/demo/journal.bin --listen tcp/127.0.0.1:7447 --speed 1
    python -m ground replay --recorded out/demo/journal.bin --speed 1 --out out/recorded   # with a ground

The recording holds every wire message the ground accepted, as it came off the wire. They are published
again, byte for byte, under their flight's keys, as the onboard node would: each frame at its capture time
(``--speed S``: S x real time; 0 = as fast as they go), each keyframe with its frame, the camera first, and the
statuses where they were recorded. A recording that does not end with a "finished" status gets one, so that a
ground knows the stream is complete. Any other process can subscribe to what it publishes.

A bad recording gets a clear error naming the file: not a journal (or of another version), a schema version
this build cannot read, another flight than ``--flight-id``. A recording cut mid-record, or with damaged
records, plays every complete record and says what it skipped.
"""

from __future__ import annotations

import dataclasses

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path

from ground.link.journal import JournalError, read_journal_report
from pomar import wire
from pomar.cli import InputError

log = logging.getLogger(__name__)


class PlayerError(InputError, ValueError):
    """A recording that cannot be played; the message names the file."""


@dataclass
class Recording:
    path: Path
    flight_id: str
    drone_id: str
    items: list[tuple[float, str, bytes, object]]  # (seconds from the first frame, kind, payload, message)
    frames: int
    damaged_bytes: int = 0
    undecodable: int = 0
    problems: list[str] = field(default_factory=list)

    @property
    def seconds(self) -> float:
        """The flight's capture-time length: its frames' span and one frame period more (a flight's frames / fps)."""
        t = [t for t, _, _, m in self.items if isinstance(m, wire.FrameMessage)]
        span = max(t) - min(t)
        return span + span / (len(t) - 1) if len(t) > 1 else 0.0


def load_recording(path, flight_id: str | None = None) -> Recording:
    """Read and check a recording; schedule every message on the flight's capture-time clock."""
    path = Path(path)
    if not path.is_file():
        raise PlayerError(f"{path}: no such recording")
    try:
        jr = read_journal_report(path)
    except JournalError as exc:
        raise PlayerError(str(exc)) from None
    problems = []
    if jr.damaged:
        problems.append(f"{jr.damaged_bytes} damaged bytes in {len(jr.damaged)} place(s) skipped (a recording cut "
                        f"short, or damaged); the {len(jr.records)} complete records are played")
    msgs, bad = [], 0
    for i, payload in enumerate(jr.records):
        try:
            msgs.append((wire.decode(payload), payload))
        except wire.WireError as exc:
            if exc.reason == "schema_version" or not msgs:
                raise PlayerError(f"{path}: record {i}: {exc}") from None
            bad += 1
    if not msgs:
        raise PlayerError(f"{path}: no complete record to play")
    if bad:
        problems.append(f"{bad} records that do not decode skipped")
    flights = {(m.flight_id, m.drone_id) for m, _ in msgs}
    ids = sorted({f for f, _ in flights})
    if len(ids) > 1:
        raise PlayerError(f"{path}: holds several flights ({', '.join(ids)}); a ground's journal holds one")
    if flight_id is not None and ids[0] != flight_id:
        raise PlayerError(f"{path}: a recording of flight {ids[0]!r}, not {flight_id!r}")
    drones = sorted({d for _, d in flights})
    # capture-time schedule: frames at their capture times, keyframes with their frames, the rest where they were
    t_frame = {m.frame: m.t_capture for m, _ in msgs if isinstance(m, wire.FrameMessage)}
    if not t_frame:
        raise PlayerError(f"{path}: no frame in the recording")
    t0 = min(t_frame.values())
    items, t_last = [], 0.0
    for m, payload in msgs:
        if isinstance(m, wire.FrameMessage):
            t_last = max(t_last, m.t_capture - t0)
            t = m.t_capture - t0
        elif isinstance(m, wire.KeyframeMessage):
            t = t_frame.get(m.frame, t0 + t_last) - t0
        else:
            t = t_last
        items.append((t, wire.kind_of(m), payload, m))
    items.sort(key=lambda it: (it[0], it[1] != "camera"))
    cams = [it for it in items if it[1] == "camera"]
    items = cams[:1] + [it for it in items if it[1] != "camera"]  # the camera first: the ground needs it to start
    return Recording(path, ids[0], drones[0], items, len(t_frame), jr.damaged_bytes, bad, problems)


def play(rec: Recording, publisher, speed: float = 1.0, progress_s: float = 5.0) -> dict:
    """Publish the recording's messages at ``speed`` x their capture-time pace (0: at once); returns a summary."""
    start = time.monotonic()
    last_report = start
    sent = {k: 0 for k in wire.KINDS}
    finished = False
    for t, kind, payload, msg in rec.items:
        if kind == "camera":  # the stream says how it comes: at a pace, or as fast as taken (speed 0: lock-step)
            payload = dataclasses.replace(msg, paced=speed > 0).encode()
        if speed > 0:
            wait = start + t / speed - time.monotonic()
            if wait > 0:
                time.sleep(wait)
        publisher.put(kind, payload)
        sent[kind] += 1
        finished |= isinstance(msg, wire.StatusMessage) and msg.state == "finished"
        now = time.monotonic()
        if now - last_report >= progress_s:
            last_report = now
            done = sent["frames"] / max(rec.frames, 1)
            log.info("played %d/%d frames (%.0f%%), %.1f s of flight in %.1f s", sent["frames"], rec.frames,
                     100 * done, t, now - start)
    if not finished:  # a recording cut before its end: say it is complete now
        publisher.put("status", wire.StatusMessage(rec.flight_id, rec.drone_id, time.time(), sent["frames"],
                                                   sent["frames"], 0, 0.0, 0.0, "finished",
                                                   "end of a recording without a finished status").encode())
        sent["status"] += 1
    wall = time.monotonic() - start
    return {"recording": str(rec.path), "flight": rec.flight_id, "drone": rec.drone_id, "speed": speed,
            "frames_processed": sent["frames"], "sent": sent, "seconds": wall, "flight_seconds": rec.seconds,
            "problems": rec.problems, "error": None}
