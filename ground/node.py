"""The ground node: the flight's zenoh stream -> pipeline -> apple map files and a rerun recording.

    python -m ground run --flight-id ID [--connect tcp/127.0.0.1:7447] [--out DIR] [--serve | --viewer URL]

It subscribes to ``pomar/<flight>/<drone>/**`` with zenoh's advanced subscriber (history + recovery),
journals every message it accepts (``OUT/journal.bin``: its checkpoint; a restarted ground replays
it, then the publisher's history fills the rest), feeds the pipeline, logs each frame to rerun and
refreshes the map files every ``refresh_s`` seconds (atomically). It ends when the drone says the
flight is finished (and every frame it announced has arrived, or ``end_grace_s`` passed), after
``idle_timeout_s`` without a message, or on Ctrl-C; in every case it writes the final outputs.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import deque
from pathlib import Path

from ground.link.envelope import ApplesSeen
from ground.link.journal import Journal, read_journal_report
from ground.memory import malloc_trim, rss_mb
from pomar.coverage import Sight
from ground.orchard.files import read_orchard_files
from ground.outputs.mapfiles import MapFiles
from ground.outputs.report import flight_report
from ground.outputs.snapshot import snapshot
from ground.outputs.tables import read_harvest
from ground.pipeline import GroundPipeline, GroundSettings
from pomar import wire

log = logging.getLogger(__name__)


# A flight that says it sent more frames than arrived, and then goes quiet: its history is asked for again after
# REQUERY_S of the link's quiet (the ground's own work not counted), at most MAX_REQUERIES times (zenoh's history and
# recovery can leave a gap).
REQUERY_S = 3.0
MAX_REQUERIES = 5
# A resumed ground holds a frame after a missing one this long for the history to bring the missing one (zenoh
# delivers the history and the live samples in either order; a frame released past is dropped when it comes).
HISTORY_WAIT_S = 3.0


class GroundNode:
    """Feed it wire messages (decoded) with :meth:`handle`; it keeps the outputs and the rerun log current."""

    def __init__(self, out_dir, settings: GroundSettings | None = None, rrd: Path | None | bool = True,
                 serve: bool = False, viewer: str | None = None, harvest: Path | None = None, refresh_s: float = 2.0,
                 stream: wire.StreamFilter | None = None, progress_s: float | None = None,
                 expected_frames: int | None = None, orchard: Path | None = None, sample_counts: Path | None = None):
        self.settings = settings or GroundSettings()
        # the grower's files first: one that does not read stops the ground before it starts (InputError, one line)
        self.harvest = read_harvest(harvest) if harvest else None
        growers = read_orchard_files(orchard, sample_counts, self.settings.load_model)
        self.out = Path(out_dir)
        self.out.mkdir(parents=True, exist_ok=True)
        self.pipe = GroundPipeline(self.out / "work", self.settings)
        self._rr_args = (self.out / "flight.rrd" if rrd is True else (rrd or None), serve, viewer)
        if any(self._rr_args):
            import ground.outputs.rerun_log  # noqa: F401  (now: rerun imports slowly, and the first frames would wait for it)
        self.rr = None
        self.refresh_s = refresh_s
        self._last_refresh = 0.0
        self.progress_s = progress_s  # a progress line this often (None: none)
        self.expected_frames = expected_frames
        self._last_progress = time.monotonic()
        self.t_start = time.monotonic()
        self.t_first_msg = None
        self.messages = 0
        self.apples_seen = ApplesSeen()
        self.errors: list[str] = []
        self._fps_t: deque[float] = deque()  # when each frame of the last FPS_WINDOW_S was mapped (monotonic)
        self._first_mapped: float | None = None
        self._live: dict = {}  # what the summary says of the frame being mapped
        self.memory: list[tuple[int, float]] = []  # (frames mapped, resident MB), see sample_memory
        self.progress: list[tuple[float, int]] = []  # (seconds since start, frames mapped), sampled with memory
        self.latency: list[float] = []
        self.stream = stream  # the filter in front of the pipeline: what it let in and refused
        self.ignored_end_claims = 0  # "finished" statuses contradicted by the stream
        self._trim = malloc_trim()
        self.history_requeries = 0  # times the publishers' history was asked for again (frames missing at the end)
        self.journal_damage: dict | None = None
        self.journal: Journal | None = None  # the journal being written (run_ground)
        self.files = MapFiles(self.out, self.settings.tree_spacing_m, growers, self.settings.load_model)

    def _rerun(self):
        if self.rr is None and self.pipe.flight_id is not None and any(self._rr_args):
            from ground.outputs.rerun_log import RerunLog

            rrd, serve, viewer = self._rr_args
            try:
                self.rr = RerunLog(self.pipe.flight_id, rrd, serve, viewer)
            except Exception as exc:  # its file cannot be started (a full disk): the flight goes on without it
                log.warning("the rerun recording %s cannot be written (%s): the flight goes on without it", rrd, exc)
                self.errors.append(f"recording: {exc}")
                self._rr_args = (None, serve, viewer)
        return self.rr

    def handle(self, msg, step: bool = True) -> None:
        """Take one message and, unless ``step=False`` (more are queued: call :meth:`step` after them), process
        what it makes ready."""
        if self.t_first_msg is None:
            self.t_first_msg = time.monotonic()
        self.messages += 1
        self.apples_seen.take(msg)
        try:
            events = self.pipe.take(msg, step)
        except Exception as exc:  # never stop on one bad message: log it, keep the state
            log.exception("message %s failed: %s", type(msg).__name__, exc)
            self.errors.append(f"{type(msg).__name__}: {exc}")
            return
        self._after(events)

    def step(self) -> None:
        """Process what the messages so far make ready; the frames released go to the log and the map files as they
        come, so a long backlog (a lock-step replay takes the stream in batches) shows its progress meanwhile."""
        try:
            self.pipe.step(on_events=self._after)
        except Exception as exc:
            log.exception("processing failed: %s", exc)
            self.errors.append(f"step: {exc}")

    def _after(self, events) -> None:
        self._log_events(events)
        if time.monotonic() - self._last_refresh > self.refresh_s:
            self.refresh()
        self.log_progress()

    def log_progress(self) -> None:
        """One line, every progress_s: frames received and mapped, the rate of the last FPS_WINDOW_S, an ETA where
        the flight's length is known."""
        now = time.monotonic()
        if self.progress_s is None or now - self._last_progress <= self.progress_s:
            return
        self._last_progress = now
        c, n = self.pipe.counters, self.expected_frames
        mapped, fps = self.pipe.arrivals.released + 1, self.ground_fps()
        eta = f", ETA {(n - mapped) / fps:.0f} s" if n and fps == fps and fps > 0 else ""
        rejected = sum(self.stream.rejected.values()) if self.stream else 0
        log.info("frames %d received, %d%s mapped (%.1f fps%s), keyframes %d, apples %d, wall %.0f s%s",
                 c["frames"], mapped, f"/{n}" if n else "", fps, eta, c["keyframes"],
                 len(self.pipe.apples.count.apples),
                 now - self.t_start, f", {rejected} messages rejected" if rejected else "")

    def _log_events(self, events):
        rr = self._rerun()
        now = time.time()
        for e in events:
            t = time.monotonic()
            self._fps_t.append(t)
            self._first_mapped = self._first_mapped or t
            latency = now - e.t_capture if abs(now - e.t_capture) < 3600 else None  # None: a replay's recorded times
            if latency is not None:
                self.latency.append(latency)
            behind = self.pipe.arrivals.newest_t - e.t_capture
            fps = self.ground_fps()
            st = self.pipe.status
            # the drone's rate as its heartbeat measures it (frames processed a second), not the video's nominal one
            drone_fps = float(st.fps) if st is not None and st.fps > 0 else None
            self._live = {"frame": e.frame, "behind_s": behind, "ground_fps": fps, "drone_fps": drone_fps}
            if rr is not None:
                rr.fps = self.pipe.fps
                rejected = self.stream.rejected if self.stream else {}
                to_enu = self.pipe.poses.map_to_enu() if self.pipe.poses is not None else None
                rr.frame(e, self.pipe.camera, {
                    "rate/ground": fps, "rate/drone": drone_fps,
                    "delay/behind_drone_s": behind, "delay/ground_latency_s": latency,
                    "delay/detector_s": float(st.detector_latency_s) if st else None,
                    "link/dropped_onboard": float(st.frames_dropped) if st else None,
                    "link/missing_frames": float(self.pipe.arrivals.counters["missing_frames"]),
                    **{f"rejected/{reason}": float(n) for reason, n in rejected.items()},
                }, to_enu=to_enu)
                for a in e.new_apples:
                    rr.apple_views(a.id, self.pipe.apples.boxes(a))

    def sample_memory(self, stop: threading.Event, period_s: float = 1.0) -> None:
        """Record (frames mapped, resident MB) every period_s until ``stop`` (run it in a thread: a lock-step backlog
        is mapped in one long step); at most 400 samples, thinned evenly."""
        while not stop.wait(period_s):
            self.memory.append((self.pipe.arrivals.released + 1, round(rss_mb(), 1)))
            self.progress.append((round(time.monotonic() - self.t_start, 2), self.pipe.arrivals.released + 1))
            if len(self.memory) > 400:
                self.memory = self.memory[::2]
                self.progress = self.progress[::2]
                period_s *= 2

    def link_stats(self) -> dict:
        """What the stream filter refused, by reason, and the repeats it dropped."""
        sf = self.stream
        return {"drone_ids": sorted(sf.drone_ids) if sf else [],
                "rejected": dict(sorted(sf.rejected.items())) if sf else {},
                "rejected_total": sum(sf.rejected.values()) if sf else 0,
                "duplicates": sf.duplicates if sf else 0, "last_rejections": sf.errors[-10:] if sf else [],
                "ignored_end_claims": self.ignored_end_claims, "history_requeries": self.history_requeries,
                "journal": self.journal_damage,
                # the journal could not be written (a full disk): the flight could no longer be resumed from it
                "journal_write_failed": self.journal.failed if self.journal is not None else None,
                # the map files could not be written at the last refresh (a full disk)
                "outputs_write_failed": self.files.failed,
                # ... and where they were written instead
                "outputs_rescued_to": str(self.files.rescued_to) if self.files.rescued_to else None}

    FPS_WINDOW_S = 5.0

    def ground_fps(self) -> float:
        """Frames mapped per second over the last FPS_WINDOW_S; NaN for the first FPS_WINDOW_S after the first frame
        was mapped (a backlog released at once would read as hundreds of frames per second)."""
        t, now = self._fps_t, time.monotonic()
        while t and t[0] < now - self.FPS_WINDOW_S:
            t.popleft()
        if self._first_mapped is None or now - self._first_mapped < self.FPS_WINDOW_S:
            return float("nan")
        return len(t) / self.FPS_WINDOW_S

    def refresh(self, final: bool = False, out: Path | None = None) -> dict:
        """Write the map files and report.json (atomically; to ``out``, by default the node's folder) and log the map
        to rerun."""
        self._last_refresh = time.monotonic()
        if self._trim is not None:  # hand freed heap back to the system: the map's arrays are rebuilt at each refresh
            self._trim(0)
        snap = snapshot(self.pipe, final)  # the map once, for the tables, the report and rerun
        seen = self.apples_seen
        maps = self.files.write_tables(snap, out, Sight(seen.camera, seen.min_px, seen.scales))
        report = flight_report(self.pipe, maps.apples, maps.rows, final, apples_seen=seen,
                               wall_s=time.monotonic() - self.t_start, latency=self.latency, memory=self.memory,
                               progress=self.progress, link=self.link_stats(), errors=self.errors,
                               harvest=self.harvest, orchard=maps.orchard,
                               load=maps.load, scale=maps.scale)
        rr = self._rerun()
        if rr is not None and self.pipe.arrivals.released >= 0:
            from ground.outputs.summary import summary_markdown

            poses, last = self.pipe.poses, self.pipe.arrivals.released
            rr.apples(last, snap.frame_times.get(last, float("nan")), maps.apples, snap.apples, maps.rows,
                      drone_latlon=maps.drone_latlon(), force=True,
                      points=poses.sparse_points() if poses is not None else None,
                      summary=summary_markdown(report, self._live), trajectory_latlon=maps.trajectory_latlon(),
                      trees=maps.trees)
        self.files.write_report(report, out)
        return report

    def finish(self, hurry: bool = False) -> dict:
        """The flight's end: the pipeline's (``hurry``: told to stop, within seconds), then the map files, the report,
        the model files and the recording."""
        try:
            self.pipe.finish(on_events=self._log_events, hurry=hurry)
        except Exception as exc:
            log.exception("finishing the flight failed: %s", exc)
            self.errors.append(f"finish: {exc}")
        report = self.refresh(final=True)
        from ground.outputs.summary import remap_advice

        advice = remap_advice(report, self.out / "journal.bin")
        if advice:
            log.warning(advice)
        if self.files.failed:
            report = self.files.rescue(self.pipe.flight_id, lambda out: self.refresh(final=True, out=out))
        if self.pipe.poses is not None and self.pipe.poses.submodels() and not self.files.failed:
            self.files.write_model(self.pipe.poses)
        if self.rr is not None:
            try:
                self.rr.close(compact=not hurry)
            except Exception as exc:  # its writer stopped (a full disk): what it wrote stays a readable recording
                log.warning("the rerun recording could not be written to the end (%s): it holds the flight up to where "
                            "it stopped", exc)
                self.errors.append(f"recording: {exc}")
        return report


def run_ground(flight_id: str, out_dir, connect=None, listen=None, zenoh_config=None, drone_ids=None,
               settings: GroundSettings | None = None, rrd=True, serve=False, viewer=None, harvest=None, orchard=None,
               sample_counts=None, idle_timeout_s: float = 60.0, end_quiet_s: float = 1.0, resume: bool = True,
               progress_s: float = 5.0, expected_frames: int | None = None, max_ahead_s: float = 60.0) -> dict:
    """Map one flight from its zenoh stream until the drone says it is finished, or idle_timeout_s passes.

    Only what :class:`pomar.wire.StreamFilter` lets in reaches the pipeline: this flight, its drones
    (``drone_ids``; default the first heard), valid messages; the rest is counted by reason in report.json
    (``rejected``) and the rerun log. A "finished" (or "error") status ends the flight only when exactly the
    frames it says were sent (from the first frame it says it sent: a node restarted mid-flight counts from there)
    have arrived and no frame came for end_quiet_s: a drone still flying sends
    more, which contradicts it; it is then logged and ignored, and the flight ends at the idle timeout.
    """
    from pomar import transport

    out = Path(out_dir)
    journal_path = out / "journal.bin"
    stream = wire.StreamFilter(flight_id, drone_ids, max_ahead_s=max_ahead_s)
    # an unreadable journal, harvest or layout file raises before anything is overwritten
    read = read_journal_report(journal_path) if resume and journal_path.is_file() else None
    node = GroundNode(out, settings, rrd, serve, viewer, harvest, stream=stream, progress_s=progress_s,
                      expected_frames=expected_frames, orchard=orchard, sample_counts=sample_counts)
    if read is None:
        try:
            journal_path.unlink(missing_ok=True)
        except OSError:  # a folder it cannot write (read-only): the journal says so once, and the flight goes on
            pass
    if read is not None:
        log.info("resuming from %s: %d messages%s", journal_path, len(read.records),
                 f", {read.damaged_bytes} damaged bytes skipped" if read.damaged else "")
        node.journal_damage = {"records_read": len(read.records), "damaged_bytes": read.damaged_bytes,
                               "damaged_at": [o for o, _ in read.damaged], "side_files": [str(p) for p in read.side_files]}
        for payload in read.records:
            try:
                msg = stream.accept(payload, check_window=False)
            except wire.WireError as exc:
                log.warning("journal record skipped: %s", exc)
                continue
            if msg is not None:
                node.handle(msg)
                node.pipe.wait_for_mapping()
    journal = node.journal = Journal(journal_path)
    sampling = threading.Event()
    threading.Thread(target=node.sample_memory, args=(sampling,), daemon=True, name="memory").start()
    session = transport.open_session(listen=listen, connect=connect, config_file=zenoh_config)
    sub = transport.FlightSubscriber(session, flight_id, stream, on_accept=journal.append)
    if read is not None and read.records:
        node.pipe.hold_gaps(HISTORY_WAIT_S)

    def link_clock() -> float:
        """Seconds the ground spent waiting on the link: its own work (take, step) left out, so that the end's quiet,
        the re-queries and the idle timeout measure the link, not how fast or busy this machine is."""
        return time.monotonic() - node.pipe.work_s

    last_msg = link_clock()
    claim = None  # (the status saying the flight ended, when it came)

    def contradicted(m: wire.StatusMessage) -> bool:
        """An end claim that says fewer frames were sent than arrived: counted, logged, and to be ignored (the flight
        then ends at the idle timeout)."""
        have = node.pipe.arrivals.arrived_from(m.first_frame)
        if have <= m.frames_processed:
            return False
        node.ignored_end_claims += 1
        log.warning("a %r status says %d frames were sent, but %d arrived: ignored; the flight ends at the idle "
                    "timeout", m.state, m.frames_processed, have)
        return True

    last_frame = 0.0  # when the last frame message came
    asked = 0.0  # when the publishers' history was last asked for again
    report = None
    stopped = False
    try:
        while True:
            msg = sub.recv(timeout=0.2)
            now = link_clock()
            if msg is not None:
                last_msg = now
                # take everything queued up meanwhile, then process once
                batch = [msg]
                while len(batch) < 1000 and (more := sub.recv(timeout=0)) is not None:
                    batch.append(more)
                for m in batch:
                    node.handle(m, step=False)
                    if isinstance(m, wire.FrameMessage):
                        last_frame = now
                    if isinstance(m, wire.StatusMessage) and m.state in ("finished", "error"):
                        log.info("the drone says the flight is %s (%d frames processed)", m.state, m.frames_processed)
                        # judged as it comes, not only the batch's last: a false claim followed by the true one in
                        # the same batch is still seen for what it is
                        if not contradicted(m):
                            claim = (m, now)
                node.step()
            elif node.pipe.arrivals.pending:
                node.step()  # frames may wait on the mapping process (its first model)
            if claim is not None:
                have = node.pipe.arrivals.arrived_from(claim[0].first_frame)
                said = claim[0].frames_processed
                awaited = len(node.pipe.arrivals.kf_awaited)  # keyframes announced by their frames that did not come
                if have == said and not awaited and now - max(claim[1], last_frame) >= end_quiet_s:
                    break
                if contradicted(claim[0]):
                    claim = None
                elif (have < said or awaited) and now - claim[1] > idle_timeout_s:
                    log.warning("%d of the %d frames and %d of the keyframes announced did not arrive; finishing",
                                said - have, said, awaited)
                    break
                elif ((have < said or awaited) and now - max(claim[1], last_msg, asked) >= REQUERY_S
                      and sub.refreshes < MAX_REQUERIES):
                    log.warning("%d of the %d frames the drone sent arrived, %d keyframes announced did not, and "
                                "nothing came for %.0f s: asking the drone for its history again", have, said,
                                awaited, REQUERY_S)
                    sub.refresh()
                    node.history_requeries = sub.refreshes
                    asked = now
            if now - last_msg > idle_timeout_s:
                log.warning("no message for %.0f s: finishing the flight", idle_timeout_s)
                break
            node.log_progress()
    except KeyboardInterrupt:
        log.warning("interrupted: writing what there is")
        stopped = True
    finally:
        sub.close()
        session.close()
        journal.close()
        sampling.set()
        report = node.finish(hurry=stopped)
    return report
