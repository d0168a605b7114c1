"""Incremental registration with real pycolmap on a short simulated flight."""

from __future__ import annotations

import csv
import shutil
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import ROOT


@pytest.fixture(scope="module")
def reg_flight(tmp_path_factory):
    """A 480x270 flight of 23 frames with frame 12 blanked (unregisterable)."""
    import imageio_ffmpeg

    from pomar.flight import FlightDir
    from pomar.video import iter_frames
    from sim import config
    from sim.flight import simulate_flight

    base = tmp_path_factory.mktemp("reg")
    simulate_flight(config.load(ROOT / "sim" / "configs" / "register-test.toml"), base / "flight", jobs=2, progress=False)
    fl = FlightDir(base / "flight")
    blank = base / "blank"
    shutil.copytree(fl.path, blank)
    meta = fl.meta()
    w = imageio_ffmpeg.write_frames(str(blank / "video.mp4"), (meta.width, meta.height), fps=meta.fps, codec="libx264",
                                    pix_fmt_in="bgr24", quality=None, macro_block_size=2, ffmpeg_log_level="error",
                                    output_params=["-crf", "18"])
    w.send(None)
    for i, img in iter_frames(fl.video):
        w.send(np.zeros_like(img) if i == 12 else img)
    w.close()
    return FlightDir(blank)


def read_poses(path: Path):
    with open(path) as f:
        return list(csv.DictReader(f))


def test_registers_georeferences_and_falls_back_to_telemetry(reg_flight, tmp_path):
    from ground.register_flight import register_flight

    res = register_flight(reg_flight.path, tmp_path / "a", every=1, max_interp_gap=1)
    rows = read_poses(tmp_path / "a" / "poses.csv")
    assert len(rows) == reg_flight.meta().frame_count
    assert rows[12]["source"] == "telemetry"  # the blank frame: flagged as a telemetry pose
    assert sum(r["source"] == "registered" for r in rows) >= 20
    assert res["registered_fraction"] > 0.9
    # georeferenced in ENU within a loose bound: rotation well under a degree; position within the GPS error
    assert res["rotation_error_median_deg"] < 0.5
    assert res["position_error_median_m"] < 4.0
    assert res["position_error_median_without_mean_offset_m"] < 0.15
    assert float(rows[12]["sigma_m"]) > float(rows[11]["sigma_m"])  # a telemetry pose is less certain
    assert (tmp_path / "a" / "model" / "0" / "images.txt").exists()


def test_unregistered_frame_between_registered_ones_is_interpolated(reg_flight, tmp_path):
    from ground.register_flight import register_flight

    res = register_flight(reg_flight.path, tmp_path / "b", every=1, max_interp_gap=4)
    rows = read_poses(tmp_path / "b" / "poses.csv")
    assert rows[12]["source"] == "interpolated"
    assert res["by_source"]["interpolated"]["rotation_error_median_deg"] < 0.5


def test_colmap_sift_registers_too(reg_flight, tmp_path):
    """The mapper reads only keypoints and verified matches: COLMAP's own SIFT still works in their place."""
    from ground.register_flight import register_flight
    from ground.registration import RegistrationSettings

    res = register_flight(reg_flight.path, tmp_path / "c", every=1, settings=RegistrationSettings(sift="colmap"),
                          progress=False, frames_limit=12)
    assert res["registered_fraction"] > 0.9
    assert res["rotation_error_median_deg"] < 0.5


def test_finished_submodels_leave_memory_and_come_back_for_the_model_files(reg_flight, tmp_path):
    """Sub-models of 8 keyframes, one kept in memory: the older ones are written out, their poses kept, and the
    final model files hold every sub-model, read back."""
    from ground.register_flight import register_flight
    from ground.registration import RegistrationSettings

    s = RegistrationSettings(submodel_size=8, overlap=4, keep_submodels=1)
    all_in = register_flight(reg_flight.path, tmp_path / "all", every=1, progress=False,
                             settings=RegistrationSettings(submodel_size=8, overlap=4, keep_submodels=99))
    res = register_flight(reg_flight.path, tmp_path / "d", every=1, settings=s, progress=False)
    assert res["submodels"] >= 3
    written = sorted((tmp_path / "d" / "work" / "submodels").iterdir())
    assert len(written) == res["submodels"] - 1
    # the poses as with every sub-model in memory (RANSAC is seeded: runs repeat; the bound leaves room for the
    # order of a multi-threaded bundle adjustment's sums)
    assert res["registered_fraction"] == all_in["registered_fraction"]
    assert abs(res["rotation_error_median_deg"] - all_in["rotation_error_median_deg"]) < 0.01
    for k in range(res["submodels"]):
        assert (tmp_path / "d" / "model" / str(k) / "images.txt").exists()
