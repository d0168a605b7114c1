"""The apples as the frames come: each posed frame's detections go to the windowed association, the apples it finds
go to the counting, and a frame's corrected pose moves the apples seen in it.

    apples = AppleStage(association_params, counting_settings, min_score)
    apples.camera = camera                                  # once the camera message came
    new = apples.take_frame(msg, pose, steps, metres_per_unit)  # a released frame: the apples it confirmed
    apples.repose(corrected_poses, steps, metres_per_unit)  # frame -> corrected pose
    apples.finish(steps, metres_per_unit)                   # end of the flight
    apples.count.apples                                     # id -> Apple (map frame)
"""

from __future__ import annotations

import numpy as np

from ground.apples.association import Apple, AssociationParams, FrameDetections
from ground.apples.windowed import WindowedAssociation
from ground.apples.counting import Counting, CountingSettings
from ground.apples.frames import AssociationFrames
from ground.apples.landmarks import place_by_apples
from pomar import wire


class AppleStage:
    def __init__(self, association: AssociationParams, counting: CountingSettings, min_score: float = 0.0):
        self.assoc = WindowedAssociation(association)
        self.frames = AssociationFrames()  # the frames fed to the association: poses, camera matrices
        self.count = Counting(counting, self.frames, reach=association.merge_window + 2 * association.k)
        self.min_score = min_score  # detections below this score are not used
        self.detections = 0  # detections used

    @property
    def camera(self):
        """The camera (pomar.camera.Camera) once the camera message came: the counting's (its expected views need
        it)."""
        return self.count.camera

    @camera.setter
    def camera(self, camera) -> None:
        self.count.camera = camera

    @property
    def box_response(self) -> tuple[float, float] | None:
        """How the drone's detector's boxes answer an apple's size (the camera message's): the counting's fruit sizes
        take it back."""
        return self.count.box_response

    @box_response.setter
    def box_response(self, response) -> None:
        self.count.box_response = response

    def take_frame(self, msg: wire.FrameMessage, pose, steps, metres_per_unit: float) -> list[Apple]:
        """A posed frame's detections (``steps``: the frame-index steps between the last frames released); returns
        the apples it confirmed."""
        keep = np.asarray(msg.scores) >= self.min_score
        xy = msg.centres[keep]
        self.detections += len(xy)
        P = self.camera.projection_matrix(pose.R, pose.t)
        # The association's window is the next k frames *of the stream*: a real-time onboard node
        # that drops frames sends indices with gaps, so the association counts frames, not indices.
        seq = self.frames.add(msg.frame, pose, P, msg.scale)
        self.assoc.metres_per_unit = metres_per_unit
        fd = FrameDetections(seq, P, xy, np.asarray(msg.boxes, float).reshape(-1, 4)[keep],
                             np.asarray(msg.scores)[keep])
        return self.count.confirm(self.assoc.add_frame(fd), steps)

    def place(self, msg: wire.FrameMessage) -> tuple | None:
        """A frame that no image placed, placed by the apples it sees (:mod:`ground.apples.landmarks`), from the two
        frames fed before it where neither had only its telemetry: its (R, t), or None where that cannot be done."""
        n = self.frames.newest
        before, last = self.frames.pose_at(n - 1), self.frames.pose_at(n)
        if before is None or last is None or "telemetry" in (before.source, last.source):
            return None
        keep = np.asarray(msg.scores) >= self.min_score
        return place_by_apples(self.camera, msg.centres[keep], self.assoc.landmarks(), before, last)

    def repose(self, new: dict, steps, metres_per_unit: float) -> tuple[list[Apple], list[tuple[int, int]]]:
        """Frames fed earlier took corrected poses (frame -> pose): their apples are triangulated again, and merged
        where they turn out to be one apple. Returns (apples moved, (gone, into) merges)."""
        P = {}
        for f, pose in new.items():
            Pf = self.camera.projection_matrix(pose.R, pose.t)
            P[self.frames.correct(f, pose, Pf)] = Pf
        self.assoc.metres_per_unit = metres_per_unit
        changed, merged = self.assoc.repose(P)
        for gone, into in merged:
            self.count.merged(gone, into)
        self.count.confirm(changed, steps)
        return changed, merged

    def finish(self, steps, metres_per_unit: float) -> None:
        """End of the flight: every track closes."""
        self.assoc.metres_per_unit = metres_per_unit
        self.count.confirm(self.assoc.finish(), steps)

    def boxes(self, a: Apple) -> list[tuple[int, np.ndarray]]:
        """(frame, box xyxy in camera pixels) of the apple's detections within the association's reach, in frame
        order."""
        return sorted(((self.frames.frame[o.frame], np.array(o.box)) for o in self.count.in_reach(a)),
                      key=lambda fb: fb[0])
