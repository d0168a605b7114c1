"""A flight's .rrd file after the recording: compacted and indexed in place, and read back (the tests and the
benchmarks read what the viewer would show)."""

from __future__ import annotations

import logging
import os
from pathlib import Path

log = logging.getLogger(__name__)


def finish_rrd(path: Path, timeout_s: float = 600.0) -> bool:
    """Compact a flight's .rrd and give it its chunk index, in place (``rerun rrd optimize``, in its own process, so
    its memory is not the ground's). The file as written stays if that fails: it is a valid recording without an
    index. Returns whether the file was replaced."""
    import subprocess
    import sys
    import time

    path = Path(path)
    tmp = path.with_name(path.name + ".optimizing")
    t0, size = time.monotonic(), path.stat().st_size
    cmd = [sys.executable, "-m", "rerun", "rrd", "optimize", str(path), "-o", str(tmp)]
    try:
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s)
        ok = proc.returncode == 0 and tmp.exists() and tmp.stat().st_size > 0
        why = proc.stderr.strip().splitlines()[-1] if not ok and proc.stderr.strip() else f"exit {proc.returncode}"
    except (OSError, subprocess.TimeoutExpired) as exc:
        ok, why = False, str(exc)
    if not ok:
        tmp.unlink(missing_ok=True)
        log.warning("rerun: %s kept as written, without its chunk index (`rerun rrd optimize` failed: %s)", path, why)
        return False
    os.replace(tmp, path)
    log.info("rerun: %s compacted and indexed in %.1f s (%.1f -> %.1f MB)", path, time.monotonic() - t0, size / 1e6,
             path.stat().st_size / 1e6)
    return True


def rrd_entities(path) -> dict[str, int]:
    """Entity path -> number of rows logged, read back from an .rrd file (rerun's RrdReader)."""
    from rerun.chunk import RrdReader

    counts: dict[str, int] = {}
    for chunk in RrdReader(str(path)).stream():
        p = str(chunk.entity_path)
        counts[p] = counts.get(p, 0) + chunk.num_rows
    return counts


def rrd_rows(path, prefix: str = "/") -> dict[str, list[dict]]:
    """Entity path -> its rows, read back from an .rrd file: each row a dict of ``frame`` (None when static) and
    the components logged (``Archetype:field`` -> Python value), in frame order."""
    from rerun.chunk import RrdReader

    out: dict[str, list[dict]] = {}
    for chunk in RrdReader(str(path)).stream():
        p = str(chunk.entity_path)
        if not p.startswith(prefix):
            continue
        rb = chunk.to_record_batch()
        comps = {c: rb.column(c).to_pylist() for c in rb.schema.names if ":" in c}
        frames = rb.column("frame").to_pylist() if "frame" in rb.schema.names else [None] * chunk.num_rows
        for i in range(chunk.num_rows):
            out.setdefault(p, []).append({"frame": frames[i], **{c: v[i] for c, v in comps.items()}})
    for rows in out.values():
        rows.sort(key=lambda r: -1 if r["frame"] is None else r["frame"])
    return out
