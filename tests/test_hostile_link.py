"""Hostile messages published into a live flight (issue 18's table), all processes separate, real zenoh on
loopback: the ground refuses each, counts it under its reason in report.json and the rerun log, nobody dies,
and the map ends as the clean run's within a loose bound."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

from ground.link.journal import read_journal
from ground.replay import stop_process

HERE = Path(__file__).resolve().parent


def _fly(flight, out: Path, inject: bool) -> tuple[dict, dict, dict | None]:
    """One real-time flight of the truth-replay onboard node into a ground node; with ``inject``, the hostile
    peer publishes its messages once the ground has taken a few. Returns the ground's report, the onboard
    summary and what the injector sent."""
    from ground.replay import free_port

    meta = flight.meta()
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    drone_ep, ground_ep = f"tcp/127.0.0.1:{free_port()}", f"tcp/127.0.0.1:{free_port()}"
    out.mkdir(parents=True)
    procs, sent = [], None
    ground = subprocess.Popen([sys.executable, "-m", "ground", "run", "--flight-id", meta.flight_id, "--connect", drone_ep,
                               "--listen", ground_ep, "--out", str(out), "--fresh", "--idle-timeout", "30"],
                              stdout=subprocess.DEVNULL, stderr=open(out / "ground.log", "w"), env=env)
    procs.append(ground)
    try:
        if inject:
            injector = subprocess.Popen([sys.executable, str(HERE / "hostile_injector.py"), ground_ep, meta.flight_id,
                                         meta.drone_id, str(flight.path / "camera.json")],
                                        stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, env=env)
            procs.append(injector)
            assert injector.stdout.readline().strip() == "ready"
        onboard = subprocess.Popen([sys.executable, "-m", "onboard", "run", str(flight.path), "--listen", drone_ep,
                                    "--detector", "truth-replay", "--realtime", "--wait-for-ground", "30", "--keyframe-every", "1",
                                    "--keyframe-width", "0", "--linger", "120", "--summary", str(out / "onboard.json")],
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=env)
        procs.append(onboard)
        if inject:
            journal = out / "journal.bin"
            t0 = time.monotonic()
            while not (journal.is_file() and len(read_journal(journal)) >= 6) and time.monotonic() - t0 < 60:
                time.sleep(0.05)
            injector.stdin.write("go\n")
            injector.stdin.flush()
            sent = json.loads(injector.stdout.readline())
        ground.wait(240)
        assert ground.returncode == 0, (out / "ground.log").read_text()[-3000:]
        for p in procs[1:]:
            assert p.poll() is None, "a process died"
    finally:
        if inject and injector.poll() is None:
            injector.stdin.write("stop\n")
            injector.stdin.flush()
        for p in procs:
            stop_process(p)
    return json.loads((out / "report.json").read_text()), json.loads((out / "onboard.json").read_text()), sent


def test_hostile_messages_are_refused_counted_and_harmless(replay_test_flight, tmp_path):
    from ground.outputs.rrd_file import rrd_entities

    clean, clean_sent, _ = _fly(replay_test_flight, tmp_path / "clean", inject=False)
    rep, onboard, sent = _fly(replay_test_flight, tmp_path / "hostile", inject=True)
    link = rep["link"]
    # each case counted under its reason; the valid ones (a false "finished", a camera with an int fps) harmless
    expected: dict[str, int] = {}
    for reason in sent.values():
        if reason != "accepted":
            expected[reason] = expected.get(reason, 0) + 1
    assert link["rejected"] == expected, (link, sent)
    assert link["drone_ids"] == [replay_test_flight.meta().drone_id]
    assert link["ignored_end_claims"] >= 1  # the "finished" status sent while the drone flew
    # the flight ran to its end, with every frame the drone sent and nothing else
    assert rep["final"] and rep["frames"]["frames"] == onboard["frames_processed"]
    assert rep["frames"]["late_frames"] == 0 and rep["registration"]["failed"] <= clean["registration"]["failed"] + 2
    # the map as the clean run's, within a loose bound: a live ground's poses depend on when each frame is mapped
    # against the model's progress, and on this 20-frame flight clean runs give 15-21 apples; what the attacks did
    # before was to multiply the map (636 and 489 apples against 190)
    assert 0.5 * clean["apples"] - 2 <= rep["apples"] <= 1.5 * clean["apples"] + 2, (rep["apples"], clean["apples"])
    # the refusals are in the rerun log too
    ents = rrd_entities(tmp_path / "hostile" / "flight.rrd")
    for reason in expected:
        assert f"/stats/rejected/{reason}" in ents, (reason, sorted(e for e in ents if e.startswith("/stats")))
