"""The mapper in a process of its own (live): :class:`MapperProcess` has :class:`ground.poses.mapper.Mapper`'s
interface and runs it in a child process (:class:`MappingWorker`, started early so that its imports do not hold up
the first model), so that mapping never holds up per-frame tracking (pycolmap's feature extraction and mapper hold
Python's GIL, so a thread would). A process that dies, or answers nothing for too long with a keyframe in work, is
restarted, given every keyframe of the map it had (kept on disk), and its rebuilt model, placed in the map's frame
(:mod:`ground.poses.restart`), becomes the map.

The process maps one keyframe at a time; the newest proposal waits meanwhile, replacing any that came before it
(counted in ``skipped``): mapping falls behind by at most one keyframe's work, and the keyframes it maps are further
apart when it is slow. After each keyframe it sends back what tracking and the pose interface read: the registered
poses it moved, the fit, the reference.
"""

from __future__ import annotations

import bisect
import logging
import multiprocessing as mp
import multiprocessing.connection
import os
import pickle
import queue
import shutil
import threading
import time
from pathlib import Path

import cv2
import numpy as np

from ground.poses.mapper import Mapper
from ground.poses.registration import RegistrationSettings, Submodel
from ground.poses.restart import align_models, move_pose, move_reference
from ground.poses.tracking import Reference
from pomar.align import Similarity, compose, inverse
from pomar.camera import Camera

log = logging.getLogger(__name__)


def _exit_with_parent() -> None:
    """Stop this process as soon as the ground that started it is gone, even in the middle of a job: the pipe's EOF
    is only read between jobs, and one registration can take many seconds."""
    parent = mp.parent_process()
    if parent is None:
        return

    def watch():
        mp.connection.wait([parent.sentinel])
        log.warning("the ground process is gone: the mapping process stops")
        os._exit(0)

    threading.Thread(target=watch, daemon=True, name="parent-watch").start()


def _serve(jobs, results) -> None:
    """The mapping process: take the mapper's settings, map each job, send back what changed; on None, write the
    sub-models to disk and say where."""
    # the ground's level (POMAR_LOG_LEVEL, as ground's CLI reads it)
    level = logging.getLevelName(os.environ.get("POMAR_LOG_LEVEL", "INFO").upper())
    logging.basicConfig(level=level if isinstance(level, int) else logging.INFO,
                        format="%(asctime)s %(levelname)s %(name)s [mapping]: %(message)s")
    _exit_with_parent()
    try:
        config = jobs.recv()
    except EOFError:
        results.cancel_join_thread()
        return
    if config is None:  # stopped before it had anything to map
        return
    kf_camera, camera, workdir, settings, sigma_att_deg, points_every = config
    m = Mapper(kf_camera, camera, workdir, settings, sigma_att_deg)
    while True:
        try:  # one at a time: the parent holds the newest proposal while this one is mapped
            job = jobs.recv()
        except EOFError:  # the ground died (the pipe's only writer): nobody to map for
            log.warning("the ground process is gone: the mapping process stops")
            results.cancel_join_thread()  # results nobody will read must not hold the exit
            return
        if job is None:
            break
        frame, jpeg, tel, features = job
        first = not m.has_model
        img = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
        ok = m.add(frame, img, tel, features) if img is not None else False
        points = m.sparse_points() if ok and points_every and len(m.model_pose) % points_every == 1 else None
        results.put({"frame": frame, "ok": ok, "poses": m.changed, "fit": (m.fit, m.fit_residual_m),
                     "ref": m.reference() if ok else None, "points": points, "stats": m.stats(),
                     "first_refs": m.first_references if ok and first else None,
                     "processed": m.processed, "attempts": m.attempts})
    m.close()
    points = m.sparse_points()
    subs = []
    for k, sm in enumerate(m.registrar.submodels):
        m.registrar.offload(k)
        # one the folder did not take (mapped in memory): only its poses come back, its model files are not written
        subs.append(Submodel(None, sm.names, sm.to_first, sm.path, sm.cam_from_world()))
    results.put({"closed": subs, "points": points, "stats": m.stats()})


class MappingWorker:
    """The mapping process, started ahead of its first keyframe (its imports take about half a second, which would
    otherwise delay the first model), waiting for a :class:`MapperProcess` to give it its settings."""

    def __init__(self):
        ctx = mp.get_context("spawn")  # not forked: the ground's zenoh threads must not be copied
        # jobs go down a one-way pipe whose writing end only the ground holds: if the ground dies, even mid-message,
        # the mapping process reads EOF and stops (a Queue's pipe has both ends in both processes, and would hang it)
        jobs_in, self.jobs = ctx.Pipe(duplex=False)
        self.results = ctx.Queue()
        self.proc = ctx.Process(target=_serve, name="pomar-mapping", daemon=True, args=(jobs_in, self.results))
        self.proc.start()
        jobs_in.close()
        # a pipe's send blocks until the other side reads: a thread sends instead
        self.outbox: queue.SimpleQueue = queue.SimpleQueue()
        threading.Thread(target=self._sender, daemon=True, name="mapping-jobs").start()
        # and a thread receives: a process killed while it wrote a result (a reference's image is hundreds of kB)
        # leaves half a message in the pipe, and reading it would wait for the rest for ever. That thread waits,
        # the ground does not (it froze for 10 minutes so)
        self.inbox: queue.SimpleQueue = queue.SimpleQueue()
        threading.Thread(target=self._receiver, daemon=True, name="mapping-results").start()

    def _receiver(self) -> None:
        while True:
            try:
                self.inbox.put(self.results.get())
            except (EOFError, OSError, ValueError):  # the queue was closed
                return

    def _sender(self) -> None:
        while True:
            job = self.outbox.get()
            try:
                self.jobs.send(job)
            except OSError:  # the mapping process is gone; MapperProcess.close reports it
                return
            if job is None:
                self.jobs.close()
                return

    def stop(self) -> None:
        """Stop a worker that was never given a mapper."""
        self.outbox.put(None)
        self.proc.join(timeout=10)
        if self.proc.is_alive():
            self.proc.kill()
            self.proc.join()


class MapperProcess:
    """:class:`Mapper` in a process of its own (a :class:`MappingWorker`, given or started here), with the same
    reading interface; what it sends back is taken in whenever the caller reads.

    A process that dies (killed, out of memory, a crash in pycolmap) is started again, up to MAX_RESTARTS times, and
    given first every keyframe the map held and those it had not answered (each job is kept, on disk where the work
    folder takes it): it rebuilds the dead one's model, which is placed in the old one's frame by the keyframes both
    placed (:mod:`ground.poses.restart`) and then replaces it, every keyframe's pose included, and the flight goes on
    mapping in one model. Until then, and if that never happens, frames are tracked against the map that was.

    A new model from only the last keyframes (the rule before, issue 74) left the earlier keyframes at the poses the
    dead process last gave them, never refined again, beside a second model grown from a few: on the bundled flight
    killed 4 s in, the cameras drifted 3-6 cm from a clean run's and the map lost 0.1 of F1."""

    #: Times a mapping process that died is started again in one flight.
    MAX_RESTARTS = 3

    def __init__(self, kf_camera: Camera, camera: Camera, workdir, settings: RegistrationSettings | None = None,
                 sigma_att_deg: float = 0.5, points_every: int = 10, worker: MappingWorker | None = None):
        self.settings = settings or RegistrationSettings()
        worker = worker or MappingWorker()
        self._proc, self._results, self._outbox = worker.proc, worker.inbox, worker.outbox
        self._config = (kf_camera, camera, str(workdir), self.settings, sigma_att_deg, points_every)
        self._outbox.put(self._config)
        self.model_pose: dict[int, tuple[np.ndarray, np.ndarray]] = {}
        self.kf_sorted: list[int] = []
        self.fit: Similarity | None = None
        self.fit_residual_m = float("nan")
        self._ref: Reference | None = None
        self.first_references: list[Reference] = []
        self._points: dict[int, np.ndarray] = {}
        self._stats = {"keyframes_processed": 0, "failed": 0, "submodels": 0, "seconds": [],
                       "revisits": 0, "reanchored": 0, "rejoined": 0,
                       "stage_seconds_median": dict.fromkeys(("features", "matching", "mapping"))}
        self._submodels: list[Submodel] = []
        self.moved: set[int] = set()
        self.processed = -1
        self.attempts = self.skipped = self.sent = self.answered = 0
        self._held = None  # the newest proposal, while the process maps the one before
        self._sift = None  # SIFT here, made when the first keyframe has to wait for the process
        self.early_extracted = 0  # keyframes whose features were extracted here
        self._closed = False
        #: When the mapping process died by itself: its exit code, the keyframes it had mapped, those sent and lost.
        self.died: dict | None = None
        #: Each restart: when, why, and whether (and how well) its model was placed in the old frame.
        self.restarts: list[dict] = []
        self._answered_at_restart = 0  # keyframes answered when the process last restarted
        # every keyframe job sent, for a restarted process: beside the mapper's folder, which each process empties
        self._jobs = _JobStore(Path(workdir).with_name(Path(workdir).name + "-keyframe-jobs")
                               if workdir is not None else None)
        self._newest_sent = -1  # the newest keyframe sent to the process
        self._to_old: Similarity | None = None  # a restarted process's frame -> the map's frame, once known
        self._new_pose: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # its poses in its own frame, until then
        self._new_ref: Reference | None = None
        self._base_attempts = 0  # attempts of the processes before this one
        self._earlier_stats: dict = {}  # their stats
        self._closing = False
        self._given_up = False  # died more than MAX_RESTARTS times
        self._last_progress = time.monotonic()  # the last answer, or the start of work after an idle spell
        #: The keyframes the map held when the process last restarted: a restarted process's model is to be placed in
        #: the map's frame where there were some (without a map before, its model is the map).
        self._map_before: set[int] = set()
        self._new_frames: set[int] = set()  # the keyframes the restarted process placed

    def add(self, frame: int, image_bgr: np.ndarray, tel) -> None:
        """Hand over a keyframe: sent now if the process is free, else held, replacing any held before it (the
        process's pipe would otherwise queue them, and the newest could not win).

        For the first model's tries (its first_model_tries keyframes, while there is none), keyframes go to the
        process at once, in order (up to INIT_QUEUE waiting), and one that would wait there behind another has its
        SIFT features extracted here first: the first model needs several images, each a SIFT extraction, and this
        process is idle until it comes (every frame waits for it), so the two processes share that work when images
        come faster than the process extracts them. One that would wait only for the keyframe in work goes at once:
        extracting it here would hold it back longer than the process takes to be free. Past those tries (a flight
        that starts over ground with nothing to match) this process does not spend its time on SIFT."""
        if self._closed or not self._running():
            return
        # the process maps in frame order: behind a newer keyframe sent or held, this one would be skipped there
        newest = max(self._newest_sent, self._held[0] if self._held is not None else -1)
        if frame <= newest:
            log.debug("keyframe %d not handed over: keyframe %d is newer", frame, newest)
            return
        ok, jpeg = cv2.imencode(".jpg", image_bgr, [cv2.IMWRITE_JPEG_QUALITY, 95])
        self._poll()
        job = (frame, jpeg.tobytes(), tel, None)
        first_tries = not self.model_pose and self.sent < self.settings.first_model_tries
        if first_tries and self.settings.sift == "colmap" and self.sent - self.answered < self.INIT_QUEUE:
            if self.sent - self.answered >= 2:  # another waits there besides the one in work: extract here meanwhile
                if self._sift is None:
                    from ground.poses.sift import SiftExtractor

                    self._sift = SiftExtractor(self.settings)
                kp, raw, _ = self._sift(image_bgr)
                job = (*job[:3], (kp, raw))
                self.early_extracted += 1
            self._put(job)
            return
        if self._held is not None:
            self.skipped += 1
        self._held = job
        self._send()

    #: Keyframes sent to the process before the first model and not yet mapped, at most (then the newest is held).
    INIT_QUEUE = 4

    def _send(self) -> None:
        if self._held is not None and self.answered == self.sent:
            if self._held[0] > self._newest_sent:  # else newer ones went first (the first model's tries, in order)
                self._put(self._held)
            self._held = None

    def _put(self, job) -> None:
        if self.answered == self.sent:  # the process was idle: its work on this one starts now
            self._last_progress = time.monotonic()
        self._outbox.put(job)
        self.sent += 1
        self._newest_sent = max(self._newest_sent, job[0])
        self._jobs.put(job)

    def busy(self) -> bool:
        """Whether a keyframe handed over is still being mapped, or waiting to be (never, once the process died: it
        answers nothing more)."""
        self._poll()
        return (self.answered < self.sent or self._held is not None) and self._running()

    def _running(self) -> bool:
        """Whether the process runs. When it is found dead (killed, out of memory, a crash in pycolmap), that is logged
        and kept (``died``, ``restarts``), and it is started again while MAX_RESTARTS allow; the frames go on meanwhile,
        tracked against the map it left."""
        if self._proc is None:
            return False
        stalled = self._proc.is_alive() and self._stalled()
        if self._proc.is_alive() and not stalled:
            return True
        if self._closed or self._closing or self._given_up:
            return False
        if stalled:
            limit, median = self._stall_limit()
            log.error("the mapping process has answered nothing for %.0f s with a keyframe in work: stopped (its limit "
                      "%.0f s: %g times its median %.2f s per keyframe, at least %g s)",
                      time.monotonic() - self._last_progress, limit, self.STALL_FACTOR, median, self.STALL_MIN_S)
            self._proc.kill()
            self._proc.join(5)
        self._poll()
        death = {"exit_code": self._proc.exitcode, "keyframes_mapped": self.answered,
                 "keyframes_lost": self.sent - self.answered + (self._held is not None), "stalled": stalled}
        if self.died is None:
            self.died = death
        if len(self.restarts) >= self.MAX_RESTARTS:
            self._given_up = True
            log.error("the mapping process died (exit code %s) after mapping %d keyframes, restarted %d times already: "
                      "the frames go on, tracked against the map it left; nothing more is mapped",
                      self._proc.exitcode, self.answered, len(self.restarts))
            return False
        self._restart(death)
        return True

    #: A process that answers nothing for this long with a keyframe in work is taken for dead: STALL_FACTOR times its
    #: median seconds per keyframe so far, and at least STALL_MIN_S (a first model takes several keyframes' time).
    STALL_MIN_S, STALL_FACTOR = 60.0, 20.0

    def _stall_limit(self) -> tuple[float, float]:
        """(seconds of silence taken for a stall, the median seconds per keyframe it follows from; nan before any)."""
        secs = self._stats.get("seconds") or []
        median = float(np.median(secs)) if secs else float("nan")
        return max(self.STALL_MIN_S, self.STALL_FACTOR * median if secs else 0.0), median

    def _stalled(self) -> bool:
        quiet = time.monotonic() - self._last_progress
        if self.answered >= self.sent or self._closing:
            return False
        return quiet > self._stall_limit()[0]

    def _restart(self, death: dict) -> None:
        """A new mapping process, given first, in order, every keyframe the map holds and those the old one had not
        answered (those it tried and could not place are not tried again)."""
        n = len(self.restarts) + 1
        kf_camera, camera, workdir, *rest = self._config
        worker = MappingWorker()
        self._proc, self._results, self._outbox = worker.proc, worker.inbox, worker.outbox
        self._outbox.put((kf_camera, camera, str(Path(workdir) / f"restart-{n}"), *rest))
        self._base_attempts = self.attempts
        self._earlier_stats = dict(self._stats)
        self.answered = self._answered_at_restart = self.sent
        resend = [f for f in self._jobs.frames() if f in self.model_pose or f > self.processed]
        for f in resend:
            self._put(self._jobs.get(f))
        self._to_old, self._new_pose, self._new_ref = None, {}, None
        self._map_before, self._new_frames = set(self.model_pose), set()
        self.restarts.append({**death, "restart": n, "at_keyframe": self.processed, "keyframes_remapped": len(resend),
                              "map_keyframes": sorted(self._map_before),
                              "placed": None if self._map_before else "no map before it: its model is the map"})
        log.error("the mapping process died (exit code %s) after %d keyframes; started again (restart %d of at most "
                  "%d) with the map's %d keyframes to map again; its model replaces the map once rebuilt",
                  death["exit_code"], death["keyframes_mapped"], n, self.MAX_RESTARTS, len(resend))

    def wait(self, timeout_s: float = 120.0) -> None:
        """Until every keyframe handed over is mapped (or the process died, or timeout_s passed)."""
        t_end = time.monotonic() + timeout_s
        while self.busy() and self._proc is not None and self._proc.is_alive() and time.monotonic() < t_end:
            self._poll(timeout=0.5)

    def _poll(self, timeout: float | None = 0.0) -> bool:
        """Take in what the process sent; ``timeout``: wait that long for one message (None: for ever)."""
        got = False
        while True:
            try:
                r = self._results.get(timeout=timeout) if timeout != 0.0 else self._results.get_nowait()
            except queue.Empty:
                return got
            got, timeout = True, 0.0
            self._stats = self._with_earlier(r["stats"])
            if "closed" in r:
                points = r.get("points")
                if points is not None and self._map_before:
                    points = self._to_first_model({}, None, None, points)[3]
                if points is not None:
                    self._points = points
                self._submodels = r["closed"]
                self._closed = True
                return got
            self.answered += 1
            self._last_progress = time.monotonic()
            if log.isEnabledFor(logging.DEBUG):  # how far the mapper moved the keyframes it had already placed
                moved = [np.linalg.norm(self.model_pose[f][0].T @ self.model_pose[f][1] - R.T @ t)
                         for f, (R, t) in r["poses"].items() if f in self.model_pose]
                log.debug("keyframe %d mapped (%s): the keyframes before it moved up to %.4f model units",
                          r["frame"], r["ok"], max(moved, default=0.0))
            poses, fit, ref, points = r["poses"], r["fit"][0], r["ref"], r.get("points")
            if self._map_before:  # a restarted process: its frame is moved onto the map's, once both share keyframes
                poses, fit, ref, points = self._to_first_model(poses, fit, ref, points)
            elif r["first_refs"]:
                self.first_references = r["first_refs"]
            if points is not None:
                self._points = points
            for f in poses:
                if f not in self.model_pose:
                    bisect.insort(self.kf_sorted, f)
            self.model_pose.update(poses)
            self.moved.update(poses)
            if fit is not None:
                self.fit, self.fit_residual_m = fit, r["fit"][1]
            if ref is not None:
                self._ref = ref
            self.processed = max(self.processed, r["processed"])
            self.attempts = self._base_attempts + r["attempts"]
            self._send()

    #: Counts in the mapper's stats that add up over the processes of one flight.
    _ADDITIVE = ("keyframes_processed", "failed", "submodels", "revisits", "reanchored", "rejoined")

    def _with_earlier(self, stats: dict) -> dict:
        """A process's stats with those of the processes before it (after a restart) added in."""
        if not self._earlier_stats:
            return stats
        out = dict(stats)
        for k in self._ADDITIVE:
            out[k] = stats.get(k, 0) + self._earlier_stats.get(k, 0)
        out["seconds"] = self._earlier_stats.get("seconds", []) + list(stats.get("seconds", []))
        if self._earlier_stats.get("in_memory_from") is not None:  # the folder refused a process before this one
            out["in_memory_from"] = self._earlier_stats["in_memory_from"]
        return out

    def _to_first_model(self, poses, fit, ref, points):
        """A restarted process's poses, fit, reference and points in the coordinates the mapper gave before the
        restart; nothing until it can be placed."""
        self._new_frames.update(poses)
        if self._to_old is None:
            self._new_pose.update(poses)
            self._new_ref = ref if ref is not None else self._new_ref
            if self.answered - self._answered_at_restart < self.restarts[-1]["keyframes_remapped"]:
                return {}, None, None, None  # placed by every keyframe both can hold: the more, the surer its scale
            placed = align_models(self.model_pose, self._new_pose)
            if placed is None:
                return {}, None, None, None
            self._to_old, info = placed
            self.restarts[-1]["placed"] = {**info, "scale": self._to_old.scale}
            log.warning("the restarted mapping process's model placed in the map's frame by %d keyframes (centres "
                        "within %.3g of the map's %.3g extent, orientations within %.2f deg)", info["keyframes"],
                        info["centre_residual_max"], info["extent"], info["rotation_residual_max_deg"])
            poses, ref = self._new_pose, self._new_ref
        S = self._to_old
        # the rebuilt model is the map from now on: every keyframe's pose, the old ones' too (one model, refined by
        # its own bundle adjustments as the flight goes on), and its georeference, fitted to the same keyframes
        poses = {f: move_pose(S, R, t) for f, (R, t) in poses.items()}
        fit = compose(fit, inverse(S)) if fit is not None else None
        points = {k: S.apply(X) for k, X in points.items()} if points is not None else None
        return poses, fit, move_reference(S, ref), points

    @property
    def has_model(self) -> bool:
        self._poll()
        return bool(self.model_pose)

    @property
    def alive(self) -> bool:
        """Whether the mapping process still runs (it answers nothing more once it died)."""
        return self._running()

    def reference(self) -> Reference | None:
        self._poll()
        return self._ref

    def take_moved(self) -> list[int]:
        """The keyframes whose poses changed (or came) since the last call, in order."""
        self._poll()
        out, self.moved = sorted(self.moved), set()
        return out

    def registered(self):
        self._poll()
        return self.model_pose, self.kf_sorted, self.fit

    def stats(self) -> dict:
        self._poll()
        return self._stats

    def submodels(self) -> list[Submodel]:
        return self._submodels

    def sparse_points(self, **kw) -> dict[int, np.ndarray]:
        self._poll()
        return self._points

    def close(self, timeout_s: float = 600.0) -> None:
        """Map what is waiting, take in the results and the sub-models (written to disk), stop the process; all within
        ``timeout_s`` (a ground told to stop gives it seconds): past it the process is killed, and what it had not sent
        back is lost (the map's model files; the frames' poses and the apples are the ground's)."""
        if self._proc is None:
            return
        self._closing = True
        t_end = time.monotonic() + timeout_s
        while self._held is not None and self._proc.is_alive() and time.monotonic() < t_end:  # the last one too
            self._poll(timeout=min(1.0, max(t_end - time.monotonic(), 0.0)))
            self._send()
        self._outbox.put(None)
        while not self._closed and time.monotonic() < t_end:
            if not self._poll(timeout=min(1.0, max(t_end - time.monotonic(), 0.01))) and not self._proc.is_alive():
                log.error("the mapping process ended without its results (exit code %s)", self._proc.exitcode)
                break
        if not self._closed and self._proc.is_alive():
            log.warning("the mapping process did not finish within %.0f s: stopped; the model files are not written",
                        timeout_s)
            self._proc.kill()  # its time is up: not another wait
        self._proc.join(timeout=min(10.0, max(t_end - time.monotonic(), 0.5)))
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join()
        self._proc = None
        self._jobs.clear()


class _JobStore:
    """Every keyframe job sent to the mapping process, by frame: pickled in ``folder`` (a long flight's keyframe
    images would fill the memory), or kept in memory where the folder cannot be written."""

    def __init__(self, folder: Path | None):
        self.folder: Path | None = folder
        self._memory: dict[int, tuple] = {}
        self._frames: set[int] = set()

    def put(self, job: tuple) -> None:
        frame = job[0]
        if frame in self._frames:
            return
        self._frames.add(frame)
        if self.folder is not None:
            try:
                self.folder.mkdir(parents=True, exist_ok=True)
                tmp = self.folder / f"{frame}.pkl.tmp"
                tmp.write_bytes(pickle.dumps(job, protocol=pickle.HIGHEST_PROTOCOL))
                tmp.replace(self.folder / f"{frame}.pkl")
                return
            except OSError as e:
                log.warning("%s: %s; the keyframes a restarted mapping process needs are kept in memory instead",
                            self.folder, e.strerror or e)
                self._memory.update(self._read_all())
                self.folder = None
        self._memory[frame] = job

    def _read_all(self) -> dict[int, tuple]:
        got = {}
        for f in self._frames:
            try:
                got[f] = self.get(f)
            except (OSError, pickle.UnpicklingError):
                pass
        return got

    def clear(self) -> None:
        """Forget every job (the flight's mapping is over: no process will be restarted)."""
        if self.folder is not None:
            shutil.rmtree(self.folder, ignore_errors=True)
        self._memory, self._frames = {}, set()

    def frames(self) -> list[int]:
        return sorted(self._frames)

    def get(self, frame: int) -> tuple:
        if frame in self._memory:
            return self._memory[frame]
        return pickle.loads((self.folder / f"{frame}.pkl").read_bytes())
