"""CPU time of the field-vector test's per-step loop and of `review_log` per flight (issue 29).

    .venv/bin/python benchmarks/field_vector.py                  # both parts
    .venv/bin/python benchmarks/field_vector.py --part loop --repeats 3
    .venv/bin/python benchmarks/field_vector.py --part review --fleet /tmp/fleet
    .venv/bin/python benchmarks/field_vector.py --part review --parts   # where review's time goes
    .venv/bin/python benchmarks/field_vector.py --missions 1 --repeats 1 --logs 1   # the smoke run

loop: four simulated missions (mission-bump and mission-motor, seeds 0 and 1, calibrated on board)
are read and their detector inputs made once; then ``field_consistency`` alone runs on them,
``--repeats`` times, and the least process CPU time is printed per IMU step.
review: ``review_log`` on the first 8 flights of a 3 × 4 simulated fleet (seed 0), process CPU
seconds and logs per CPU-second; with ``--parts`` also the CPU time spent inside the in-flight WMM
fit (its jackknife and reference-field terms, the solver calls it makes itself) and the field-vector
test, added up by wrapping those functions (cProfile charges every Python call, so it inflates the
per-step loop of the field-vector test against the numpy of the fit: its shares are not these).
The machine is shared: CPU time, not wall time, is the figure; compare before and after in
alternate runs.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

PARTS = (("estimators.wmm_fit", "fit_wmm", "fit_wmm (all)"),
         ("estimators.wmm_fit", "_with_jackknife", "  jackknife"),
         ("estimators.wmm_fit", "_with_flight_wide_errors", "  reference-field and tilt terms"),
         ("estimators.wmm_fit", "solve", "  solve() called by wmm_fit"),
         ("groundstation.jobs.inputs", "field_consistency", "field_consistency (field-vector test)"))
MISSIONS = (("mission-bump", 0), ("mission-bump", 1), ("mission-motor", 0), ("mission-motor", 1))


def loop_inputs(tmp: Path, missions: int) -> list[tuple[tuple, dict]]:
    """The arguments analyze gives ``field_consistency`` on each of the first ``missions`` missions."""
    import groundstation.jobs.inputs as inputs
    from groundstation.io.logs import read_log
    from groundstation.sim.scenarios import simulate
    calls: list[tuple[tuple, dict]] = []
    real = inputs.field_consistency

    def keep(*args, **kw):
        calls.append((args, kw))
        return real(*args, **kw)

    inputs.field_consistency = keep
    try:
        for name, seed in MISSIONS[:missions]:
            log = read_log(simulate(name, seed, onboard_calibration=True).write(tmp / f"{name}-{seed}.tlog"))
            inputs.detection_inputs(log)
    finally:
        inputs.field_consistency = real
    return calls


def time_loop(repeats: int, missions: int) -> None:
    from estimators.field_consistency import field_consistency
    with tempfile.TemporaryDirectory() as tmp:
        calls = loop_inputs(Path(tmp), missions)
    steps = sum(len(args[0]) for args, _ in calls)
    best = float("inf")
    for _ in range(repeats):
        t0 = time.process_time()
        for args, kw in calls:
            field_consistency(*args, **kw)
        best = min(best, time.process_time() - t0)
    print(f"field-vector loop: {steps} IMU steps, {best:.2f} CPU s (least of {repeats}), "
          f"{1e6 * best / steps:.1f} us per step")


def _wrap(module, name: str, label: str, spent: Counter, depth: Counter) -> None:
    """Add the process CPU time of the outermost calls of ``module.name`` to ``spent[label]``
    (wherever it was imported by name)."""
    real = getattr(module, name)

    def timed(*args, **kw):
        depth[label] += 1
        t0 = time.process_time()
        try:
            return real(*args, **kw)
        finally:
            depth[label] -= 1
            if depth[label] == 0:
                spent[label] += time.process_time() - t0

    for mod in list(sys.modules.values()):
        if getattr(mod, name, None) is real:
            setattr(mod, name, timed)


def time_review(fleet: Path | None, n_logs: int, parts: bool = False) -> None:
    import importlib
    from groundstation.jobs.fleet import discover_logs
    from groundstation.jobs.review_row import ReviewSettings, review_log
    from groundstation.sim.fleet import FleetSettings, simulate_fleet
    spent, depth = Counter(), Counter()
    for module, name, label in PARTS if parts else ():
        _wrap(importlib.import_module(module), name, label, spent, depth)
    with tempfile.TemporaryDirectory() as tmp:
        folder = fleet or Path(tmp)
        if not (folder / "fleet.truth.json").exists():
            flights = max(2, -(-n_logs // 2))  # the first logs listed are the first two vehicles'
            simulate_fleet(folder, FleetSettings(vehicles=3, flights=flights, seed=0, drift_vehicles=1,
                                                 payload_vehicles=1), workers=1)
        logs = discover_logs([folder])[:n_logs]
        t0 = time.process_time()
        for p in logs:
            review_log(p, ReviewSettings())
        cpu = time.process_time() - t0
    print(f"review_log: {len(logs)} logs, {cpu:.2f} CPU s, {len(logs) / cpu:.2f} logs per CPU-s")
    for _, _, label in PARTS if parts else ():
        print(f"  {label:40s} {spent[label]:7.3f} CPU s  {100 * spent[label] / cpu:3.0f} %")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--part", choices=("loop", "review", "both"), default="both")
    ap.add_argument("--repeats", type=int, default=3, help="runs of the loop; the least CPU time is printed")
    ap.add_argument("--missions", type=int, default=len(MISSIONS), choices=range(1, len(MISSIONS) + 1),
                    help="the loop on the first N missions")
    ap.add_argument("--logs", type=int, default=8, help="review the first N flights of the fleet")
    ap.add_argument("--fleet", type=Path, help="keep (or reuse) the simulated fleet in this folder")
    ap.add_argument("--parts", action="store_true", help="review: the CPU time inside the WMM fit and the "
                    "field-vector test too")
    args = ap.parse_args(argv)
    if args.logs < 1:
        ap.error("--logs must be at least 1")
    if args.part in ("loop", "both"):
        time_loop(args.repeats, args.missions)
    if args.part in ("review", "both"):
        time_review(args.fleet, args.logs, args.parts)
    return 0


if __name__ == "__main__":
    sys.exit(main())
