"""Many flights at once (issue 73): ``ground batch`` replays each flight as one task on Dask, on this machine's own
local cluster (nothing to start) or on an existing one (``--cluster ADDRESS``), and writes one farm report.

    python -m ground batch FLIGHT_DIR... --out DIR [--resume] [--retries N] [--cluster tcp://HOST:8786]
    python -m ground batch --flights flights.csv --out DIR

A flight is what ``ground replay`` takes: a flight directory, or a video with its log and camera. The flights CSV
lists one a line: ``block`` and ``flight`` (a directory), or ``video``, ``log`` and ``camera`` in place of
``flight``; optionally ``name`` (its output folder; default the directory's or the video's name), ``orchard`` (the
block's layout), ``sample_counts`` (the block's hand counts) and ``args`` (more ``ground replay`` options, as on a
command line). Each flight is replayed lock-step into ``DIR/<name>/`` exactly as ``ground replay --out`` writes it, with
the replay's output (``batch.log``) and its attempts so far (``batch-attempts.txt``) beside.

Each flight is one task asking for ``--cpus-per-flight`` cores and ``--memory-per-flight-gb`` of memory (Dask's worker
resources ``cpus`` and ``memory``: a local cluster declares the machine's; an existing cluster's workers are started
with ``--resources "cpus=N memory=BYTES"``, else the tasks go without). A flight that fails, or whose worker is killed,
is tried again ``--retries`` times, then reported failed with its error; the others go on. ``--resume`` skips the
flights whose folder holds a finished replay. ``DIR/batch.json`` gives each flight's status, attempts, error, seconds,
CPU-seconds (its replay's processes together) and peak memory (its largest process); the farm report (ground.farm)
follows.
"""

from __future__ import annotations

import csv
import json
import logging
import os
import shlex
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from pomar.cli import InputError

log = logging.getLogger(__name__)

#: Columns of a flights CSV: required, and the two ways to name the flight itself.
REQUIRED = ("block",)
FLIGHT_WAYS = (("flight",), ("video", "log", "camera"))
OPTIONAL = ("name", "orchard", "sample_counts", "args")


class BatchError(InputError, ValueError):
    """A flights list, a flight or a cluster that cannot be used: the message names it and what is wrong."""


@dataclass
class BatchSettings:
    #: Times a failed or killed flight is tried again before it is reported failed.
    retries: int = 1
    #: Cores each flight's replay asks for (its onboard node, its ground, its mapper).
    cpus_per_flight: float = 2.0
    #: Memory each flight's replay asks for (GB).
    memory_per_flight_gb: float = 3.0
    #: Skip the flights whose output folder holds a finished replay.
    resume: bool = False
    #: An existing Dask scheduler's address (tcp://HOST:PORT); none: a local cluster on this machine.
    cluster: str | None = None


@dataclass
class FlightJob:
    name: str
    block: str
    #: ``ground replay``'s arguments for this flight, without --out.
    argv: list[str] = field(default_factory=list)
    orchard: str | None = None
    sample_counts: str | None = None


def _check_flight_dir(path: Path, where: str) -> None:
    from pomar.flight import FlightDir

    if not path.is_dir():
        raise BatchError(f"{where}: {path}: no such flight directory")
    try:
        FlightDir(path).meta()
    except InputError as e:
        raise BatchError(f"{where}: {e}") from None
    except (OSError, ValueError, KeyError) as e:
        raise BatchError(f"{where}: {path}: not a flight directory that reads ({e})") from None


def _job(d: dict, where: str, base: Path) -> FlightJob:
    """One flight from a CSV line (or a directory given on the command line: ``{"flight": DIR}``)."""
    def path(key):
        v = (d.get(key) or "").strip()
        return str((base / v).resolve()) if v else None

    block = (d.get("block") or "").strip()
    if not block:
        raise BatchError(f"{where}: no block (each flight belongs to a block of the farm)")
    if path("flight"):
        flight = Path(path("flight"))
        _check_flight_dir(flight, where)
        argv, name = [str(flight)], flight.name
    elif all(path(k) for k in ("video", "log", "camera")):
        for k in ("video", "log"):
            if not Path(path(k)).is_file():
                raise BatchError(f"{where}: {path(k)}: no such {k} file")
        camera = d["camera"].strip()
        camera = path("camera") if Path(path("camera")).is_file() else camera  # a file, or a built-in camera
        argv, name = ["--video", path("video"), "--log", path("log"), "--camera", camera], Path(path("video")).stem
    else:
        raise BatchError(f"{where}: give the flight (a directory) or its video, log and camera")
    name = (d.get("name") or "").strip() or name
    orchard, counts = path("orchard"), path("sample_counts")
    for flag, p in (("--orchard", orchard), ("--sample-counts", counts)):
        if p:
            if not Path(p).is_file():
                raise BatchError(f"{where}: {p}: no such file")
            argv += [flag, p]
    try:
        argv += shlex.split(d.get("args") or "")
    except ValueError as e:
        raise BatchError(f"{where}: its args do not read as a command line ({e})") from None
    return FlightJob(name, block, argv, orchard, counts)


def read_flights(flights: list[str], flights_csv: str | None) -> list[FlightJob]:
    """The flights of a batch, checked before any starts: directories given on the command line (each its own
    block, named by the directory) and the lines of a flights CSV."""
    jobs = [_job({"flight": f, "block": Path(f).name}, f, Path.cwd()) for f in flights]
    if flights_csv:
        p = Path(flights_csv)
        try:
            with open(p, newline="") as f:
                rd = csv.DictReader(f)
                lines = list(rd)
                cols = set(rd.fieldnames or [])
        except FileNotFoundError:
            raise BatchError(f"{p}: no such flights file") from None
        except (UnicodeDecodeError, csv.Error) as e:
            raise BatchError(f"{p}: not a CSV file ({e})") from None
        missing = [c for c in REQUIRED if c not in cols]
        if missing or not any(set(w) <= cols for w in FLIGHT_WAYS):
            raise BatchError(f"{p}: a flights file needs columns block and flight (or video, log and camera); it has "
                             f"{', '.join(sorted(cols)) or 'none'}")
        jobs += [_job(d, f"{p} line {i}", p.parent) for i, d in enumerate(lines, start=2)]
    if not jobs:
        raise BatchError("no flights: give flight directories, or --flights FILE")
    seen: dict[str, FlightJob] = {}
    layouts: dict[str, str | None] = {}
    for j in jobs:
        if j.name in seen:
            raise BatchError(f"two flights are named {j.name}: give each its own name (the flights file's name "
                             "column)")
        seen[j.name] = j
        if j.block in layouts and layouts[j.block] != j.orchard:
            raise BatchError(f"block {j.block}: its flights give different layouts ({layouts[j.block]}, {j.orchard}): "
                             "a block's flights share its one layout")
        layouts[j.block] = j.orchard
    return jobs


def finished(folder: Path) -> bool:
    """Whether ``folder`` holds a finished replay (its report.json, final)."""
    try:
        return bool(json.loads((folder / "report.json").read_text()).get("final"))
    except (OSError, ValueError, AttributeError):
        return False


def run_flight(job: dict, out: str) -> dict:
    """One flight's task (on a Dask worker): ``ground replay`` into ``out``; its figures, or an exception with the
    replay's last error line (Dask tries it again, up to the batch's retries)."""
    out_dir = Path(out)
    out_dir.mkdir(parents=True, exist_ok=True)
    attempts = out_dir / "batch-attempts.txt"
    n = int(attempts.read_text() or 0) + 1 if attempts.is_file() else 1
    attempts.write_text(str(n))
    t0 = time.monotonic()
    with open(out_dir / "batch.log", "w") as logf:
        proc = subprocess.Popen([sys.executable, "-m", "ground", "replay", *job["argv"], "--out", str(out_dir),
                                 "--quiet"], stdout=logf, stderr=subprocess.STDOUT)
        # this replay's own usage, its processes' with it (a worker runs several flights at once: the worker's
        # RUSAGE_CHILDREN would mix theirs)
        _, status, ru = os.wait4(proc.pid, 0)
    proc.returncode = code = os.waitstatus_to_exitcode(status)  # reaped here: Popen must not wait for it again
    if code != 0:
        lines = [x for x in (out_dir / "batch.log").read_text(errors="replace").splitlines() if x.strip()]
        why = lines[-1].strip() if lines else f"exit {code}"
        raise RuntimeError(f"{job['name']}: the replay failed (exit {code}, attempt {n}): {why[:300]}")
    report = json.loads((out_dir / "report.json").read_text())
    return {"name": job["name"], "seconds": time.monotonic() - t0,
            "cpu_s": ru.ru_utime + ru.ru_stime, "max_rss_mb": ru.ru_maxrss / 1024.0, "apples": report.get("apples"), "attempts": n}


def _machine() -> tuple[int, float]:
    """This machine's cores and memory (bytes)."""
    import psutil

    return os.cpu_count() or 1, float(psutil.virtual_memory().total)


def connect(s: BatchSettings):
    """A Dask client: on the cluster at ``s.cluster`` (one that does not answer: BatchError, before any flight), or on
    a local cluster of this machine, one worker process with the machine's cores and memory as its resources."""
    from distributed import Client, LocalCluster

    if s.cluster:
        try:
            return Client(s.cluster, timeout="10s", set_as_default=False)
        except (OSError, TimeoutError, ValueError) as e:
            raise BatchError(f"--cluster {s.cluster}: no Dask scheduler answers there ({type(e).__name__}: "
                             f"{str(e).splitlines()[0][:120] if str(e) else 'no answer'})") from None
    cores, memory = _machine()
    slots = max(1, int(min(cores // max(s.cpus_per_flight, 1e-9), memory // (s.memory_per_flight_gb * 1e9))) or 1)
    cluster = LocalCluster(n_workers=1, threads_per_worker=max(slots, 1), processes=True, dashboard_address=None,
                           resources={"cpus": float(max(cores, s.cpus_per_flight)),
                                      "memory": float(max(memory, s.memory_per_flight_gb * 1e9))},
                           silence_logs=logging.ERROR)
    return Client(cluster, set_as_default=False)


def _resources(client, s: BatchSettings) -> dict | None:
    """The resources each flight asks for, where the cluster's workers declare them (else None: tasks go without)."""
    workers = client.scheduler_info().get("workers", {}).values()
    if workers and all({"cpus", "memory"} <= set(w.get("resources") or {}) for w in workers):
        return {"cpus": s.cpus_per_flight, "memory": s.memory_per_flight_gb * 1e9}
    log.warning("the cluster's workers declare no cpus and memory resources (start them with --resources "
                "\"cpus=N memory=BYTES\"): each flight is placed without asking for its cores and memory")
    return None


#: Seconds between progress lines while no flight finishes.
PROGRESS_S = 30.0


def run_batch(jobs: list[FlightJob], out: Path, s: BatchSettings, progress=None, client=None) -> dict:
    """Replay ``jobs`` into ``out/<name>/`` as Dask tasks; the batch's report (also ``out/batch.json``).
    ``progress(line)``: called with a progress line as flights finish (and every PROGRESS_S). ``client``: one
    :func:`connect` gave (default: connect here); closed at the end."""
    from distributed import wait

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.monotonic()
    status = {j.name: {"name": j.name, "block": j.block, "status": "waiting", "attempts": 0} for j in jobs}
    todo = []
    for j in jobs:
        if s.resume and finished(out / j.name):
            status[j.name]["status"] = "skipped"
        else:
            todo.append(j)
    client = client or connect(s)
    engine = s.cluster or "dask local cluster"
    try:
        res = _resources(client, s) if todo else None
        futures = {client.submit(run_flight, asdict(j), str((out / j.name).resolve()), key=f"flight-{j.name}-{os.getpid()}",
                                 retries=s.retries, resources=res, pure=False): j for j in todo}
        for j in todo:
            status[j.name]["status"] = "running"
        durations: list[float] = []
        last_done = None  # when a flight last finished: the ETA counts down from it
        pending = set(futures)
        while pending:
            try:  # a progress line as flights finish, and every PROGRESS_S while they run
                with client.as_current():
                    finished_now, pending = wait(pending, timeout=PROGRESS_S, return_when="FIRST_COMPLETED")
            except TimeoutError:
                finished_now = set()
            if finished_now:
                last_done = time.monotonic()
            for fut in finished_now:
                j = futures[fut]
                st = status[j.name]
                try:
                    figs = fut.result()
                    st.update(status="done", **{k: figs[k] for k in ("seconds", "cpu_s", "max_rss_mb", "apples",
                                                                     "attempts")})
                    durations.append(figs["seconds"])
                except Exception as e:  # noqa: BLE001 - the flight's last attempt failed, or its worker died each time
                    st.update(status="failed", error=str(e).splitlines()[0][:400] if str(e) else type(e).__name__)
                    a = out / j.name / "batch-attempts.txt"
                    st["attempts"] = int(a.read_text() or 0) if a.is_file() else 0
            if progress is not None:
                progress(_progress_line(status, durations, client, time.monotonic() - t0,
                                        time.monotonic() - (last_done or t0)))
    finally:
        client.close()
        if not s.cluster:
            try:
                client.cluster.close()
            except Exception:  # noqa: BLE001 - a local cluster already gone
                pass
    report = {"engine": engine, "settings": asdict(s), "wall_s": time.monotonic() - t0,
              "flights": list(status.values()),
              "done": sum(v["status"] == "done" for v in status.values()),
              "skipped": sum(v["status"] == "skipped" for v in status.values()),
              "failed": sum(v["status"] == "failed" for v in status.values())}
    from ground.outputs.tables import write_json

    write_json(out / "batch.json", report)
    return report


def _progress_line(status: dict, durations: list[float], client, elapsed: float, since_done: float) -> str:
    """Flights done, running, waiting, failed, the time so far and the ETA: the mean flight's time for each left, as
    many at once as run now, less the time since a flight last finished."""
    n = {k: sum(v["status"] == k for v in status.values()) for k in ("done", "running", "failed", "skipped")}
    left = n["running"]
    try:
        busy = sum(len(v) for v in client.processing().values())
    except Exception:  # noqa: BLE001 - a scheduler gone at the end
        busy = 0
    eta = ""
    if durations and left:
        slots = max(busy, 1)
        eta = f"; ETA {max(sum(durations) / len(durations) * left / slots - since_done, 0.0) / 60:.1f} min"
    return (f"flights: {n['done']} done, {busy} running, {left - busy} waiting, {n['failed']} failed"
            + (f", {n['skipped']} skipped (done before)" if n["skipped"] else "") + f" ({elapsed / 60:.1f} min{eta})")
