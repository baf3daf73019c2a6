"""Hostile-file fuzzing, smoke size: 300 seeded mutations (bit flips, truncation, inserted garbage,
huge length fields, hostile numbers and nesting) of tlog/bin/ulg/csv/plan/waypoints/calibration
files through read_log / read_mission and the CLI commands, in process (benchmarks/fuzz.py runs
thousands).  Every run must be clean, warnings with counts, or a one-line error: no traceback,
no hang, no numpy warning or raw control character on the terminal."""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

import fuzz  # noqa: E402


def test_mutations_are_deterministic():
    a, b = fuzz.make_cases(40, seed=3), fuzz.make_cases(40, seed=3)
    assert [c.data for c in a] == [c.data for c in b]
    assert len({c.kind for c in a}) >= 6 and len({c.data for c in a}) == 40


def test_300_mutated_files_give_no_traceback_hang_or_leak():
    counts, bad, secs = fuzz.run(300, seed=0, budget_s=60.0)
    summary = ", ".join(f"{o} {counts[o]}" for o in fuzz.OUTCOMES)
    print(f"\n300 mutated files in {secs:.0f} s: {summary}")
    assert sum(counts[o] for o in fuzz.OUTCOMES) == 300
    assert counts["traceback"] == counts["hang"] == counts["leak"] == 0, "\n".join(bad)
    # the harness exercises every outcome it is meant to tell apart
    assert counts["warnings"] > 50 and counts["error"] > 30


def test_ulog_seeds_are_shipped_and_read():
    """The fuzz has .ulg seeds without ../shared: a ULog written by the harness, read back whole."""
    import tempfile

    from groundstation.io.logs import read_log
    written = dict(fuzz.seeds()["ulg"])["written"]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "written.ulg"
        path.write_bytes(written)
        log = read_log(path)
    assert log.autopilot == "px4" and len(log.mag) == 400 and not log.warnings
    assert abs(float(log.mag[-1, 0] - log.mag[0, 0]) - 399 / 50.0) < 1e-3       # 50 Hz
    assert abs(float(log.mag[0, 3]) - 450.0) < 0.01                                # 0.45 G down, in mG


def test_parameters_that_are_nan_inf_or_3_4e38_are_flagged_not_a_traceback():
    rows = fuzz.absurd_params()
    assert [kind for kind, _, _ in rows] == ["tlog", "bin", "ulg"]
    for kind, outcome, flagged in rows:
        assert outcome == "warnings", (kind, outcome)
        names = fuzz.ABSURD_PARAMS if kind != "ulg" else fuzz.ABSURD_PX4_PARAMS
        assert set(flagged) == set(names), (kind, flagged)
