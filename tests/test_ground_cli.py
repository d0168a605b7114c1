"""The ground's command line: `ground replay` hands every ground option on to the ground process it starts."""

from __future__ import annotations

import argparse

from ground.__main__ import _ground_argv, _ground_options, _settings


def test_replay_hands_every_ground_option_to_the_ground():
    p = argparse.ArgumentParser()
    _ground_options(p)
    given = ["--track-points", "600", "--min-share-to-go-on", "0.3", "--init-frames", "4", "--init-spacing-s", "0.7",
             "--upright", "--no-revisit", "--confirm-score", "0.8", "--mapping", "inline"]
    args = p.parse_args(given)
    again = p.parse_args(_ground_argv(args))
    # every option as given, but --mapping, which the replay chooses (lock-step or live)
    assert vars(again) == {**vars(args), "mapping": p.get_default("mapping")}
    s = _settings(again)
    assert s.tracking.max_points == 600 and s.tracking.min_share_to_go_on == 0.3
    assert s.registration.init_frames == 4 and s.init_spacing_s == 0.7
    assert s.registration.upright and not s.registration.revisit and s.counting.confirm_score == 0.8
    # switches left off stay off
    assert "--upright" not in _ground_argv(p.parse_args([]))


def test_sigterm_stops_the_ground_as_ctrl_c_does(tmp_path):
    """`kill PID` on a running ground: it finishes and writes its map and report, as on Ctrl-C, instead of dying with
    nothing written (a real zenoh session on loopback, no publisher)."""
    import json
    import signal
    import subprocess
    import sys
    import time

    from ground.replay import free_port

    cmd = [sys.executable, "-m", "ground", "run", "--flight-id", "sim-sigterm", "--listen",
           f"tcp/127.0.0.1:{free_port()}", "--out", str(tmp_path), "--no-rrd", "--idle-timeout", "120"]
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        t0 = time.monotonic()
        while not (tmp_path / "journal.bin").exists() and time.monotonic() - t0 < 60:
            time.sleep(0.2)
        time.sleep(1.0)  # its session open and listening
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err[-2000:]
    assert "interrupted" in err
    assert json.loads((tmp_path / "report.json").read_text())["final"]
