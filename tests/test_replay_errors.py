"""`ground replay` tells the truth: a flight the onboard node cannot play ends the replay with a non-zero exit
and the onboard node's error, naming the file; ids that zenoh key expressions forbid and a directory given
as a log are refused with a message, not a traceback."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys

import pytest


def _run(*args, timeout=120) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", *args], capture_output=True, text=True, timeout=timeout)


def _heartbeat_only_tlog(path) -> None:
    """A real MAVLink 2 .tlog with heartbeats and attitude but no position."""
    import struct

    from pomar.mavlink import dialect

    mav = dialect().MAVLink(None, srcSystem=1, srcComponent=1)
    with open(path, "wb") as f:
        for i in range(20):
            t = 1.5e9 + i * 0.1
            for m in (mav.heartbeat_encode(2, 3, 0, 0, 4), mav.attitude_encode(i * 100, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)):
                f.write(struct.pack(">Q", int(t * 1e6)) + m.pack(mav))


@pytest.mark.parametrize("case", ["video", "tlog", "no-position", "camera-json", "camera-size"])
def test_replay_exits_non_zero_with_the_onboard_error(replay_test_flight, tmp_path, case):
    fl = tmp_path / "flight"
    shutil.copytree(replay_test_flight.path, fl)
    expect = {"video": "video.mp4", "tlog": "telemetry.tlog", "no-position": "no position",
              "camera-json": "camera.json", "camera-size": "320x180"}[case]
    if case == "video":
        (fl / "video.mp4").write_bytes(b"not a video" * 100)
    elif case == "tlog":
        (fl / "telemetry.tlog").write_bytes(bytes(range(256)) * 40)
    elif case == "no-position":
        _heartbeat_only_tlog(fl / "telemetry.tlog")
    elif case == "camera-json":
        (fl / "camera.json").write_text("{ this is not json")
    else:
        cam = json.loads((fl / "camera.json").read_text())
        cam["width"], cam["height"] = 320, 180
        (fl / "camera.json").write_text(json.dumps(cam))
    r = _run("ground", "replay", str(fl), "--out", str(tmp_path / "out"), "--detector", "truth-replay", "--quiet")
    assert r.returncode != 0, r.stdout[-2000:]
    assert "error:" in r.stderr and expect in r.stderr, r.stderr[-2000:]
    assert "Traceback" not in r.stderr
    if case == "camera-size":
        assert "640x360" in r.stderr  # both sizes named


def test_bad_ids_and_a_directory_as_log_are_refused_with_a_message(replay_test_flight, tmp_path):
    fl = tmp_path / "flight"
    shutil.copytree(replay_test_flight.path, fl)
    meta = json.loads((fl / "flight.json").read_text())
    meta["flight_id"] = "orchard/north"
    (fl / "flight.json").write_text(json.dumps(meta))
    for args in (("ground", "replay", str(fl), "--out", str(tmp_path / "o")),
                 ("onboard", "run", str(fl), "--detector", "truth-replay"),
                 ("ground", "run", "--flight-id", "a/b", "--out", str(tmp_path / "g")),
                 ("onboard", "telemetry", str(fl))):
        r = _run(*args, timeout=60)
        assert r.returncode == 2, (args, r.stderr[-1500:])
        assert "Traceback" not in r.stderr and ("orchard/north" in r.stderr or "'a/b'" in r.stderr
                                                or "is a directory" in r.stderr), (args, r.stderr[-1500:])


def test_an_output_folder_the_replay_cannot_write_is_refused_with_a_message(replay_test_flight, tmp_path):
    """Nothing is computed yet: one line names the folder and why, and the replay starts nothing."""
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    r = _run("ground", "replay", str(replay_test_flight.path), "--out", str(blocker / "out"), "--detector",
             "truth-replay", "--quiet")
    assert r.returncode == 1 and "Traceback" not in r.stderr, r.stderr[-2000:]
    assert f"error: {blocker / 'out'}: the replay cannot write there" in r.stderr, r.stderr[-2000:]
