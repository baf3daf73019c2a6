"""Smoke runs of the heading, ingest and live benchmarks (the full runs live in benchmarks/).

Accuracy targets are asserted; speed and latency figures depend on machine load, so these tests
only check that the benchmark ran and measured something sane.  (The calibration and detection
benchmarks have their smoke runs in test_calibration.py and test_detection.py.)
"""
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _run(*args: str, timeout: float = 240) -> str:
    out = subprocess.run([sys.executable, *args], cwd=ROOT, capture_output=True, text=True, timeout=timeout)
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout


def test_heading_benchmark_quick():
    out = _run("benchmarks/heading.py", "--quick")
    targets = dict((name.strip(), state) for state, name in re.findall(r"^  (met   |MISSED)  (.+)$", out, re.M))
    for name in ("static 45 deg step RMS <= 0.5 deg", "static level-vs-roll RMS <= 0.3 deg",
                 "static true-heading error max < 1.5 deg",
                 "outage, bias all flight: heading error < 2 deg"):
        assert targets.get(name) == "met   ", (name, out)
    # the outage rows are there for every feedback law (the targets they miss are in the README)
    for law in ("open-loop INS", "field feedback, PI (seed 003)", "field feedback, Kalman (default)",
                "Kalman tuned for a bias step"):
        assert len(re.findall(rf"^  {re.escape(law)}\s+[\d.]+", out, re.M)) == 2, (law, out)


def test_ingest_benchmark_small_log():
    out = _run("benchmarks/ingest.py", "--minutes", "0.5", "--repeats", "1")
    rows = {m.group(1): m for m in re.finditer(r"^\| ([^|]+?) \| [\d.]+ \| ([\d.]+) \| (\d+)", out, re.M)}
    assert {"pymavlink bare parse (tlog)", "tlog", "bin", "csv"} <= rows.keys(), out
    # 30 s at 50 Hz: 1500 mag + 1500 IMU + 1500 attitude rows (+ GPS) from every generated format
    for name in ("tlog", "bin"):
        assert int(rows[name].group(3)) >= 4500, out
    assert int(rows["csv"].group(3)) == 1500, out


def test_live_benchmark_quick():
    out = _run("benchmarks/live.py", "--quick", "--rates", "50")
    row = re.search(r"^\s+50\s+(\d+)\s+([\d.]+)\s+([\d.]+)", out, re.M)
    assert row, out
    packets, p50_ms, p99_ms = int(row.group(1)), float(row.group(2)), float(row.group(3))
    assert packets > 100 and 0.0 < p50_ms <= p99_ms
