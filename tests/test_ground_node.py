"""The ground node end to end: two processes over real zenoh on loopback, real pycolmap, real onnxruntime,
the outputs and the .rrd read back; a ground killed mid-flight resumes and ends with every frame."""

from __future__ import annotations

import contextlib
import csv
import json
import os
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from ground.link.journal import Journal, read_journal
from ground.outputs.tables import APPLE_COLUMNS, CANDIDATE_COLUMNS, harvest_correlation, read_harvest
from pomar.cli import InputError


def test_replay_end_to_end(replayed_test_flight):
    from ground.outputs.rrd_file import rrd_entities
    from ground.evaluation.scoring import evaluate_map

    replay_test_flight, out, rep = replayed_test_flight
    # every frame went through, most with registered poses
    log_tail = "\n".join((out / "ground.log").read_text().splitlines()[-15:])
    assert rep["frames"]["frames"] == 20 and rep["frames"]["missing_frames"] == 0, (rep["frames"], log_tail)
    assert rep["frames"]["registered"] >= 10
    assert rep["final"] and rep["wall_seconds"] > 0 and rep["realtime_factor"] > 0
    # apples found, within a loose bound of the truth (the shipped detector, a tiny flight)
    ev = rep["evaluation"]
    assert {"precision", "recall", "f1", "count", "truth_count", "count_error_pct", "median_error_m"} <= set(ev)
    assert 0.3 * ev["truth_count"] <= ev["count"] <= 3 * ev["truth_count"]
    # the tiny flight's live map sits 5-15 cm off (640x360 keyframes, 20 frames: later bundle adjustments
    # move the model after frames were used), around the 10 cm match radius; within 30 cm most apples match
    loose = evaluate_map(replay_test_flight, out, match_m=0.3)
    assert loose["precision"] > 0.35 and loose["recall"] > 0.4, loose
    # output files
    with open(out / "apples.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == APPLE_COLUMNS and len(rows) == rep["apples"]
    gj = json.loads((out / "apples.geojson").read_text())
    assert gj["type"] == "FeatureCollection" and len(gj["features"]) == rep["apples"]
    lon, lat, _ = gj["features"][0]["geometry"]["coordinates"]
    assert abs(lat - -28.516) < 0.01 and abs(lon - -50.881) < 0.01
    ply = (out / "apples.ply").read_text().splitlines()
    assert ply[0] == "ply" and f"element vertex {rep['apples']}" in ply
    with open(out / "rows.csv", newline="") as f:
        assert sum(int(r["count"]) for r in csv.DictReader(f)) == rep["apples"]
    # every apple the count was chosen from: the counted ones are apples.csv's, the others say which check
    with open(out / "candidates.csv", newline="") as f:
        cand = list(csv.DictReader(f))
    assert list(cand[0]) == CANDIDATE_COLUMNS
    assert sorted(int(c["id"]) for c in cand if c["left_out"] == "") == sorted(int(r["id"]) for r in rows)
    left = [c["left_out"] for c in cand if c["left_out"]]
    assert set(left) <= {"small", "narrow", "few_views"} and len(cand) == rep["apples"] + len(left)
    assert left.count("small") == rep["counting"]["left_out_small"]
    assert left.count("narrow") == rep["counting"]["left_out_narrow"]
    assert left.count("few_views") == rep["counting"]["left_out_few_views"]
    assert all(float(c["expected_views"]) >= 0 and int(c["observations"]) >= 3 for c in cand)
    assert (out / "model" / "0" / "images.txt").is_file()
    # the rerun recording, read back
    ents = rrd_entities(out / "flight.rrd")
    for e in ("/world/camera", "/world/camera/image", "/world/camera/image/detections", "/world/apples",
              "/world/trajectory", "/world/rows", "/map/apples", "/map/rows", "/stats/apples", "/summary"):
        assert e in ents, (e, sorted(ents))
    assert ents["/world/camera"] == 20
    assert any(e.startswith("/world/tracks/") for e in ents)


def test_the_candidates_are_labelled_as_the_score_counts_them(replayed_test_flight, tmp_path):
    """label_candidates (what benchmarks/count_rule.py studies) agrees with evaluate_map: on the counted candidates
    alone, those it labels countable are the map's true positives among the countable apples."""
    import shutil

    from ground.evaluation.scoring import evaluate_map, label_candidates

    flight, out, _ = replayed_test_flight
    with open(out / "candidates.csv", newline="") as f:
        cand = list(csv.DictReader(f))
    shutil.copy(out / "poses.csv", tmp_path / "poses.csv")
    shutil.copy(out / "apples.csv", tmp_path / "apples.csv")
    with open(tmp_path / "candidates.csv", "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(cand[0]), lineterminator="\n")
        w.writeheader()
        w.writerows(c for c in cand if c["left_out"] == "")
    lab = label_candidates(flight, tmp_path)
    ev = evaluate_map(flight, tmp_path)
    assert len(lab["label"]) == ev["count"] and len(lab["countable"]) == ev["truth_count"]
    assert int((lab["label"] == "countable").sum()) == round(ev["recall"] * ev["truth_count"]) > 0
    assert int(lab["found"].sum()) == int((lab["label"] == "countable").sum())
    assert (lab["views"] >= 3).all()
    assert set(lab["label"]) <= {"countable", "partial", "misplaced", "none"}
    misplaced = lab["label"] == "misplaced"
    assert (lab["ray_apple"][misplaced] >= 0).all() and (lab["apple_id"][misplaced] == -1).all()
    assert (lab["ray_apple"][~misplaced] == -1).all()


def test_the_detector_visibility_table_reads_the_stream_the_ground_received(replayed_test_flight):
    """benchmarks/detector_visibility.py, as a user runs it on a replay: the shipped detector finds the apples in full
    view far more often than those mostly hidden, and the table says where half are found."""
    from ground.evaluation.scoring import found_by_visibility, stream_detections

    flight, out, _ = replayed_test_flight
    vis, found = found_by_visibility(flight, stream_detections(out / "journal.bin", 0.9))
    assert len(vis) and found[vis >= 0.8].mean() > 0.8 > 0.2 > found[vis < 0.2].mean()
    r = subprocess.run([sys.executable, "benchmarks/detector_visibility.py", "--replay", str(out), str(flight.path)],
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    assert "half at" in r.stdout and r.stdout.strip().splitlines()[-1].startswith("the definition")
    # the shipped model run on the flight itself (a candidate is judged so before it ships): the same frames, so the
    # same apples found as in the stream the replay sent
    r2 = subprocess.run([sys.executable, "benchmarks/detector_visibility.py", "--flight", str(flight.path), "--every",
                         "1"], capture_output=True, text=True, timeout=300)
    assert r2.returncode == 0, r2.stderr[-2000:]
    row = [line for line in r.stdout.splitlines() if line.startswith(flight.path.name)]
    assert row and row == [line for line in r2.stdout.splitlines() if line.startswith(flight.path.name)]
    r = subprocess.run([sys.executable, "benchmarks/detector_visibility.py", "--replay", str(flight.path),
                        str(flight.path)], capture_output=True, text=True, timeout=300)
    assert r.returncode == 2 and r.stderr.startswith("error: ") and len(r.stderr.strip().splitlines()) == 1


def _wait_for(pred, timeout, what):
    t0 = time.monotonic()
    while time.monotonic() - t0 < timeout:
        if pred():
            return
        time.sleep(0.1)
    raise TimeoutError(what)


def test_killed_ground_resumes_with_every_frame(replay_test_flight, tmp_path):
    from ground.replay import free_port

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    out = tmp_path / "ground"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    onboard = subprocess.Popen([sys.executable, "-m", "onboard", "run", str(replay_test_flight.path), "--listen", endpoint,
                                "--detector", "truth-replay", "--realtime", "--wait-for-ground", "30",
                                "--keyframe-every", "1", "--keyframe-width", "0", "--linger", "120", "--summary", str(tmp_path / "onboard.json")],
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    ground_cmd = [sys.executable, "-m", "ground", "run", "--flight-id", "sim-replay-test", "--connect", endpoint,
                  "--out", str(out), "--no-rrd", "--idle-timeout", "30"]
    procs = [onboard]
    err = ""
    try:
        first = subprocess.Popen(ground_cmd + ["--fresh"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
        procs.append(first)
        journal = out / "journal.bin"
        _wait_for(lambda: journal.is_file() and len(read_journal(journal)) >= 12, 60, "the ground journals messages")
        mapping = _children(first.pid)  # its mapping process, started with it
        first.send_signal(signal.SIGKILL)  # no clean shutdown: what survives is the journal
        first.wait(10)
        assert first.returncode == -signal.SIGKILL
        assert mapping and _gone(mapping, 30), "the killed ground's mapping process lives on"
        before = len(read_journal(journal))
        second = subprocess.Popen(ground_cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, env=env, text=True)
        procs.append(second)
        _, err = second.communicate(timeout=180)
        assert second.returncode == 0, err[-3000:]
        assert "resuming from" in err
    finally:
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    p.kill()
    rep = json.loads((out / "report.json").read_text())
    assert rep["final"]
    # Every frame the onboard node published, once. In real time it drops the frames it cannot keep up
    # with (the detector and this ground share the machine's cores): those are the only ones missing.
    sent = json.loads((tmp_path / "onboard.json").read_text())
    assert sent["frames_processed"] + sent["frames_dropped"] == 20 and sent["frames_processed"] >= 10
    assert rep["frames"]["frames"] == sent["frames_processed"], (rep["frames"], err[-3000:])
    assert rep["frames"]["missing_frames"] <= sent["frames_dropped"] and rep["frames"]["late_frames"] == 0
    assert len(read_journal(out / "journal.bin")) > before
    assert rep["apples"] > 0


def _children(pid: int) -> list[int]:
    from ground.replay import child_pids

    return child_pids(pid)


def _gone(pids: list[int], timeout_s: float) -> bool:
    """Whether every one of ``pids`` has exited (or is a zombie) within ``timeout_s``."""
    t0 = time.monotonic()
    while True:
        alive = []
        for p in pids:
            try:
                if open(f"/proc/{p}/stat").read().rsplit(")", 1)[1].split()[0] != "Z":
                    alive.append(p)
            except OSError:
                pass
        if not alive or time.monotonic() - t0 > timeout_s:
            for p in alive:
                os.kill(p, signal.SIGKILL)
            return not alive
        time.sleep(0.2)


def test_journal_skips_damaged_records_and_keeps_every_intact_one(tmp_path):
    from ground.link.journal import MARKER, JournalError, read_journal_report

    path = tmp_path / "journal.bin"
    payloads = [bytes([i % 251]) * (10 + i) + b"PJR" for i in range(100)]  # a marker's first bytes inside, too
    j = Journal(path)
    for p in payloads:
        j.append(p)
    j.close()
    data = bytearray(path.read_bytes())
    starts = [i for i in range(len(data)) if data.startswith(MARKER, i)]
    assert len(starts) == 100
    data[starts[40] + 4] ^= 0x01  # one bit of record 40's length prefix
    data[starts[60] + 20] ^= 0xFF  # a byte of record 60's payload
    data[starts[61]:starts[61] + 4] = b"XXXX"  # record 61's marker
    path.write_bytes(bytes(data))
    size = len(data)
    res = read_journal_report(path)
    assert res.records == [p for i, p in enumerate(payloads) if i not in (40, 60, 61)]
    assert len(res.damaged) == 2 and path.stat().st_size == size  # never truncated in place
    assert all(f.is_file() and f.stat().st_size > 0 for f in res.side_files)
    # a record cut short by a kill, then the resumed ground appends after it: both sides are read
    with open(path, "ab") as f:
        f.write(MARKER + b"\x10\x00\x00\x00abc")
    j = Journal(path)
    j.append(b"after the cut")
    j.close()
    res = read_journal_report(path)
    assert res.records[-1] == b"after the cut" and len(res.records) == 98 and len(res.damaged) == 3
    # a journal written before records had markers and checksums
    old = tmp_path / "old.bin"
    old.write_bytes(b"\x05\x00\x00\x00hello")
    with pytest.raises(JournalError, match="old.bin.*--fresh"):
        read_journal(old)
    with pytest.raises(JournalError, match="old.bin"):
        Journal(old)


def test_pipeline_survives_bad_keyframes_and_late_frames(replay_test_flight, tmp_path):
    """Messages made by the onboard node (no zenoh here): a keyframe that does not decode, a frame that comes
    after a later one was mapped, repeats; every other frame still gets a pose and nothing stops."""
    from ground.outputs.snapshot import snapshot
    from ground.outputs.tables import apple_table
    from ground.pipeline import GroundPipeline, GroundSettings
    from pomar import wire

    msgs = _onboard_messages(replay_test_flight, keyframe_every=1)
    for m in msgs:
        if isinstance(m, wire.KeyframeMessage) and m.frame == 9:
            m.jpeg = b"\xff\xd8" + b"not a jpeg" * 10
    late = next(m for m in msgs if isinstance(m, wire.FrameMessage) and m.frame == 3)
    pipe = GroundPipeline(tmp_path / "work", GroundSettings())
    events = []
    for m in msgs + msgs[:5]:  # repeats at the end
        events += pipe.take(m)
    events += pipe.take(late)
    events += pipe.finish()
    assert [e.frame for e in events] == list(range(20))
    assert all(e.pose is not None for e in events)
    assert pipe.counters["bad_keyframes"] == 1 and pipe.counters["late_frames"] >= 1
    assert next(e for e in events if e.frame == 9).pose.source in ("interpolated", "telemetry")
    assert pipe.counters["registered"] >= 10
    t, _ = apple_table(snapshot(pipe))
    assert len(t["id"]) == len(pipe.apples.count.counted_ids()) > 0 and np.isfinite(t["lat"]).all()


def _onboard_messages(flight, **settings):
    """The messages the onboard node publishes for ``flight`` (truth-replay detector), status left out."""
    from onboard.node import NodeSettings, OnboardNode
    from onboard.replay_detector import TruthReplayDetector
    from pomar import wire

    class Collect:
        def __init__(self):
            self.msgs = []
            self.sent = {k: 0 for k in wire.KINDS}
            self.bytes = {k: 0 for k in wire.KINDS}

        def publish(self, msg):
            self.msgs.append(msg)

    sink = Collect()
    OnboardNode(flight.path, sink, TruthReplayDetector(flight.path), NodeSettings(**settings)).run()
    return [m for m in sink.msgs if not isinstance(m, wire.StatusMessage)]


def test_every_frame_tracked_keyframes_mapped_and_a_failed_track_falls_back_flagged(replay_test_flight, tmp_path):
    """Every frame's image is tracked against the map (KLT + PnP); only the frames the tracker proposes are
    registered by pycolmap. A frame whose image cannot be tracked (here: a blank one) gets an interpolated or
    telemetry pose, is flagged, and tracking goes on after it."""
    import cv2

    from ground.pipeline import GroundPipeline, GroundSettings
    from pomar import wire

    msgs = _onboard_messages(replay_test_flight, keyframe_every=1)
    kf = next(m for m in msgs if isinstance(m, wire.KeyframeMessage) and m.frame == 12)
    h, w = cv2.imdecode(np.frombuffer(kf.jpeg, np.uint8), cv2.IMREAD_GRAYSCALE).shape
    kf.jpeg = cv2.imencode(".jpg", np.full((h, w, 3), 128, np.uint8))[1].tobytes()  # decodes, holds nothing to track
    pipe = GroundPipeline(tmp_path / "work", GroundSettings())
    events = []
    for m in msgs:
        events += pipe.take(m)
    events += pipe.finish()
    assert [e.frame for e in events] == list(range(20)) and all(e.pose is not None for e in events)
    src = {e.frame: e.pose.source for e in events}
    assert 12 in pipe.poses.tracking.failed_frames and src[12] in ("interpolated", "extrapolated", "telemetry")
    assert any(src[f] in ("tracked", "registered") for f in range(13, 20))
    assert pipe.counters["tracked"] >= 3, pipe.counters
    # fewer keyframes mapped than images: tracking carries the rest
    assert 3 <= pipe.poses.mapper.stats()["keyframes_processed"] < 19
    assert len(pipe.apples.count.apples) > 0


def test_lock_step_repeats_bit_for_bit(replay_test_flight, tmp_path):
    """The same messages, fed twice (mapping inline, as a lock-step replay does; the second time in one batch, as a
    ground node takes what queued up): the same poses and the same apples, to the bit."""
    from ground.pipeline import GroundPipeline, GroundSettings

    msgs = _onboard_messages(replay_test_flight, keyframe_every=1)
    runs = []
    for k, batched in enumerate((False, True)):
        pipe = GroundPipeline(tmp_path / f"work{k}", GroundSettings())
        for m in msgs:
            pipe.take(m, step=not batched)
        pipe.finish()
        poses = {f: np.concatenate([p.R.ravel(), p.t]) for f, p in pipe.apples.frames.poses.items()}
        runs.append((poses, {i: a.X.copy() for i, a in pipe.apples.count.apples.items()}))
    (p0, a0), (p1, a1) = runs
    assert p0.keys() == p1.keys() and all(np.array_equal(p0[f], p1[f]) for f in p0)
    assert a0.keys() == a1.keys() and len(a0) > 0 and all(np.array_equal(a0[i], a1[i]) for i in a0)


def test_lock_step_keeps_its_poses_when_the_images_come_late_on_a_busy_machine(replay_test_flight, tmp_path):
    """A lock-step ground that gets every frame message first and the images only after a long pause (a loaded
    machine, or zenoh delivering the two streams' histories apart) maps the flight exactly as one fed in order: the
    wall clock decides nothing. Live, the same pause is a drone that stopped sending images: the frames go on with
    telemetry poses, flagged."""
    from ground.pipeline import GroundPipeline, GroundSettings
    from pomar import wire

    runs = []
    for k, mapping in enumerate(("inline", "inline", "process")):
        # live, keyframes at 480 px: a ground that goes on before the first image sizes its keyframe camera from the
        # camera message (else it would enlarge every keyframe to the camera's width, for the mapper to work on)
        msgs = _onboard_messages(replay_test_flight, keyframe_every=1, keyframe_width=480 if k == 2 else 0)
        images = [m for m in msgs if isinstance(m, wire.KeyframeMessage)]
        rest = [m for m in msgs if not isinstance(m, wire.KeyframeMessage)]
        pipe = GroundPipeline(tmp_path / f"work{k}", GroundSettings(mapping=mapping, max_wait_s=0.2))
        if k == 0:
            for m in msgs:
                pipe.take(m)
        else:
            for m in rest:
                pipe.take(m)
            time.sleep(0.5)  # longer than max_wait_s, and the frames flew 4 s past the first one
            pipe.step()
            if mapping == "process":  # live: released without waiting for the images that did not come
                assert pipe.arrivals.released == 19 and pipe.counters["telemetry"] == 20, pipe.counters
                assert (pipe.poses.kf_cam.width, pipe.poses.kf_cam.height) == (480, 270)
            else:
                assert pipe.arrivals.released == -1, pipe.counters
            for m in images:
                pipe.take(m)
        pipe.finish()
        runs.append(({f: np.concatenate([p.R.ravel(), p.t]) for f, p in pipe.apples.frames.poses.items()},
                     {i: a.X.copy() for i, a in pipe.apples.count.apples.items()}, pipe.counters))
    (p0, a0, c0), (p1, a1, c1) = runs[:2]
    assert c0["registered"] + c0["tracked"] >= 10 and c1 == c0, (c0, c1)
    assert p0.keys() == p1.keys() and all(np.array_equal(p0[f], p1[f]) for f in p0)
    assert a0.keys() == a1.keys() and len(a0) > 0 and all(np.array_equal(a0[i], a1[i]) for i in a0)


def test_lock_step_waits_for_the_keyframes_the_frames_announce_when_the_link_brings_them_late(replay_test_flight,
                                                                                            tmp_path):
    """Each frame message says whether a keyframe of it follows. A lock-step ground whose first keyframes come last
    (zenoh's history can miss the first samples of a stream on a loaded machine, and the ground asks for them again)
    tracks and maps nothing past them until they come, then maps the flight exactly as one fed in order."""
    from ground.pipeline import GroundPipeline, GroundSettings
    from pomar import wire

    msgs = _onboard_messages(replay_test_flight, keyframe_every=2)
    kfs = {m.frame for m in msgs if isinstance(m, wire.KeyframeMessage)}
    frames = [m for m in msgs if isinstance(m, wire.FrameMessage)]
    assert {m.frame for m in frames if m.keyframe} == kfs and len(kfs) == 10
    late = [m for m in msgs if isinstance(m, wire.KeyframeMessage) and m.frame in (0, 2)]
    runs = []
    for k in range(2):
        pipe = GroundPipeline(tmp_path / f"work{k}", GroundSettings(mapping="inline"))
        for m in (msgs if k == 0 else [m for m in msgs if m not in late]):
            pipe.take(m)
        if k == 1:
            assert pipe.arrivals.kf_awaited == {0, 2} and pipe.arrivals.released == -1, pipe.counters
            for m in late:
                pipe.take(m)
            assert not pipe.arrivals.kf_awaited
        pipe.finish()
        runs.append(({f: np.concatenate([p.R.ravel(), p.t]) for f, p in pipe.apples.frames.poses.items()},
                     {i: a.X.copy() for i, a in pipe.apples.count.apples.items()}, pipe.counters))
    (p0, a0, c0), (p1, a1, c1) = runs
    assert c0["registered"] + c0["tracked"] >= 10 and c1 == c0, (c0, c1)
    assert p0.keys() == p1.keys() and all(np.array_equal(p0[f], p1[f]) for f in p0)
    assert a0.keys() == a1.keys() and len(a0) > 0 and all(np.array_equal(a0[i], a1[i]) for i in a0)


@contextlib.contextmanager
def _listening_ground(first, out, idle_timeout_s: float):
    """A ``ground run`` process listening on a free loopback port (mapping inline, no recording), and a publisher of
    ``first``'s flight and drone connected to it: (process, publisher). The process is killed if still running, and
    the session closed, when the block ends."""
    from ground.replay import free_port
    from pomar import transport

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    ground = subprocess.Popen([sys.executable, "-m", "ground", "run", "--flight-id", first.flight_id, "--listen",
                               endpoint, "--out", str(out), "--no-rrd", "--mapping", "inline", "--idle-timeout",
                               str(idle_timeout_s), "--fresh"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                              text=True, env=dict(os.environ, PYTHONUNBUFFERED="1"))
    session = transport.open_session(connect=[endpoint])
    try:
        pub = transport.FlightPublisher(session, first.flight_id, first.drone_id)
        assert pub.wait_for_subscriber(60)
        yield ground, pub
    finally:
        if ground.poll() is None:
            ground.kill()
            ground.wait()
        session.close()


def test_a_ground_does_not_end_the_flight_while_an_announced_keyframe_is_missing(replay_test_flight, tmp_path):
    """Over real zenoh: the drone says the flight is finished with every frame sent, but the first keyframe its frame
    message announced has not come (a history that missed it). The ground does not end at the usual quiet second:
    it waits (asking for the history again), and the keyframe, sent 2.5 s later, is mapped."""
    from pomar import wire

    msgs = _onboard_messages(replay_test_flight, keyframe_every=2)
    held = next(m for m in msgs if isinstance(m, wire.KeyframeMessage) and m.frame == 0)
    first = msgs[0]
    out = tmp_path / "ground"
    with _listening_ground(first, out, idle_timeout_s=30) as (ground, pub):
        for m in msgs:
            if m is not held:
                pub.publish(m)
        n = sum(isinstance(m, wire.FrameMessage) for m in msgs)
        pub.publish(wire.StatusMessage(first.flight_id, first.drone_id, time.time(), n, n, state="finished"))
        time.sleep(2.5)
        assert ground.poll() is None  # still waiting for keyframe 0
        pub.publish(held)
        _, err = ground.communicate(timeout=120)
    assert ground.returncode == 0, err[-3000:]
    rep = json.loads((out / "report.json").read_text())
    assert rep["frames"]["keyframes"] == sum(isinstance(m, wire.KeyframeMessage) for m in msgs) == 10
    from ground.pipeline import GroundPipeline, GroundSettings

    pipe = GroundPipeline(tmp_path / "in-order", GroundSettings(mapping="inline"))
    for m in msgs:
        pipe.take(m)
    pipe.finish()  # the same stream in order: the same poses by source
    assert rep["frames"]["frames"] == n and all(rep["frames"][k] == pipe.counters[k]
                                                for k in ("registered", "tracked", "interpolated", "telemetry"))


def test_frames_that_come_before_the_camera_message_go_on_once_it_comes(replay_test_flight, tmp_path):
    """The link keeps no order between its streams: a ground may hear frames, keyframes and statuses before the
    camera message that opens the stream. They wait in the arrivals (nothing is released without a camera), and
    once the camera message comes the flight maps as if it had come first."""
    from ground.pipeline import GroundPipeline, GroundSettings
    from pomar import wire

    msgs = _onboard_messages(replay_test_flight, keyframe_every=2)
    camera = next(m for m in msgs if isinstance(m, wire.CameraMessage))
    late = GroundPipeline(tmp_path / "late", GroundSettings(mapping="inline"))
    assert all(late.take(m) == [] for m in msgs if m is not camera)  # stored, nothing released
    events = late.take(camera) + late.finish()
    in_order = GroundPipeline(tmp_path / "in-order", GroundSettings(mapping="inline"))
    for m in msgs:
        in_order.take(m)
    in_order.finish()
    assert [e.frame for e in events] == sorted(m.frame for m in msgs if isinstance(m, wire.FrameMessage))
    assert late.counters == in_order.counters
    assert len(late.apples.count.counted_ids()) == len(in_order.apples.count.counted_ids()) > 0


def test_a_drone_whose_node_restarted_mid_flight_ends_the_flight_when_it_says(replay_test_flight, tmp_path):
    """Over real zenoh: the onboard node dies after frame 9 and a new one takes up the flight at frame 12 (the frames
    between were taken while none ran). The new node's 'finished' counts only its own frames, from the first it sent
    (first_frame): the ground takes it as true and ends the flight at once, not at the idle timeout."""
    from pomar import wire

    msgs = _onboard_messages(replay_test_flight, keyframe_every=2)
    lost = {10, 11}
    first = msgs[0]
    out = tmp_path / "ground"
    with _listening_ground(first, out, idle_timeout_s=60) as (ground, pub):
        for m in msgs:
            if getattr(m, "frame", -1) not in lost:
                pub.publish(m)
        after = sum(isinstance(m, wire.FrameMessage) and m.frame > max(lost) for m in msgs)
        pub.publish(wire.StatusMessage(first.flight_id, first.drone_id, time.time() - 5, 10, 10))  # the old node's
        t0 = time.monotonic()
        pub.publish(wire.StatusMessage(first.flight_id, first.drone_id, time.time(), after, after, state="finished",
                                       first_frame=max(lost) + 1))
        _, err = ground.communicate(timeout=120)
        took = time.monotonic() - t0
    assert ground.returncode == 0, err[-3000:]
    assert took < 30, (took, err[-2000:])  # the idle timeout is 60 s
    rep = json.loads((out / "report.json").read_text())
    assert rep["final"] and rep["frames"]["frames"] == 20 - len(lost) and rep["frames"]["missing_frames"] == len(lost)
    assert "ignored" not in err
    assert rep["frames"]["onboard_restarts"] == 1 and "started again" in err


def test_a_backlog_mapped_in_one_step_shows_its_progress_as_it_goes(replay_test_flight, tmp_path, caplog):
    """A lock-step replay hands the ground its stream in batches, and one step maps a whole batch (minutes on a long
    flight): its frames reach the log, the map files and the progress line as they are released, not at its end."""
    import logging
    import re

    from ground.node import GroundNode

    msgs = _onboard_messages(replay_test_flight, keyframe_every=1)
    node = GroundNode(tmp_path / "out", rrd=False, progress_s=0.0, expected_frames=20)
    for m in msgs:
        node.handle(m, step=False)
    with caplog.at_level(logging.INFO, logger="ground"):
        node.step()
    mapped = [int(m.group(1)) for r in caplog.records if (m := re.search(r"(\d+)/20 mapped", r.getMessage()))]
    assert len(mapped) >= 3 and mapped == sorted(mapped) and mapped[0] < mapped[-1], mapped
    report = node.finish()
    assert report["frames"]["frames"] == 20 and report["apples"] > 0


def test_mapping_in_its_own_process_maps_every_frame(replay_test_flight, tmp_path):
    """Live, the mapper runs in its own process: frames are tracked meanwhile, every frame gets a pose, and the
    sub-models come back written to disk when the flight ends."""
    from ground.pipeline import GroundPipeline, GroundSettings

    msgs = _onboard_messages(replay_test_flight, keyframe_every=1)
    pipe = GroundPipeline(tmp_path / "work", GroundSettings(mapping="process"))
    events = []
    for m in msgs:  # at the flight's 5 fps, as the drone sends them
        events += pipe.take(m)
        time.sleep(0.1)
    events += pipe.finish()
    assert [e.frame for e in events] == list(range(20)) and all(e.pose is not None for e in events)
    assert pipe.poses.mapper.stats()["keyframes_processed"] >= 3
    subs = pipe.poses.mapper.submodels()
    assert subs and all(sm.path is not None and (sm.path / "images.bin").is_file() for sm in subs)
    assert len(subs[0].reconstruction().images) >= 3


def _fed_at_flight_pace(flight, tmp_path, sig, until=None, on_hit=None):
    """The test flight's messages to a ground mapping in a process; ``sig`` sent to the mapping process once it has a
    model and has mapped 4 keyframes. Until then each message waits for the mapper to map what it was given (so that
    a slow machine gets there too), then they come at the flight's 5 fps. ``until(pipeline)``: after the last
    message, the ground goes on waiting (as live, between frames) until it holds; ``on_hit()`` runs as the signal
    goes. (pipeline, events, the pid signalled or None)."""
    from ground.pipeline import GroundPipeline, GroundSettings

    msgs = _onboard_messages(flight, keyframe_every=1)
    pipe = GroundPipeline(tmp_path / "work", GroundSettings(mapping="process"))
    events, hit = [], None
    for m in msgs:
        events += pipe.take(m)
        mapper = pipe.poses.mapper if pipe.poses is not None else None
        if hit is None:
            pipe.wait_for_mapping()
        if hit is None and mapper is not None and mapper.has_model and mapper.answered >= 4:
            hit = mapper._proc.pid
            if on_hit is not None:
                on_hit()
            os.kill(hit, sig)
        time.sleep(0.1)
    t0 = time.monotonic()
    while until is not None and hit is not None and not until(pipe) and time.monotonic() - t0 < 600:
        events += pipe.step()  # a guard, not a limit: the ground's own limit ends the wait
        time.sleep(0.1)
    events += pipe.finish()
    return pipe, events, hit


def test_a_mapping_process_that_dies_leaves_the_flight_going(replay_test_flight, tmp_path):
    """Live, the mapping process is killed (SIGKILL) part way: the ground does not wait for it for ever (it froze for
    12 minutes), every frame still gets a pose, the flight ends with a map, and the mapper's death is kept for the
    report (exit code, keyframes mapped)."""
    import os
    import signal

    from ground.outputs.summary import summary_markdown

    t0 = time.monotonic()
    pipe, events, killed = _fed_at_flight_pace(replay_test_flight, tmp_path, signal.SIGKILL)
    assert killed is not None, "the mapper never had a model to lose"
    assert time.monotonic() - t0 < 120
    assert [e.frame for e in events] == list(range(20)) and all(e.pose is not None for e in events)
    died = pipe.poses.mapper.died
    assert died and died["exit_code"] == -signal.SIGKILL and died["keyframes_mapped"] >= 4, died
    assert pipe.apples.count.apples, "no apple mapped"
    text = summary_markdown({"apples": 0, "registration": {"mapper_died": died}}, {})
    assert "mapping process died" in text


_MAPPING_OWNER = """
import sys, time
import numpy as np
from ground.poses.mapper_process import MapperProcess
from pomar.camera import Camera

cam = Camera(320, 180, 300.0, 300.0, 160.0, 90.0)
m = MapperProcess(cam, cam, sys.argv[1])
rng = np.random.default_rng(0)
for f in range(3):
    m.add(f, rng.integers(0, 255, (180, 320, 3), dtype=np.uint8), (np.zeros(3), np.array([1.0, 0, 0, 0]), 2.0))
print(m._proc.pid, flush=True)
time.sleep(600)
"""


def test_a_killed_ground_leaves_no_mapping_process_behind(tmp_path):
    """The mapping process stops by itself when the ground that spawned it is killed (SIGKILL: no clean-up runs)."""
    owner = subprocess.Popen([sys.executable, "-c", _MAPPING_OWNER, str(tmp_path)], stdout=subprocess.PIPE, text=True)
    try:
        child = int(owner.stdout.readline())
        os.kill(owner.pid, signal.SIGKILL)
        owner.wait(10)
        t0 = time.monotonic()
        while time.monotonic() - t0 < 60 and os.path.exists(f"/proc/{child}") and \
                open(f"/proc/{child}/stat").read().split()[2] != "Z":
            time.sleep(0.2)
        gone = not os.path.exists(f"/proc/{child}") or open(f"/proc/{child}/stat").read().split()[2] == "Z"
        if not gone:
            os.kill(child, signal.SIGKILL)
        assert gone, "the mapping process outlived its ground"
    finally:
        if owner.poll() is None:
            owner.kill()


def test_apples_need_fewer_strong_views_when_frames_come_sparser(replay_test_flight, tmp_path):
    from ground.apples.counting import CountingSettings
    from ground.pipeline import GroundPipeline, GroundSettings

    needed = {}
    for every in (1, 2, 4):
        pipe = GroundPipeline(tmp_path / f"work-{every}", GroundSettings(counting=CountingSettings(confirm_views=3)))
        for m in _onboard_messages(replay_test_flight, every=every, keyframe_every=0):
            pipe.take(m)
        pipe.finish()
        needed[every] = pipe.apples.count.views_needed(pipe.arrivals.steps)
    assert needed == {1: 3, 2: 2, 4: 2}


def test_harvest_correlation(tmp_path):
    p = tmp_path / "harvest.csv"
    p.write_text("row,kg\n0,10\n1,20\n2,31\n")
    h = read_harvest(p)
    r = harvest_correlation([{"row": 0, "count": 100}, {"row": 1, "count": 210}, {"row": 2, "count": 300}], h)
    assert r["rows"] == 3 and r["r"] > 0.99
    bad = tmp_path / "bad.csv"
    bad.write_text("row,weight\n0,1\n")
    with pytest.raises(ValueError, match="bad.csv"):
        read_harvest(bad)
    # each bad line named, one line each
    for text, says in (("row,kg\n0,10\nB,3\n", "bad.csv:3: row 'B' is not a whole number"),
                       ("row,kg\n0,ten\n", "bad.csv:2: kg 'ten' is not a number"),
                       ("row,kg\n0,10\n1,-2\n", "bad.csv:3: kg -2 is not a yield"),
                       ("row,kg\n0,10\n1,3\n0,4\n", "bad.csv:4: row 0 is given twice")):
        bad.write_text(text)
        with pytest.raises(InputError) as e:
            read_harvest(bad)
        assert str(e.value).startswith(str(bad.parent / says)) and "\n" not in str(e.value), str(e.value)


def test_replay_takes_a_harvest_file(replayed_test_flight, tmp_path):
    """`ground replay --harvest FILE` (as `ground run`): the report correlates the rows' counts with their yields; a
    harvest file that does not read stops it before it starts, with one line naming the line, exit 2."""
    _, out, rep = replayed_test_flight
    rows = [r["row"] for r in rep["rows"]]
    h = tmp_path / "harvest.csv"
    h.write_text("row,kg\n" + "".join(f"{r},{10.0 + 3 * i}\n" for i, r in enumerate(rows)))
    cmd = [sys.executable, "-m", "ground", "replay", "--recorded", str(out / "journal.bin"), "--speed", "0", "--quiet",
           "--out", str(tmp_path / "out"), "--harvest", str(h)]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    got = json.loads((tmp_path / "out" / "report.json").read_text())["harvest_correlation"]
    assert got["rows"] == len(rows), got
    h.write_text("row,kg\n1,x\n")
    r = subprocess.run(cmd[:-2] + ["--out", str(tmp_path / "out2"), "--harvest", str(h)], capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 2 and r.stderr.strip() == f"error: {h}:2: kg 'x' is not a number", r.stderr
    assert not (tmp_path / "out2").exists()


def test_an_apple_counts_once_enough_views_are_strong(tmp_path):
    """Weak detections extend a track; the apple enters the map once confirm_views views scored
    confirm_score, and a merge that brings views from beyond the association's reach never takes it back out."""
    import numpy as np

    from ground.apples.association import Apple, Detection
    from ground.apples.counting import CountingSettings
    from ground.pipeline import GroundPipeline, GroundSettings
    from pomar.camera import Camera

    s = GroundSettings(counting=CountingSettings(confirm_score=0.9, confirm_views=3))
    pipe = GroundPipeline(tmp_path / "work", s)
    pipe.apples.count.camera = Camera.from_fov(640, 360, 60.0)
    pipe.apples.frames.frame = list(range(5))
    views = [Detection(f, 0, score=sc) for f, sc in enumerate([0.95, 0.8, 0.93, 0.75, 0.91])]
    a = Apple(7, np.zeros(3), views[:4], 0.5)
    assert pipe.apples.count.confirm([a], pipe.arrivals.steps) == [] and 7 not in pipe.apples.count.apples  # two strong views of four
    a.observations.append(views[4])
    assert pipe.apples.count.confirm([a], pipe.arrivals.steps) == [a] and pipe.apples.count.apples[7] is a  # a third strong view
    # the flight goes on: frames 0-2 fall out of the association's reach; the count stays
    pipe.apples.frames.frame = list(range(s.association.merge_window + 2 * s.association.k + 3))
    assert pipe.apples.count.confirm([a], pipe.arrivals.steps) == [a]


def test_views_are_confirmed_at_the_score_the_drones_model_operates_at(tmp_path):
    """A drone whose model operates at 0.75 (its camera message says so): a view of 0.8 confirms, as that model's own
    detections count; the ground's confirm_score (0.9) holds where the drone does not say, or when told to."""
    import numpy as np

    from ground.apples.association import Apple, Detection
    from ground.apples.counting import CountingSettings
    from ground.pipeline import GroundPipeline, GroundSettings
    from pomar import wire

    cam = {"model": "PINHOLE", "width": 640, "height": 360, "params": [300.0, 300.0, 320.0, 180.0]}
    for said, own, want in ((0.75, True, 0.75), (None, True, 0.9), (0.75, False, 0.9)):
        pipe = GroundPipeline(tmp_path / f"work-{said}-{own}",
                              GroundSettings(counting=CountingSettings(confirm_at_model_score=own)))
        pipe.start(wire.CameraMessage("f", "d", cam, 10.0, operating_score=said), step=False)
        assert pipe.apples.count.confirm_score == want
        pipe.apples.frames.frame = list(range(5))
        a = Apple(7, np.zeros(3), [Detection(f, 0, score=0.8) for f in range(4)], 0.5)
        assert bool(pipe.apples.count.confirm([a], pipe.arrivals.steps)) == (want < 0.8)
        assert pipe.apples.count.report()["confirm_score"] == want


def test_a_resumed_ground_waits_for_the_frames_its_history_brings(replay_test_flight, tmp_path):
    """A restarted ground gets the frames it missed from the publisher's history and the live ones at once, in either
    order: while it holds gaps, the later frames wait for the missing ones, and none is dropped as late."""
    from ground.pipeline import GroundPipeline, GroundSettings
    from pomar import wire

    msgs = _onboard_messages(replay_test_flight, keyframe_every=1)
    live = [m for m in msgs if getattr(m, "frame", -1) >= 13]
    history = [m for m in msgs if 8 <= getattr(m, "frame", -1) < 13]
    journal = [m for m in msgs if getattr(m, "frame", -1) < 8]  # and the camera message
    for hold, want_late in ((5.0, 0), (0.0, 5)):
        pipe = GroundPipeline(tmp_path / f"work-{hold}", GroundSettings())
        events = []
        for m in journal:
            events += pipe.take(m)
        pipe.hold_gaps(hold)
        for m in live + history:  # the live frames first
            events += pipe.take(m)
        events += pipe.finish()
        assert pipe.counters["late_frames"] == want_late, (hold, pipe.counters)
        if hold:
            assert [e.frame for e in events] == list(range(20)) and all(e.pose is not None for e in events)


@pytest.mark.system
def test_sigterm_during_a_mapper_stall_stops_the_ground_within_5_s(replay_test_flight, tmp_path):
    """The mapping process stalls (SIGSTOP: it answers nothing more) while frames keep coming; `kill PID` on the ground
    ends it within 5 s, with its map files, report and recording written, and its mapping process gone."""
    from ground.replay import free_port

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    out = tmp_path / "ground"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    onboard = subprocess.Popen([sys.executable, "-m", "onboard", "run", str(replay_test_flight.path), "--listen",
                                endpoint, "--detector", "truth-replay", "--realtime", "--wait-for-ground", "30",
                                "--keyframe-every", "1", "--keyframe-width", "0", "--linger", "120"],
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
    errf = open(tmp_path / "ground.err", "w")  # a file, not a pipe nobody reads while the ground runs
    ground = subprocess.Popen([sys.executable, "-m", "ground", "run", "--flight-id", "sim-replay-test", "--connect",
                               endpoint, "--out", str(out), "--fresh", "--idle-timeout", "120"],
                              stdout=subprocess.DEVNULL, stderr=errf, env=env)
    mapping = []
    try:
        journal = out / "journal.bin"
        _wait_for(lambda: journal.is_file() and len(read_journal(journal)) >= 6, 60, "the ground journals messages")
        mapping = _children(ground.pid)
        assert mapping, "no mapping process"
        for pid in mapping:
            os.kill(pid, signal.SIGSTOP)
        time.sleep(2.0)  # frames and keyframes keep coming; the mapper answers nothing
        t0 = time.monotonic()
        ground.send_signal(signal.SIGTERM)
        ground.wait(60)
        took = time.monotonic() - t0
    finally:
        errf.close()
        err = (tmp_path / "ground.err").read_text()
        for pid in mapping:
            try:
                os.kill(pid, signal.SIGCONT)
            except ProcessLookupError:
                pass
        for p in (ground, onboard):
            if p.poll() is None:
                p.send_signal(signal.SIGINT)
                try:
                    p.wait(10)
                except subprocess.TimeoutExpired:
                    p.kill()
    assert took < 5.0, (took, err[-2000:])
    assert ground.returncode == 0, err[-2000:]
    assert json.loads((out / "report.json").read_text())["final"]
    for name in ("apples.csv", "poses.csv", "rows.csv", "flight.rrd"):
        assert (out / name).is_file(), name
    assert _gone(mapping, 10), "the stalled mapping process lives on"



def _mapped_with_a_process(flight, out, msgs, kill_after_keyframes: int | None = None) -> tuple[dict, object]:
    """The messages through a ground pipeline whose mapping runs in a process, each keyframe mapped before the next
    message (so that two runs differ only by what is done to the process); the mapping process killed (SIGKILL)
    once it has mapped ``kill_after_keyframes``. apples.csv and poses.csv written to ``out``, scored against truth."""
    from ground.evaluation.scoring import evaluate_map
    from ground.outputs.snapshot import snapshot
    from ground.outputs.tables import apple_table, apples_csv, pose_table, poses_csv
    from ground.pipeline import GroundPipeline, GroundSettings

    pipe = GroundPipeline(out / "work", GroundSettings(mapping="process"))
    killed = None
    for m in msgs:
        pipe.take(m)
        mapper = pipe.poses.mapper if pipe.poses is not None else None
        if mapper is None:
            continue
        mapper.wait()
        if kill_after_keyframes is not None and killed is None and mapper.answered >= kill_after_keyframes:
            killed = mapper._proc.pid
            os.kill(killed, signal.SIGKILL)
            mapper._proc.join(10)
    pipe.finish()
    (out / "apples.csv").write_text(apples_csv(apple_table(snapshot(pipe))[0]))
    (out / "poses.csv").write_text(poses_csv(pose_table(snapshot(pipe))))
    return evaluate_map(flight, out), pipe


@pytest.mark.parametrize("kill_after", [4, 14, 30])
def test_a_mapping_process_killed_mid_flight_is_restarted_and_the_map_holds(tmp_path, kill_after):
    """The bundled flight, its mapping process killed (SIGKILL) after 4, 14 or 30 keyframes (of about 40): early, as
    8 s into a live run, and near the end. The ground starts another, gives it every keyframe the map held, places
    its rebuilt model in the map's frame by the keyframes both hold, takes it as the map, and maps on: the flight ends
    by itself with a map within 0.03 F1 and 3 % count of the clean run's, and the report and the viewer's summary
    name the restart. (Killed with no restart, the same flight's map fell to F1 0.01-0.04: tracked against a map
    that no longer grew. Rebuilt from the last 16 keyframes only, a kill 4 s into a live run cost 0.1 of F1: issue
    74. Live at 1x, `benchmarks/mapper_restart.py`.)"""
    from ground.outputs.summary import summary_markdown
    from pomar.flight import FlightDir
    from tests.conftest import BUNDLED

    flight = FlightDir(BUNDLED)
    msgs = _onboard_messages(flight)
    (tmp_path / "clean").mkdir()
    (tmp_path / "killed").mkdir()
    clean, _ = _mapped_with_a_process(flight, tmp_path / "clean", msgs)
    ev, pipe = _mapped_with_a_process(flight, tmp_path / "killed", msgs, kill_after_keyframes=kill_after)
    mapper = pipe.poses.mapper
    assert mapper.died and mapper.died["exit_code"] == -signal.SIGKILL, mapper.died
    assert len(mapper.restarts) == 1, mapper.restarts
    placed = mapper.restarts[0]["placed"]
    assert isinstance(placed, dict) and placed["keyframes"] >= 3, placed
    assert placed["centre_residual_max"] < 0.01 * placed["extent"], placed
    restart = mapper.restarts[0]
    # every keyframe the map held was mapped again, and the new model holds them: one model, not a second beside it
    assert restart["keyframes_remapped"] >= len(held := restart["map_keyframes"]) > 0, restart
    assert set(held) <= set(mapper._new_frames), sorted(set(held) - set(mapper._new_frames))
    # mapping went on after the restart: keyframes mapped by the new process, not only tracked against the old map
    assert mapper.stats()["keyframes_processed"] > restart["keyframes_mapped"] + restart["keyframes_remapped"]
    assert abs(ev["f1"] - clean["f1"]) <= 0.03, (ev["f1"], clean["f1"])
    assert abs(ev["count"] - clean["count"]) <= 0.03 * clean["count"], (ev["count"], clean["count"])
    reg = {"mapper_died": mapper.died, "mapper_restarts": mapper.restarts}
    text = summary_markdown({"apples": 0, "registration": reg}, {})
    assert "restarted" in text and "became the map" in text and "lock-step" not in text
    # at the flight's end, the summary (and the ground's log) says how to get the map as if nothing had died
    text = summary_markdown({"apples": 0, "final": True, "registration": reg}, {})
    assert "replay the journal lock-step (`python -m ground replay --recorded OUT/journal.bin --speed 0" in text


@pytest.mark.parametrize("detector", ["truth-replay", "onnx"])
def test_one_lock_step_stream_gives_the_same_map_through_every_entry_point(replay_test_flight, tmp_path, detector):
    """The ground takes its profile from the stream, not from how it was started: a lock-step stream gives the same
    apples.csv, byte for byte, through `ground replay`, `onboard run` + `ground run`, and its recording played at
    --speed 0; the ground says at start which profile the stream asked for. (The bundled flight gave 221 apples one
    way and 202 the other when the start chose.) With the shipped detector too: every entry point's onboard node
    publishes the same detections (pomar.countable.publish_score of the model's threshold; `ground replay` once
    published from 0.7 and `onboard run` from the model's 0.9, 207 apples against 196 on the bundled flight)."""
    from ground.replay import free_port

    flight = replay_test_flight.path
    r = subprocess.run([sys.executable, "-m", "ground", "replay", str(flight), "--detector", detector,
                        "--out", str(tmp_path / "replay"), "--quiet"], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    onboard_log = tmp_path / "onboard.log"
    with open(onboard_log, "w") as olog:
        onboard = subprocess.Popen([sys.executable, "-m", "onboard", "run", str(flight), "--listen", endpoint,
                                    "--detector", detector, "--wait-for-ground", "30", "--linger", "120"],
                                   stdout=olog, stderr=subprocess.STDOUT)
        # the drone lingers as a real one does, serving its history until the ground has everything: with 3 s, a
        # keyframe lost on the link (CI, 2026-11-29) was asked for again just as the drone left, and the map differed
        try:
            g = subprocess.run([sys.executable, "-m", "ground", "run", "--flight-id",
                                replay_test_flight.meta().flight_id, "--connect", endpoint, "--out",
                                str(tmp_path / "run"), "--fresh", "--idle-timeout", "60"],
                               capture_output=True, text=True, timeout=600)
        finally:
            onboard.send_signal(signal.SIGINT)
            try:
                onboard.wait(30)
            except subprocess.TimeoutExpired:
                onboard.kill()
                onboard.wait()
    assert g.returncode == 0, g.stderr[-2000:]
    assert "profile lockstep, from the stream" in g.stderr
    p = subprocess.run([sys.executable, "-m", "ground", "replay", str(flight), "--recorded",
                        str(tmp_path / "replay" / "journal.bin"), "--speed", "0", "--out", str(tmp_path / "played"),
                        "--quiet"], capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr[-2000:]
    first = (tmp_path / "replay" / "apples.csv").read_bytes()
    assert first.count(b"\n") > 5
    # a mismatch under load (2026-11-27 and in CI 2026-11-29, a keyframe lost and the drone gone): what each side
    # received says why
    def why() -> str:
        return (json.dumps(json.loads((tmp_path / "run" / "report.json").read_text()).get("frames"))
                + "\n--- ground run ---\n" + g.stderr[-3000:] + "\n--- onboard run ---\n"
                + onboard_log.read_text()[-2000:])
    assert (tmp_path / "run" / "apples.csv").read_bytes() == first, why()
    assert (tmp_path / "played" / "apples.csv").read_bytes() == first
    report = json.loads((tmp_path / "run" / "report.json").read_text())
    assert report["registration"]["mapping"] == "inline"
    if detector == "onnx":  # the drone said what it sent (from under its model's own threshold), what the tracks need
        from onboard.detector import DEFAULT_MODEL
        from pomar.countable import count_scores

        sent = count_scores(json.loads(DEFAULT_MODEL.with_suffix(".json").read_text()))[1]
        assert report["detections"] == {"published_from": pytest.approx(sent), "needed_from": pytest.approx(sent),
                                        "short": False}
        assert json.loads((tmp_path / "replay" / "report.json").read_text())["detections"] == report["detections"]


def test_a_mapping_process_that_stops_answering_is_taken_for_dead_and_restarted(replay_test_flight, tmp_path,
                                                                                monkeypatch):
    """The mapping process stalls (SIGSTOP) with a keyframe in work: past its stall limit (the product's: 20 times its
    median seconds per keyframe on this machine; at least 2 s once stopped, instead of 60, which is the first model's
    allowance) the ground stops it and starts another, as for one that died; the flight ends with every frame posed.
    (Limits of 1 times the median, or 2 s before the first keyframes were timed, took a healthy process on a busy
    machine for dead.)"""
    from ground.poses.mapper_process import MapperProcess

    pipe, events, stopped = _fed_at_flight_pace(
        replay_test_flight, tmp_path, signal.SIGSTOP, until=lambda p: p.poses.mapper.restarts,
        on_hit=lambda: monkeypatch.setattr(MapperProcess, "STALL_MIN_S", 2.0))
    assert stopped is not None
    assert [e.frame for e in events] == list(range(20)) and all(e.pose is not None for e in events)
    restarts = pipe.poses.mapper.restarts
    assert restarts and restarts[0]["stalled"] and restarts[0]["exit_code"] == -signal.SIGKILL, restarts
    assert _gone([stopped], 10)


def test_frames_after_the_keyframes_stop_are_placed_by_the_apples_they_see(tmp_path):
    """The bundled flight's first 12 s, without its keyframes after 8 s: the frames after them have no image to place
    them, and took their telemetry poses (GPS and gimbal: 0.2 m off), which lost half of a row's apples (live, F1
    0.57 against 0.95, benchmarks/faults.py --only keyframes-stop). They are placed by the apples already mapped
    that they see, and the map holds within 0.03 F1 and 3 % count of the flight's with every keyframe."""
    from ground.evaluation.scoring import evaluate_map
    from ground.outputs.snapshot import snapshot
    from ground.outputs.tables import apple_table, apples_csv, pose_table, poses_csv
    from ground.pipeline import GroundPipeline, GroundSettings
    from pomar import wire
    from pomar.flight import FlightDir
    from tests.conftest import BUNDLED

    flight = FlightDir(BUNDLED)
    fps = flight.meta().fps
    stop, end = int(8 * fps), int(12 * fps)  # the flight's first 12 s, keyframes stopped after 8 s
    msgs = [m for m in _onboard_messages(flight) if getattr(m, "frame", 0) < end]  # the camera message has none
    runs = {}
    for name, stream in (("clean", msgs), ("stopped", [m for m in msgs if not (isinstance(m, wire.KeyframeMessage)
                                                                              and m.frame >= stop)])):
        out = tmp_path / name
        out.mkdir()
        pipe = GroundPipeline(out / "work", GroundSettings(mapping="inline"))
        for m in stream:
            pipe.take(m)
        pipe.finish()
        (out / "apples.csv").write_text(apples_csv(apple_table(snapshot(pipe))[0]))
        (out / "poses.csv").write_text(poses_csv(pose_table(snapshot(pipe))))
        runs[name] = (evaluate_map(flight, out), pipe.counters)
    (clean, _), (ev, counters) = runs["clean"], runs["stopped"]
    assert counters["apples"] >= 0.8 * (end - stop), counters
    assert abs(ev["f1"] - clean["f1"]) <= 0.03, (ev["f1"], clean["f1"])
    assert abs(ev["count"] - clean["count"]) <= 0.03 * clean["count"], (ev["count"], clean["count"])
