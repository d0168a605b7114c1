"""The association's settings and records (Santos & Gebler 2021, Section 2.1.3): detections + camera matrices ->
apples in 3-D. The two associations are in :mod:`ground.apples.paper` (the paper's offline Algorithms 1 and 2) and
:mod:`ground.apples.windowed` (the streaming one the ground runs); both score paths by
:mod:`ground.apples.ransac` and merge duplicates by :mod:`ground.apples.merging`."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ground.apples.geometry import triangulate


@dataclass
class AssociationParams:
    k: int = 5  # frames ahead linked in the graph (tolerates k-1 missed detections)
    tau_epipolar: float = 4.0  # px, point-to-epipolar-line gate
    tau_geom: float = 3.0  # px, RANSAC inlier reprojection threshold
    ransac_iterations: int = 50  # RANSAC hypotheses tried per track
    min_inliers: int = 3  # views an apple needs (inliers of its RANSAC triangulation)
    max_paths: int = 500  # offline DFS bound per node
    max_branches: int = 8  # windowed: young hypotheses kept per root detection
    #: One apple seen twice (hidden for more than k frames, then seen again) gives two estimates.
    #: They are merged when their views triangulate together within tau_geom and the estimates are
    #: within merge_search_m (short tracks are uncertain in depth); 0 = off (the paper as is).
    merge_search_m: float = 1.0
    #: Estimates closer than this are one apple, whatever their views say: two apples' centres are at least the sum
    #: of their radii (>= 6 cm) apart, and this is half that. It catches one apple seen from both sides of its row,
    #: whose two caps' centres the views' test can keep apart.
    merge_m: float = 0.03
    #: Windowed: how long (frames) an emitted apple stays a candidate for such a merge.
    merge_window: int = 600
    #: Windowed: every apple of the map stays a candidate (found through a spatial index, so the cost stays flat
    #: as the map grows): an apple seen again from a later pass, minutes after, merges into the first estimate.
    #: False = only apples of the last merge_window frames (one pass's worth).
    cross_pass: bool = True
    #: An apple from another pass (beyond merge_window), or one merging after a pose correction, merges only if the
    #: joint point stays within this of the better-seen of the two (more observations): one apple's two estimates
    #: differ by a cap's offset (at most its radius) and the poses' disagreement (a few cm), while a glimpse of a
    #: neighbour along the other apple's rays can triangulate with its views by pulling it 10 cm or more along them.
    #: 0 = off. Not applied to the other merges within merge_window, where it refused true ones (docs/benchmarks.md).
    max_merge_shift_m: float = 0.08
    #: An apple's final position minimises the reprojection error over its inliers (the linear
    #: solution's depth is biased over the short baselines of a few frames); False = linear only.
    nonlinear: bool = True
    seed: int = 0


@dataclass(frozen=True, order=True)
class Detection:
    """One detection, as an apple keeps it (norfair's ``Detection``): the map frame it was seen in, its
    index there, and the detector's box (xyxy, px; NaN where only the centre is known) and score. Two detections are
    the same when frame and index are."""

    frame: int
    index: int
    box: tuple = field(default=(np.nan,) * 4, compare=False, repr=False)
    score: float = field(default=float("nan"), compare=False)


@dataclass
class FrameDetections:
    """One frame fed to the association: its index (the association counts frames in the order they come), 3x4
    camera matrix, detection centres (N, 2), and the detector's boxes (N, 4) and scores (N,) where known."""

    frame: int
    P: np.ndarray
    xy: np.ndarray
    boxes: np.ndarray | None = None
    scores: np.ndarray | None = None

    def __post_init__(self):
        self.P = np.asarray(self.P, float)
        if self.P.shape != (3, 4) or not np.isfinite(self.P).all():
            raise ValueError(f"frame {self.frame}: P must be a finite 3x4 matrix, got shape {self.P.shape}")
        xy = np.asarray(self.xy, float)
        if xy.size and (xy.ndim != 2 or xy.shape[1] != 2):
            raise ValueError(f"frame {self.frame}: detections must be (N, 2) centres, got shape {xy.shape}")
        self.xy = xy.reshape(-1, 2)
        n = len(self.xy)
        self.boxes = np.full((n, 4), np.nan) if self.boxes is None else np.asarray(self.boxes, float).reshape(n, 4)
        self.scores = np.full(n, np.nan) if self.scores is None else np.asarray(self.scores, float).reshape(n)
        self._records: list[Detection] | None = None

    def detection(self, i: int) -> Detection:
        """The i-th detection's record (made once per frame, shared by every track that takes it)."""
        if self._records is None:
            self._records = [Detection(self.frame, k, tuple(map(float, b)), float(s))
                             for k, (b, s) in enumerate(zip(self.boxes, self.scores))]
        return self._records[i]


@dataclass
class Apple:
    """One apple found: 3-D position (world frame of the P_i) and the detections it was seen as."""

    id: int
    X: np.ndarray
    observations: list[Detection]  # the inliers, in frame order
    reprojection_error: float  # mean over inliers, px
    #: Views kept to test a merge: (V, 3, 4) camera matrices and (V, 2) pixels, a sample of the inliers.
    views: tuple[np.ndarray, np.ndarray] | None = field(default=None, repr=False)
    #: The frames of those views (V,): how a view's camera matrix is found again when the frame's pose is corrected.
    view_frames: np.ndarray | None = field(default=None, repr=False)
    first_frame: int = field(init=False)
    last_frame: int = field(init=False)

    def __post_init__(self):
        frames = [o.frame for o in self.observations]
        self.first_frame, self.last_frame = min(frames), max(frames)

    @property
    def n_observations(self) -> int:
        return len(self.observations)
