"""`magstation review` and `magstation simulate fleet`: argument parsing and terminal output
(the work is in ``groundstation.jobs.fleet`` and ``groundstation.sim.fleet``)."""
from __future__ import annotations

import argparse
import sys
import time
from contextlib import closing
from pathlib import Path
from urllib.parse import urlparse

from groundstation.io import fleet_db

__all__ = ["add_review_parser", "cmd_review", "cmd_simulate_fleet", "add_fleet_simulate_options"]

LOOPBACK = ("127.0.0.1", "localhost", "::1")


def add_review_parser(sub) -> None:
    p = sub.add_parser("review", help="review every log under the paths on Dask (fleet compass history)",
                       description="Review every .tlog/.bin/.ulg/.csv under the paths on a Dask cluster: one row "
                                   "per log and compass into the fleet history (SQLite), Parquet and an HTML report.")
    p.add_argument("paths", nargs="+", metavar="PATH", help="log files or folders (searched recursively)")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="an existing Dask scheduler (tcp://HOST:PORT); default: a local cluster on loopback")
    p.add_argument("--workers", type=int, default=2, help="local Dask worker processes (default 2; ignored with --scheduler)")
    p.add_argument("--out", default="magstation-review", metavar="DIR",
                   help="report folder: rows.parquet, report.html (default ./magstation-review)")
    p.add_argument("--db", metavar="FILE", help=f"fleet history (default $MAGSTATION_FLEET_DB or {fleet_db.default_db_path()})")
    p.add_argument("--airframes", metavar="MAPPING", help="airframe mapping (.json or .csv): identity -> airframe, payload (default: none)")
    p.add_argument("--force", action="store_true", help="review logs already in the history again (default: skip them)")
    p.add_argument("--timeout", type=float, default=600.0, metavar="S", help="per-log time limit (default 600 s)")
    p.add_argument("--memory-limit", default="2GiB", help="memory limit of each local worker, e.g. 2GiB or 512MiB (default 2GiB)")
    add_params_options(p)
    p.set_defaults(func=cmd_review)


def add_params_options(p: argparse.ArgumentParser) -> None:
    """--params / --assume-uncalibrated: the corrections in force when a log holds none."""
    g = p.add_argument_group("parameters in force when the log has none")
    g.add_argument("--params", metavar="FILE.param",
                   help="the vehicle's parameters (Mission Planner NAME,VALUE; MAVProxy/QGC NAME VALUE; QGC export) "
                        "(default: none; a log without its own compass parameters then has unknown corrections)")
    g.add_argument("--assume-uncalibrated", action="store_true",
                   help="the vehicle was never calibrated: the autopilot's default compass parameters in force")


def add_fleet_simulate_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--vehicles", type=int, default=20, help="fleet: number of vehicles (default 20)")
    p.add_argument("--flights", type=int, default=50, help="fleet: flights per vehicle (default 50)")
    p.add_argument("--workers", type=int, default=None, help="fleet: writer processes (default: every core)")


def _check_scheduler(address: str) -> None:
    url = urlparse(address if "://" in address else f"tcp://{address}")
    if not url.hostname or not url.port:
        raise ValueError(f"--scheduler {address!r}: expected tcp://HOST:PORT")
    if url.hostname not in LOOPBACK:
        print(f"warning: {url.hostname} is not loopback; Dask's protocol is not authenticated, use it on a "
              "trusted network (or TLS) only, and the workers must see the same log paths", file=sys.stderr)


class _Progress:
    """tqdm on a terminal; otherwise a line every 10 % (and at the end)."""

    def __init__(self, total: int) -> None:
        self.bar = None
        self.next_pct = 10
        if sys.stderr.isatty():
            from tqdm import tqdm
            self.bar = tqdm(total=total, unit="log", file=sys.stderr, leave=False)

    def __call__(self, p) -> None:
        text = f"done {p.done} failed {p.failed} skipped {p.skipped} left {p.left} ({p.rate_per_s:.2f} logs/s)"
        if self.bar is not None:
            self.bar.update(p.done + p.skipped - self.bar.n)
            self.bar.set_postfix_str(text, refresh=False)
        elif p.total and 100 * (p.total - p.left) / p.total >= self.next_pct:
            print(f"review: {text}", file=sys.stderr)
            self.next_pct += 10

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _print_summary(summary, out: Path) -> None:
    p = summary.progress
    minutes = summary.flight_seconds / 60.0
    print(f"reviewed {p.done} logs ({p.failed} failed), skipped {p.skipped} already in the history, "
          f"{p.elapsed_s:.1f} s on {summary.workers} workers ({p.rate_per_s:.2f} logs/s)")
    if minutes > 0:
        print(f"per-log cost {summary.log_seconds / minutes:.3f} s per flight-minute on the workers "
              f"({summary.log_cpu_seconds / minutes:.3f} s of CPU); "
              f"peak worker memory {summary.peak_worker_rss_MB or 0:.0f} MB")
    for f in summary.failures[:20]:
        print(f"  {f['status']}: {f['error']}")
    if len(summary.failures) > 20:
        print(f"  ... and {len(summary.failures) - 20} more (report.html lists them all)")
    kinds = {}
    for a in summary.alerts:
        kinds.setdefault(a["kind"], []).append(a)
    for kind, alerts in sorted(kinds.items()):
        print(f"{kind}: {len(alerts)}")
        for a in alerts[:10] if kind != "interference" else []:
            print(f"  {a['message']}")
    print(f"history {summary.db_path}; report {out / 'report.html'}, rows {out / 'rows.parquet'}")


def cmd_review(args: argparse.Namespace) -> int:
    try:
        import dask.distributed  # noqa: F401
        import pyarrow  # noqa: F401
    except ImportError as err:
        raise ValueError(f"magstation review needs {err.name}, a dependency of magstation: reinstall it "
                         "(./run, or pip install -e .)") from None
    from groundstation.jobs.airframes import load_airframes
    from groundstation.jobs.compass_history import analyse_fleet
    from groundstation.jobs.fleet import discover_logs, fleet_client, run_review
    from groundstation.jobs.fleet_report import write_html, write_parquet

    if args.workers < 1:
        raise ValueError("--workers must be at least 1")
    if args.scheduler:
        _check_scheduler(args.scheduler)
    airframes = load_airframes(args.airframes) if args.airframes else None
    total = len(discover_logs(args.paths))
    if not total:
        raise ValueError(f"no .tlog/.bin/.ulg/.csv logs under {', '.join(args.paths)}")
    db = Path(args.db) if args.db else fleet_db.default_db_path()
    out = Path(args.out)
    progress = _Progress(total)
    started = time.time()
    with fleet_client(args.scheduler, args.workers, args.memory_limit) as (client, dashboard):
        print(f"Dask dashboard: {dashboard or 'not available (install bokeh)'}; {total} logs", file=sys.stderr)
        try:
            summary = run_review(client, args.paths, db, force=args.force, airframes=airframes,
                                 timeout_s=args.timeout, on_progress=progress, dashboard=dashboard,
                                 settings=_review_settings(args))
        finally:
            progress.close()
    with closing(fleet_db.connect(db, read_only=True)) as con:
        rows, cals = fleet_db.flight_rows(con), fleet_db.calibration_rows(con)
    findings = analyse_fleet(rows, cals)
    write_parquet(rows, findings.site_of, out / "rows.parquet")
    write_html(rows, findings, out / "report.html", failures=summary.failures)
    _print_summary(summary, out)
    _print_calibrations(rows, started)
    _print_offsets(rows)
    return 1 if total and summary.progress.failed == summary.progress.done else 0


def _review_settings(args: argparse.Namespace):
    """ReviewSettings with --params / --assume-uncalibrated (the values in force when a log has none)."""
    from groundstation.cli import in_force_params
    from groundstation.jobs.review_row import ReviewSettings

    values, label = in_force_params(args)
    if values is None:
        return ReviewSettings()
    return ReviewSettings(params=tuple(sorted(values.items())), params_label=label)


def _print_offsets(rows: list[dict]) -> None:
    """Each airframe's in-flight offsets across its flights: combined, spread, drift (compass_history)."""
    from groundstation.cli_common import printable
    from groundstation.jobs.compass_history import offset_summaries

    summaries = offset_summaries(rows)
    if summaries:
        print("in-flight offsets across flights (raw sensor frame):")
    for s in summaries:
        print(f"  {printable(s['line'])}")


def _print_calibrations(rows: list[dict], since_unix_s: float) -> None:
    """Which calibration each log reviewed now was analysed with (one line per log, compass 0)."""
    for r in rows:
        if (r.get("compass") or 0) == 0 and (r.get("reviewed_unix_s") or 0) >= since_unix_s \
                and r.get("calibration_used"):
            print(f"  {r.get('file_name')}: calibration {r['calibration_used']}; "
                  f"{r.get('alarm_count') or 0} alarm(s)" + (f", first at {r['first_alarm_s']:.1f} s"
                                                             if r.get("first_alarm_s") is not None else ""))


def cmd_simulate_fleet(args: argparse.Namespace) -> int:
    from groundstation.sim.fleet import FleetSettings, simulate_fleet

    settings = FleetSettings(vehicles=args.vehicles, flights=args.flights, seed=args.seed,
                             drift_vehicles=min(3, max(0, args.vehicles - 1)), payload_vehicles=1 if args.vehicles > 1 else 0)
    t0 = time.perf_counter()

    def progress(done: int, total: int) -> None:
        if sys.stderr.isatty():
            print(f"\rsimulate fleet: {done}/{total} flights", end="", file=sys.stderr)

    truth = simulate_fleet(args.out, settings, workers=args.workers, progress=progress)
    if sys.stderr.isatty():
        print(file=sys.stderr)
    print(f"wrote {len(truth['flights'])} flights and {len(truth['corrupt'])} damaged files of {args.vehicles} "
          f"vehicles to {args.out} in {time.perf_counter() - t0:.0f} s; truth {Path(args.out) / 'fleet.truth.json'}, "
          f"airframe mapping {Path(args.out) / 'airframes.json'}")
    return 0
