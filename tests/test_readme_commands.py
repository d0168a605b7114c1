"""README's "Your own flight" commands, read from README.md and run as written, end to end, on a short simulated
flight (sim/configs/readme-test.toml: a Phantom 4 Pro's lens, 60 degrees below the horizon, looking across the rows):
the files they name (DJI_0042.MP4, DJI_0042.SRT, flight.mp4, 00000042.BIN, camera.json, log_42.ulg) are made in a
working folder under those names; the DJI commands run once per SRT layout of the real files in
../shared/datasets/logs/dji-srt, with and without attitude fields. A README command that breaks fails here."""

from __future__ import annotations

import csv
import json
import re
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
LOGS = ROOT.parent / "shared" / "datasets" / "logs"
CONFIG = ROOT / "sim" / "configs" / "readme-test.toml"


def readme_commands(section: str = "### Your own flight") -> list[str]:
    """The commands of the first bash block under ``section`` in README.md, one per line (comments left out)."""
    text = (ROOT / "README.md").read_text()
    block = re.search(r"```bash\n(.*?)```", text[text.index(section):], re.S).group(1)
    return [line.strip() for line in block.splitlines() if line.strip() and not line.lstrip().startswith("#")]


def command(*words: str) -> str:
    """The one README command holding all these words."""
    found = [c for c in readme_commands() if all(w in c for w in words)]
    assert len(found) == 1, (words, found)
    return found[0]


def run(cmd: str, cwd: Path, timeout: float = 300, **kw) -> subprocess.CompletedProcess:
    """A README command as written, in ``cwd``, with this interpreter for ``.venv/bin/python``."""
    argv = shlex.split(cmd)
    assert argv[0] == ".venv/bin/python", cmd
    return subprocess.run([sys.executable] + argv[1:], cwd=cwd, capture_output=True, text=True, timeout=timeout, **kw)


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    from pomar.flight import FlightDir
    from sim import config
    from sim.flight import simulate_flight

    out = tmp_path_factory.mktemp("readme") / "flight"
    simulate_flight(config.load(CONFIG), out, jobs=2, progress=False)
    r = subprocess.run([sys.executable, "-m", "sim", "logs", str(out)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    return FlightDir(out)


def workdir(tmp_path: Path, files: dict[str, Path]) -> Path:
    """A folder holding ``files`` under README's names, and the repository's models where README names them."""
    for name, src in files.items():
        shutil.copy(src, tmp_path / name)
    (tmp_path / "onboard").symlink_to(ROOT / "onboard")
    return tmp_path


def score(flight, out: Path) -> dict:
    from ground.evaluation.scoring import evaluate_map

    return evaluate_map(flight, out)


#: (layout, with attitudes) -> the least shape F1 its map must reach. The one-a-second layouts that write 4 decimals
#: (11 m) scale their maps by the heights above take-off (ground.poses.mapper); the Mavic 2's layout writes neither a
#: height nor an altitude, and nothing scales its map: it must run to a map without an error, its F1 is printed.
DJI = {("mavic3", False): 0.7, ("mavic3", True): 0.7, ("air2s", False): 0.7, ("p4p", True): 0.7,
       ("p4p", False): 0.7, ("home", False): 0.7, ("m300", False): 0.7, ("mavic2", False): None}


@pytest.mark.parametrize("layout,attitude", sorted(DJI))
def test_dji_command(flight, tmp_path, layout, attitude):
    """README's DJI command on the flight's MP4 with an SRT of this layout: a map, scored against the truth."""
    out = tmp_path / "srt"
    r = subprocess.run([sys.executable, "-m", "sim", "logs", str(flight.path), "--out", str(out), "--srt-layout", layout]
                       + ([] if attitude else ["--no-attitude"]), capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    (tmp_path / "wd").mkdir()
    wd = workdir(tmp_path / "wd", {"DJI_0042.MP4": flight.video, "DJI_0042.SRT": out / "video.SRT"})
    r = run(command("ground replay", "DJI_0042.SRT"), wd)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "Traceback" not in r.stderr
    res = wd / "out" / "replay" / "DJI_0042"
    rep = json.loads((res / "report.json").read_text())
    assert rep["frames"]["frames"] == flight.meta().frame_count
    # every frame posed, those past a once-a-second log's last subtitle too (carried on from the map's poses)
    assert rep["frames"]["frames_without_pose"] == 0, rep["frames"]
    print({k: rep["frames"][k] for k in ("registered", "tracked", "interpolated", "extrapolated", "apples", "telemetry")})
    ev = score(flight, res)
    least = DJI[(layout, attitude)]
    print(f"{layout} {'with' if attitude else 'without'} attitudes: {rep['apples']} apples, shape F1 {ev['f1']:.3f}, "
          f"count error {ev['count_error_pct']:+.1f} %")
    if least is not None:
        assert ev["f1"] >= least, ev
    # positions rounded to 11 m cannot scale a map: the barometric heights above take-off (H, BAROMETER) do; a layout
    # without a height is scaled by its positions (the Air 2S's `altitude` is of no stated reference)
    scaled_by = rep["registration"]["georeference_scale_from"]
    # the scale, its 1-sigma and each source's estimate and weight (ground.poses.scale); the heaviest names it
    sc = rep["registration"]["georeference_scale"]
    used = {s["name"]: s["weight"] for s in sc["sources"] if s["weight"] > 0}
    assert 0 < sc["sigma_pct"] < 100 and abs(sum(used.values()) - 1) < 1e-9 and max(used, key=used.get) == scaled_by, sc
    if layout in ("home", "m300") or (layout == "p4p" and not attitude):
        assert scaled_by == "heights", rep["registration"]
    if layout in ("air2s", "mavic2"):
        assert scaled_by == "positions", rep["registration"]
    # only abs_alt places the map above sea level; a height above take-off (H, BAROMETER) or an altitude of no stated
    # reference leaves the outputs' alt empty and the GeoJSON 2-D, as report.json says
    above = layout == "mavic3"
    assert rep["map"]["above_sea_level"] is above and rep["map"]["origin"] is not None, rep["map"]
    alt = np.array([float(r["alt"]) for r in csv.DictReader((res / "apples.csv").open())])
    assert len(alt) and np.isfinite(alt).all() == above and np.isnan(alt).all() != above
    dims = {len(f["geometry"]["coordinates"]) for f in json.loads((res / "apples.geojson").read_text())["features"]}
    assert dims == {3 if above else 2}, dims


def test_ardupilot_command(flight, tmp_path):
    """README's ArduPilot command: the video, the DataFlash .bin (CAM events time the frames, MNT the gimbal)."""
    wd = workdir(tmp_path, {"flight.mp4": flight.video, "00000042.BIN": flight.path / "telemetry.bin",
                            "camera.json": flight.path / "camera.json"})
    r = run(command("ground replay", "00000042.BIN"), wd)
    assert r.returncode == 0, r.stderr[-3000:]
    res = wd / "out" / "replay" / "flight"
    ev = score(flight, res)
    assert ev["f1"] >= 0.7, ev


@pytest.mark.skipif(not LOGS.is_dir(), reason="../shared/datasets/logs not present")
def test_px4_command(flight, tmp_path):
    """README's PX4 command: a video whose container starts 5 s into the shared .ulg (a drone on the ground: its
    positions cannot place a moving camera, so the map is scored for the record, not held to a figure)."""
    from pomar.telemetry import read_log

    ulg = LOGS / "px4-ulog" / "sample_px4_events.ulg"
    start = int(read_log(ulg).position.t[0]) + 5
    wd = workdir(tmp_path, {"log_42.ulg": ulg, "camera.json": flight.path / "camera.json"})
    data = bytearray(flight.video.read_bytes())
    i = data.find(b"mvhd")
    data[i + 8:i + 12] = (start + 2082844800).to_bytes(4, "big")
    (wd / "flight.mp4").write_bytes(bytes(data))
    r = run(command("ground replay", "log_42.ulg"), wd)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "the container's creation time" in r.stderr, r.stderr[-3000:]
    rep = json.loads((wd / "out" / "replay" / "flight" / "report.json").read_text())
    assert rep["frames"]["frames"] == flight.meta().frame_count
    score(flight, wd / "out" / "replay" / "flight")


def test_onboard_command_feeds_a_ground(flight, tmp_path):
    """README's live-style command, the onboard node alone, with a ground connected to its default endpoint."""
    wd = workdir(tmp_path, {"DJI_0042.MP4": flight.video})
    r = subprocess.run([sys.executable, "-m", "sim", "logs", str(flight.path), "--out", str(tmp_path / "srt"),
                        "--no-attitude"], capture_output=True, text=True)
    assert r.returncode == 0
    shutil.copy(tmp_path / "srt" / "video.SRT", wd / "DJI_0042.SRT")
    ground = subprocess.Popen([sys.executable, "-m", "ground", "run", "--flight-id", "dji-0042", "--connect",
                               "tcp/127.0.0.1:7447", "--out", str(tmp_path / "ground"), "--no-rrd", "--idle-timeout",
                               "60"], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        cmd = command("onboard run", "DJI_0042.SRT") + " --linger 5"
        r = run(cmd, wd)
        assert r.returncode == 0, r.stderr[-3000:]
        assert ground.wait(timeout=120) == 0
    finally:
        if ground.poll() is None:
            ground.kill()
            ground.wait()
    ev = score(flight, tmp_path / "ground")
    assert ev["f1"] >= 0.7, ev


def test_telemetry_flight_cameras_and_scale_commands(flight, tmp_path):
    """The other commands of the section: what a log holds, the flight directory alone and sim info on it, the
    built-in cameras, the apple size foreseen."""
    wd = workdir(tmp_path, {"DJI_0042.MP4": flight.video})
    r = subprocess.run([sys.executable, "-m", "sim", "logs", str(flight.path), "--out", str(tmp_path / "srt"),
                        "--no-attitude"], capture_output=True, text=True)
    assert r.returncode == 0
    shutil.copy(tmp_path / "srt" / "video.SRT", wd / "DJI_0042.SRT")
    r = run(command("onboard telemetry", "DJI_0042.SRT"), wd)
    assert r.returncode == 0, r.stderr
    summary = json.loads((wd / "out" / "DJI_0042-telemetry.json").read_text())
    assert summary["format"] == "srt" and summary["positions"] == flight.meta().frame_count
    assert any("--camera-yaw-deg" in p for p in summary["problems"])
    r = run(command("pomar flight", "DJI_0042.SRT"), wd)
    assert r.returncode == 0, r.stderr
    assert (wd / "out" / "flights" / "DJI_0042" / "flight.json").is_file()
    r = run(command("sim info"), wd)
    assert r.returncode == 0 and "telemetry (srt" in r.stdout, r.stdout + r.stderr
    r = run(command("pomar cameras"), wd)
    assert r.returncode == 0 and "phantom-4-pro" in r.stdout
    r = run(command("pomar scale"), wd)
    assert r.returncode == 0 and "apple radius foreseen at 12 m" in r.stdout, r.stdout + r.stderr


def test_every_command_of_the_section_is_run_here():
    """Each command of the section is one of those the tests above run."""
    ran = [("ground replay", "DJI_0042.SRT"), ("ground replay", "00000042.BIN"), ("ground replay", "log_42.ulg"),
           ("onboard run", "DJI_0042.SRT"), ("onboard telemetry", "DJI_0042.SRT"), ("pomar flight", "DJI_0042.SRT"),
           ("sim info",), ("pomar cameras",), ("pomar scale",)]
    for c in readme_commands():
        assert sum(all(w in c for w in words) for words in ran) == 1, c


def test_make_check_is_the_quick_tier():
    """README's `make check`: what it runs (make -n shows it, as written in the Makefile) selects every test that is
    not marked `system`, none that renders or replays a flight, and runs in the environment `make test` set up."""
    import os
    import re
    import shlex
    import subprocess
    import sys

    from tests.conftest import SYSTEM_FILES

    env = dict(os.environ, VENV=str(Path(sys.executable).parents[1]))  # the environment these tests run in
    dry = subprocess.run(["make", "-n", "check"], cwd=ROOT, capture_output=True, text=True, env=env, timeout=60)
    assert dry.returncode == 0, dry.stderr
    line = [ln for ln in dry.stdout.splitlines() if "-m pytest" in ln][-1]
    cmd = shlex.split(line)
    assert cmd[cmd.index("-m", cmd.index("pytest")) + 1] == "not system"
    listed = subprocess.run([sys.executable, *[c for c in cmd[1:] if c != "-q"], "--collect-only", "-q"], cwd=ROOT,
                            capture_output=True,
                            text=True, timeout=300)
    assert listed.returncode == 0, listed.stdout[-2000:]
    ids = [ln for ln in listed.stdout.splitlines() if "::" in ln]
    assert len(ids) > 100
    assert not [i for i in ids if i.split("::")[0].rsplit("/", 1)[-1] in SYSTEM_FILES]
    assert re.search(r"\d+/\d+ tests collected \(\d+ deselected\)", listed.stdout)
