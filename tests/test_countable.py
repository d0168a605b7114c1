"""One definition of a countable apple (pomar.countable): the detector's training labels, the simulator's truth as the
scorer counts it, and the truth-replay detector agree with it, and no other visibility threshold is written."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from pomar.countable import IGNORE_ABOVE, MIN_VIEWS, MIN_VISIBLE, countable_ids

ROOT = Path(__file__).resolve().parents[1]

# a visibility threshold or a views count written as a number: `visible_fraction"] >= 0.5`, `min_visible=0.35`,
# `min_visible: float = 0.5`, `truth_min_views: int = 3`, `min_views=3`
LITERAL = re.compile(r"visible_fraction\"?\]?\s*>=?\s*0?\.\d|min_visible\s*(:\s*float\s*)?=\s*0?\.\d"
                     r"|min_views\s*(:\s*int\s*)?=\s*\d")


def test_no_other_threshold_is_written():
    found = []
    for pkg in ("pomar", "onboard", "ground", "export", "sim", "benchmarks"):
        for p in (ROOT / pkg).rglob("*.py"):
            if p.name == "countable.py" and p.parent.name == "pomar":
                continue
            for n, line in enumerate(p.read_text().splitlines(), 1):
                if LITERAL.search(line):
                    found.append(f"{p.relative_to(ROOT)}:{n}: {line.strip()}")
    assert not found, "\n".join(found)


def test_labels_truth_and_scorer_agree(bundled_flight):
    """On the bundled flight (simulated, with its truth): the training's boxes to find are the truth's detections at
    least MIN_VISIBLE visible, its ignored ones those between IGNORE_ABOVE and it; the scorer counts the apples
    countable_ids gives (and finds every one of them where they are); the truth-replay detector sends the same boxes
    the training takes."""
    from export.data import sim_frame_boxes
    from ground.evaluation.scoring import score_map
    from onboard.replay_detector import TruthReplayDetector

    d = bundled_flight.truth_detections()
    vis = d["visible_fraction"]
    boxes = sim_frame_boxes(bundled_flight.path)
    det = TruthReplayDetector(bundled_flight.path)
    for f in np.unique(d["frame"]):
        sel = d["frame"] == f
        pos, ign = boxes.get(int(f), (np.zeros((0, 4)), np.zeros((0, 4))))
        assert len(pos) == int((sel & (vis >= MIN_VISIBLE)).sum())
        assert len(ign) == int((sel & (vis >= IGNORE_ABOVE) & (vis < MIN_VISIBLE)).sum())
        assert len(det.detect(int(f))[0]) == len(pos)
    ids = countable_ids(d["apple_id"], vis)
    seen = {i: n for i, n in zip(*np.unique(d["apple_id"][vis >= MIN_VISIBLE], return_counts=True))}
    assert set(ids.tolist()) == {i for i, n in seen.items() if n >= MIN_VIEWS}
    a = bundled_flight.truth_apples()
    xyz = np.stack([a["x"], a["y"], a["z"]], 1)[np.isin(a["apple_id"], ids)]
    s = score_map(bundled_flight, xyz)
    assert s["truth_count"] == len(ids) and s["count"] == len(ids) and s["recall"] == 1.0
