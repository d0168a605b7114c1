"""A recorded stream (a ground's journal.bin) played again over real zenoh on loopback into a ground in another
process, at its capture-time pace; bad recordings refused with a message naming the file."""

from __future__ import annotations

import json

import msgpack
import pytest

from ground.link.journal import HEADER, record
from ground.link.player import PlayerError, load_recording


def test_recorded_stream_at_real_time_maps_as_the_lock_step_replay(replayed_test_flight, tmp_path):
    from ground.replay import replay

    flight, out, ref = replayed_test_flight
    rep = replay(flight.path, tmp_path / "played", recorded=out / "journal.bin", speed=1.0, quiet=True)
    assert rep["replay"]["recorded"] and rep["onboard"]["frames_processed"] == 20
    assert rep["frames"]["frames"] == 20 and rep["frames"]["missing_frames"] == 0 and rep["final"]
    # at the recording's pace (20 frames at 5 fps): the replay takes about the flight's 4 s, not less
    assert rep["onboard"]["seconds"] >= 0.9 * (19 / 5)
    assert 0.5 * ref["apples"] - 2 <= rep["apples"] <= 1.5 * ref["apples"] + 2, (rep["apples"], ref["apples"])
    assert rep["timings"]["frame_delay_p95_s"] is not None
    assert abs(sum(rep["pose_shares"].values()) - 1.0) < 1e-9


def test_readme_after_the_flight_command_maps_a_recorded_stream_alone(replayed_test_flight, tmp_path):
    """README's "After the flight" command, as written, in a folder holding a ground's journal where it says: the
    stream alone (no flight directory) gives the map its flight's lock-step replay gives, byte for byte, with nothing
    to score against."""
    import re
    import shlex
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    from ground.replay import replay

    flight, out, _ = replayed_test_flight
    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    block = re.search(r"```bash\n(.*?)```", text[text.index("**After the flight.**"):], re.S).group(1)
    (cmd,) = [line for line in block.splitlines() if line.strip()]
    argv = shlex.split(cmd)
    assert argv[:4] == [".venv/bin/python", "-m", "ground", "replay"] and "--recorded" in argv, cmd
    journal = tmp_path / argv[argv.index("--recorded") + 1]
    journal.parent.mkdir(parents=True)
    shutil.copy(out / "journal.bin", journal)
    r = subprocess.run([sys.executable] + argv[1:], cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stdout + r.stderr
    final = tmp_path / argv[argv.index("--out") + 1]
    ref = replay(flight.path, tmp_path / "with-flight", recorded=out / "journal.bin", speed=0, quiet=True)
    assert (final / "apples.csv").read_bytes() == (tmp_path / "with-flight" / "apples.csv").read_bytes()
    rep = json.loads((final / "report.json").read_text())
    assert rep["flight_id"] == "sim-replay-test" and rep["final"] and rep["frames"]["frames"] == 20
    assert "evaluation" not in rep and "evaluation" in ref and rep["replay"]["flight"] is None
    assert rep["flight_seconds"] == pytest.approx(20 / 5, rel=0.01)


def test_live_pose_corrections_wait_for_their_period_and_still_come(replayed_test_flight, tmp_path, slowness):
    """Live, the poses given out are corrected at most once per --correction-every-s: with a period longer than the
    flight, only the end's round runs, and it still corrects the frames the mapper's keyframes moved. The stream is
    played at the flight's pace slowed by the machine's slowness (tests/machine.py): on a busy machine at the flight's
    own pace the live ground mapped 7 keyframes of 20, none moved, and there was nothing to correct. No round can come
    during the flight, so the frames corrected are the end's rounds' (without them, none is)."""
    from ground.replay import replay

    flight, out, ref = replayed_test_flight
    rep = replay(flight.path, tmp_path / "played", recorded=out / "journal.bin", speed=1.0 / slowness, quiet=True,
                 ground_args=["--correction-every-s", "600"])
    c = rep["corrections"]
    assert 1 <= c["rounds"] <= 2 and c["frames"] > 0, (c, slowness, rep["frames"], rep["registration"])
    assert 0.5 * ref["apples"] - 2 <= rep["apples"] <= 1.5 * ref["apples"] + 2, (rep["apples"], ref["apples"])


def test_bad_recordings_are_refused_naming_the_file(replayed_test_flight, tmp_path):
    _, out, _ = replayed_test_flight
    journal = (out / "journal.bin").read_bytes()
    good = load_recording(out / "journal.bin")
    assert good.flight_id == "sim-replay-test" and good.frames == 20 and good.items[0][1] == "camera"
    # another flight than asked for
    with pytest.raises(PlayerError, match="journal.bin: a recording of flight 'sim-replay-test', not 'other'"):
        load_recording(out / "journal.bin", "other")
    # not a journal at all
    junk = tmp_path / "junk.bin"
    junk.write_bytes(b"\x00\x01garbage" * 100)
    with pytest.raises(PlayerError, match="junk.bin: not a pomar journal"):
        load_recording(junk)
    # a schema version this build cannot read
    future = tmp_path / "future.bin"
    future.write_bytes(HEADER + record(msgpack.packb({"v": 99, "type": "frame2"})) + journal[len(HEADER):])
    with pytest.raises(PlayerError, match="future.bin: record 0: unknown schema version 99"):
        load_recording(future)
    # cut in the middle of a record: every complete record before the cut still plays
    cut = tmp_path / "cut.bin"
    cut.write_bytes(journal[: len(journal) * 2 // 3])
    part = load_recording(cut)
    assert 0 < len(part.items) < len(good.items) and part.damaged_bytes > 0
    assert any("damaged bytes" in p for p in part.problems)
    assert [it[2] for it in part.items][:5] == [it[2] for it in good.items][:5]
