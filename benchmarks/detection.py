"""Interference detection benchmark (issue 5), beside seed 002 tables 1 and 2.

Each run is end to end: simulate -> write .tlog -> read_log -> calibrate (the same seed's
calibration dance, groundstation.jobs.calibrate) -> analyze_log.

    .venv/bin/python benchmarks/detection.py            # 10 seeds (default)
    .venv/bin/python benchmarks/detection.py --seeds 20
    .venv/bin/python benchmarks/detection.py --quick    # 2 seeds, short clean flights (smoke run)

Targets: fast ramp (60 mG/s) first combined alarm <= 4 s after onset; slow ramp (12.5 mG/s)
<= 7 s; zero combined false alarms on clean 5-minute flights with gusts and motor-current field;
analyze >= 200x real time on a 50 Hz log.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from groundstation.jobs.analyze import analyze_log  # noqa: E402
from groundstation.jobs.calibrate import calibrate_log  # noqa: E402
from groundstation.io.logs import read_log  # noqa: E402
from groundstation.sim.scenarios import simulate  # noqa: E402

SEED_TABLE1 = {"threshold": [63.23 - 60.79, 60.22 - 56.29, 63.10 - 59.51, 61.10 - 57.26, 61.64 - 59.13],
               "path": [76.33 - 60.79, 67.76 - 56.29, 71.32 - 59.51, 70.11 - 57.26, 66.23 - 59.13]}
SEED_TABLE2 = {"threshold": [91.21 - 56.39, 99.27 - 61.96, 101.25 - 56.70, 110.34 - 60.20, 93.21 - 59.06],
               "path": [60.99 - 56.39, 66.27 - 61.96, 67.80 - 56.70, 66.71 - 60.20, 65.10 - 59.06]}


def _first_after(alarms: list[dict], kind: str, onset: float) -> float | None:
    starts = [a["start_s"] for a in alarms if a["kind"] == kind and
              (a["end_s"] is None or a["end_s"] >= onset - 0.5)]
    starts = [max(s, onset) for s in starts]
    return min(starts) - onset if starts else None


def run_one(scenario: str, seed: int, cal: dict | None, tmp: Path, **over) -> tuple[dict, float, float]:
    sim = simulate(scenario, seed, **over)
    log = read_log(sim.write(tmp / f"{scenario}-{seed}.tlog"))
    el = np.inf
    for _ in range(3):          # best of 3: the machine is shared, the minimum is the code's speed
        t0 = time.perf_counter()
        report, _ = analyze_log(log, cal)
        el = min(el, time.perf_counter() - t0)
    onset = sim.truth["interference"]["onset_s"]
    return report, (onset if onset is not None else np.nan), log.duration_s / el


def _stats(x: list) -> str:
    v = [a for a in x if a is not None]
    missed = len(x) - len(v)
    if not v:
        return f"{'—':>7} {'—':>7}  missed {missed}"
    return f"{np.median(v):7.2f} {max(v):7.2f}" + (f"  missed {missed}" if missed else "")


def main(argv: list[str] | None = None) -> int:
    """Print the table; return 0 when every target is met."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--quick", action="store_true", help="2 seeds, ramps only, 120 s clean flights")
    a = ap.parse_args(argv)
    seeds = list(range(2 if a.quick else a.seeds))
    clean_s = 120.0 if a.quick else 300.0
    lat = {k: {"combined": [], "heading_difference": [], "path_deviation": [], "field_anomaly": []}
           for k in ("fast", "slow", "step", "bump")}
    false_alarms = {"combined": 0, "heading_difference": 0, "path_deviation": 0, "field_anomaly": 0}
    pre_onset_false = 0
    speeds = []
    t_start = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmpd:
        tmp = Path(tmpd)
        for seed in seeds:
            cal = calibrate_log(read_log(simulate("calibration", seed).write(tmp / f"cal-{seed}.tlog")))
            cal = cal if cal.get("status") == "ok" else None
            cases = (("fast", "mission-fast"), ("slow", "mission-slow"), ("step", "mission-step"),
                     ("bump", "mission-bump"))
            for key, scen in cases[:2] if a.quick else cases:
                rep, onset, sp = run_one(scen, seed, cal, tmp)
                speeds.append(sp)
                pre_onset_false += sum(1 for x in rep["alarms"] if x["kind"] == "combined" and x["start_s"] < onset - 0.5
                                       and (x["end_s"] or 1e9) < onset)
                for kind in lat[key]:
                    lat[key][kind].append(_first_after(rep["alarms"], kind, onset))
            rep, _, sp = run_one("mission-clean", seed, cal, tmp, duration_s=clean_s)
            speeds.append(sp)
            for x in rep["alarms"]:
                false_alarms[x["kind"]] += 1
    n = len(seeds)
    st1, st2 = SEED_TABLE1, SEED_TABLE2
    print(f"Interference detection, {n} seeds per row (median / worst latency after onset, s)")
    print(f"{'case':44s} {'median':>7} {'worst':>7}   seed 002 (tables 1/2, 5 flights)")
    print(f"{'fast ramp 60 mG/s, combined (target <= 4 s)':44s} {_stats(lat['fast']['combined'])}")
    print(f"{'  heading difference alone':44s} {_stats(lat['fast']['heading_difference'])}"
          f"   threshold method {min(st1['threshold']):.1f}-{max(st1['threshold']):.1f}")
    print(f"{'  path deviation alone':44s} {_stats(lat['fast']['path_deviation'])}"
          f"   path method {min(st1['path']):.1f}-{max(st1['path']):.1f}")
    print(f"{'  field anomaly alone':44s} {_stats(lat['fast']['field_anomaly'])}   (not in seed)")
    print(f"{'slow ramp 12.5 mG/s, combined (target <= 7 s)':44s} {_stats(lat['slow']['combined'])}")
    print(f"{'  heading difference alone':44s} {_stats(lat['slow']['heading_difference'])}"
          f"   threshold method {min(st2['threshold']):.1f}-{max(st2['threshold']):.1f}")
    print(f"{'  path deviation alone':44s} {_stats(lat['slow']['path_deviation'])}"
          f"   path method {min(st2['path']):.1f}-{max(st2['path']):.1f}")
    print(f"{'  field anomaly alone':44s} {_stats(lat['slow']['field_anomaly'])}   (not in seed)")
    print(f"{'step 150 mG on Y, combined':44s} {_stats(lat['step']['combined'])}")
    print(f"{'  heading difference alone':44s} {_stats(lat['step']['heading_difference'])}")
    print(f"{'rise-then-fall 250 mG over 60 s, combined':44s} {_stats(lat['bump']['combined'])}")
    print(f"{'  path deviation alone':44s} {_stats(lat['bump']['path_deviation'])}")
    print(f"false alarms on {n} clean {clean_s / 60:.0f}-min flights (gusts, motor-current field):")
    print(f"  combined {false_alarms['combined']} (target 0); heading difference alone "
          f"{false_alarms['heading_difference']}; path deviation alone {false_alarms['path_deviation']}; "
          f"field anomaly alone {false_alarms['field_anomaly']}   (seed: threshold method 3 in one clean sim)")
    print(f"  combined alarms before interference onset in ramp flights: {pre_onset_false}")
    print(f"analyze speed (best of 3 per log): median {np.median(speeds):.0f}x real time, "
          f"slowest log {min(speeds):.0f}x (target >= 200x)")
    print(f"(benchmark wall time {time.perf_counter() - t_start:.0f} s)")
    ok = (all(v is not None and v <= 4.0 for v in lat["fast"]["combined"])
          and all(v is not None and v <= 7.0 for v in lat["slow"]["combined"])
          and false_alarms["combined"] == 0 and min(speeds) >= 200)
    print("targets met" if ok else "TARGETS NOT MET")
    return 0 if ok else 1


if __name__ == "__main__":
    raise SystemExit(main())
