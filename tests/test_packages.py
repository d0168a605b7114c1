"""Package layout: every package runs with --help; onboard and ground never import torch."""

from __future__ import annotations

import subprocess
import sys

import pytest


@pytest.mark.parametrize("package", ["sim", "onboard", "ground", "export", "pomar"])
def test_help(package):
    r = subprocess.run([sys.executable, "-m", package, "--help"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert f"python -m {package}" in r.stdout


def test_onboard_and_ground_do_not_import_torch():
    code = ("import sys, pomar.flight, pomar.camera, pomar.geo, onboard, ground, ground.apples.geometry; "
            "assert 'torch' not in sys.modules and 'torchvision' not in sys.modules; print('ok')")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
    assert r.returncode == 0 and "ok" in r.stdout, r.stderr


def test_demo_commands_on_bundled_flight(tmp_path):
    from tests.conftest import BUNDLED

    r = subprocess.run([sys.executable, "-m", "sim", "info", str(BUNDLED)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    assert "178 frames" in r.stdout and "CAMERA_FEEDBACK 178" in r.stdout
    png = tmp_path / "f.png"
    r = subprocess.run([sys.executable, "-m", "sim", "show", str(BUNDLED), "--frame", "80", "--out", str(png)],
                       capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    import cv2

    assert cv2.imread(str(png)).shape == (720, 1280, 3)


def test_missing_flight_dir_is_a_clear_error(tmp_path):
    r = subprocess.run([sys.executable, "-m", "sim", "info", str(tmp_path / "nowhere")], capture_output=True, text=True)
    assert r.returncode == 2 and "nowhere" in r.stderr and "Traceback" not in r.stderr


def test_nothing_generated_is_committed():
    """The repository's root holds the project's folders and files only; logs and outputs live in git-ignored
    folders (out/)."""
    import shutil
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    if shutil.which("git") is None or not (root / ".git").exists():
        pytest.skip("not a git checkout")
    r = subprocess.run(["git", "ls-files"], cwd=root, capture_output=True, text=True, check=True)
    files = r.stdout.splitlines()
    top = {f.split("/")[0] for f in files}
    allowed = {".ci", ".gitignore", "Makefile", "README.md", "pyproject.toml", "requirements.lock", "benchmarks", "docs",
               "export", "ground",
               "onboard", "pomar", "replay_data", "sim", "tests"}
    assert top <= allowed, sorted(top - allowed)
    assert not [f for f in files if f.endswith(".log") or f.startswith("out/")]


def _imports(path) -> set[str]:
    """The modules a source file imports, anywhere in it (function-level imports too)."""
    import ast

    names = set()
    for n in ast.walk(ast.parse(path.read_text())):
        if isinstance(n, ast.Import):
            names.update(a.name for a in n.names)
        elif isinstance(n, ast.ImportFrom) and n.module:
            names.add(n.module)
    return names


def test_the_link_sits_below_the_pipeline_and_the_outputs():
    """ground/link/ (the stream in: journal, arrivals, envelope, player) imports neither the pipeline, nor the
    outputs, nor the ground's program: the one way the ground's imports go is down."""
    from pathlib import Path

    link = Path(__file__).resolve().parents[1] / "ground" / "link"
    above = ("ground.pipeline", "ground.outputs", "ground.node", "ground.replay", "ground.poses", "ground.apples")
    bad = {p.name: sorted(m for m in _imports(p) if m.startswith(above)) for p in sorted(link.glob("*.py"))}
    assert not any(bad.values()), {k: v for k, v in bad.items() if v}


def test_nothing_outside_the_pose_stage_reaches_into_its_parts():
    """The pose stage (ground/poses/) answers through PoseStage' own methods: what a frame's pose is, the corrections,
    when it is ready, its figures. Nothing else in ground/ reaches its tracking, mapper or map frame."""
    import re
    from pathlib import Path

    ground = Path(__file__).resolve().parents[1] / "ground"
    reach = re.compile(r"(?<![\w.])poses\.(tracking|mapper|map_frame)\b|(?<!ground)\.poses\.(tracking|mapper|map_frame)\b")
    bad = [f"{p.relative_to(ground)}:{k}: {line.strip()}" for p in sorted(ground.rglob("*.py"))
           if "poses" not in p.relative_to(ground).parts[:1]
           for k, line in enumerate(p.read_text().splitlines(), 1) if reach.search(line)]
    assert not bad, bad
