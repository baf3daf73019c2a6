"""`magstation review`: the per-log job (``groundstation.jobs.review_row.review_log``) mapped over every
log under the given paths on Dask distributed; the only module that imports Dask.

    with fleet_client(workers=2) as (client, dashboard):     # loopback LocalCluster of processes
        summary = run_review(client, paths, "fleet.sqlite")
    with fleet_client(scheduler="tcp://127.0.0.1:8786") as (client, dashboard):   # an existing cluster
        ...

Shape (as dask/distributed's LocalCluster examples): worker *processes* with one thread each, so a
worker reads one log at a time; the client submits at most ``2 × workers`` tasks ahead (a sliding
window over ``as_completed``), never opens a log, and gets back rows of a few kB that it writes to
the SQLite history in batches.  Each task hashes its file (SHA-256); a log whose hash is already in
the history is skipped unless ``force``.  A log that fails gives a row with its error; a log that
runs past ``timeout_s`` is interrupted in its worker (an exception raised in the job's thread) and
gives a "timeout" row; a worker that dies (memory limit) gives an "error" row; the run goes on.
Workers are given a memory limit (the nanny restarts a worker above it).  With an existing
scheduler the workers must see the same paths (a shared file system).

The local cluster runs with ``LEAN_CONFIG``: Dask's defaults sample every worker thread's stack
every 10 ms (the worker profiler), tick the event loops every 20 ms, poll the GIL every 1 ms and
let the scheduler look for work to steal every 100 ms.  Measured on this 2-core machine with two
idle workers: 7 % of a core in the client/scheduler process and 5 % in each worker with the
defaults, 1.4 % and 0.5 % with ``LEAN_CONFIG`` — CPU the logs need when the workers fill the cores.
A log is seconds of work and the client keeps every worker fed, so stealing gains nothing.
"""
from __future__ import annotations

import contextlib
import ctypes
import io
import logging
import os
import threading
import time
from contextlib import closing, contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Iterable, Iterator

from groundstation.io import fleet_db
from groundstation.io.logs import READERS
from groundstation.jobs.airframes import AirframeEntry, resolve_airframe
from groundstation.jobs.compass_history import DriftSettings, refresh_alerts
from groundstation.jobs.review_calibration import history_calibrations
from groundstation.jobs.review_row import ROW_VERSION, ReviewSettings, review_log

__all__ = ["discover_logs", "fleet_client", "run_review", "ReviewProgress", "ReviewSummary", "LogTimeout",
           "LEAN_CONFIG"]

LOG_SUFFIXES = tuple(READERS)           # .tlog .bin .ulg .csv
FAILED = ("error", "timeout")

# Dask settings of the local cluster (see the module docstring); the memory monitor stays on.
LEAN_CONFIG = {
    "distributed.scheduler.allowed-failures": 1,      # a log that kills its worker twice: an error row
    "distributed.worker.profile.enabled": False,
    "distributed.admin.tick.interval": "500ms",
    "distributed.admin.system-monitor.interval": "2s",
    "distributed.admin.system-monitor.gil.enabled": False,
    "distributed.worker.memory.monitor-interval": "500ms",
    "distributed.scheduler.work-stealing": False,
}


class LogTimeout(BaseException):
    """Raised inside a job's thread when it runs past the timeout (BaseException: the job's own
    ``except Exception`` must not swallow it)."""


def discover_logs(paths: Iterable[str | os.PathLike]) -> list[Path]:
    """Every supported log under the paths (recursively; hidden folders skipped), sorted, no duplicates.
    Raises FileNotFoundError for a path that does not exist."""
    found: set[Path] = set()
    for p in map(Path, paths):
        if not p.exists():
            raise FileNotFoundError(f"{p}: no such file or folder")
        if p.is_file():
            if p.suffix.lower() in LOG_SUFFIXES:
                found.add(p.resolve())
            continue
        for root, dirs, files in os.walk(p):
            dirs[:] = sorted(d for d in dirs if not d.startswith("."))
            found.update(Path(root, f).resolve() for f in files if Path(f).suffix.lower() in LOG_SUFFIXES)
    return sorted(found)


@contextmanager
def fleet_client(scheduler: str | None = None, workers: int = 2, memory_limit: str = "2GiB",
                 ) -> Iterator[tuple[object, str | None]]:
    """(client, dashboard URL): a LocalCluster of ``workers`` processes (one thread each) on loopback,
    closed on exit, or a client of the existing scheduler at ``scheduler``."""
    import dask
    from dask.distributed import Client, LocalCluster

    if scheduler:
        with Client(scheduler, timeout="20s") as client:
            yield client, client.dashboard_link if "dashboard" in client.scheduler_info().get("services", {}) else None
        return
    with dask.config.set(LEAN_CONFIG), LocalCluster(
            n_workers=workers, threads_per_worker=1, processes=True, host="127.0.0.1",
            dashboard_address="127.0.0.1:0", memory_limit=memory_limit, silence_logs=logging.ERROR) as cluster, \
            Client(cluster) as client:
        yield client, cluster.dashboard_link if cluster.scheduler.services.get("dashboard") else None


# ------------------------------------------------------------------------------ worker side
def _raise_in_thread(thread: threading.Thread, exc: type[BaseException]) -> None:
    ctypes.pythonapi.PyThreadState_SetAsyncExc(ctypes.c_ulong(thread.ident), ctypes.py_object(exc))


def run_job_with_timeout(job: Callable[..., list[dict]], path: str, timeout_s: float, *args) -> list[dict]:
    """``job(path, *args)`` in a thread; past ``timeout_s`` an exception is raised in that thread and a
    "timeout" row comes back (a job stuck inside one C call finishes that call first)."""
    box: dict = {}

    def target() -> None:
        try:
            box["rows"] = job(path, *args)
        except LogTimeout:
            box["timeout"] = True
        except BaseException as err:   # a job that raises despite its contract: still a row
            box["error"] = f"{type(err).__name__}: {err}"

    thread = threading.Thread(target=target, daemon=True, name=f"review {Path(path).name}")
    t0 = time.perf_counter()
    thread.start()
    thread.join(timeout_s)
    if thread.is_alive():
        _raise_in_thread(thread, LogTimeout)
        thread.join(5.0)
        return [_failure_row(path, "timeout", f"review took longer than {timeout_s:g} s (interrupted)", t0)]
    if "rows" in box:
        return box["rows"]
    return [_failure_row(path, "timeout" if box.get("timeout") else "error", box.get("error", "interrupted"), t0)]


def _failure_row(path: str, status: str, message: str, t0: float | None = None) -> dict:
    row = fleet_db.empty_row()
    p = Path(path)
    row.update(log_hash=f"{status}:{p}", compass=0, path=str(p), file_name=p.name, status=status, error=message,
               reviewed_unix_s=time.time(), review_s=None if t0 is None else round(time.perf_counter() - t0, 3))
    try:
        row["file_bytes"] = p.stat().st_size
    except OSError:
        pass
    return row


def _review_task(path: str, skip: frozenset, settings: ReviewSettings, timeout_s: float,
                 job: Callable[..., list[dict]]) -> list[dict]:
    """What a worker runs for one log."""
    from distributed import get_worker

    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        # log readers that print (pymavlink's DFReader writes "bad header ..." to stderr)
        rows = run_job_with_timeout(job, path, timeout_s, settings, skip)
    try:
        address = get_worker().address
    except ValueError:        # called outside a worker (tests)
        address = None
    for r in rows:
        r["worker"] = address
    return rows


# ------------------------------------------------------------------------------ client side
@dataclass
class ReviewProgress:
    total: int
    done: int = 0            # reviewed (rows written), failures included
    failed: int = 0
    skipped: int = 0
    elapsed_s: float = 0.0

    @property
    def left(self) -> int:
        return self.total - self.done - self.skipped

    @property
    def rate_per_s(self) -> float:
        return (self.done + self.skipped) / self.elapsed_s if self.elapsed_s > 0 else 0.0


@dataclass
class ReviewSummary:
    progress: ReviewProgress
    db_path: str
    dashboard: str | None
    workers: int
    failures: list[dict] = field(default_factory=list)       # path, status, error
    peak_worker_rss_MB: float | None = None
    log_seconds: float = 0.0        # summed per-log review time (worker side, wall clock)
    log_cpu_seconds: float = 0.0    # ... and the CPU time the jobs got (less than log_seconds on a busy machine)
    flight_seconds: float = 0.0     # summed flight duration of the reviewed logs
    alerts: list[dict] = field(default_factory=list)


def _label_rows(rows: list[dict], airframes: list[AirframeEntry] | None) -> None:
    for r in rows:
        if r.get("status") in FAILED:
            continue
        r["airframe"], r["payload"] = resolve_airframe(r, airframes or [])


def _relabel_history(con, airframes: list[AirframeEntry]) -> None:
    updates = []
    for r in fleet_db.flight_rows(con):
        name, payload = resolve_airframe(r, airframes)
        if (name, payload) != (r["airframe"], r["payload"]) and r.get("status") not in FAILED:
            updates.append((name, payload, r["log_hash"], r["compass"]))
    fleet_db.set_airframes(con, updates)


def _account(summary: ReviewSummary, rows: list[dict]) -> list[dict]:
    """Update counts from one task's rows; returns the rows to store."""
    p = summary.progress
    if rows and rows[0].get("status") == "skipped":
        p.skipped += 1
        return []
    p.done += 1
    head = rows[0] if rows else {}
    if head.get("status") in FAILED:
        p.failed += 1
        summary.failures.append({k: head.get(k) for k in ("path", "status", "error")})
    rss = [r["worker_peak_rss_MB"] for r in rows if r.get("worker_peak_rss_MB") is not None]
    if rss:
        summary.peak_worker_rss_MB = max(rss + [summary.peak_worker_rss_MB or 0.0])
    summary.log_seconds += head.get("review_s") or 0.0
    summary.log_cpu_seconds += head.get("review_cpu_s") or 0.0
    if head.get("status") == "ok":
        summary.flight_seconds += head.get("duration_s") or 0.0
    return rows


def _recalibrated(con) -> frozenset:
    """Log hashes reviewed before a calibration of their vehicle was added to the history: they are
    reviewed again (a log without its own dance is analysed with the airframe's calibration)."""
    try:
        rows = con.execute("SELECT DISTINCT f.log_hash FROM flights f JOIN calibrations c "
                           "ON c.airframe IN (f.identity, f.airframe) WHERE c.calibration_json IS NOT NULL "
                           "AND c.recorded_unix_s > f.reviewed_unix_s").fetchall()
    except Exception:          # an older history without the columns: nothing to redo
        return frozenset()
    return frozenset(r[0] for r in rows)


def run_review(client, paths: Iterable[str | os.PathLike], db_path: str | os.PathLike, *, force: bool = False,
               airframes: list[AirframeEntry] | None = None, timeout_s: float = 600.0,
               settings: ReviewSettings = ReviewSettings(), drift: DriftSettings = DriftSettings(),
               on_progress: Callable[[ReviewProgress], None] | None = None, dashboard: str | None = None,
               job: Callable[..., list[dict]] = review_log) -> ReviewSummary:
    """Review every log under ``paths`` on ``client``'s cluster into the history at ``db_path``."""
    from dask.distributed import as_completed

    logs = [str(p) for p in discover_logs(paths)]
    nworkers = max(1, len(client.scheduler_info().get("workers", {})))
    summary = ReviewSummary(ReviewProgress(total=len(logs)), str(db_path), dashboard, nworkers)
    t0 = time.perf_counter()
    with closing(fleet_db.connect(db_path)) as con:
        skip = frozenset() if force else frozenset(fleet_db.known_hashes(con, only_ok=True,
                                                                          min_row_version=ROW_VERSION))
        skip -= _recalibrated(con)
        settings = replace(settings, calibrations=history_calibrations(con))
        skip_future = client.scatter([skip], broadcast=True)[0]   # one object, not its elements
        pending = iter(logs)
        path_of: dict[str, str] = {}

        def submit(path: str):
            fut = client.submit(_review_task, path, skip_future, settings, timeout_s, job, pure=False)
            path_of[fut.key] = path
            return fut

        futures = as_completed([submit(p) for _, p in zip(range(2 * nworkers + 1), pending)])
        batch: list[dict] = []
        last_write = time.monotonic()
        for fut in futures:
            path = path_of.pop(fut.key)
            try:
                rows = fut.result()
            except Exception as err:                 # the worker died (memory limit, killed)
                rows = [_failure_row(path, "error", f"worker lost: {type(err).__name__}: {err}")]
            fut.release()
            batch += _account(summary, rows)
            nxt = next(pending, None)
            if nxt is not None:
                futures.add(submit(nxt))
            summary.progress.elapsed_s = time.perf_counter() - t0
            if batch and (len(batch) >= 50 or time.monotonic() - last_write > 2.0):
                _label_rows(batch, airframes)
                fleet_db.upsert_rows(con, batch)
                batch, last_write = [], time.monotonic()
            if on_progress:
                on_progress(summary.progress)
        _label_rows(batch, airframes)
        fleet_db.upsert_rows(con, batch)
        if airframes:
            _relabel_history(con, airframes)
        summary.alerts = refresh_alerts(con, drift).alerts
    summary.progress.elapsed_s = time.perf_counter() - t0
    return summary
