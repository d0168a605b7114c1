"""A whole-plot flight in small (issue 16): two passes over the same rows with a turn between them, through both
processes (truth detections, zenoh on loopback, pycolmap), scored against the flight's truth."""

from __future__ import annotations

import csv
import json
import subprocess
import sys

import numpy as np
import pytest

from tests.conftest import ROOT


@pytest.fixture(scope="module")
def two_pass_flight(tmp_path_factory):
    from pomar.flight import FlightDir
    from sim import config
    from sim.flight import simulate_flight

    path = tmp_path_factory.mktemp("two-pass") / "flight"
    simulate_flight(config.load(ROOT / "sim" / "configs" / "two-pass-test.toml"), path, jobs=2, progress=False)
    return FlightDir(path)


def test_two_passes_count_every_apple_once_and_keep_one_model(two_pass_flight, tmp_path):
    out = tmp_path / "out"
    subprocess.run([sys.executable, "-m", "ground", "replay", str(two_pass_flight.path), "--detector", "truth-replay",
                    "--out", str(out), "--quiet"], check=True, cwd=ROOT, stdout=subprocess.DEVNULL, timeout=600)
    rep = json.loads((out / "report.json").read_text())
    reg, ev = rep["registration"], rep["evaluation"]
    # the turn keeps one model: one sub-model, nothing re-joined, every keyframe after the turn registered; the
    # second pass matched keyframes of the first where they look at the same place
    assert reg["submodels"] == 1 and reg["rejoined"] == 0 and reg["revisits"] >= 1
    assert rep["pose_shares"]["telemetry"] == 0
    # the poses given out were corrected as the mapper refined the keyframes, and the apples seen in them with them
    assert rep["corrections"]["frames"] > 0 and rep["corrections"]["apples_moved"] > 0
    # every apple once: none counted twice, and many of them seen from both passes (the frames on either side of
    # the turn, where the drone's direction along the rows reverses)
    assert ev["duplicates"] == 0
    assert ev["precision"] >= 0.95 and ev["recall"] >= 0.75
    fr = two_pass_flight.truth_frames()
    along = two_pass_flight.origin().to_enu(fr["lat"], fr["lon"], fr["alt"])[:, 1]
    turn = int(np.argmax(np.diff(along) < 0))
    with open(out / "apples.csv") as f:
        both = [r for r in csv.DictReader(f) if int(r["first_frame"]) < turn - 5 and int(r["last_frame"]) > turn + 5]
    assert len(both) >= 10
