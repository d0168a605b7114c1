"""What a countable apple is, for every label and score in the project: an apple at least MIN_VISIBLE visible (the
share of its disc not hidden by leaves, branches or other apples) in at least MIN_VIEWS frames.

- The simulator's truth counts these (``countable_ids``); ``ground replay``'s scoring, ``ground evaluate``,
  ``export evaluate`` and the benchmarks score against them.
- The detector is taught the same: in simulated frames an apple at least MIN_VISIBLE visible is a box to find, and
  any less visible apple is background (``export/train.py`` has no ignore regions). Its scores (``export evaluate``)
  leave the apples between IGNORE_ABOVE and MIN_VISIBLE out, neither found nor missed, and say what share of them it
  finds (``partial``).
- MIN_VIEWS: fewer views cannot be triangulated by the paper's RANSAC (three at least).

MIN_VISIBLE is the scoring threshold every figure so far was measured at. ADD256's annotators circled apples about
40 % visible and more (``benchmarks/label_visibility.py``): close to it. The shipped detector (the GPU-trained one of
2026-11-27) is the first trained on this definition; the one before took apples from 35 % visible as boxes.
"""

from __future__ import annotations

import numpy as np

#: An apple counts in a frame when at least this share of it is visible ...
MIN_VISIBLE = 0.5
#: ... and in the flight when it does in at least this many frames.
MIN_VIEWS = 3
#: In the detector's scores, apples less visible than MIN_VISIBLE but at least this visible are ignored (neither
#: found nor missed); training takes them as background.
IGNORE_ABOVE = 0.05
#: The onboard node publishes the detections scored at least this, whichever way it is started (``onboard run``,
#: ``onboard live``, ``ground replay``'s node): those under the count's confirm score (ground.apples.counting) extend
#: the tracks, and the count decides which apples count. The camera message says what the drone sent; a ground given
#: less says so in its log and report.json.
PUBLISH_SCORE = 0.7
#: ... and, for a model whose operating score (its JSON's ``score_thresh``, where the count confirms) lies closer to it,
#: from this far below that score: the band of weak views the tracks were tuned with (0.7 under the default's 0.9). A
#: model confirming at 0.75 and publishing from 0.7 lost 2-4 % of each tuning flight's 3-D F1 (docs/benchmarks.md).
PUBLISH_BELOW = 0.2


def publish_score(operating_score: float | None) -> float:
    """The score the onboard node publishes detections from, for a model of this operating score (None: unknown):
    PUBLISH_SCORE, or PUBLISH_BELOW under the operating score where that is lower."""
    if operating_score is None:
        return PUBLISH_SCORE
    return max(0.0, min(PUBLISH_SCORE, float(operating_score) - PUBLISH_BELOW))


def count_scores(meta: dict) -> tuple[float | None, float]:
    """(confirm, publish) for a detector of this metadata: the score a view needs to confirm an apple in the count
    (the camera message's operating score) and the score the drone publishes detections from. A model's ``count``
    gives both where they were chosen on tuning flights for it (issue 70: a model's single-photo threshold,
    ``score_thresh``, is not where its maps count best); else the count confirms at ``score_thresh`` and publishes
    from :func:`publish_score` of it."""
    count = meta.get("count") or {}
    confirm = count.get("confirm_score", meta.get("score_thresh"))
    confirm = None if confirm is None else float(confirm)
    publish = count.get("publish_score")
    return confirm, float(publish) if publish is not None else publish_score(confirm)


def visible(visible_fraction) -> np.ndarray:
    """Which detections of the truth (their ``visible_fraction``) show a countable apple in their frame."""
    return np.asarray(visible_fraction, float) >= MIN_VISIBLE


def countable_ids(apple_id, visible_fraction, min_visible: float = MIN_VISIBLE, min_views: int = MIN_VIEWS) -> np.ndarray:
    """The ids of the apples a flight's truth detections (one row per apple and frame) count: at least ``min_visible``
    visible in at least ``min_views`` frames (the definition's, unless a study asks for another)."""
    ok = np.asarray(visible_fraction, float) >= min_visible
    ids, n = np.unique(np.asarray(apple_id)[ok], return_counts=True)
    return ids[n >= min_views]
