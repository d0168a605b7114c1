"""Counting baselines the method is compared with, on the same detections.

* :func:`count_per_frame_sum` — the sum of per-frame detections (every apple counted once per frame).
* :class:`SortTracker` — a 2-D multi-object tracker in the image (SORT-style: constant-velocity
  prediction, Hungarian matching on centre distance, tracks dropped after ``max_age`` missed frames);
  the count is the number of track ids confirmed by ``min_hits`` detections.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment


def count_per_frame_sum(frames_xy: list[np.ndarray]) -> int:
    return int(sum(len(x) for x in frames_xy))


class SortTracker:
    def __init__(self, max_distance_px: float = 20.0, max_age: int = 5, min_hits: int = 3):
        self.max_distance_px = max_distance_px
        self.max_age = max_age
        self.min_hits = min_hits
        self._pos = np.zeros((0, 2))
        self._vel = np.zeros((0, 2))
        self._age = np.zeros(0, int)
        self._hits = np.zeros(0, int)
        self._ids = np.zeros(0, int)
        self._next = 0
        self.confirmed: set[int] = set()

    def update(self, xy: np.ndarray) -> None:
        xy = np.asarray(xy, float).reshape(-1, 2)
        pred = self._pos + self._vel
        matched_t = np.zeros(len(pred), bool)
        matched_d = np.zeros(len(xy), bool)
        if len(pred) and len(xy):
            d = np.linalg.norm(pred[:, None] - xy[None], axis=2)
            r, c = linear_sum_assignment(np.where(d < self.max_distance_px, d, 1e6))
            ok = d[r, c] < self.max_distance_px
            r, c = r[ok], c[ok]
            self._vel[r] = 0.5 * self._vel[r] + 0.5 * (xy[c] - self._pos[r])
            self._pos[r] = xy[c]
            self._age[r] = 0
            self._hits[r] += 1
            matched_t[r], matched_d[c] = True, True
        self._pos[~matched_t] = pred[~matched_t]
        self._age[~matched_t] += 1
        new = xy[~matched_d]
        self._pos = np.concatenate([self._pos, new])
        # new tracks start with the mean velocity of the matched ones (the whole image moves together)
        v0 = self._vel[matched_t].mean(0) if matched_t.any() else np.zeros(2)
        self._vel = np.concatenate([self._vel, np.tile(v0, (len(new), 1))])
        self._age = np.concatenate([self._age, np.zeros(len(new), int)])
        self._hits = np.concatenate([self._hits, np.ones(len(new), int)])
        self._ids = np.concatenate([self._ids, np.arange(self._next, self._next + len(new))])
        self._next += len(new)
        self.confirmed.update(self._ids[self._hits >= self.min_hits].tolist())
        keep = self._age <= self.max_age
        self._pos, self._vel, self._age, self._hits, self._ids = (a[keep] for a in (self._pos, self._vel, self._age, self._hits, self._ids))

    @property
    def count(self) -> int:
        return len(self.confirmed)
