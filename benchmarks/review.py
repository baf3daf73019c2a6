"""Fleet review benchmark: `magstation review` on a simulated fleet against its truth, and its
throughput with 1 and 2 Dask workers measured in the same run.

    .venv/bin/python benchmarks/review.py                       # 20 vehicles × 50 flights (the target)
    .venv/bin/python benchmarks/review.py --vehicles 4 --flights 8 --max-logs 6 --serial-logs 2   # smoke

The fleet (``groundstation.sim.fleet``) is generated once into ``--fleet DIR`` and reused.  Then:
1. a plain loop over ``--serial-logs`` logs in this process (the peer: no Dask, as `magstation
   calibrate` loops today), its in-flight fit (``jobs.calibrate``'s WMM fit with the review's
   settings) scored against the truth on flights without interference away from the anomaly site;
2. review of the whole fleet with 2 workers, scored against the truth (``groundstation.sim.fleet_score``);
3. review with 1 worker and with 2 workers of the first ``--throughput-logs`` logs (default all: then
   the 2-worker figure is run 2's), each a fresh LocalCluster and a fresh history.
Prints one table: our figure, the target, the verdict; and the machine load (`uptime`) around each
timed part: the machine is shared, so speed figures depend on what else runs.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from contextlib import closing
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

from groundstation.io import fleet_db  # noqa: E402
from groundstation.jobs.airframes import load_airframes  # noqa: E402
from groundstation.jobs.fleet import discover_logs, fleet_client, run_review  # noqa: E402
from groundstation.jobs.review_row import ReviewSettings, review_log  # noqa: E402
from groundstation.sim.fleet import TRUTH_NAME, FleetSettings, simulate_fleet  # noqa: E402
from groundstation.sim.fleet_score import score_review  # noqa: E402

TARGET_SPEEDUP = 1.7


def load_avg() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


def ensure_fleet(directory: Path, vehicles: int, flights: int, seed: int) -> tuple[dict, float | None]:
    truth_file = directory / TRUTH_NAME
    if truth_file.is_file():
        truth = json.loads(truth_file.read_text())
        s = truth["settings"]
        if (s["vehicles"], s["flights"], s["seed"], s.get("yaw_sweep_deg_s")) == (
                vehicles, flights, seed, FleetSettings.yaw_sweep_deg_s):
            return truth, None
    settings = FleetSettings(vehicles=vehicles, flights=flights, seed=seed,
                             drift_vehicles=min(3, vehicles - 1), payload_vehicles=1 if vehicles > 1 else 0)
    t0 = time.perf_counter()
    truth = simulate_fleet(directory, settings, progress=lambda d, n: print(f"\rgenerating {d}/{n}", end="",
                                                                            file=sys.stderr))
    print(file=sys.stderr)
    return truth, time.perf_counter() - t0


def timed_review(logs: list[Path], workers: int, db: Path, mapping) -> tuple[object, dict]:
    before = load_avg()
    with fleet_client(workers=workers) as (client, dashboard):
        t0 = time.perf_counter()
        summary = run_review(client, logs, db, airframes=mapping)
        wall = time.perf_counter() - t0
    with closing(fleet_db.connect(db, read_only=True)) as con:
        rows = fleet_db.flight_rows(con)
    per_worker: dict[str, float] = {}
    for r in rows:
        if r.get("worker") and r.get("worker_peak_rss_MB") is not None:
            per_worker[r["worker"]] = max(per_worker.get(r["worker"], 0.0), r["worker_peak_rss_MB"])
    return summary, {"wall_s": wall, "logs_per_s": summary.progress.done / wall, "load_before": before,
                     "load_after": load_avg(), "rss_MB": per_worker, "rows": rows}


def serial_peer(logs: list[Path], truth: dict) -> dict:
    """A plain loop (no Dask) of the per-log job; its in-flight fit's accuracy on the flights
    without interference away from anomaly sites."""
    before = load_avg()
    by_file = {f["file"]: f for f in truth["flights"]}
    anomalous = {s["name"] for s in truth["sites"] if s["anomaly_ned_mG"]}
    t0 = time.perf_counter()
    flight_s, ofs_err, motor_err = 0.0, [], []
    for p in logs:
        head = review_log(p, ReviewSettings())[0]
        if head.get("status") == "ok":
            flight_s += head.get("duration_s") or 0.0
        f = by_file.get(f"{p.parent.name}/{p.name}")
        if not f or f["interference"] or f["site"] in anomalous or head.get("fit_ofs_x_mG") is None:
            continue
        ofs_err.append(float(np.linalg.norm([head[f"fit_ofs_{a}_mG"] - v for a, v in zip("xyz", f["offsets_mG"])])))
        if head.get("motor_x_mG_per_A") is not None:
            k = np.array([head[f"motor_{a}_mG_per_A"] for a in "xyz"])
            motor_err.append(float(np.linalg.norm(k - f["motor_mG_per_A"]) / np.linalg.norm(f["motor_mG_per_A"])))
    wall = time.perf_counter() - t0
    pct = lambda v, q: float(np.percentile(v, q)) if v else float("nan")  # noqa: E731
    return {"wall_s": wall, "logs_per_s": len(logs) / wall, "s_per_flight_min": wall / (flight_s / 60.0)
            if flight_s else float("nan"), "load_before": before, "load_after": load_avg(), "logs": len(logs),
            "ofs_med": pct(ofs_err, 50), "ofs_p90": pct(ofs_err, 90), "motor_med": pct(motor_err, 50),
            "fitted": len(ofs_err)}


def verdict(ok: bool) -> str:
    return "met" if ok else "MISSED"


def table(score: dict, one, two, full, serial: dict, generated_s: float | None, flights_total: int,
          timed_logs: int) -> list[str]:
    d, p, s, i, c, f = (score[k] for k in ("drift", "payload", "anomaly_sites", "interference", "corrupt", "fit"))
    s1, m1 = one
    s2, m2 = two
    sf, mf = full
    speedup = m2["logs_per_s"] / m1["logs_per_s"]
    flight_min = sf.flight_seconds / 60.0
    rows = [
        ("planted drifts found", f"{d['found']}/{d['planted']}", "all", verdict(d["found"] == d["planted"])),
        ("false drift alerts on steady airframes", f"{len(d['false'])}/{d['steady_airframes']}", "0",
         verdict(not d["false"])),
        ("payload changes found (flight error)", f"{p['found']}/{p['planted']} ({p['flight_error']})", "all",
         verdict(p["found"] == p["planted"] and not p["false"])),
        ("anomaly sites found / false", f"{s['found']}/{s['planted']} / {len(s['false'])}", "all / 0",
         verdict(s["found"] == s["planted"] and not s["false"])),
        ("interference events found", f"{i['found']}/{i['planted']} (median delay {i['median_delay_s']:.1f} s)"
         if i["median_delay_s"] is not None else f"{i['found']}/{i['planted']}", "all", verdict(i["found"] == i["planted"])),
        ("clean flights with an alarm", f"{i['false_alarm_flights']}/{i['clean_flights']}", "(reported)", ""),
        ("damaged files reported, run not stopped", f"{c['reported']}/{c['planted']}, {sf.progress.done} logs done",
         "all", verdict(c["reported"] == c["planted"] and sf.progress.left == 0)),
        ("whole fleet, 2 workers", f"{mf['logs_per_s']:.2f} logs/s ({mf['wall_s']:.0f} s)", "", ""),
        ("fitted offsets error median / p90", f"{f['offset_error_median_mG']:.1f} / {f['offset_error_p90_mG']:.1f} mG",
         "(reported)", ""),
        ("motor field per A error, median", f"{100 * f['motor_rel_error_median']:.1f} %", "(reported)", ""),
        ("serial loop, no Dask (peer)", f"{serial['logs_per_s']:.2f} logs/s ({serial['logs']} logs)", "", ""),
        ("in-flight WMM fit, serial loop: offsets median / p90, motor",
         f"{serial['ofs_med']:.1f} / {serial['ofs_p90']:.1f} mG, {100 * serial['motor_med']:.1f} % "
         f"({serial['fitted']} flights)", "(reported)", ""),
        (f"1 worker ({timed_logs} logs)", f"{m1['logs_per_s']:.2f} logs/s ({m1['wall_s']:.0f} s)", "", ""),
        (f"2 workers ({timed_logs} logs)", f"{m2['logs_per_s']:.2f} logs/s ({m2['wall_s']:.0f} s)", "", ""),
        ("2 workers / 1 worker", f"{speedup:.2f}x", f">= {TARGET_SPEEDUP}x", verdict(speedup >= TARGET_SPEEDUP)),
        ("per-log cost (worker time / flight time)", f"{sf.log_seconds / flight_min:.3f} s per flight-minute",
         "(reported)", ""),
        ("serial peer cost", f"{serial['s_per_flight_min']:.3f} s per flight-minute", "(reported)", ""),
        ("peak memory per worker (1 / 2 workers)", f"{max(m1['rss_MB'].values()):.0f} / "
         f"{', '.join(f'{v:.0f}' for v in m2['rss_MB'].values())} MB", "bounded (< 2 GiB limit)",
         verdict(max(list(m1["rss_MB"].values()) + list(m2["rss_MB"].values())) < 2048)),
    ]
    out = [f"fleet: {flights_total} flights + {c['planted']} damaged files"
           + (f", generated in {generated_s:.0f} s" if generated_s else " (reused)"),
           "| metric | ours | target | verdict |", "|---|---|---|---|"]
    out += [f"| {a} | {b} | {t} | {v} |" for a, b, t, v in rows]
    out.append(f"load average (1/5/15 min) serial {serial['load_before']} -> {serial['load_after']}; whole fleet "
               f"{mf['load_before']} -> {mf['load_after']}; 1 worker {m1['load_before']} -> {m1['load_after']}; "
               f"2 workers {m2['load_before']} -> {m2['load_after']}")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--vehicles", type=int, default=20)
    ap.add_argument("--flights", type=int, default=50)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--fleet", type=Path, help="fleet folder (default: a temp folder per size, reused)")
    ap.add_argument("--serial-logs", type=int, default=60, help="logs in the no-Dask peer loop")
    ap.add_argument("--max-logs", type=int, help="review only the first N logs (smoke runs; findings then incomplete)")
    ap.add_argument("--throughput-logs", type=int,
                    help="time 1 vs 2 workers on the first N logs (default: all, the 2-worker run is the scored one)")
    a = ap.parse_args(argv)
    fleet = a.fleet or Path(tempfile.gettempdir()) / f"magstation-fleet-{a.vehicles}x{a.flights}-s{a.seed}"
    truth, generated_s = ensure_fleet(fleet, a.vehicles, a.flights, a.seed)
    mapping = load_airframes(fleet / "airframes.json")
    logs = discover_logs([fleet])[: a.max_logs]
    serial = serial_peer(logs[: a.serial_logs], truth)
    subset = logs[: a.throughput_logs] if a.throughput_logs else logs
    with tempfile.TemporaryDirectory() as tmp:
        full = timed_review(logs, 2, Path(tmp) / "full.sqlite", mapping)
        with closing(fleet_db.connect(Path(tmp) / "full.sqlite", read_only=True)) as con:
            alerts = fleet_db.alert_rows(con)
        one = timed_review(subset, 1, Path(tmp) / "one.sqlite", mapping)
        two = full if subset == logs else timed_review(subset, 2, Path(tmp) / "two.sqlite", mapping)
    score = score_review(truth, full[1]["rows"], alerts)
    print("\n".join(table(score, one, two, full, serial, generated_s, len(truth["flights"]), len(subset))))
    missed = {k: v for k, v in score.items() if isinstance(v, dict) and (v.get("missed") or v.get("false")
                                                                        or v.get("not_reported"))}
    if missed:
        print("details: " + json.dumps(missed))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
