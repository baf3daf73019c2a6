"""Why `analyze` alarms on clean simulated fleet flights: the same planned flights (no interference
event, away from the anomaly site unless ``--anomaly-site``) simulated several ways and reviewed,
counting flights with a combined alarm.

    .venv/bin/python benchmarks/review_clean_alarms.py --airframes AF-03,AF-19 --flights 24
    .venv/bin/python benchmarks/review_clean_alarms.py --airframes AF-01,AF-18 --flights 24
    .venv/bin/python benchmarks/review_clean_alarms.py --anomaly-site --flights 16

* ``as simulated``: the fleet simulator's flight (nose turning at ``yaw_sweep_deg_s``, the vehicle's
  uncompensated motor-current field);
* ``nose along the legs``: the same flight with ``yaw_sweep_deg_s = 0`` (the nose turns only at the
  leg ends);
* ``no motor field``: the same flight with the motor-current field removed;
* ``no misalignment``: the magnetometer mounted square (the rotation part of its matrix removed,
  the part an ArduPilot calibration cannot hold: COMPASS_DIA/ODI is symmetric);
* ``no site anomaly`` (with ``--anomaly-site``): the site's constant anomaly removed.

Same seeds, sensor errors, winds and sites in the three; only the named part changes.  Each
flight's motor interference (% of the Earth field at the highest current, from the review's fit)
is printed beside its alarms.
"""
from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from estimators.calibration import polar_decomposition  # noqa: E402
from groundstation.jobs.review_row import review_log  # noqa: E402
from groundstation.sim.fleet import FleetSettings, FlightPlan, plan_fleet, write_flight  # noqa: E402

def _square(plan: FlightPlan) -> dict:
    """The plan's sensor matrix without its rotation (and the calibration in force to match)."""
    _, sym = polar_decomposition(np.asarray(plan.matrix, float))
    return {"matrix": tuple(map(tuple, sym.tolist())), "cal_matrix": tuple(map(tuple, np.linalg.inv(sym).tolist()))}


VARIANTS = {"as simulated": lambda p: {}, "nose along the legs": lambda p: {"yaw_sweep_deg_s": 0.0},
            "no motor field": lambda p: {"motor_mG_per_A": (0.0, 0.0, 0.0)}, "no misalignment": _square,
            "no site anomaly": lambda p: {"site": dataclasses.replace(p.site, anomaly_ned_mG=None)}}


def one(args: tuple[str, FlightPlan, str]) -> tuple[str, str, dict]:
    variant, plan, out = args
    plan = dataclasses.replace(plan, **VARIANTS[variant](plan))
    folder = Path(out) / variant.replace(" ", "-")
    write_flight(plan, folder)
    row = review_log(folder / plan.file)[0]
    return variant, plan.file, {k: row.get(k) for k in ("alarm_count", "alarm_evidence", "first_alarm_s",
                                                        "interference_pct", "fit_status")}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--airframes", default=None, help="airframes of the default 20 × 50 fleet (seed 0); default AF-03,AF-19")
    ap.add_argument("--flights", type=int, default=24, help="clean flights to simulate")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--anomaly-site", action="store_true",
                    help="clean flights at the anomaly site instead (of every airframe unless --airframes is given)")
    ap.add_argument("--variants", default=None, help="comma-separated subset of: " + ", ".join(VARIANTS))
    a = ap.parse_args(argv)
    if a.airframes is None and not a.anomaly_site:
        a.airframes = "AF-03,AF-19"
    variants = a.variants.split(",") if a.variants else [v for v in VARIANTS if a.anomaly_site or v != "no site anomaly"]
    plans, _ = plan_fleet(FleetSettings())
    airframes = a.airframes.split(",") if a.airframes else None      # None: every airframe (anomaly site)
    chosen = [p for p in plans if (airframes is None or p.airframe in airframes) and not p.interference
              and (p.site.anomaly_ned_mG is not None) == a.anomaly_site][: a.flights]
    with tempfile.TemporaryDirectory() as out, ProcessPoolExecutor(a.workers) as pool:
        results = list(pool.map(one, [(v, p, out) for p in chosen for v in variants]))
    by_flight: dict[str, dict] = {}
    for variant, name, r in results:
        by_flight.setdefault(name, {})[variant] = r
    print("| flight | interference % | " + " | ".join(f"alarms {v}" for v in variants) + " |")
    print("|---|---|" + "---|" * len(variants))
    for name, r in by_flight.items():
        pct = r["as simulated"]["interference_pct"]
        cells = [f"{r[v]['alarm_count'] or 0} {r[v]['alarm_evidence'] or ''}".strip() for v in variants]
        print(f"| {name} | {'-' if pct is None else f'{pct:.0f}'} | " + " | ".join(cells) + " |")
    counts = {v: sum(bool(r[v]["alarm_count"]) for r in by_flight.values()) for v in variants}
    print("flights with an alarm: " + ", ".join(f"{v} {counts[v]}/{len(by_flight)}" for v in variants))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
