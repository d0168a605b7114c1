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
    # every option as given, --mapping too (by default the stream chooses: lock-step or live)
    assert vars(again) == vars(args)
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


def test_every_ground_setting_option_comes_from_its_field():
    """Settings declared once: each option of `ground run` that sets the ground's settings takes its default from
    the live profile's field and its help from the field's doc (none without one)."""
    from ground.__main__ import (ASSOCIATION_FIELDS, COUNTING_FIELDS, GROUND_FIELDS, REGISTRATION_FIELDS,
                                 TRACKING_FIELDS)
    from ground.pipeline import GroundSettings, profile
    from pomar.settings import field_docs

    p = argparse.ArgumentParser()
    _ground_options(p)
    g = GroundSettings()
    helps = {a.dest: a.help for a in p._actions}
    for obj, names in ((g.association, ASSOCIATION_FIELDS), (g.registration, REGISTRATION_FIELDS),
                       (g.tracking, TRACKING_FIELDS), (g.counting, COUNTING_FIELDS), (g, GROUND_FIELDS)):
        docs = field_docs(type(obj))
        for n in names:
            assert p.get_default(n) == getattr(obj, n), n
            assert docs.get(n) and docs[n].split()[0].rstrip(",.:;") in helps[n], (n, helps[n])
    assert p.get_default("mapping") == "stream"
    assert profile("live").mapping == "process" and profile("lockstep").mapping == "inline"


def test_ground_run_help_lists_every_setting_as_readme_says():
    """README: `python -m ground run --help` lists each setting with its default."""
    import subprocess
    import sys

    r = subprocess.run([sys.executable, "-m", "ground", "run", "--help"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    for opt in ("--confirm-score", "--max-interp-gap", "--track-points", "--no-revisit", "--mapping"):
        assert opt in r.stdout, opt
    assert "default 0.9" in " ".join(r.stdout.split())


def test_every_onboard_setting_option_comes_from_its_field():
    """The same for `onboard run`: NodeSettings' fields are its options (the keyframe width was 960 on the command
    line and 0 in the dataclass); the parsed options give the NodeSettings the node runs with."""
    import onboard.__main__ as om
    from onboard.node import NodeSettings
    from pomar.settings import field_docs, from_options

    p = argparse.ArgumentParser()
    om.add_options(p, NodeSettings(), om.RUN_FIELDS)
    om._link_options(p)
    om.add_options(p, NodeSettings(), om.SCALE_FIELDS)
    om.mount_arguments(p)
    docs = field_docs(NodeSettings)
    for n in om.RUN_FIELDS + om.LINK_FIELDS + om.SCALE_FIELDS:
        assert p.get_default(n) == getattr(NodeSettings(), n) and docs.get(n), n
    fields = om.RUN_FIELDS + om.LINK_FIELDS + om.SCALE_FIELDS + om.MOUNT_FIELDS
    s = from_options(NodeSettings(), p.parse_args(["--realtime", "--keyframe-width", "0", "--camera-tilt-deg", "60"]),
                     fields)
    assert s.realtime and s.keyframe_width == 0 and s.camera_tilt_deg == 60.0 and s.detector_scale == "auto"
