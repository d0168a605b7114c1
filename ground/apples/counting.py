"""Which apples count. The association finds apples; an apple enters the map once enough of its views are strong
(:meth:`Counting.confirm`), and counts unless a check leaves it out (:meth:`Counting.checks`): too small for its size
to be whole, views that meet at too narrow an angle (off by default), or detected in too few of the frames it lies
in.

    count = Counting(CountingSettings(), frames, reach=merge_window + 2 * k)
    count.camera = camera                     # once the camera message came
    count.confirm(apples, steps)              # new or updated apples of the association
    count.counted_ids()                       # the apples that count
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ground.apples.association import Apple, Detection
from ground.apples.frames import AssociationFrames


@dataclass
class CountingSettings:
    #: An apple is counted once at least confirm_views of its views scored confirm_score or more (where the drone
    #: does not say its model's: the former default's threshold). Weaker detections still extend and place it: an
    #: onboard node that sends detections down to 0.7 gives longer tracks without counting apples that
    #: are only ever glimpsed (bundled flight, journal re-run: F1 0.832 -> 0.865, count +4.7 %).
    confirm_score: float = 0.9
    #: Where the drone's camera message gives its model's operating score (its count's confirm score,
    #: pomar.countable.count_scores), confirm at that instead of confirm_score, whichever model flies (issue 70).
    confirm_at_model_score: bool = True
    #: ... at the full frame rate. When the ground gets only every s-th frame (a real-time onboard node
    #: that drops what it cannot detect in time), ceil(confirm_views / s) views, at least 2, are asked
    #: for: an apple is in fewer of the frames sent (real-time replays, journal re-run: bundled flight F1
    #: 0.742 -> 0.776, count -40 % -> -32 %; second flight 0.802 -> 0.852, -30 % -> -20 %). 4 with the shipped
    #: model (issue 70, its count rule on the tuning flights: with 3 views tune-2's 3-D F1 fell 0.02 under the former's).
    confirm_views: int = 4
    #: 3-D size consistency: an apple counts only if its radius (boxes x depth) is at least this fraction of the
    #: median radius of the apples mapped (once MIN_SIZED apples have one); 0 = off. An apple half hidden by
    #: leaves shows a smaller box than it is: partly hidden apples of the far rows, seen through the near row.
    min_radius_ratio: float = 0.8
    #: Expected views: an apple counts only if it was detected in at least this share of the frames it projects
    #: into (the mapped frames around its track); 0 = off. An apple glimpsed through leaves, or a false detection
    #: that happened to triangulate, is seen in few of the frames it lies in.
    min_view_ratio: float = 0.15
    #: Parallax: an apple counts only if the rays from its first and last views meet at this angle or more (degrees);
    #: 0 = off (the default). Views over a narrower angle (a few frames at 30 fps, or the flight's first and last
    #: frames) leave its depth uncertain, but such apples are real ones placed off along their rays, not false ones
    #: (benchmarks/count_rule.py), and the definition counts them: off, the nine tuning flights' count errors came
    #: closer (rms 6.7 -> 5.9 %), the 30-fps flight's F1 fell 0.026.
    min_parallax_deg: float = 0.0


class Counting:
    #: Apples with a radius needed before the size check applies.
    MIN_SIZED = 20
    #: Frames either side of an apple's track (map frames) searched for the views it should have had.
    VIEW_SEARCH = 300
    VIEW_MARGIN_PX = 10

    def __init__(self, settings: CountingSettings, frames: AssociationFrames, reach: int):
        self.s = settings
        self.frames = frames
        self.reach = reach  # map frames back from the newest that an apple's views are judged over
        self.camera = None  # pomar.camera.Camera, once known: the expected views need its size and focal length
        #: how the drone's detector's boxes answer an apple's size (wire.CameraMessage.box_response), once known
        self.box_response: tuple[float, float] | None = None
        #: the drone's model's operating score (wire.CameraMessage.operating_score), once known
        self.model_score: float | None = None
        self.apples: dict[int, Apple] = {}  # confirmed apples, by id
        self.radius: dict[int, float] = {}  # apple id -> radius from its boxes and depths (map frame's unit)
        self.size: dict[int, float] = {}  # apple id -> the fruit's radius, from its least hidden views (map's unit)
        self.strong: dict[int, int] = {}  # apple id -> views scored confirm_score or more
        self.size_rejected = 0  # confirmed apples left out of the map by the size check (counted_ids)
        self.views_rejected = 0  # ... by the expected views
        self.parallax_rejected = 0  # ... and by the parallax of their views

    @property
    def confirm_score(self) -> float:
        """The score a view needs to confirm an apple: the drone's model's own operating score where its camera
        message says it (and confirm_at_model_score), else confirm_score."""
        if self.s.confirm_at_model_score and self.model_score is not None:
            return float(self.model_score)
        return self.s.confirm_score

    def views_needed(self, steps) -> int:
        """Strong views an apple needs to count, given how sparse the frames that reach the ground are (``steps``:
        the frame-index steps between the last frames mapped)."""
        if len(steps) < 3:
            return self.s.confirm_views
        step = float(np.median(steps))
        return max(min(2, self.s.confirm_views), int(np.ceil(self.s.confirm_views / step - 1e-9)))

    def confirm(self, apples: list[Apple], steps) -> list[Apple]:
        """Put the apples (new, or updated by a merge) with enough strong views into the map; returns them."""
        out = []
        need = self.views_needed(steps) if apples else 0
        threshold = np.float32(self.confirm_score)  # scores are float32 on the wire: compared as such
        for a in apples:
            strong = sum(int(np.float32(o.score) >= threshold) for o in self.in_reach(a))
            # a merge may bring views from beyond the association's reach: never count down
            strong = self.strong[a.id] = max(strong, self.strong.get(a.id, 0))
            if strong >= need:
                self.apples[a.id] = a
                r, size = self.radius_of(a)
                if np.isfinite(r):
                    self.radius[a.id], self.size[a.id] = r, size
                out.append(a)
        return out

    def merged(self, gone: int, into: int) -> None:
        """Apple ``gone`` merged into ``into``: its strong views go with it, it leaves the map."""
        self.strong[into] = max(self.strong.get(into, 0), self.strong.pop(gone, 0))
        self.apples.pop(gone, None)
        self.radius.pop(gone, None)
        self.size.pop(gone, None)

    def in_reach(self, a: Apple) -> list[Detection]:
        """The apple's views within the association's reach (``reach`` frames back from the newest): the ones its
        strong views and size are judged from, as its tracks and merges bring them."""
        oldest = self.frames.newest - self.reach
        return [o for o in a.observations if o.frame > oldest]

    def radius_of(self, a: Apple) -> tuple[float, float]:
        """The apple's radius in the map frame's unit from its views' boxes (half-size times depth over focal length):
        the median over its views (how whole it usually looked: the size check compares it with the others'), and the
        fruit's size, the median of its largest tenth (the largest of fewer than 20). Leaves only ever shrink a box (a
        box of an apple half hidden is 0.8 of its radius, of one wholly seen 1.0, on the tuning flights), so the least
        hidden views give its size; on a long track their median, not the maximum, keeps one loose box from setting it
        (on issue 59's tuning flights: 1 % small, where the largest third read 4 % small). The boxes are first taken back
        through the detector's box response (at the scale it saw each frame), which pulls sizes towards a middle one
        (0.84 x radius + 0.9 px for the shipped model): else a row's fruit would read by its distance from the camera.
        NaN, NaN without a posed view."""
        r, size = [], []
        slope, icpt = self.box_response or (1.0, 0.0)
        for o in self.in_reach(a):
            pose = self.frames.pose_at(o.frame)
            if pose is None:
                continue
            depth = float((pose.R @ a.X + pose.t)[2])
            x0, y0, x1, y1 = o.box
            if depth > 0:
                half, s = (x1 - x0 + y1 - y0) / 4, self.frames.scale[o.frame]
                r.append(half * depth / self.camera.fx)
                size.append(max(half * s - icpt, 0.0) / slope / s * depth / self.camera.fx)
        if not r:
            return float("nan"), float("nan")
        return float(np.median(r)), float(np.median(np.sort(size)[-max(1, len(size) // 10):]))

    def expected_views(self, a: Apple, proj: np.ndarray | None = None) -> int:
        """Mapped frames around the apple's track whose camera sees it (in front, inside the image by a margin), in the
        runs of such frames that hold one of its detections: a pass that only flew past it (another pass of a
        whole-plot flight, which may see the other side of the row, where leaves hide it) is not a pass that missed
        it. ``proj``: the camera matrices as one (N, 3, 4) array, when the caller asks for many apples."""
        proj = self.frames.projections() if proj is None else proj
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
        seen = [o.frame - lo for o in a.observations if lo <= o.frame < hi]
        kept = np.unique(run[seen]) if seen else np.zeros(0, int)
        return int(np.isin(run, kept[kept > 0]).sum())

    def parallax_deg(self, a: Apple) -> float:
        """The angle (degrees) at the apple between the camera centres of its first and last views; NaN (never left
        out) where either frame has no pose."""
        p0, p1 = self.frames.pose_at(a.first_frame), self.frames.pose_at(a.last_frame)
        if p0 is None or p1 is None:
            return float("nan")
        u, v = p0.centre - a.X, p1.centre - a.X
        c = float(u @ v / max(np.linalg.norm(u) * np.linalg.norm(v), 1e-12))
        return float(np.degrees(np.arccos(np.clip(c, -1.0, 1.0))))

    def checks(self, all_expected: bool = False) -> dict[str, np.ndarray]:
        """Every confirmed apple and what the checks made of it: id, radius (map frame's unit), observations,
        strong views, expected views (NaN where the check is off or the size check already left the apple out, unless
        ``all_expected``) and ``left_out`` ("" counted, "small" by the size check, "narrow" by the parallax of its
        views, "few_views" by expected views)."""
        ids = sorted(self.apples)
        r = np.array([self.radius.get(i, np.nan) for i in ids], float)
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
            proj = self.frames.projections()
            for k, i in enumerate(ids):
                if reason[k] == "" or all_expected:
                    expected[k] = self.expected_views(self.apples[i], proj)
            reason[(reason == "") & (nobs < self.s.min_view_ratio * expected)] = "few_views"
        self.size_rejected = int((reason == "small").sum())
        self.parallax_rejected = int((reason == "narrow").sum())
        self.views_rejected = int((reason == "few_views").sum())
        return {"id": np.array(ids, int), "radius": r, "observations": nobs,
                "strong_views": np.array([self.strong.get(i, 0) for i in ids], int),
                "expected_views": expected, "left_out": reason}

    def counted_ids(self) -> list[int]:
        """The apples that count: those confirmed, less those too small for their size to be whole (size check), those
        whose views meet at too narrow an angle (parallax) and those detected in too few of the frames they lie in
        (expected views)."""
        c = self.checks()
        return [int(i) for i in c["id"][c["left_out"] == ""]]

    def report(self) -> dict:
        """The counting's part of report.json."""
        return {"confirmed": len(self.apples), "confirm_score": self.confirm_score,
                "confirm_score_from": ("the drone's model (its operating score)" if self.s.confirm_at_model_score
                                       and self.model_score is not None else "the ground's setting"),
                "min_radius_ratio": self.s.min_radius_ratio,
                "left_out_small": self.size_rejected, "min_view_ratio": self.s.min_view_ratio,
                "left_out_few_views": self.views_rejected,
                "min_parallax_deg": self.s.min_parallax_deg, "left_out_narrow": self.parallax_rejected}
