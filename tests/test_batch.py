"""Many flights at once (`ground batch`, ground.batch and ground.farm; issue 73): a Dask cluster started by the test
replays three small simulated flights, one made to fail; the failed one is retried and reported, the others' outputs
are a replay's; a resumed batch replays nothing done; the farm report's rows are each flight's own; bad input gets
one line before any flight starts."""

from __future__ import annotations

import csv
import json
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _rows(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


@pytest.fixture()
def cluster():
    """A Dask cluster on loopback, its worker declaring 2 cores and 8 GB: the scheduler's address."""
    from distributed import LocalCluster

    c = LocalCluster(n_workers=1, threads_per_worker=2, processes=True, host="127.0.0.1", dashboard_address=None,
                     resources={"cpus": 2.0, "memory": 8e9})
    try:
        yield c.scheduler_address
    finally:
        c.close()


def test_a_batch_on_a_cluster_retries_the_failed_flight_resumes_and_writes_the_farm_report(tmp_path, cluster,
                                                                                             replay_test_flight):
    src = replay_test_flight.path
    for name in ("a", "b", "c"):
        shutil.copytree(src, tmp_path / "flights" / name)
    # c's video is torn: the replay fails mid-way, every time
    video = tmp_path / "flights" / "c" / "video.mp4"
    video.write_bytes(video.read_bytes()[:2000])
    layout = tmp_path / "orchard.csv"
    r = subprocess.run([sys.executable, "-m", "sim", "layout", "--config", str(ROOT / "sim" / "configs" /
                                                                                "replay-test.toml"),
                        "--out", str(layout)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    (tmp_path / "flights.csv").write_text("block,flight,orchard\nnorth,flights/a,orchard.csv\neast,flights/b,orchard.csv\n"
                                          "north,flights/c,orchard.csv\n")
    out = tmp_path / "batch"
    cmd = [sys.executable, "-m", "ground", "batch", "--flights", str(tmp_path / "flights.csv"), "--out", str(out),
           "--cluster", cluster, "--retries", "1", "--cpus-per-flight", "1", "--memory-per-flight-gb", "2"]
    r = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
    assert r.returncode == 1, r.stderr[-3000:]  # one flight failed: the batch says so in its exit status
    report = json.loads((out / "batch.json").read_text())
    st = {f["name"]: f for f in report["flights"]}
    assert st["a"]["status"] == st["b"]["status"] == "done" and st["c"]["status"] == "failed"
    assert st["c"]["attempts"] == 2 and "the replay failed" in st["c"]["error"], st["c"]
    assert "c: failed after 2 attempts" in r.stderr and "flights: " in r.stderr
    for name in ("a", "b"):  # each flight's folder as `ground replay --out` writes it
        rep = json.loads((out / name / "report.json").read_text())
        assert rep["final"] and (out / name / "apples.csv").is_file() and (out / name / "trees.csv").is_file()
        assert st[name]["apples"] == rep["apples"] and st[name]["cpu_s"] > 0
    # the farm report: each block's rows are its one finished flight's own
    farm = _rows(out / "farm" / "rows.csv")
    for block, name in (("north", "a"), ("east", "b")):
        own = _rows(out / name / "rows.csv")
        mine = [r for r in farm if r["block"] == block]
        assert [(r["row"], r["count"]) for r in mine] == [(r["row"], r["count"]) for r in own]
    blocks = {b["block"]: b for b in _rows(out / "farm" / "blocks.csv")}
    assert blocks["north"]["flights"] == "2" and int(blocks["east"]["apples"]) == sum(
        int(r["count"]) for r in _rows(out / "b" / "rows.csv"))
    import pyarrow.parquet as pq

    t = pq.read_table(out / "farm" / "farm.parquet")
    geo = json.loads(t.schema.metadata[b"geo"])
    assert geo["primary_column"] == "geometry" and geo["columns"]["geometry"]["encoding"] == "WKB"
    assert t.num_rows == len(farm) + len(_rows(out / "farm" / "trees.csv"))
    assert (out / "farm" / "farm.png").stat().st_size > 1000
    # resumed: what is done is not replayed again, the failed flight is tried again
    before = {n: (out / n / "report.json").stat().st_mtime_ns for n in ("a", "b")}
    r = subprocess.run(cmd + ["--resume"], capture_output=True, text=True, timeout=900)
    assert r.returncode == 1, r.stderr[-3000:]
    again = {f["name"]: f for f in json.loads((out / "batch.json").read_text())["flights"]}
    assert again["a"]["status"] == again["b"]["status"] == "skipped" and again["c"]["status"] == "failed"
    assert {n: (out / n / "report.json").stat().st_mtime_ns for n in ("a", "b")} == before


def test_what_a_batch_cannot_use_gets_one_line_before_any_flight_starts(tmp_path, replay_test_flight):
    from ground.replay import free_port

    good = str(replay_test_flight.path)
    (tmp_path / "nocol.csv").write_text("flight\n" + good + "\n")
    (tmp_path / "noblock.csv").write_text("block,flight\n," + good + "\n")
    (tmp_path / "twolayouts.csv").write_text(f"block,flight,name,orchard\nx,{good},p,{tmp_path / 'l1.csv'}\n"
                                             f"x,{good},q,{tmp_path / 'l2.csv'}\n")
    for n in ("l1.csv", "l2.csv"):
        (tmp_path / n).write_text("row,start_lat,start_lon,end_lat,end_lon,tree_spacing_m,first_tree_m\n")
    (tmp_path / "notaflight").mkdir()
    cases = [([str(tmp_path / "notaflight")], "notaflight"),
             (["--flights", str(tmp_path / "nocol.csv")], "needs columns block and flight"),
             (["--flights", str(tmp_path / "noblock.csv")], "no block"),
             (["--flights", str(tmp_path / "twolayouts.csv")], "different layouts"),
             (["--flights", str(tmp_path / "missing.csv")], "no such flights file"),
             ([good, good], "two flights are named"),
             ([good, "--cluster", f"tcp://127.0.0.1:{free_port()}"], "no Dask scheduler answers")]
    for args, says in cases:
        r = subprocess.run([sys.executable, "-m", "ground", "batch", *args, "--out", str(tmp_path / "out")],
                           capture_output=True, text=True, timeout=120)
        assert r.returncode == 2 and says in r.stderr and "Traceback" not in r.stderr, (args, r.stderr[-1500:])
        assert len([x for x in r.stderr.splitlines() if x.strip()]) == 1, r.stderr
    assert not (tmp_path / "out" / Path(good).name).exists()


def test_readmes_many_flights_command_as_written(tmp_path, replay_test_flight):
    """README's "Many flights" command, run as written in a folder holding its flights.csv: two small flights of two
    blocks on the command's own local Dask cluster, each folder a replay's, the farm report written."""
    from tests.test_readme_commands import readme_commands, run

    (cmd,) = readme_commands("### Many flights")
    for name in ("north-1", "south-1"):
        shutil.copytree(replay_test_flight.path, tmp_path / name)
    (tmp_path / "flights.csv").write_text("block,flight\nnorth,north-1\nsouth,south-1\n")
    r = run(cmd, tmp_path, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    out = tmp_path / "out" / "farm-day"
    assert {f["status"] for f in json.loads((out / "batch.json").read_text())["flights"]} == {"done"}
    assert {b["block"] for b in _rows(out / "farm" / "blocks.csv")} == {"north", "south"}
    assert (out / "north-1" / "report.json").is_file() and (out / "farm" / "farm.png").is_file()
