"""Smoke run of benchmarks/real_logs.py: one short simulated flight (dance telemetry, mission
telemetry, one DataFlash layout), no real logs, no magfit_WMM (left to the full benchmark)."""
from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_real_logs_benchmark_smoke():
    out = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "real_logs.py"), "--smoke"],
                         capture_output=True, text=True, timeout=240)
    assert out.returncode == 0, out.stderr
    assert "MAG_CAL_REPORT" in out.stdout and "flight bin timeus_instance" in out.stdout
    assert out.stdout.count("PASS") >= 12 and "FAIL" not in out.stdout, out.stdout
    assert "Warning" not in out.stderr and "Traceback" not in out.stderr, out.stderr
