"""Smoke runs of the heading, AHRS, ingest, live, detection and page-cost benchmarks (the full runs live in benchmarks/).

Accuracy targets are asserted; speed and latency figures depend on machine load, so these tests
only check that the benchmark ran and measured something sane.  (The calibration and detection
benchmark has its smoke run in test_calibration.py.)
"""
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from conftest import SHARED_DATA, needs_shared, shared_data

ROOT = Path(__file__).resolve().parent.parent


def _run(*args: str, timeout: float = 240) -> str:
    out = subprocess.run([sys.executable, *args], cwd=ROOT, capture_output=True, text=True, timeout=timeout)
    assert out.returncode == 0, out.stderr[-2000:]
    return out.stdout


def test_heading_benchmark_quick():
    out = _run("benchmarks/heading.py", "--quick")
    targets = dict((name.strip(), state) for state, name in re.findall(r"^  (met   |MISSED)  (.+)$", out, re.M))
    for name in ("static Cairo: 45 deg step RMS <= 0.5 deg", "static Cairo: level-vs-roll RMS <= 0.3 deg",
                 "static Tromso: 45 deg step RMS <= 0.5 deg", "static Tromso: level-vs-roll RMS <= 0.3 deg",
                 "random static 45 deg: 45 deg step RMS <= 0.5 deg", "random static 45 deg: level-vs-tilt RMS <= 0.3 deg",
                 "random static 78 deg: 45 deg step RMS <= 0.5 deg", "random static 78 deg: level-vs-tilt RMS <= 0.3 deg",
                 "outage Hangzhou: heading error < 2 deg", "outage Hangzhou: roll/pitch error < 2 deg"):
        assert targets.get(name) == "met   ", (name, out)
    # both estimators in the static tables (2 protocols, 3 randomised groups), the INS rows in both
    # outage cases, speed measured
    assert len(re.findall(r"^  ours \(AHRS\)\s+[\d.]+", out, re.M)) == 5, out
    assert len(re.findall(r"^  seed 000 filters\s+[\d.]+", out, re.M)) == 5, out
    assert len(re.findall(r"^  Hangzhou seed 1 .+INS/GPS default\s+[\d.]+", out, re.M)) == 2, out
    assert re.search(r"^  ours \(AHRS\)\s+batch\s+[\d,]+\s+per-sample\s+[\d,]+", out, re.M), out


def test_ahrs_benchmark_quick():
    """BROAD side by side (benchmarks/ahrs.py): ours (causal, offline), seed 000 and every peer
    (VQF, offlineVQF, Fusion, Madgwick, Mahony) on the first trial's first 70 s."""
    pytest.importorskip("h5py")
    for peer in ("imufusion", "ahrs", "vqf"):
        pytest.importorskip(peer)
    shared_data("broad")
    out = _run("benchmarks/ahrs.py", "--quick", "--jobs", "1")
    row = re.search(r"^02_undisturbed\S*((?:\s+[\d.]+/[\d.]+)+)\s*$", out, re.M)
    assert row, out
    cells = [tuple(map(float, c.split("/"))) for c in row.group(1).split()]
    assert len(cells) == 8                                   # ours x2, seed 000, five peers
    (ours_h, ours_i), (off_h, off_i), (seed_h, seed_i) = cells[:3]
    assert ours_h < 2.0 and ours_i < 0.6 and ours_i < seed_i and off_i < ours_i   # measured 1.02/0.39, offline 0.33
    assert re.search(r"^\d+ of 2 trial metrics: ours causal at or below VQF default", out, re.M), out


def test_ahrs_population_benchmark_quick():
    """The held-out AHRS check (benchmarks/ahrs_population.py) on two simulated 60 s flights: the
    truth and every filter's frames agree (a frame or declination slip would be tens of degrees)."""
    pytest.importorskip("vqf")
    out = _run("benchmarks/ahrs_population.py", "--quick")
    rows = re.findall(r"^\s+0\s+[\d.-]+\s+[\d.]+\s+\S+\s+[\d.]+((?:\s+[\d.]+/[\d.]+){4})\s*$", out, re.M)
    assert len(rows) == 2, out                                # seed 0, both field variants
    for row in rows:
        (c_h, c_i), (o_h, o_i), (v_h, v_i), _ = [tuple(map(float, c.split("/"))) for c in row.split()]
        assert c_h < 3.0 and o_h < 3.0 and v_h < 8.0 and max(c_i, o_i, v_i) < 3.0, out   # measured 1.53/0.79, 0.19/0.75, 4.9/4.3
    assert re.search(r"^  \d+ of 4 flight-metrics: ours causal at or below VQF", out, re.M), out


def test_ingest_benchmark_small_log():
    out = _run("benchmarks/ingest.py", "--minutes", "0.5", "--repeats", "1")
    rows = {m.group(1): m for m in re.finditer(r"^\| ([^|]+?) \| [\d.]+ \| ([\d.]+) \| (\d+)", out, re.M)}
    assert {"pymavlink bare parse (tlog)", "DFReader bare parse (bin)", "tlog", "bin", "csv"} <= rows.keys(), out
    # 30 s at 50 Hz: 1500 mag + 1500 IMU + 1500 attitude rows (+ GPS) from every generated format
    for name in ("tlog", "bin"):
        assert int(rows[name].group(3)) >= 4500, out
    assert int(rows["csv"].group(3)) == 1500, out
    # the bare parses read every message of the same files: 30 s of the tlog's 7 streams, the bin's 4
    assert int(rows["pymavlink bare parse (tlog)"].group(3)) == 1500 * 2 + 300 + 150 * 3 + 30, out
    assert int(rows["DFReader bare parse (bin)"].group(3)) >= 1500 * 3 + 150, out
    speeds = dict(re.findall(r"^(tlog|bin): ours ([\d.]+)x the bare parse", out, re.M))
    assert speeds.keys() == {"tlog", "bin"} and all(float(v) > 0 for v in speeds.values()), out


def test_live_benchmark_quick():
    out = _run("benchmarks/live.py", "--quick", "--rates", "50")
    row = re.search(r"^\s+50\s+(\d+)\s+([\d.]+)\s+([\d.]+)", out, re.M)
    assert row, out
    packets, p50_ms, p99_ms = int(row.group(1)), float(row.group(2)), float(row.group(3))
    assert packets > 100 and 0.0 < p50_ms <= p99_ms


def test_detection_benchmark_quick(tmp_path):
    """benchmarks/detection.py --quick: one seed's fast ramp and one clean motor-current flight,
    every variant on the same flights; the default meets the fast-ramp target with no false alarm,
    and the latency-vs-false-alarm chart is written."""
    png = tmp_path / "det.png"
    out = _run("benchmarks/detection.py", "--quick", "--png", str(png))
    assert "+ field vector alone, gating the others (default): all targets met" in out, out
    rows = re.findall(r"^  fast\s+([\d.]+)\s+([\d.]+)\s+0 ", out, re.M)
    assert len(rows) == 4 and all(float(med) <= 1.5 for med, _ in rows), out
    assert len(re.findall(r"clean motor-current 0 / 1 flights", out)) >= 2, out
    ends = re.findall(r"^  fast .* end\s+([\d.-]+)\s+([\d.-]+)\s+0 ", out, re.M)
    assert len(ends) == 4 and float(ends[-1][1]) <= 5.0, out     # the default's alarm ends with the disturbance
    assert png.exists() and png.stat().st_size > 1000


def test_alarm_kinds_benchmark_quick():
    """benchmarks/alarm_kinds.py --quick: seed 0's payload and anomaly flights, each alarm counted
    against the kind the simulator planted (the full run: every scenario over 10 seeds)."""
    out = _run("benchmarks/alarm_kinds.py", "--quick")
    rows = dict(re.findall(r"^\| (mission-\w+) \| [^|]+ \| (\d+ \| \d+) \|", out, re.M))
    assert set(rows) == {"mission-payload", "mission-anomaly"}, out
    for alarms_right in rows.values():
        alarms, right = map(int, alarms_right.split(" | "))
        assert alarms >= 1 and right == alarms, out
    assert "within 15 m: met" in out, out


@needs_shared("broad")
def test_detection_broad_benchmark_quick():
    """benchmarks/detection_broad.py --quick: analyze's detection on real motion (the whole of
    BROAD 09, fast rotation with rests, and the first 60 s of 35, a magnet attached 4 cm from the
    sensor) beside Fusion's magnetic-disturbance flag: no alarm on 09, where the test ran part of
    the time (a tilt learned at hand-held spin rates once alarmed over a third of it)."""
    out = _run("benchmarks/detection_broad.py", "--quick")
    rows = {m[0][:2]: [float(v) for v in m[1:]] for m in
            re.findall(r"^\| (\w+) \| ([\d.]+) \| ([\d.]+) \| ([\d.]+) \|", out, re.M)}
    assert set(rows) == {"09", "35"}, out
    assert rows["09"][1] > 0.03 and rows["09"][2] == 0.0, out       # tested, never alarmed
    assert "Fusion" in out and "without a magnet: met" in out


def test_memory_benchmark_small_log():
    """benchmarks/memory.py: every consumer ran in its own child (exit 0/1, no failure line) and
    its wall time and peak RSS were measured next to the bare parse, with the verdicts."""
    out = _run("benchmarks/memory.py", "--minutes", "0.5")
    rows = {m.group(1): m for m in re.finditer(
        r"^\| ([^|]+?) \| ([\d.]+) \| ([\d.]+)x \| (\d+) \| ([\d.]+)x \| (-?\d+) \| (-?[\d.]+)x \| ([^|]*)\|$", out, re.M)}
    for name in ("pymavlink bare parse", "magstation info", "magstation calibrate", "magstation analyze",
                 "magstation analyze --csv"):
        assert name in rows, out
        assert float(rows[name].group(2)) > 0 and int(rows[name].group(4)) > 10, out   # seconds, MB
        assert "exit" not in rows[name].group(8), out
    assert rows["pymavlink bare parse"].group(3) == "1.00", out
    for name in ("magstation info", "magstation analyze"):
        assert re.match(r"time (met|MISSED) memory (met|MISSED)", rows[name].group(8)), out
    assert re.search(r"^\| imports only \(no log\) \| [\d.]+ \| \| \d+ \|", out, re.M), out


def test_memory_benchmark_measures_the_child_not_the_parent():
    """benchmarks/memory.py's peak is the child's own: after this process held 300 MB, a child
    that only starts Python reads tens of MB (wait4's ru_maxrss would read 300+ MB: the parent's
    peak carried into a vfork-and-exec child)."""
    import numpy as np
    sys.path.insert(0, str(ROOT / "benchmarks"))
    try:
        import memory
    finally:
        sys.path.remove(str(ROOT / "benchmarks"))
    held = np.ones(300 * 2**20 // 8)          # 300 MB resident in this process
    held[::512] += 1.0
    del held
    wall, peak_mb, code = memory.measure("import sys\nsys.exit(0)\n")
    assert code == 0 and 1.0 < peak_mb < 100.0, peak_mb


def test_field_vector_benchmark_smoke():
    """benchmarks/field_vector.py on one mission and one fleet flight: the loop ran over the
    mission's IMU steps and review_log reviewed the flight, both timed in CPU seconds."""
    out = _run("benchmarks/field_vector.py", "--missions", "1", "--repeats", "1", "--logs", "1", "--parts")
    loop = re.search(r"^field-vector loop: (\d+) IMU steps, ([\d.]+) CPU s \(least of 1\), ([\d.]+) us per step$",
                     out, re.M)
    assert loop, out
    assert int(loop.group(1)) > 1000 and float(loop.group(3)) > 0, out
    review = re.search(r"^review_log: 1 logs, ([\d.]+) CPU s, ([\d.]+) logs per CPU-s$", out, re.M)
    assert review and float(review.group(1)) > 0, out
    parts = dict((label.strip(), float(s)) for label, s in re.findall(r"^  (.+?)\s+([\d.]+) CPU s\s+\d+ %$", out, re.M))
    # the fit and the field-vector test both ran inside the review, the jackknife inside the fit
    assert set(parts) >= {"fit_wmm (all)", "jackknife", "field_consistency (field-vector test)"}, out
    assert 0 < parts["jackknife"] <= parts["fit_wmm (all)"] <= float(review.group(1)), out
    assert 0 < parts["field_consistency (field-vector test)"] <= float(review.group(1)), out


def test_page_cpu_benchmark_smoke():
    """The page-cost benchmark opens the station page on a running replay and reads the browser's
    CPU and the page's main-thread figures (the page renders states: layouts happen)."""
    from conftest import CHROMIUM
    if not Path(CHROMIUM).exists():
        pytest.skip("Debian chromium not installed (/usr/bin/chromium)")
    out = _run("benchmarks/page_cpu.py", "--seconds", "3", timeout=180)
    r = json.loads(out.strip().splitlines()[-1])
    assert r["renderer_cpu_s"] > 0 and r["page_LayoutCount"] > 3 and r["page_TaskDuration"] > 0, r
    assert "3-D view off" in out, out
