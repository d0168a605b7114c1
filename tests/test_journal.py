"""The journal on a disk that fills up or a folder it cannot write to: the journal stops, the flight does not."""

from __future__ import annotations

import json
import logging
import os
from pathlib import Path

import pytest

from ground.link.journal import Journal, read_journal


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full (Linux) to fill a disk")
def test_a_full_disk_stops_the_journal_once_and_keeps_the_records_before(tmp_path, caplog):
    path = tmp_path / "journal.bin"
    j = Journal(path)
    j.append(b"one")
    j.append(b"two")
    j._f.flush()
    j._f.close()
    j._f = open("/dev/full", "ab")  # the disk is full from here on: every write fails with ENOSPC
    with caplog.at_level(logging.WARNING, logger="ground.link.journal"):
        for k in range(5):
            j.append(b"lost %d" % k)  # no exception: the ground goes on mapping
        j.close()
    assert j.failed and "No space left" in j.failed
    assert sum("cannot be written" in r.getMessage() for r in caplog.records) == 1  # warned once
    assert read_journal(path) == [b"one", b"two"]  # what was written before is intact


def test_a_journal_in_a_folder_that_cannot_be_made_is_a_warning(tmp_path, caplog):
    blocker = tmp_path / "out"
    blocker.write_text("a file where the output folder should be")
    with caplog.at_level(logging.WARNING, logger="ground.link.journal"):
        j = Journal(blocker / "journal.bin")
        j.append(b"one")
        j.close()
    assert j.failed and str(blocker) in j.failed
    assert any("can no longer be resumed" in r.getMessage() for r in caplog.records)


def test_map_files_the_disk_refuses_leave_the_flight_going_and_the_files_before_whole(tmp_path, caplog):
    """A disk that refuses the map files (full, or a path taken): the refresh warns once, the report says why, the
    files written before stay whole, no temporary file is left, and the next refresh that can write does."""
    from ground.node import GroundNode

    out = tmp_path / "out"
    node = GroundNode(out, rrd=False)
    node.refresh()
    before = (out / "apples.csv").read_bytes()
    (out / ".apples.csv.tmp").mkdir()  # the write of apples.csv fails with an OSError, as on a full disk
    with caplog.at_level(logging.WARNING, logger="ground"):
        rep = node.refresh()
        node.refresh()
    assert "apples.csv" in rep["link"]["outputs_write_failed"]
    assert sum("cannot be written" in r.getMessage() for r in caplog.records) == 1
    assert (out / "apples.csv").read_bytes() == before and (out / "report.json").is_file()
    (out / ".apples.csv.tmp").rmdir()
    rep = node.refresh(final=True)
    assert rep["link"]["outputs_write_failed"] is None and (out / "candidates.csv").is_file()
    assert not list(out.glob(".*.tmp"))


def test_map_files_the_disk_refuses_at_the_end_go_to_a_rescue_folder(tmp_path, monkeypatch):
    """Nothing computed is lost: when the flight's last map files cannot be written where asked, they are written to
    the system's temporary directory and the report says where (and that the first place failed)."""
    import tempfile

    from ground.node import GroundNode

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    (tmp_path / "tmp").mkdir()
    out = tmp_path / "out"
    node = GroundNode(out, rrd=False)
    (out / ".apples.csv.tmp").mkdir()
    rep = node.finish()
    rescued = Path(rep["link"]["outputs_rescued_to"])
    assert rescued.parent == tmp_path / "tmp" and "apples.csv" in rep["link"]["outputs_write_failed"]
    assert {"apples.csv", "rows.csv", "trees.csv", "poses.csv", "candidates.csv", "report.json"} <= {
        p.name for p in rescued.iterdir()}
    assert json.loads((rescued / "report.json").read_text())["link"]["outputs_rescued_to"] == str(rescued)


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="needs /dev/full (Linux) to fill a disk")
def test_a_recording_the_disk_refuses_leaves_the_flight_and_its_map_files(tmp_path, caplog):
    """A rerun recording that cannot be written (its disk full from the start, here /dev/full) is a warning: the
    flight goes on without it, and its end writes the map files and the report as ever."""
    from ground.node import GroundNode
    from pomar import wire

    out = tmp_path / "out"
    node = GroundNode(out, rrd=Path("/dev/full"))
    cam = {"model": "PINHOLE", "width": 1280, "height": 720, "params": [1372.0, 1372.0, 640.0, 360.0]}
    with caplog.at_level(logging.WARNING, logger="ground"):
        node.handle(wire.CameraMessage("f", "d", cam, 10.0))
        node.refresh()
        rep = node.finish()
    assert node.rr is None and any("recording" in e for e in rep["errors"])
    assert sum("rerun recording" in r.getMessage() for r in caplog.records) == 1  # said once
    assert json.loads((out / "report.json").read_text())["final"] is True and (out / "apples.csv").is_file()
