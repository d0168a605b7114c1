"""Split an apple map into tree rows.

* :func:`kmeans_rows` — the paper's way: K-means on the horizontal positions, K given.
* :func:`direction_rows` — uses what rows are, parallel lines: estimate the row direction (the
  direction along which the apples' across-row coordinate is most concentrated), then split the
  across-row coordinate at the gaps between rows. Needs no K.

Both return labels 0..R-1 ordered across the rows (left to right looking along the row direction).
"""

from __future__ import annotations

import numpy as np
from sklearn.cluster import KMeans


def _order_labels(labels: np.ndarray, across: np.ndarray) -> np.ndarray:
    uniq = np.unique(labels)
    centres = np.array([np.median(across[labels == u]) for u in uniq])
    rank = {u: r for r, u in enumerate(uniq[np.argsort(centres)])}
    return np.array([rank[u] for u in labels], dtype=np.int64)


def row_direction(xy: np.ndarray, step_deg: float = 0.25, bin_m: float = 0.25) -> float:
    """Azimuth (radians, in ENU, from +x) of the rows: the direction that makes the histogram of the
    across-row coordinate sharpest (lowest entropy)."""
    xy = np.asarray(xy, float)
    xy = xy - np.median(xy, 0)
    best, best_h = 0.0, np.inf
    for a in np.radians(np.arange(0.0, 180.0, step_deg)):
        across = xy @ np.array([-np.sin(a), np.cos(a)])
        # the histogram spans the central 99 % of the apples: one wild estimate far away would otherwise ask for
        # millions of bins (gigabytes) and flatten the rest into one
        lo, hi = np.percentile(across, [0.5, 99.5])
        hist, _ = np.histogram(across, bins=max(2, int((hi - lo) / bin_m) + 1), range=(lo, hi + 1e-9))
        pr = hist[hist > 0] / len(across)
        h = -(pr * np.log(pr)).sum()
        if h < best_h:
            best, best_h = a, h
    return float(best)


def direction_rows(xy: np.ndarray, min_gap_m: float = 1.0, direction: float | None = None,
                   min_share: float = 0.02) -> tuple[np.ndarray, float]:
    """Row labels from the row direction and the gaps between rows; returns (labels, direction).

    Groups holding less than ``min_share`` of the apples (stray estimates between rows) join the
    nearest row."""
    xy = np.asarray(xy, float)
    if len(xy) == 0:
        return np.zeros(0, np.int64), 0.0
    a = row_direction(xy) if direction is None else direction
    across = xy @ np.array([-np.sin(a), np.cos(a)])
    order = np.argsort(across)
    gaps = np.diff(across[order]) > min_gap_m
    labels = np.empty(len(xy), np.int64)
    labels[order] = np.concatenate([[0], np.cumsum(gaps)])
    uniq, counts = np.unique(labels, return_counts=True)
    big = uniq[counts >= max(1, min_share * len(xy))]
    if 0 < len(big) < len(uniq):
        centres = np.array([np.median(across[labels == u]) for u in big])
        small = ~np.isin(labels, big)
        labels[small] = big[np.argmin(np.abs(across[small, None] - centres[None]), axis=1)]
    return _order_labels(labels, across), a


def kmeans_rows(xy: np.ndarray, n_rows: int, seed: int = 0) -> np.ndarray:
    """The paper's K-means on horizontal positions, labels ordered across the rows (by the first principal axis's normal)."""
    xy = np.asarray(xy, float)
    if len(xy) == 0:
        return np.zeros(0, np.int64)
    n_rows = max(1, min(n_rows, len(xy)))
    labels = KMeans(n_clusters=n_rows, n_init=10, random_state=seed).fit_predict(xy)
    a = row_direction(xy)
    return _order_labels(labels, xy @ np.array([-np.sin(a), np.cos(a)]))
