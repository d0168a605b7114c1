"""The frames the association was fed, in the order they went: its frame numbers 0, 1, 2 ... (whatever indices the
stream skipped: a real-time onboard node drops frames, and the association counts the frames it got), each one's
frame index, pose and camera matrix, corrected as the mapper moves the keyframes about them, and the scale the drone
resized it by for its detector."""

from __future__ import annotations

import numpy as np


class AssociationFrames:
    def __init__(self):
        self.frame: list[int] = []  # map frame -> frame index
        self.seq: dict[int, int] = {}  # frame index -> map frame
        self.P: list[np.ndarray] = []  # map frame -> camera matrix (map frame of reference)
        self.poses: dict = {}  # frame index -> its pose (ground.poses.stage.Pose), corrected since
        self.scale: list[float] = []  # map frame -> the scale its detector saw it at (wire.FrameMessage.scale)

    def __len__(self) -> int:
        return len(self.frame)

    @property
    def newest(self) -> int:
        """The newest map frame (-1 before the first)."""
        return len(self.frame) - 1

    def add(self, frame: int, pose, P: np.ndarray, scale: float = 1.0) -> int:
        """A frame fed to the association; returns its map frame number."""
        seq = len(self.frame)
        self.frame.append(frame)
        self.scale.append(float(scale))
        self.seq[frame] = seq
        self.P.append(P)
        self.poses[frame] = pose
        return seq

    def correct(self, frame: int, pose, P: np.ndarray) -> int:
        """A fed frame's corrected pose; returns its map frame number."""
        seq = self.seq[frame]
        self.poses[frame] = pose
        self.P[seq] = P
        return seq

    def pose_at(self, seq: int):
        """The pose of an map frame (None where it has none)."""
        return self.poses.get(self.frame[seq]) if 0 <= seq < len(self.frame) else None

    def projections(self) -> np.ndarray:
        """Every map frame's camera matrix, (N, 3, 4)."""
        return np.asarray(self.P).reshape(-1, 3, 4)
