"""Incremental registration with real pycolmap on a short simulated flight."""

from __future__ import annotations

import csv
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from tests.conftest import ROOT


@pytest.fixture(scope="module")
def reg_base(tmp_path_factory):
    """A 480x270 flight of 23 frames (5 fps, 8 m of one pass)."""
    from sim import config
    from sim.flight import simulate_flight

    base = tmp_path_factory.mktemp("reg")
    simulate_flight(config.load(ROOT / "sim" / "configs" / "register-test.toml"), base / "flight", jobs=2, progress=False)
    return base / "flight"


def blanked(src: Path, dst: Path, frames: range):
    """A copy of the flight whose video has the given frames black (nothing to register)."""
    import imageio_ffmpeg

    from pomar.flight import FlightDir
    from pomar.video import iter_frames

    fl = FlightDir(src)
    shutil.copytree(fl.path, dst)
    meta = fl.meta()
    w = imageio_ffmpeg.write_frames(str(dst / "video.mp4"), (meta.width, meta.height), fps=meta.fps, codec="libx264",
                                    pix_fmt_in="bgr24", quality=None, macro_block_size=2, ffmpeg_log_level="error",
                                    output_params=["-crf", "18"])
    w.send(None)
    for i, img in iter_frames(fl.video):
        w.send(np.zeros_like(img) if i in frames else img)
    w.close()
    return FlightDir(dst)


@pytest.fixture(scope="module")
def reg_flight(reg_base):
    """The flight with frame 12 blanked (unregisterable)."""
    return blanked(reg_base, reg_base.parent / "blank", range(12, 13))


@pytest.fixture(scope="module")
def gap_flight(reg_base):
    """The flight with frames 6-14 blanked: more keyframes in a row than the matching window, as a turn over bare
    ground would leave."""
    return blanked(reg_base, reg_base.parent / "gap", range(6, 15))


def read_poses(path: Path):
    with open(path) as f:
        return list(csv.DictReader(f))


def test_registers_georeferences_and_falls_back_to_telemetry(reg_flight, tmp_path):
    from ground.evaluation.register_flight import register_flight

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
    from ground.evaluation.register_flight import register_flight

    res = register_flight(reg_flight.path, tmp_path / "b", every=1, max_interp_gap=4)
    rows = read_poses(tmp_path / "b" / "poses.csv")
    assert rows[12]["source"] == "interpolated"
    assert res["by_source"]["interpolated"]["rotation_error_median_deg"] < 0.5


def test_colmap_sift_registers_too(reg_flight, tmp_path):
    """The mapper reads only keypoints and verified matches: COLMAP's own SIFT still works in their place."""
    from ground.evaluation.register_flight import register_flight
    from ground.poses.registration import RegistrationSettings

    res = register_flight(reg_flight.path, tmp_path / "c", every=1, settings=RegistrationSettings(sift="colmap"),
                          progress=False, frames_limit=12)
    assert res["registered_fraction"] > 0.9
    assert res["rotation_error_median_deg"] < 0.5


def test_a_matching_window_wider_than_the_revisits_gap_registers_every_keyframe(reg_base, tmp_path):
    """Keyframes of the matching window are not matched again as revisits: with ``match_window`` 10 (the default; the
    revisits look 8 keyframes back) the same pair was written twice, and every keyframe from the ninth on failed on
    the database's constraint."""
    from ground.evaluation.register_flight import register_flight
    from ground.poses.registration import RegistrationSettings

    res = register_flight(reg_base, tmp_path / "w", every=1, settings=RegistrationSettings(match_window=10),
                          progress=False, frames_limit=14)
    assert res["registered_fraction"] == 1.0


def test_finished_submodels_leave_memory_and_come_back_for_the_model_files(reg_flight, tmp_path):
    """Sub-models of 8 keyframes, one kept in memory: the older ones are written out, their poses kept, and the
    final model files hold every sub-model, read back."""
    from ground.evaluation.register_flight import register_flight
    from ground.poses.registration import RegistrationSettings

    s = RegistrationSettings(submodel_size=8, overlap=4, keep_submodels=1)
    all_in = register_flight(reg_flight.path, tmp_path / "all", every=1, progress=False,
                             settings=RegistrationSettings(submodel_size=8, overlap=4, keep_submodels=99))
    res = register_flight(reg_flight.path, tmp_path / "d", every=1, settings=s, progress=False)
    assert res["submodels"] >= 3
    written = sorted((tmp_path / "d" / "work" / "submodels").iterdir())
    assert len(written) == res["submodels"] - 1
    # the poses exactly as with every sub-model in memory: how many stay in memory moves nothing (RANSAC is seeded,
    # bundle adjustment runs on one thread; a chain that breaks is placed by the same sub-models either way)
    assert res["registered_fraction"] == all_in["registered_fraction"]
    assert res["rotation_error_median_deg"] == all_in["rotation_error_median_deg"]
    assert res["position_error_median_m"] == all_in["position_error_median_m"]
    for k in range(res["submodels"]):
        assert (tmp_path / "d" / "model" / str(k) / "images.txt").exists()


def test_every_sub_model_keeps_the_calibrated_focal_length(reg_base, tmp_path):
    """The camera is calibrated: no sub-model's start may estimate another focal length. Live, on a 92-s flight cut
    for 30 s, sub-models started with one 3-12 % off (that run's keyframes, mapped again in its order, gave 1150.6 px
    for 1029.4 at the second sub-model's first keyframe), and the frames tracked against them sat 0.3 m off along the
    view. The database's camera says its focal length is known (COLMAP then never estimates it), and every sub-model
    written keeps it; this short flight's sub-models keep it either way."""
    import pycolmap

    from ground.evaluation.register_flight import register_flight
    from ground.poses.registration import RegistrationSettings
    from pomar.flight import FlightDir

    res = register_flight(reg_base, tmp_path / "d", every=1, progress=False,
                          settings=RegistrationSettings(submodel_size=6, overlap=3, keep_submodels=99))
    assert res["submodels"] >= 3
    db = pycolmap.Database.open(str(next((tmp_path / "d" / "work").rglob("*.db"))))
    cams = db.read_all_cameras()
    db.close()
    assert cams and all(c.has_prior_focal_length for c in cams)
    fx = FlightDir(reg_base).camera().fx
    for k in range(res["submodels"]):
        for line in (tmp_path / "d" / "model" / str(k) / "cameras.txt").read_text().splitlines():
            if not line.startswith("#"):
                # the keyframes' camera: the flight's, scaled to the keyframes' width
                focal, width = float(line.split()[4]), int(line.split()[2])
                assert focal == pytest.approx(fx * width / FlightDir(reg_base).camera().width, rel=1e-9)


def _offset_before_and_after(flight, out: Path, gap: range):
    """Mean ENU error of the registered frames before the gap and after it (the GPS bias the map shares)."""
    rows = read_poses(out / "poses.csv")
    o, fr = flight.origin(), flight.truth_frames()
    est = o.to_enu(*(np.array([float(r[k]) for r in rows]) for k in ("lat", "lon", "alt")))
    err = est - o.to_enu(fr["lat"], fr["lon"], fr["alt"])
    reg = np.array([r["source"] == "registered" for r in rows])
    f = np.arange(len(rows))
    before, after = reg & (f < gap.start), reg & (f >= gap.stop)
    return err[before].mean(0), err[after].mean(0), int(after.sum())


def test_a_broken_chain_rejoins_the_same_map(gap_flight, tmp_path):
    """Nine black keyframes in a row, more than the matching window (5 here), break the chain (matching only the
    previous keyframes): the keyframes after them make a new sub-model, placed by their telemetry against the model's,
    and the flight stays one map."""
    from ground.evaluation.register_flight import register_flight
    from ground.poses.registration import RegistrationSettings

    res = register_flight(gap_flight.path, tmp_path / "r", every=1, settings=RegistrationSettings(revisit=False, match_window=5))
    assert res["rejoined"] == 1 and res["submodels"] == 2
    before, after, n_after = _offset_before_and_after(gap_flight, tmp_path / "r", range(6, 15))
    assert n_after == 23 - 15  # every keyframe after the gap registered
    # one map: both sides carry the same GPS bias, within the telemetry's error (the map alone would be metres off).
    # The new sub-model is placed by the GPS of its 8 keyframes (0.5 m horizontal, 0.8 m vertical a fix): the two
    # sides' mean errors differ by about 0.5 m at one standard deviation, so the bound is one fix's error, 1 m.
    assert np.linalg.norm(before - after) < 1.0
    assert res["rotation_error_median_deg"] < 0.5


def test_an_earlier_keyframe_of_the_same_place_bridges_the_gap(gap_flight, tmp_path):
    """With revisits, the first keyframe after the gap matches the keyframes before it that look at the same place:
    the chain holds, one sub-model (the gap is wider than the matching window, 5 here)."""
    from ground.evaluation.register_flight import register_flight
    from ground.poses.registration import RegistrationSettings

    res = register_flight(gap_flight.path, tmp_path / "v", every=1, settings=RegistrationSettings(match_window=5))
    assert res["revisits"] >= 1 and res["rejoined"] == 0 and res["submodels"] == 1
    before, after, n_after = _offset_before_and_after(gap_flight, tmp_path / "v", range(6, 15))
    assert n_after == 23 - 15
    assert np.linalg.norm(before - after) < 0.3


def test_the_mapping_process_shares_the_first_model_s_sift_with_the_ground(reg_base, tmp_path):
    """Keyframes that arrive together before the first model: those the mapping process is not free for have their
    SIFT features extracted by the ground meanwhile, and the first model comes out as the inline mapper's."""
    from ground.poses.mapper import Mapper
    from ground.poses.mapper_process import MapperProcess
    from ground.poses.registration import RegistrationSettings
    from pomar.camera import Camera
    from pomar.flight import FlightDir
    from pomar.video import iter_frames

    fl = FlightDir(reg_base)
    cam = Camera.load(fl.path / "camera.json")
    images = [img for i, img in iter_frames(fl.video) if i < 8]
    tel = (np.full(3, np.nan), np.full(4, np.nan), 2.0)
    settings = RegistrationSettings(init_frames=4)
    live = MapperProcess(cam, cam, tmp_path / "live", settings)
    inline = Mapper(cam, cam, tmp_path / "inline", settings)
    try:
        for f, img in enumerate(images):  # together: the mapping process is busy from the second on
            live.add(f, img, tel)
        live.wait(120)
        for f, img in enumerate(images):
            if f in live.model_pose:
                inline.add(f, img, tel)
        assert live.early_extracted >= 2
        shared = sorted(live.model_pose)
        assert len(shared) >= 4 and sorted(inline.model_pose) == shared
        centres = [np.array([-R.T @ t for R, t in (m.model_pose[f] for f in shared)]) for m in (live, inline)]
        steps = [np.linalg.norm(np.diff(c, axis=0), axis=1) for c in centres]
        rel = [s / s.sum() for s in steps]  # the model's scale is its own: compare the spacing's shape
        assert np.abs(rel[0] - rel[1]).max() < 0.01, rel
    finally:
        live.close()
        inline.close()


def test_a_keyframe_behind_only_the_one_in_work_goes_to_the_mapping_process_as_it_is(reg_base, tmp_path):
    """Before the first model, a keyframe that would wait in the mapping process only for the one in work is sent
    as it is (extracting its SIFT here would hold it back longer than the process takes to be free); those behind
    two or more have it extracted here."""
    from ground.poses.mapper_process import MapperProcess
    from ground.poses.registration import RegistrationSettings
    from pomar.camera import Camera
    from pomar.flight import FlightDir
    from pomar.video import iter_frames

    fl = FlightDir(reg_base)
    cam = Camera.load(fl.path / "camera.json")
    tel = (np.full(3, np.nan), np.full(4, np.nan), 2.0)
    live = MapperProcess(cam, cam, tmp_path / "live", RegistrationSettings(init_frames=4))
    try:
        for f, img in ((i, im) for i, im in iter_frames(fl.video) if i < 5):  # together
            live.add(f, img, tel)
        live.wait(120)
        # the first two went as they were, the next two (behind two) were extracted here, the fifth was held
        # (INIT_QUEUE) until the process was free
        assert live.sent == 5 and 1 <= live.early_extracted <= 2, live.early_extracted
    finally:
        live.close()


def test_the_ground_stops_extracting_sift_once_the_first_model_s_tries_are_spent(tmp_path):
    """A flight that starts over something with nothing to match (noise here): the ground shares the SIFT only for
    the first model's tries, then leaves the mapping process to it, and keeps its own time."""
    from ground.poses.mapper_process import MapperProcess
    from ground.poses.registration import RegistrationSettings
    from pomar.camera import Camera

    cam = Camera(960, 540, 800.0, 800.0, 480.0, 270.0)
    rng = np.random.default_rng(0)
    tel = (np.full(3, np.nan), np.full(4, np.nan), 2.0)
    settings = RegistrationSettings(init_frames=4)
    live = MapperProcess(cam, cam, tmp_path / "live", settings)
    try:
        for f in range(30):  # one every 0.1 s: the process is busy with most of them
            live.add(f, rng.integers(0, 255, (540, 960, 3), dtype=np.uint8), tel)
            time.sleep(0.1)
        live.wait(120)
        assert not live.has_model
        assert 1 <= live.early_extracted <= 3 * settings.init_frames, live.early_extracted
        assert live.sent > 3 * settings.init_frames  # the later ones went too, the newest first
    finally:
        live.close()


def test_sift_on_a_shrunk_keyframe_gives_keyframe_pixels():
    """--sift-width: SIFT runs on the keyframe shrunk, and its keypoints come back in the keyframe's own pixels (the
    mapper's camera): the same corners found at either size lie within a pixel of each other."""
    import cv2

    from ground.poses.registration import RegistrationSettings
    from ground.poses.sift import SiftExtractor
    from pomar.video import iter_frames

    _, bgr = next(iter(iter_frames(ROOT / "replay_data" / "demo-flight" / "video.mp4")))
    full_kp, _, full_d = SiftExtractor(RegistrationSettings())(bgr)
    kp, _, d = SiftExtractor(RegistrationSettings(sift_width=bgr.shape[1] * 5 // 8))(bgr)
    assert 0.2 * len(full_kp) < len(kp) < 0.8 * len(full_kp)  # fewer features: the point of shrinking
    assert kp[:, 0].max() > 0.9 * bgr.shape[1] and kp[:, 1].max() > 0.9 * bgr.shape[0]
    # mutual nearest descriptors with Lowe's ratio: the same image structure seen at both sizes
    matches = cv2.BFMatcher(cv2.NORM_L2).knnMatch(d, full_d, k=2)
    back = cv2.BFMatcher(cv2.NORM_L2, crossCheck=True).match(d, full_d)
    mutual = {(m.queryIdx, m.trainIdx) for m in back}
    good = [a for a, b in matches if a.distance < 0.7 * b.distance and (a.queryIdx, a.trainIdx) in mutual]
    assert len(good) >= 100
    err = np.linalg.norm(kp[[m.queryIdx for m in good], :2] - full_kp[[m.trainIdx for m in good], :2], axis=1)
    assert np.median(err) < 0.5, np.median(err)
    # SIFT's scale comes back in keyframe pixels too
    ratio = kp[[m.queryIdx for m in good], 2] / full_kp[[m.trainIdx for m in good], 2]
    assert 0.8 < np.median(ratio) < 1.25, np.median(ratio)


#: Maps the flight (argv 1) in the folder argv 2 with every file it writes limited to argv 3 bytes (a disk that fills:
#: SQLite and numpy's writes fail beyond it), then writes its poses and what its registrar says to argv 4.
_LIMITED_MAPPER = """
import pickle, resource, signal, sys
from pathlib import Path
import numpy as np
from ground.poses.mapper import Mapper
from ground.poses.registration import RegistrationSettings
from pomar.camera import Camera
from pomar.flight import FlightDir
from pomar.video import iter_frames

fl = FlightDir(Path(sys.argv[1]))
cam = Camera.load(fl.path / "camera.json")
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails (EFBIG) instead of killing
resource.setrlimit(resource.RLIMIT_FSIZE, (int(sys.argv[3]), resource.RLIM_INFINITY))
m = Mapper(cam, cam, sys.argv[2], RegistrationSettings(submodel_size=8, overlap=4, keep_submodels=1))
for f, img in iter_frames(fl.video):
    m.add(f, img, (np.full(3, np.nan), np.full(4, np.nan), 2.0))
m.close()
resource.setrlimit(resource.RLIMIT_FSIZE, (resource.RLIM_INFINITY, resource.RLIM_INFINITY))
pickle.dump({"poses": m.model_pose, "in_memory_from": m.stats()["in_memory_from"],
             "failed": m.registrar.failed}, open(sys.argv[4], "wb"))
"""


def test_a_mapper_without_a_folder_or_whose_folder_refuses_writes_maps_in_memory_as_on_disk(reg_base, tmp_path):
    """Without a folder (``workdir`` None), the mapper keeps its database, finished sub-models and their anchors in
    memory, and no keyframe images. Where its folder refuses a write midway (a disk that fills), its database moves
    into memory with every keyframe in it and it maps on. Over a chain of sub-models both place the keyframes exactly
    as the mapper with a folder does (which writes the older sub-models to it)."""
    import pickle

    from ground.poses.mapper import Mapper
    from ground.poses.keyframe_db import write_refused
    from ground.poses.registration import RegistrationSettings
    from pomar.camera import Camera
    from pomar.flight import FlightDir
    from pomar.video import iter_frames

    refusing = subprocess.Popen([sys.executable, "-c", _LIMITED_MAPPER, str(reg_base), str(tmp_path / "full"),
                                 str(1_000_000), str(tmp_path / "full.pkl")], cwd=ROOT, stderr=subprocess.PIPE,
                                text=True)
    fl = FlightDir(reg_base)
    cam = Camera.load(fl.path / "camera.json")
    tel = (np.full(3, np.nan), np.full(4, np.nan), 2.0)
    s = RegistrationSettings(submodel_size=8, overlap=4, keep_submodels=1)
    on_disk, in_memory = Mapper(cam, cam, tmp_path / "work", s), Mapper(cam, cam, None, s)
    try:
        for f, img in iter_frames(fl.video):
            on_disk.add(f, img, tel)
            in_memory.add(f, img, tel)
        assert in_memory.registrar.db_path == ":memory:" and len(in_memory.model_pose) >= 20
        kept = in_memory.registrar.submodels
        assert len(kept) >= 4 and all(sm.rec is not None for sm in kept)
        assert any(sm.rec is None for sm in on_disk.registrar.submodels)  # written to the folder
        assert (tmp_path / "work" / "database.db").is_file()
        assert not {p.name for p in tmp_path.iterdir()} - {"work", "full", "full.pkl"}  # nothing else written
        _, err = refusing.communicate(timeout=300)
        assert refusing.returncode == 0, err[-2000:]
        full = pickle.loads((tmp_path / "full.pkl").read_bytes())
        assert 0 < full["in_memory_from"] < 22, full["in_memory_from"]
        assert "refused a write" in err and "mapping goes on in memory" in err
        assert full["failed"] == on_disk.registrar.failed  # the keyframe in work when the disk filled registered
        for other in (in_memory.model_pose, full["poses"]):
            assert sorted(other) == sorted(on_disk.model_pose)
            for f, (R, t) in on_disk.model_pose.items():
                assert np.allclose(other[f][0], R, atol=1e-9) and np.allclose(other[f][1], t, atol=1e-9)
    finally:
        on_disk.close()
        in_memory.close()
        refusing.kill()
    assert write_refused(RuntimeError("[database_sqlite.cc:1296] SQLite error: database or disk is full"))
    assert write_refused(OSError(28, "No space left on device")) and write_refused(OSError(13, "Permission denied"))
    assert not write_refused(OSError(2, "No such file or directory")) and not write_refused(ValueError("bad image"))


def test_a_keyframe_older_than_one_handed_over_never_reaches_the_mapping_process(reg_base, tmp_path):
    """The mapping process maps in frame order and skips a keyframe older than one it has mapped (with a warning a
    clean flight should not show). The ground hands over none older than the newest it sent or holds."""
    from ground.poses.mapper_process import MapperProcess
    from ground.poses.registration import RegistrationSettings
    from pomar.camera import Camera
    from pomar.flight import FlightDir
    from pomar.video import iter_frames

    fl = FlightDir(reg_base)
    cam = Camera.load(fl.path / "camera.json")
    images = [img for i, img in iter_frames(fl.video) if i < 8]
    tel = (np.full(3, np.nan), np.full(4, np.nan), 2.0)
    live = MapperProcess(cam, cam, tmp_path / "live", RegistrationSettings(init_frames=4))
    try:
        for f, img in enumerate(images):
            live.add(f, img, tel)
        sent = live.sent
        live.add(5, images[5], tel)  # older than keyframes sent (or held) before it
        assert live.sent == sent
        live.wait(120)
        assert live.sent == sent + (sent < len(images)) and live.processed == len(images) - 1
    finally:
        live.close()
