"""Consumers of a long log: wall time and peak memory of `magstation analyze`, `calibrate` and
`info` next to pymavlink's bare parse of the same file (issue 29).

    .venv/bin/python benchmarks/memory.py                 # 2-hour 50 Hz ArduPilot-style tlog (~40 MB)
    .venv/bin/python benchmarks/memory.py --minutes 1     # smoke
    .venv/bin/python benchmarks/memory.py --log FILE.tlog # an existing log

Each command runs in its own child process, as a user runs it; the wall time is the child's, the
peak memory its maximum resident set, read by the child itself as it exits
(``groundstation.process_memory.peak_rss_MB``: VmHWM).  Not ``os.wait4``'s ``ru_maxrss``: a child
started by vfork and exec carries the parent's peak into it (Linux records the old memory's
high-water mark at exec), so every row would be at least the parent's peak, e.g. the writing of
the generated log.  The interpreter with the
command's imports already holds tens of MB before the first byte is read, so the table also prints
the peak above that (``imports`` row: the same child importing the command's modules and exiting).
Targets (issue 29, one run, same file): each consumer's wall time <= 0.25x the bare parse and
its peak memory <= 2x the file.  The machine is shared: the load average is printed.
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT / "benchmarks"))

TARGET_TIME_RATIO = 0.25      # consumer wall time / bare pymavlink parse
TARGET_MEMORY_RATIO = 2.0     # peak RSS / file size

BARE_PARSE = """
import sys
from pymavlink import mavutil
conn = mavutil.mavlink_connection(sys.argv[1], robust_parsing=True, dialect="ardupilotmega")
n = 0
while conn.recv_msg() is not None:
    n += 1
"""
CLI = "import sys\nfrom groundstation.cli import main\nsys.exit(main(sys.argv[1:]))\n"
IMPORTS = ("import groundstation.cli, groundstation.io.logs, groundstation.jobs.analyze, "
           "groundstation.jobs.report, groundstation.jobs.calibrate, groundstation.io.mission\n")


PEAK_AT_EXIT = """
import atexit, os
def _write_peak():
    from groundstation.process_memory import peak_rss_MB
    with open(os.environ["MAGSTATION_PEAK_FILE"], "w") as out:
        out.write(repr(peak_rss_MB()))
atexit.register(_write_peak)
"""


def measure(code: str, *args: str) -> tuple[float, float, int]:
    """(wall s, peak RSS MB, exit code) of ``python -c code args`` in a child of its own; the peak
    is the child's VmHWM as it exits (module docstring)."""
    with tempfile.NamedTemporaryFile("r", suffix=".peak") as peak:
        t0 = time.perf_counter()
        proc = subprocess.Popen([sys.executable, "-c", PEAK_AT_EXIT + code, *args], cwd=ROOT,
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE,
                                env={**os.environ, "MAGSTATION_PEAK_FILE": peak.name})
        _, err = proc.communicate()
        wall = time.perf_counter() - t0
        text = peak.read().strip()
    if proc.returncode not in (0, 1):       # calibrate exits 1 when a compass has no usable fit
        print(f"  child failed ({proc.returncode}): {err.decode(errors='replace').strip()[-400:]}", file=sys.stderr)
    peak_mb = float(text) if text and text != "None" else float("nan")
    return wall, peak_mb, proc.returncode


def run(log: Path, tmp: Path) -> list[tuple[str, float, float, int]]:
    rows = [("pymavlink bare parse", *measure(BARE_PARSE, str(log))),
            ("imports only (no log)", *measure(IMPORTS)),
            ("magstation info", *measure(CLI, "info", str(log))),
            ("magstation calibrate", *measure(CLI, "calibrate", str(log))),
            ("magstation analyze", *measure(CLI, "analyze", str(log))),
            ("magstation analyze --csv", *measure(CLI, "analyze", str(log), "--csv", str(tmp / "steps.csv")))]
    return rows


def table(rows: list, file_mb: float) -> list[str]:
    bare_s = rows[0][1]
    base_mb = rows[1][2]
    out = ["| command | wall s | / bare parse (target <= 0.25) | peak RSS MB | / file (target <= 2) "
           "| above imports MB | / file | verdict |", "|---|---|---|---|---|---|---|---|"]
    for name, wall, rss, code in rows:
        if name.startswith("imports"):
            out.append(f"| {name} | {wall:.2f} | | {rss:.0f} | {rss / file_mb:.2f} | | | |")
            continue
        t_ratio, m_ratio = wall / bare_s, rss / file_mb
        above = rss - base_mb
        if name.startswith("pymavlink"):
            verdict = "(the floor)"
        else:
            verdict = " ".join([("time met" if t_ratio <= TARGET_TIME_RATIO else "time MISSED"),
                                ("memory met" if m_ratio <= TARGET_MEMORY_RATIO else "memory MISSED")])
        out.append(f"| {name} | {wall:.2f} | {t_ratio:.2f}x | {rss:.0f} | {m_ratio:.2f}x | {above:.0f} "
                   f"| {above / file_mb:.2f}x | {verdict}{'' if code in (0, 1) else f' (exit {code})'} |")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--minutes", type=float, default=120.0, help="length of the generated 50 Hz tlog (default 120)")
    ap.add_argument("--log", type=Path, help="measure this log instead of a generated one")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        log = args.log
        if log is None:
            from ingest import write_tlog
            log = tmp / "long.tlog"
            print(f"writing a {args.minutes:g}-minute 50 Hz tlog ...", file=sys.stderr)
            write_tlog(log, args.minutes)
        file_mb = log.stat().st_size / 2**20
        rows = run(log, tmp)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"log: {log.name}, {file_mb:.1f} MB; load average {load:.1f} on {os.cpu_count()} cores")
    print("\n".join(table(rows, file_mb)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
