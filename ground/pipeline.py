"""The ground's processing, fed wire messages one at a time: the system object that wires its three parts.

    pipe = GroundPipeline(workdir)
    for msg in messages:          # pomar.wire messages, in any order, repeats allowed
        for event in pipe.take(msg):
            ...                   # FrameEvent: a frame went through the association (its pose, new apples)
    pipe.finish()
    pipe.apples.count.apples      # id -> Apple (map frame); ground.outputs.tables.apple_table(snapshot(pipe)): ENU, WGS84

The camera message opens a stream (:meth:`GroundPipeline.start`); its frame, keyframe and status messages are fed
(:meth:`GroundPipeline.feed`); ``take`` does either. A frame goes down once and comes back once: the arrivals
(:class:`ground.link.arrivals.Arrivals`) put the messages in frame order; the poses
(:class:`ground.poses.stage.PoseStage`) take the telemetry and the images, and say when a frame's pose can be decided
and what it is; the apples (:class:`ground.apples.stage.AppleStage`) take the posed frame's detections and give back
the apples it confirmed. An image that does not decode or track is logged, and its frame gets an interpolated or
telemetry pose: nothing stops the flight.
"""

from __future__ import annotations

import contextlib
import logging
import time
from dataclasses import dataclass, field, replace

from ground.apples.association import Apple, AssociationParams
from ground.apples.counting import CountingSettings
from ground.apples.landmarks import SIGMA as APPLES_SIGMA
from ground.apples.stage import AppleStage
from ground.link.arrivals import Arrivals
from ground.orchard.calibration import DEFAULT_MODEL, MODELS
from ground.poses.stage import PoseStage, Pose
from ground.poses.mapper_process import MappingWorker
from ground.poses.registration import RegistrationSettings
from ground.poses.tracking import TrackingSettings
from pomar import wire
from pomar.camera import Camera

log = logging.getLogger(__name__)


@dataclass
class GroundSettings:
    #: The association's own gates (3 px, 3 inliers), with k = 10: the detector misses an apple for
    #: runs of frames (leaves, low scores), and tracks that bridge them are not split. From the shipped
    #: detector's output and the replays' poses (journal re-run): bundled flight count +4.2 %, F1 0.817
    #: at k = 5, 0.832 at k = 10; second flight 0.874 and 0.876. 4 px and 4 inliers (the node's gates
    #: before apples were triangulated about a camera and by least squares) gave -5.3 %, F1 0.837 on
    #: the bundled flight but -6.5 % on the second.
    association: AssociationParams = field(default_factory=lambda: AssociationParams(k=10))
    #: The first model from 4 images 0.2 s apart (init_spacing_s), not the batch registration's 6: live, every frame
    #: waits for it (README: "The ground alone, live").
    registration: RegistrationSettings = field(default_factory=lambda: RegistrationSettings(init_frames=4))
    #: Live, frames wait for the keyframe after them; when no keyframe has come for this long, they go on
    #: with interpolated or telemetry poses. Lock-step they wait for it until the stream ends.
    max_wait_s: float = 5.0
    #: A frame without a pose of its own is interpolated between the nearest posed frames only when they are at most
    #: this many frames apart (else it takes its telemetry pose).
    max_interp_gap: int = 10
    #: "stream": as the stream says (its camera message): "inline" for a lock-step stream, "process" for a paced one,
    #: "inline" where it does not say. "inline": each mapping keyframe is registered before the frames after it go on
    #: (lock-step: deterministic); "process": mapping runs in its own process and never holds up tracking (live).
    mapping: str = field(default="stream", metadata={"choices": ["stream", "inline", "process"]})
    tracking: TrackingSettings = field(default_factory=TrackingSettings)
    #: Before the first model, the mapper takes images at least this far apart in capture time: its baseline is
    #: then the same at any frame rate (at 30 fps, 6 consecutive images span too little flight for a model).
    init_spacing_s: float = 0.2
    min_score: float = 0.0  # detections below this score are not used
    #: Which apples count (ground.apples.counting).
    counting: CountingSettings = field(default_factory=CountingSettings)
    #: Trees along a row are this far apart (m): trees.csv cuts each row's line into segments this long.
    tree_spacing_m: float = 1.0
    #: How each tree's load is estimated from the hand counts (--sample-counts): ratio, linear or coverage
    #: (ground.orchard.calibration).
    load_model: str = field(default=DEFAULT_MODEL, metadata={"choices": MODELS})
    #: Live (mapping in its own process), pose corrections run at most this often (s); the keyframes the mapper moves
    #: meanwhile add up, and one round corrects them all. Lock-step corrects after every keyframe (deterministic).
    correction_every_s: float = 2.0
    #: The map's drift along the flight, corrected from the GPS: each camera is moved by the GPS's disagreement with
    #: the map, a line fitted over the registered keyframes within about this much flight (Gaussian sigma, s), and each
    #: apple by its views' mean; 0 = one similarity for the whole map. Wider than the GPS error's wander (tens of
    #: seconds), so that it stays out of the map's shape; and only where the map drifted (MapFrame.correction).
    drift_sigma_s: float = 60.0


#: Where lock-step and live need other settings, one profile each: lock-step (a replay that waits for every frame)
#: maps each keyframe before the frames after it go on, so that a stream gives one map; live maps in a process of
#: its own, which never holds up tracking.
PROFILES = {"lockstep": {"mapping": "inline"}, "live": {"mapping": "process"}}


def profile(name: str) -> GroundSettings:
    """The ground's settings for a profile of PROFILES."""
    return GroundSettings(**PROFILES[name])


def stream_profile(paced: bool | None) -> str:
    """The profile a stream asks for: live for a paced one, lock-step for one that sends every frame (or says
    nothing)."""
    return "live" if paced else "lockstep"


@dataclass
class FrameEvent:
    frame: int
    t_capture: float
    pose: Pose | None
    msg: wire.FrameMessage
    new_apples: list[Apple]
    keyframe: bytes | None = None


class GroundPipeline:
    def __init__(self, workdir, settings: GroundSettings | None = None, origin=None):
        self.workdir = workdir
        self.s = settings or GroundSettings()
        self.origin = origin
        self.camera: Camera | None = None
        self.fps = float("nan")  # the drone's frame rate, from its camera message
        self._kf_width_said: int | None = None  # the keyframes' width, as the camera message says it
        self.flight_id = self.drone_id = None
        self.altitude_reference: str | None = None  # what the frames' altitudes are measured from (camera message)
        if self.s.mapping not in ("stream", "inline", "process"):
            raise ValueError(f"GroundSettings.mapping must be 'stream', 'inline' or 'process', got {self.s.mapping!r}")
        self.arrivals = Arrivals(self.s.max_wait_s)
        self._work_depth = 0  # nesting of take() and step(): their time lengthens a hold of the gaps
        self.work_s = 0.0  # seconds spent in take() and step(), outermost calls
        self.poses: PoseStage | None = None
        self.apples = AppleStage(self.s.association, self.s.counting, self.s.min_score)
        # live, the mapping process starts now: its imports would otherwise hold up the first model
        self._mapping_worker = MappingWorker() if self.s.mapping == "process" else None
        self._kf_for_event: dict[int, bytes] = {}  # images tracked, kept for their frame's event
        self._counts = {"bad_keyframes": 0, "frames_without_pose": 0,
                        "registered": 0, "tracked": 0, "interpolated": 0, "extrapolated": 0, "apples": 0,
                        "telemetry": 0}
        self.seconds = {"poses": 0.0, "association": 0.0, "corrections": 0.0}
        self._last_correction = time.monotonic()  # the first round waits its period too
        self.corrections = {"rounds": 0, "frames": 0, "apples_moved": 0, "apples_merged": 0}

    @property
    def counters(self) -> dict[str, int]:
        """What came and what became of it: the arrivals' counts, then the poses' and the apples'."""
        c = self._counts
        return {**self.arrivals.counters, "bad_keyframes": c["bad_keyframes"],
                "frames_without_pose": c["frames_without_pose"], "detections": self.apples.detections,
                **{k: c[k] for k in ("registered", "tracked", "interpolated", "extrapolated", "apples", "telemetry")}}

    # -- inputs
    def take(self, msg, step: bool = True) -> list[FrameEvent]:
        """Any message of a stream: its camera message opens it (:meth:`start`), the others are fed (:meth:`feed`).
        The time it takes lengthens a hold of the gaps under way (the ground's work is not the link's wait)."""
        with self._working():
            return self.start(msg, step) if isinstance(msg, wire.CameraMessage) else self.feed(msg, step)

    @contextlib.contextmanager
    def _working(self):
        """Time spent in :meth:`take` and :meth:`step` (the outermost call only) goes to the arrivals' hold."""
        if self._work_depth:
            yield
            return
        self._work_depth += 1
        t0 = time.monotonic()
        try:
            yield
        finally:
            self._work_depth -= 1
            self.work_s += time.monotonic() - t0
            self.arrivals.worked(time.monotonic() - t0)

    def start(self, msg: wire.CameraMessage, step: bool = True) -> list[FrameEvent]:
        """The stream's opening (its camera message): the camera, and the profile the stream asks for. Frames that
        came before it go on now (``step``)."""
        if self.camera is None:
            camera = Camera.from_dict(msg.camera, source=f"camera message of {msg.flight_id}/{msg.drone_id}")
            self.flight_id, self.drone_id = msg.flight_id, msg.drone_id
            self.fps = msg.fps
            self.altitude_reference = msg.altitude_reference
            self._kf_width_said = msg.keyframe_width or None
            said = stream_profile(msg.paced)
            if self.s.mapping == "stream":
                self.s = replace(self.s, **PROFILES[said])
                if self.s.mapping == "process" and self._mapping_worker is None:
                    self._mapping_worker = MappingWorker()
                log.info("profile %s, from the stream (%s): mapping %s", said, "paced" if msg.paced else
                         "every frame, as fast as taken" if msg.paced is False else "it does not say", self.s.mapping)
            else:
                log.info("mapping %s, as set (the stream asks for the %s profile)", self.s.mapping, said)
            # the poses are made in step(), once the first keyframe tells the keyframes' width (or, if the frames
            # cannot wait for it, from what the camera message says)
            self.camera = self.apples.camera = camera
            self.apples.box_response = msg.box_response
            self.apples.count.model_score = msg.operating_score
        return self.step() if step else []

    def feed(self, msg: wire.FrameMessage | wire.KeyframeMessage | wire.StatusMessage,
             step: bool = True) -> list[FrameEvent]:
        """Take one message of the stream's body (its opening is :meth:`start`'s): the arrivals put it in frame order,
        whatever order it came in; ``step=False`` only stores it (the node feeds what has queued up, then steps once
        for all of them)."""
        self.arrivals.take(msg)
        return self.step() if step else []

    @property
    def status(self) -> wire.StatusMessage | None:
        """The drone's newest status message."""
        return self.arrivals.status

    def hold_gaps(self, seconds: float) -> None:
        """See :meth:`ground.link.arrivals.Arrivals.hold_gaps`."""
        self.arrivals.hold_gaps(seconds)

    # -- processing
    def step(self, final: bool = False, on_events=None) -> list[FrameEvent]:
        """Hand the waiting images to the poses (tracking; mapping keyframes), then release every frame whose pose
        can be decided. With ``on_events``, the frames released after each image go to it as they come (a backlog
        can take minutes: the map and the progress are shown meanwhile) and nothing is returned."""
        with self._working():
            return self._step(final, on_events)

    def _step(self, final: bool, on_events) -> list[FrameEvent]:
        if self.camera is None:
            return []
        arrivals = self.arrivals
        if self.poses is None:
            if not arrivals.keyframes and not final and not self._stalled():
                return []
            width = PoseStage.keyframe_width(arrivals.keyframes.values()) or self._kf_width_said
            self.poses = PoseStage(self.camera, self.workdir, keyframe_width=width, settings=self.s.registration,
                                   origin=self.origin, max_interp_gap=self.s.max_interp_gap,
                                   tracking=self.s.tracking, init_spacing_s=self.s.init_spacing_s,
                                   mapping_worker=self._mapping_worker)
            for msg in sorted(arrivals.fresh(), key=lambda m: m.frame):
                self.poses.add_frame(msg)
        for msg in arrivals.fresh():
            self.poses.add_frame(msg)
        events: list[FrameEvent] = []

        def out(evs: list[FrameEvent]) -> None:
            if on_events is None:
                events.extend(evs)
            elif evs:
                on_events(evs)
        # lock-step, an image waits for the earlier keyframes announced by their frames' messages (the stream may
        # bring them late): the images are tracked and mapped in the same order whatever the link did
        for f, jpeg in arrivals.images(final, wait_for_announced=self.s.mapping == "inline"):
            t0 = time.perf_counter()
            if self.poses.add_image(f, jpeg, arrivals.frame_times.get(f, float("nan"))):
                self.seconds["poses"] += time.perf_counter() - t0
                arrivals.image_done()  # the wait is counted from when the poses are free again
                self._kf_for_event[f] = jpeg
            else:
                self._counts["bad_keyframes"] += 1
                log.warning("keyframe %d: JPEG does not decode; the frame gets an interpolated or telemetry pose", f)
            out(self._release(final=False))
            self._correct()
        out(self._release(final))
        self._correct(final)
        return events

    def _stalled(self) -> bool:
        """Live: the drone stopped sending keyframes (:meth:`Arrivals.stalled`). Lock-step (mapping inline) never
        stalls: frames wait for their images until the stream ends, so that neither a busy machine nor the order the
        two streams happen to arrive in changes a pose."""
        return self.s.mapping != "inline" and self.arrivals.stalled()

    def _release(self, final: bool) -> list[FrameEvent]:
        """Every frame whose pose can be decided, in order, each through :meth:`_frame`."""
        events = []
        poses = self.poses
        for msg in self.arrivals.release(lambda f: poses.ready(f, final, self._stalled()), final,
                                         lambda: poses.has_model):
            events.append(self._frame(msg))
            poses.forget_before(msg.frame - 4 * self.s.association.k - 2 * self.s.max_interp_gap)
        return events

    def _frame(self, msg: wire.FrameMessage) -> FrameEvent:
        """One frame, released in order, goes down once: the poses give its pose (where only telemetry or the motion
        before it would, the apples it sees place it), then the apples take its detections with that pose and give
        back those it confirmed."""
        f = msg.frame
        pose = self.poses.pose(f)
        # where no image placed it (telemetry, or carried on past the last posed frame), the apples it sees may
        placed = self.apples.place(msg) if pose is not None and pose.source in ("telemetry", "extrapolated") else None
        if placed is not None:  # no image placed it: the apples it sees did
            pose = Pose(f, *placed, "apples", *APPLES_SIGMA)
        new: list[Apple] = []
        if pose is None:
            self._counts["frames_without_pose"] += 1
            log.warning("frame %d: no pose (no registration and no position telemetry): skipped", f)
        else:
            self._counts[pose.source] += 1
            t0 = time.perf_counter()
            new = self.apples.take_frame(msg, pose, self.arrivals.steps, self.poses.metres_per_unit())
            self.seconds["association"] += time.perf_counter() - t0
        for k in [k for k in self._kf_for_event if k < f]:
            del self._kf_for_event[k]
        return FrameEvent(f, msg.t_capture, pose, msg, new, self._kf_for_event.pop(f, None))

    def _correct(self, now: bool = False) -> None:
        """The mapper moved keyframes (bundle adjustment, a re-anchoring on an earlier pass): the frames released about
        them take their corrected poses, and the apples seen in those frames are triangulated again from them, then
        merged where they turn out to be one apple (seen on two passes, whose poses only now agree). Live, at most one
        round per ``correction_every_s`` unless ``now``."""
        if self.poses is None:
            return
        if (not now and self.s.mapping == "process"
                and time.monotonic() - self._last_correction < self.s.correction_every_s):
            return  # live: the moved keyframes wait for the next round
        moved = self.poses.take_moved()
        fed = self.apples.frames
        if not moved or not len(fed):
            return
        self._last_correction = time.monotonic()
        gap = self.poses.MAX_CORRECTION_GAP
        frames = [f for f in range(max(moved[0] - gap, 0), min(moved[-1] + gap, self.arrivals.released) + 1)
                  if f in fed.seq]
        t0 = time.perf_counter()
        new = self.poses.corrected(fed.poses, frames)
        if not new:
            return
        changed, merged = self.apples.repose(new, self.arrivals.steps, self.poses.metres_per_unit())
        self.seconds["corrections"] += time.perf_counter() - t0
        c = self.corrections
        c["rounds"] += 1
        c["frames"] += len(new)
        c["apples_moved"] += len(changed)
        c["apples_merged"] += len(merged)

    #: Seconds a ground told to stop (Ctrl-C, SIGTERM) gives its mapping process to hand back its sub-models.
    STOP_MAPPER_S = 2.0

    def finish(self, on_events=None, hurry: bool = False) -> list[FrameEvent]:
        """End of the flight: register what is left, release every frame, close every track. ``on_events`` as in
        :meth:`step`. ``hurry``: told to stop; the images not yet tracked are dropped and the mapper gets
        STOP_MAPPER_S, so that the frames are released at once, with the poses there are."""
        events = []
        if hurry:
            self.arrivals.drop_images()
            if self.poses is not None:
                self.poses.drop_waiting()
        elif self.poses is not None:
            events += self.step(on_events=on_events)
            self.poses.settle()
        if self.camera is not None:
            events += self.step(final=True, on_events=on_events)
        if self.poses is not None:
            # maps what is waiting: the model files are written from it
            self.poses.close(timeout_s=self.STOP_MAPPER_S if hurry else 600.0)
        elif self._mapping_worker is not None:  # no image ever came
            self._mapping_worker.stop()
        self.apples.finish(self.arrivals.steps, self.metres_per_unit())
        self._correct(now=True)  # the mapper's last answers
        self._kf_for_event.clear()
        return events

    def wait_for_mapping(self, timeout_s: float = 120.0) -> None:
        """Until the mapping process has mapped what it was given. A resumed journal's backlog is fed through this
        after each message, so that it is mapped keyframe by keyframe as when it came at the flight's pace: fed in a
        burst, the process mapped only the newest proposal of each spell, tracking ran off the map, and a ground
        killed and restarted ended with F1 0.01."""
        if self.poses is not None and self.s.mapping == "process":
            self.poses.wait_for_mapping(timeout_s)

    def metres_per_unit(self) -> float:
        """:meth:`MapFrame.metres_per_unit` (1 before the poses exist)."""
        return self.poses.metres_per_unit() if self.poses is not None else 1.0
