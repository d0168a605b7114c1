"""The ground's processing, fed wire messages one at a time: poses (tracking, mapping) -> windowed association.

    pipe = GroundPipeline(workdir)
    for msg in messages:          # pomar.wire messages, in any order, repeats allowed
        for event in pipe.feed(msg):
            ...                   # FrameEvent: a frame went through the association (its pose, new apples)
    pipe.finish()
    pipe.count.apples             # id -> Apple (association frame); ground.outputs.tables.apple_table(pipe): ENU, WGS84

Frames are de-duplicated and released to the association in index order, once their pose can be
decided (:class:`ground.poses.live.LivePoses`). A frame that arrives after a later one was
released is counted as late and dropped (the association only moves forward); missing frame
indices are reported as gaps. An image that does not decode or track is logged, and its frame gets an
interpolated or telemetry pose: nothing stops the flight.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from ground.apples.association import Apple, AssociationParams, FrameDetections, WindowedAssociation
from ground.apples.counting import Counting, CountingSettings
from ground.apples.frames import AssociationFrames
from ground.poses.live import LivePoses, Pose
from ground.poses.mapping import MappingWorker
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
    #: Live (mapping in its own process), pose corrections run at most this often (s); the keyframes the mapper moves
    #: meanwhile add up, and one round corrects them all. Lock-step corrects after every keyframe (deterministic).
    correction_every_s: float = 2.0
    #: The map's drift along the flight, corrected from the GPS: each camera is moved by the GPS's disagreement with
    #: the map, a line fitted over the registered keyframes within about this much flight (Gaussian sigma, s), and each
    #: apple by its views' mean; 0 = one similarity for the whole map. Wider than the GPS error's wander (tens of
    #: seconds), so that it stays out of the map's shape; and only where the map drifted (LivePoses.drift_correction).
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
        self.poses: LivePoses | None = None
        self.assoc = WindowedAssociation(self.s.association)
        self.frames = AssociationFrames()  # the frames fed to the association: poses, camera matrices
        self.count = Counting(self.s.counting, self.frames,
                              reach=self.s.association.merge_window + 2 * self.s.association.k)
        self.pending: dict[int, wire.FrameMessage] = {}
        if self.s.mapping not in ("stream", "inline", "process"):
            raise ValueError(f"GroundSettings.mapping must be 'stream', 'inline' or 'process', got {self.s.mapping!r}")
        # live, the mapping process starts now: its imports would otherwise hold up the first model
        self._mapping_worker = MappingWorker() if self.s.mapping == "process" else None
        self.keyframes: dict[int, bytes] = {}  # images waiting for tracking (and mapping)
        self._kf_for_event: dict[int, bytes] = {}
        self._kf_seen: set[int] = set()
        self.kf_awaited: set[int] = set()  # keyframes their frame messages announced that have not come yet
        self._last_kf_t = time.monotonic()
        self._last_kf_capture = float("nan")  # capture time of the last keyframe's frame (or of the first frame)
        self.released = -1
        self.status: wire.StatusMessage | None = None
        self.counters = {"frames": 0, "keyframes": 0, "late_frames": 0, "gaps": 0, "missing_frames": 0,
                         "bad_keyframes": 0, "frames_without_pose": 0, "detections": 0,
                         "registered": 0, "tracked": 0, "interpolated": 0, "telemetry": 0}
        self.seconds = {"poses": 0.0, "association": 0.0, "corrections": 0.0}
        self._last_correction = -float("inf")
        self.gaps: list[tuple[int, int]] = []
        self.frame_times: dict[int, float] = {}
        self.newest_t = float("-inf")  # the latest capture time of any frame received
        self._arrived: dict[int, float] = {}  # frame -> when its message came (monotonic clock)
        self.steps: deque[int] = deque(maxlen=20)  # frame-index steps between the last frames released
        self._hold_gaps_until = 0.0  # until then (monotonic), a frame after a missing one waits for it
        self.frame_delays: list[float] = []  # per mapped frame: seconds from its message's arrival to its release
        self.frame_delays_mapped: list[float] = []  # ... of the frames that arrived once the first model existed
        self.t_first_model: float | None = None  # when the first model was there
        self.t_first_frame: float | None = None  # when the first frame message came
        self._newest_frame = -1  # the highest frame index received
        self.corrections = {"rounds": 0, "frames": 0, "apples_moved": 0, "apples_merged": 0}

    # -- inputs
    def feed(self, msg, step: bool = True) -> list[FrameEvent]:
        """Take one message; ``step=False`` only stores it (the node feeds what has queued up, then steps
        once for all of them)."""
        if isinstance(msg, wire.CameraMessage):
            self.on_camera(msg)
        elif isinstance(msg, wire.FrameMessage):
            self.on_frame(msg)
        elif isinstance(msg, wire.KeyframeMessage):
            self.on_keyframe(msg)
        elif isinstance(msg, wire.StatusMessage):
            self.status = msg
        return self.step() if step else []

    def on_camera(self, msg: wire.CameraMessage):
        if self.camera is not None:
            return
        self.camera = Camera.from_dict(msg.camera, source=f"camera message of {msg.flight_id}/{msg.drone_id}")
        self.count.camera = self.camera
        self.fps = msg.fps
        self.flight_id, self.drone_id = msg.flight_id, msg.drone_id
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
        # the registration is made in step(), once the first keyframe tells the keyframes' width (or, if the frames
        # cannot wait for it, from what the camera message says)

    def _make_poses(self, kf_width: int):
        self.poses = LivePoses(self.camera, self.workdir, keyframe_width=kf_width, settings=self.s.registration,
                               origin=self.origin, max_interp_gap=self.s.max_interp_gap, tracking=self.s.tracking,
                               init_spacing_s=self.s.init_spacing_s, mapping_worker=self._mapping_worker)
        for f in sorted(self.pending):
            t = self.pending[f].telemetry
            self.poses.add_telemetry(f, t.lat, t.lon, t.alt, t.q_gimbal, t.h_acc, t.height, t.height_acc,
                                     t.flags)

    def hold_gaps(self, seconds: float) -> None:
        """For the next ``seconds``, a frame after a missing one waits for it instead of leaving it to come late and
        be dropped: a resumed ground gets the frames it missed from the publisher's history while the live ones
        come too, in either order."""
        self._hold_gaps_until = time.monotonic() + seconds

    def on_frame(self, msg: wire.FrameMessage):
        if msg.frame <= self.released or msg.frame in self.pending:
            if msg.frame <= self.released:
                self.counters["late_frames"] += 1
                log.warning("frame %d arrived after frame %d was processed: dropped", msg.frame, self.released)
            return
        self.pending[msg.frame] = msg
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
        if self.poses is not None:
            t = msg.telemetry
            self.poses.add_telemetry(msg.frame, t.lat, t.lon, t.alt, t.q_gimbal, t.h_acc, t.height, t.height_acc,
                                     t.flags)

    def on_keyframe(self, msg: wire.KeyframeMessage):
        if msg.frame in self._kf_seen:
            return
        self._kf_seen.add(msg.frame)
        self.kf_awaited.discard(msg.frame)
        self._last_kf_t = time.monotonic()
        self._last_kf_capture = self.frame_times.get(msg.frame, self.newest_t)
        self.keyframes[msg.frame] = msg.jpeg
        self.counters["keyframes"] += 1

    # -- processing
    def step(self, final: bool = False, on_events=None) -> list[FrameEvent]:
        """Hand the waiting images to the poses (tracking; mapping keyframes), then release every frame whose pose
        can be decided. With ``on_events``, the frames released after each image go to it as they come (a backlog
        can take minutes: the map and the progress are shown meanwhile) and nothing is returned."""
        if self.camera is None:
            return []
        if self.poses is None:
            if not self.keyframes and not final and not self._stalled():
                return []
            self._make_poses(self._first_keyframe_width() or self._kf_width_said)
        events: list[FrameEvent] = []

        def out(evs: list[FrameEvent]) -> None:
            if on_events is None:
                events.extend(evs)
            elif evs:
                on_events(evs)
        # images in order, but never ahead of the frames: a frame needs the image after it. An image waits for its
        # frame's message (the telemetry the mapper's georeferencing needs; the streams do not keep each other's
        # order), unless a later frame's came (then it was lost)
        # lock-step, an image also waits for the earlier keyframes announced by their frames' messages (the stream
        # may bring them late): the images are tracked and mapped in the same order whatever the link did
        wait_before = min(self.kf_awaited) if self.kf_awaited and self.s.mapping == "inline" and not final else None
        for f in sorted(self.keyframes):
            if f not in self.frame_times and f > self._newest_frame and not final:
                break
            if wait_before is not None and f > wait_before:
                break
            jpeg = self.keyframes.pop(f)
            self._add_image(f, jpeg)
            out(self._release(final=False))
            self._correct()
        out(self._release(final))
        self._correct(final)
        return events

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
        if not moved or not len(self.frames):
            return
        self._last_correction = time.monotonic()
        gap = self.poses.MAX_CORRECTION_GAP
        frames = [f for f in range(max(moved[0] - gap, 0), min(moved[-1] + gap, self.released) + 1)
                  if f in self.frames.seq]
        t0 = time.perf_counter()
        new = self.poses.corrected(self.frames.poses, frames)
        if not new:
            return
        P = {}
        for f, pose in new.items():
            Pf = self.camera.projection_matrix(pose.R, pose.t)
            P[self.frames.correct(f, pose, Pf)] = Pf
        self.assoc.metres_per_unit = self.metres_per_unit()
        changed, merged = self.assoc.repose(P)
        for gone, into in merged:
            self.count.merged(gone, into)
        self.count.confirm(changed, self.steps)
        self.seconds["corrections"] += time.perf_counter() - t0
        c = self.corrections
        c["rounds"] += 1
        c["frames"] += len(new)
        c["apples_moved"] += len(changed)
        c["apples_merged"] += len(merged)

    def _stalled(self) -> bool:
        """Live: no keyframe for max_wait_s, while the frames went on for max_wait_s of flight past the last one: the
        drone stopped sending keyframes. A slow onboard detector delays frames and keyframes alike and stalls
        nothing. Lock-step (mapping inline) never stalls: frames wait for their images until the stream ends, so that
        neither a busy machine nor the order the two streams happen to arrive in changes a pose."""
        if self.s.mapping == "inline":
            return False
        flown = self.newest_t - self._last_kf_capture
        return time.monotonic() - self._last_kf_t > self.s.max_wait_s and not flown <= self.s.max_wait_s

    def _first_keyframe_width(self) -> int | None:
        for jpeg in self.keyframes.values():
            img = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
            if img is not None:
                return img.shape[1]
        return None

    def _add_image(self, frame: int, jpeg: bytes):
        img = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_COLOR)
        if img is None:
            self.counters["bad_keyframes"] += 1
            log.warning("keyframe %d: JPEG does not decode; the frame gets an interpolated or telemetry pose", frame)
            return
        t0 = time.perf_counter()
        self.poses.add_image(frame, img, self.frame_times.get(frame, float("nan")))
        self.seconds["poses"] += time.perf_counter() - t0
        self._last_kf_t = time.monotonic()  # the wait is counted from when the poses are free again
        self._kf_for_event[frame] = jpeg

    def _release(self, final: bool) -> list[FrameEvent]:
        events = []
        while self.pending:
            f = min(self.pending)
            if not final and f > self.released + 1 and time.monotonic() < self._hold_gaps_until:
                break  # a frame before it may still come (hold_gaps)
            # the poses say when: once an image at or after f has been tracked
            if not self.poses.ready(f, final, self._stalled()):
                break
            msg = self.pending.pop(f)
            arrived = self._arrived.pop(f, None)
            if self.t_first_model is None and self.poses.mapper.has_model:  # seen as the next frame is released
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
            pose = self.poses.pose(f)
            new: list[Apple] = []
            if pose is None:
                self.counters["frames_without_pose"] += 1
                log.warning("frame %d: no pose (no registration and no position telemetry): skipped", f)
            else:
                self.counters[pose.source] += 1
                keep = np.asarray(msg.scores) >= self.s.min_score
                xy = msg.centres[keep]
                self.counters["detections"] += len(xy)
                P = self.camera.projection_matrix(pose.R, pose.t)
                t0 = time.perf_counter()
                # The association's window is the next k frames *of the stream*: a real-time onboard node
                # that drops frames sends indices with gaps, so the association counts frames, not indices.
                seq = self.frames.add(f, pose, P)
                self.assoc.metres_per_unit = self.metres_per_unit()
                fd = FrameDetections(seq, P, xy, np.asarray(msg.boxes, float).reshape(-1, 4)[keep],
                                     np.asarray(msg.scores)[keep])
                new = self.count.confirm(self.assoc.add_frame(fd), self.steps)
                self.seconds["association"] += time.perf_counter() - t0
            events.append(FrameEvent(f, msg.t_capture, pose, msg, new, self._kf_for_event.pop(f, None)))
            for k in [k for k in self._kf_for_event if k < f]:
                del self._kf_for_event[k]
            self.poses.forget_before(f - 4 * self.s.association.k - 2 * self.s.max_interp_gap)
        return events

    #: Seconds a ground told to stop (Ctrl-C, SIGTERM) gives its mapping process to hand back its sub-models.
    STOP_MAPPER_S = 2.0

    def finish(self, on_events=None, hurry: bool = False) -> list[FrameEvent]:
        """End of the flight: register what is left, release every frame, close every track. ``on_events`` as in
        :meth:`step`. ``hurry``: told to stop; the images not yet tracked are dropped and the mapper gets
        STOP_MAPPER_S, so that the frames are released at once, with the poses there are."""
        events = []
        if hurry:
            self.keyframes.clear()
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
        self.assoc.metres_per_unit = self.metres_per_unit()
        self.count.confirm(self.assoc.finish(), self.steps)
        self._correct(now=True)  # the mapper's last answers
        self._kf_for_event.clear()
        return events

    def wait_for_mapping(self, timeout_s: float = 120.0) -> None:
        """Until the mapping process has mapped what it was given. A resumed journal's backlog is fed through this
        after each message, so that it is mapped keyframe by keyframe as when it came at the flight's pace: fed in a
        burst, the process mapped only the newest proposal of each spell, tracking ran off the map, and a ground
        killed and restarted ended with F1 0.01."""
        if self.poses is not None and self.s.mapping == "process":
            self.poses.mapper.wait(timeout_s)

    def metres_per_unit(self) -> float:
        """The association frame's unit in metres, as the map's georeference knows it now: the frame was fixed by
        the first fit, from a few keyframes' GPS, and the later fits scale it (tens of percent with a DJI log's)."""
        return float(self.poses.assoc_to_enu().scale) if self.poses is not None else 1.0

    def apple_boxes(self, a: Apple) -> list[tuple[int, np.ndarray]]:
        """(frame, box xyxy in camera pixels) of the apple's detections within the association's reach, in frame
        order."""
        return sorted(((self.frames.frame[o.frame], np.array(o.box)) for o in self.count.in_reach(a)),
                      key=lambda fb: fb[0])
