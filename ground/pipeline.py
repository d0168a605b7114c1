"""The ground's processing, fed wire messages one at a time: poses (tracking, mapping) -> windowed association.

    pipe = GroundPipeline(workdir)
    for msg in messages:          # pomar.wire messages, in any order, repeats allowed
        for event in pipe.feed(msg):
            ...                   # FrameEvent: a frame went through the association (its pose, new apples)
    pipe.finish()
    pipe.apples                   # id -> Apple (association frame); pipe.table() in ENU / WGS84 with rows

Frames are de-duplicated and released to the association in index order, once their pose can be
decided (:class:`ground.live_poses.LivePoses`). A frame that arrives after a later one was
released is counted as late and dropped (the association only moves forward); missing frame
indices are reported as gaps. An image that does not decode or track is logged, and its frame gets an
interpolated or telemetry pose: nothing stops the flight.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from dataclasses import dataclass, field

import cv2
import numpy as np

from ground.association import Apple, AssociationParams, FrameDetections, WindowedAssociation
from ground.live_poses import LivePoses, Pose
from ground.mapping import MappingWorker
from ground.registration import RegistrationSettings
from ground.rows import direction_rows
from ground.tracking import TrackingSettings
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
    max_interp_gap: int = 10
    #: "inline": each mapping keyframe is registered before the frames after it go on (lock-step replays:
    #: deterministic); "process": mapping runs in its own process and never holds up tracking (live).
    mapping: str = "inline"
    tracking: TrackingSettings = field(default_factory=TrackingSettings)
    #: Before the first model, the mapper takes images at least this far apart in capture time: its baseline is
    #: then the same at any frame rate (at 30 fps, 6 consecutive images span too little flight for a model).
    init_spacing_s: float = 0.2
    min_score: float = 0.0  # detections below this score are not used
    #: An apple is counted once at least confirm_views of its views scored confirm_score or more (the
    #: shipped detector's operating threshold). Weaker detections still extend and place it: an
    #: onboard node that sends detections down to 0.7 gives longer tracks without counting apples that
    #: are only ever glimpsed (bundled flight, journal re-run: F1 0.832 -> 0.865, count +4.7 %).
    confirm_score: float = 0.9
    #: ... at the full frame rate. When the ground gets only every s-th frame (a real-time onboard node
    #: that drops what it cannot detect in time), ceil(confirm_views / s) views, at least 2, are asked
    #: for: an apple is in fewer of the frames sent (real-time replays, journal re-run: bundled flight F1
    #: 0.742 -> 0.776, count -40 % -> -32 %; second flight 0.802 -> 0.852, -30 % -> -20 %).
    confirm_views: int = 3
    #: Trees along a row are this far apart (m): trees.csv cuts each row's line into segments this long.
    tree_spacing_m: float = 1.0
    #: 3-D size consistency: an apple counts only if its radius (boxes x depth) is at least this fraction of the
    #: median radius of the apples mapped (once MIN_SIZED apples have one); 0 = off. An apple half hidden by
    #: leaves shows a smaller box than it is: partly hidden apples of the far rows, seen through the near row.
    min_radius_ratio: float = 0.8
    #: Expected views: an apple counts only if it was detected in at least this share of the frames it projects
    #: into (the mapped frames around its track); 0 = off. An apple glimpsed through leaves, or a false detection
    #: that happened to triangulate, is seen in few of the frames it lies in.
    min_view_ratio: float = 0.15
    #: Parallax: an apple counts only if the rays from its first and last views meet at this angle or more (degrees);
    #: 0 = off. Views over a narrower angle (a few frames at 30 fps, or the flight's last frames) leave its depth a
    #: guess, and such apples are mostly false ones, placed well off.
    min_parallax_deg: float = 2.0
    #: Live (mapping in its own process), pose corrections run at most this often (s); the keyframes the mapper moves
    #: meanwhile add up, and one round corrects them all. Lock-step corrects after every keyframe (deterministic).
    correction_every_s: float = 2.0
    #: The map's drift along the flight, corrected from the GPS: each camera is moved by the GPS's disagreement with
    #: the map, a line fitted over the registered keyframes within about this much flight (Gaussian sigma, s), and each
    #: apple by its views' mean; 0 = one similarity for the whole map. Wider than the GPS error's wander (tens of
    #: seconds), so that it stays out of the map's shape; and only where the map drifted (LivePoses.drift_correction).
    drift_sigma_s: float = 60.0


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
        self.apples: dict[int, Apple] = {}  # confirmed apples, by id
        self._scores: dict[int, np.ndarray] = {}  # stream frame -> scores of the detections it fed
        self._boxes: dict[int, np.ndarray] = {}  # stream frame -> (n, 4) boxes of those detections (xyxy, px)
        self.radius_m: dict[int, float] = {}  # apple id -> radius estimated from its boxes and depths
        self.size_rejected = 0  # confirmed apples left out of the map by the size check (counted_ids)
        self.views_rejected = 0  # ... by the expected views
        self.parallax_rejected = 0  # ... and by the parallax of their views
        self._proj: list[np.ndarray] = []  # association frame -> its camera matrix
        self._confirmed: dict[int, int] = {}  # apple id -> views scored confirm_score or more
        self.pending: dict[int, wire.FrameMessage] = {}
        if self.s.mapping not in ("inline", "process"):
            raise ValueError(f"GroundSettings.mapping must be 'inline' or 'process', got {self.s.mapping!r}")
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
        self._steps: deque[int] = deque(maxlen=20)  # frame-index steps between the last frames mapped
        self._hold_gaps_until = 0.0  # until then (monotonic), a frame after a missing one waits for it
        self.frame_delays: list[float] = []  # per mapped frame: seconds from its message's arrival to its release
        self.frame_delays_mapped: list[float] = []  # ... of the frames that arrived once the first model existed
        self.t_first_model: float | None = None  # when the first model was there
        self.t_first_frame: float | None = None  # when the first frame message came
        self._newest_frame = -1  # the highest frame index received
        self.frame_poses: dict[int, Pose] = {}  # every released frame's pose (association frame), corrected since
        self._seq_frame: list[int] = []  # association frame number -> frame index
        self._frame_seq: dict[int, int] = {}  # and back
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
        self.fps = msg.fps
        self.flight_id, self.drone_id = msg.flight_id, msg.drone_id
        self._kf_width_said = msg.keyframe_width or None
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
        if not moved or not self._seq_frame:
            return
        self._last_correction = time.monotonic()
        gap = self.poses.MAX_CORRECTION_GAP
        frames = [f for f in range(max(moved[0] - gap, 0), min(moved[-1] + gap, self.released) + 1)
                  if f in self._frame_seq]
        t0 = time.perf_counter()
        new = self.poses.corrected(self.frame_poses, frames)
        if not new:
            return
        P = {}
        for f, pose in new.items():
            self.frame_poses[f] = pose
            seq = self._frame_seq[f]
            P[seq] = self._proj[seq] = self.camera.projection_matrix(pose.R, pose.t)
        self.assoc.metres_per_unit = self.metres_per_unit()
        changed, merged = self.assoc.repose(P)
        for gone, into in merged:
            self._confirmed[into] = max(self._confirmed.get(into, 0), self._confirmed.pop(gone, 0))
            self.apples.pop(gone, None)
            self.radius_m.pop(gone, None)
        self._confirm(changed)
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
                self._steps.append(f - self.released)
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
                self.frame_poses[f] = pose
                keep = np.asarray(msg.scores) >= self.s.min_score
                xy = msg.centres[keep]
                self.counters["detections"] += len(xy)
                P = self.camera.projection_matrix(pose.R, pose.t)
                t0 = time.perf_counter()
                # The association's window is the next k frames *of the stream*: a real-time onboard node
                # that drops frames sends indices with gaps, so the association counts frames, not indices.
                seq = len(self._seq_frame)
                self._seq_frame.append(f)
                self._frame_seq[f] = seq
                self._proj.append(P)
                self._scores[seq] = np.asarray(msg.scores)[keep]
                self._boxes[seq] = np.asarray(msg.boxes, float).reshape(-1, 4)[keep]
                # scores are needed while a track or a merge can still reach back to them
                old = seq - self.s.association.merge_window - 2 * self.s.association.k
                self._scores.pop(old, None)
                self._boxes.pop(old, None)
                self.assoc.metres_per_unit = self.metres_per_unit()
                new = self._confirm(self.assoc.add_frame(FrameDetections(seq, P, xy)))
                self.seconds["association"] += time.perf_counter() - t0
            events.append(FrameEvent(f, msg.t_capture, pose, msg, new, self._kf_for_event.pop(f, None)))
            for k in [k for k in self._kf_for_event if k < f]:
                del self._kf_for_event[k]
            self.poses.forget_before(f - 4 * self.s.association.k - 2 * self.s.max_interp_gap)
        return events

    def finish(self, on_events=None) -> list[FrameEvent]:
        """End of the flight: register what is left, release every frame, close every track. ``on_events`` as in
        :meth:`step`."""
        events = []
        if self.poses is not None:
            events += self.step(on_events=on_events)
            self.poses.settle()
        if self.camera is not None:
            events += self.step(final=True, on_events=on_events)
        if self.poses is not None:
            self.poses.close()  # maps what is waiting: the model files are written from it
        elif self._mapping_worker is not None:  # no image ever came
            self._mapping_worker.stop()
        self.assoc.metres_per_unit = self.metres_per_unit()
        self._confirm(self.assoc.finish())
        self._correct(now=True)  # the mapper's last answers
        self._kf_for_event.clear()
        return events

    def views_needed(self) -> int:
        """Strong views an apple needs to count, given how sparse the frames that reach the ground are (the median
        step between the last frames mapped)."""
        if len(self._steps) < 3:
            return self.s.confirm_views
        step = float(np.median(self._steps))
        return max(min(2, self.s.confirm_views), int(np.ceil(self.s.confirm_views / step - 1e-9)))

    def _confirm(self, apples: list[Apple]) -> list[Apple]:
        """Put the apples (new, or updated by a merge) with enough strong views into the map; returns them."""
        out = []
        need = self.views_needed() if apples else 0
        for a in apples:
            strong = sum(int(self._scores[f][d] >= self.s.confirm_score) for f, d in a.observations if f in self._scores)
            # a merge may bring views whose scores were already forgotten: never count down
            strong = self._confirmed[a.id] = max(strong, self._confirmed.get(a.id, 0))
            if strong >= need:
                self.apples[a.id] = a
                r = self._radius(a)
                if np.isfinite(r):
                    self.radius_m[a.id] = r
                out.append(a)
        return out

    def metres_per_unit(self) -> float:
        """The association frame's unit in metres, as the map's georeference knows it now: the frame was fixed by
        the first fit, from a few keyframes' GPS, and the later fits scale it (tens of percent with a DJI log's)."""
        return float(self.poses.assoc_to_enu().scale) if self.poses is not None else 1.0

    def _radius(self, a: Apple) -> float:
        """The apple's radius in the association frame's unit: the median over its views of the box's half-size
        times depth over focal length (compared with the others' median; metres_per_unit() makes it metres)."""
        r = []
        for seq, d in a.observations:
            pose = self.frame_poses.get(self._seq_frame[seq]) if seq < len(self._seq_frame) else None
            if pose is None or seq not in self._boxes:
                continue
            depth = float((pose.R @ a.X + pose.t)[2])
            x0, y0, x1, y1 = self._boxes[seq][d]
            if depth > 0:
                r.append((x1 - x0 + y1 - y0) / 4 * depth / self.camera.fx)
        return float(np.median(r)) if r else float("nan")

    def apple_boxes(self, a: Apple) -> list[tuple[int, np.ndarray]]:
        """(frame, box xyxy in camera pixels) of the apple's detections that are still at hand, in frame order."""
        return sorted(((self._seq_frame[seq], self._boxes[seq][d]) for seq, d in a.observations if seq in self._boxes),
                      key=lambda fb: fb[0])

    # -- results
    def pose_table(self) -> dict[str, np.ndarray]:
        """Every mapped frame's camera: frame, capture time, source, centre (ENU and WGS84), ENU-to-camera quaternion."""
        from scipy.spatial.transform import Rotation

        frames = sorted(self.frame_poses)
        P = [self.frame_poses[f] for f in frames]
        if not P or self.poses is None:
            return {k: np.zeros(0) for k in ("frame", "t_unix", "source", "x", "y", "z", "lat", "lon", "alt",
                                             "qw", "qx", "qy", "qz", "sigma_m")}
        S = self.poses.assoc_to_enu()
        C = S.apply(np.array([p.centre for p in P])) + self.poses.drift_correction(frames, self._drift_sigma_frames())
        R = np.array([p.R for p in P]) @ S.R.T  # ENU-to-camera
        q = Rotation.from_matrix(R).as_quat()  # xyzw
        geo = np.asarray(self.poses.origin.to_geodetic(C)).reshape(-1, 3) if self.poses.origin else np.full(C.shape, np.nan)
        return {"frame": np.array(frames), "t_unix": np.array([self.frame_times.get(f, np.nan) for f in frames]),
                "source": np.array([p.source for p in P], dtype=object), "x": C[:, 0], "y": C[:, 1], "z": C[:, 2],
                "lat": geo[:, 0], "lon": geo[:, 1], "alt": geo[:, 2],
                "qw": q[:, 3], "qx": q[:, 0], "qy": q[:, 1], "qz": q[:, 2],
                "sigma_m": np.array([p.sigma_m for p in P])}

    #: Apples with a radius needed before the size check applies.
    MIN_SIZED = 20
    #: Frames either side of an apple's track (association frames) searched for the views it should have had.
    VIEW_SEARCH = 300
    VIEW_MARGIN_PX = 10

    def expected_views(self, a: Apple, proj: np.ndarray | None = None) -> int:
        """Mapped frames around the apple's track whose camera sees it (in front, inside the image by a margin), in the
        runs of such frames that hold one of its detections: a pass that only flew past it (another pass of a
        whole-plot flight, which may see the other side of the row, where leaves hide it) is not a pass that missed
        it. ``proj``: the camera matrices as one (N, 3, 4) array, when the caller asks for many apples."""
        proj = np.asarray(self._proj).reshape(-1, 3, 4) if proj is None else proj
        lo, hi = max(0, a.first_frame - self.VIEW_SEARCH), min(len(proj), a.last_frame + self.VIEW_SEARCH + 1)
        if hi <= lo:
            return 0
        x = proj[lo:hi] @ np.append(a.X, 1.0)
        z = x[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u, v = x[:, 0] / z, x[:, 1] / z
        m = self.VIEW_MARGIN_PX
        sees = (z > 0.5) & (u > m) & (u < self.camera.width - m) & (v > m) & (v < self.camera.height - m)
        run = np.cumsum(np.diff(sees.astype(np.int8), prepend=0) == 1) * sees  # 1, 2, ... per run of frames; 0 outside
        seen = [f - lo for f, _ in a.observations if lo <= f < hi]
        kept = np.unique(run[seen]) if seen else np.zeros(0, int)
        return int(np.isin(run, kept[kept > 0]).sum())

    def parallax_deg(self, a: Apple) -> float:
        """The angle (degrees) at the apple between the camera centres of its first and last views; NaN (never left
        out) where either frame has no pose."""
        f0, f1 = (self._seq_frame[s] if s < len(self._seq_frame) else None for s in (a.first_frame, a.last_frame))
        p0, p1 = self.frame_poses.get(f0), self.frame_poses.get(f1)
        if p0 is None or p1 is None:
            return float("nan")
        u, v = p0.centre - a.X, p1.centre - a.X
        c = float(u @ v / max(np.linalg.norm(u) * np.linalg.norm(v), 1e-12))
        return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))

    def count_checks(self, all_expected: bool = False) -> dict[str, np.ndarray]:
        """Every confirmed apple and what the counting checks made of it: id, radius (m), observations, strong views,
        expected views (NaN where the check is off or the size check already left the apple out, unless
        ``all_expected``) and ``left_out`` ("" counted, "small" by the size check, "narrow" by the parallax of its
        views, "few_views" by expected views)."""
        ids = sorted(self.apples)
        r = np.array([self.radius_m.get(i, np.nan) for i in ids], float)
        ok = np.isfinite(r)
        reason = np.full(len(ids), "", dtype=object)
        if self.s.min_radius_ratio > 0 and ok.sum() >= self.MIN_SIZED:
            reason[ok & (r < self.s.min_radius_ratio * np.median(r[ok]))] = "small"
        if self.s.min_parallax_deg > 0:
            narrow = np.array([self.parallax_deg(self.apples[i]) < self.s.min_parallax_deg for i in ids], bool)
            reason[(reason == "") & narrow] = "narrow"
        nobs = np.array([self.apples[i].n_observations for i in ids], int)
        expected = np.full(len(ids), np.nan)
        if (self.s.min_view_ratio > 0 or all_expected) and self.camera is not None and ids:
            proj = np.asarray(self._proj).reshape(-1, 3, 4)
            for k, i in enumerate(ids):
                if reason[k] == "" or all_expected:
                    expected[k] = self.expected_views(self.apples[i], proj)
            reason[(reason == "") & (nobs < self.s.min_view_ratio * expected)] = "few_views"
        self.size_rejected = int((reason == "small").sum())
        self.parallax_rejected = int((reason == "narrow").sum())
        self.views_rejected = int((reason == "few_views").sum())
        return {"id": np.array(ids, int), "radius_m": r * self.metres_per_unit(), "observations": nobs,
                "strong_views": np.array([self._confirmed.get(i, 0) for i in ids], int),
                "expected_views": expected, "left_out": reason}

    def counted_ids(self) -> list[int]:
        """The apples that count: those confirmed, less those too small for their size to be whole (size check), those
        whose views meet at too narrow an angle (parallax) and those detected in too few of the frames they lie in
        (expected views)."""
        c = self.count_checks()
        return [int(i) for i in c["id"][c["left_out"] == ""]]

    def candidates(self) -> dict[str, np.ndarray]:
        """count_checks with each apple's position (ENU and WGS84) and first and last frame: every apple the count was
        chosen from."""
        c = self.count_checks(all_expected=True)
        A = [self.apples[i] for i in c["id"]]
        enu = self._enu(A)
        geo = self._geodetic(enu)
        return {**c, "x": enu[:, 0], "y": enu[:, 1], "z": enu[:, 2],
                "lat": geo[:, 0], "lon": geo[:, 1], "alt": geo[:, 2],
                "first_frame": np.array([self._seq_frame[a.first_frame] for a in A], int),
                "last_frame": np.array([self._seq_frame[a.last_frame] for a in A], int)}

    def _drift_sigma_frames(self) -> float:
        return self.s.drift_sigma_s * (self.fps or 0.0)

    def _enu(self, A: list[Apple]) -> np.ndarray:
        """(N, 3) ENU positions of these apples: the map's similarity, then the drift correction averaged over the
        frames each apple was seen in (an apple seen again on a later pass takes both stretches' corrections)."""
        X = np.array([a.X for a in A]).reshape(-1, 3)
        if self.poses is None or not len(X):
            return X
        seen = [[self._seq_frame[sq] for sq, _ in a.observations] for a in A]
        frames = np.unique(np.concatenate(seen))
        off = dict(zip(frames.tolist(), self.poses.drift_correction(frames, self._drift_sigma_frames())))
        return self.poses.to_enu(X) + np.array([np.mean([off[f] for f in fs], 0) for fs in seen])

    def _geodetic(self, enu: np.ndarray) -> np.ndarray:
        """(N, 3) lat, lon, alt of ENU points; NaN before the map is georeferenced."""
        if self.poses is None or self.poses.origin is None or not len(enu):
            return np.full((len(enu), 3), np.nan)
        return np.asarray(self.poses.origin.to_geodetic(enu)).reshape(-1, 3)

    def table(self) -> dict[str, np.ndarray]:
        """Apples as columns: id, x y z (ENU), lat lon alt, row (1..N), radius, observations, reprojection error,
        first/last frame."""
        ids = self.counted_ids()
        A = [self.apples[i] for i in ids]
        enu = self._enu(A)
        geo = self._geodetic(enu)
        rows, direction = direction_rows(enu[:, :2]) if len(A) >= 2 else (np.zeros(len(A), int), 0.0)
        self.row_direction = direction
        return {"id": np.array(ids, int), "x": enu[:, 0], "y": enu[:, 1], "z": enu[:, 2],
                "lat": geo[:, 0], "lon": geo[:, 1], "alt": geo[:, 2],
                "row": np.asarray(rows, int) + 1,  # rows 1..N, left to right looking along the row direction
                "radius_m": np.array([self.radius_m.get(i, np.nan) for i in ids], float) * self.metres_per_unit(),
                "observations": np.array([a.n_observations for a in A], int),
                "reprojection_error_px": np.array([a.reprojection_error for a in A], float),
                "first_frame": np.array([self._seq_frame[a.first_frame] for a in A], int),
                "last_frame": np.array([self._seq_frame[a.last_frame] for a in A], int)}
