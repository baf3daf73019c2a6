"""Fleet review benchmark: `magstation review` on a simulated fleet against its truth, and its
throughput with 1 and 2 Dask workers measured in the same run.

    .venv/bin/python benchmarks/review.py                       # 20 vehicles × 50 flights (the target)
    .venv/bin/python benchmarks/review.py --no-score            # throughput only (5 × (1, 2 workers) on 40 logs)
    .venv/bin/python benchmarks/review.py --vehicles 3 --flights 10 --max-logs 4 --serial-logs 1 \
        --throughput-logs 2 --repeats 1                         # smoke

The fleet (``groundstation.sim.fleet``) is generated once into ``--fleet DIR`` and reused.  Then:
1. a plain loop over ``--serial-logs`` logs in this process (the peer: no Dask, as `magstation
   calibrate` loops today), its in-flight fit (``jobs.calibrate``'s WMM fit with the review's
   settings) scored against the truth on flights without interference away from the anomaly site;
2. throughput: ``--repeats`` pairs of reviews of the same first ``--throughput-logs`` flights with
   1 and with 2 workers, back to back, the order alternating (1 2 | 2 1 | ...); a LocalCluster of
   each size is started once, every worker imports the job and reviews one log outside the timed
   set (the same warm-up on both sides), each run writes a fresh history; per run the rate, the
   share of CPU the jobs got (thread CPU time / wall time: below 100 % when other processes compete
   for the cores), how idle the machine was just before and the load average;
3. unless ``--no-score``: the whole fleet on the 2-worker cluster, scored against the truth
   (``groundstation.sim.fleet_score``).
Prints the tables: our figure, the target, the verdict; the machine is shared, so speed figures
depend on what else runs: the load average is printed beside each timed run.
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
FED_SHARE = 0.9      # a run whose jobs got this share of their wall time on a CPU had the cores to itself


def load_avg() -> str:
    return " ".join(f"{v:.2f}" for v in os.getloadavg())


def idle_fraction(seconds: float = 2.0) -> float | None:
    """Share of the machine's CPU time that was idle over the next ``seconds`` (/proc/stat; None elsewhere)."""
    def sample():
        with open("/proc/stat") as f:
            v = [float(x) for x in f.readline().split()[1:]]
        return v[3] + v[4], sum(v)          # idle + iowait, total
    try:
        i0, t0 = sample()
        time.sleep(seconds)
        i1, t1 = sample()
    except (OSError, ValueError, IndexError):
        return None
    return (i1 - i0) / (t1 - t0) if t1 > t0 else None


def wait_quiet(min_idle: float, max_wait_s: float) -> float | None:
    """Wait (up to ``max_wait_s``) until the machine is at least ``min_idle`` idle; returns the idle share
    last seen.  The machine is shared: a timed run that starts while others compute measures them."""
    deadline = time.monotonic() + max_wait_s
    idle = idle_fraction()
    while idle is not None and idle < min_idle and time.monotonic() < deadline:
        idle = idle_fraction()
    return idle


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


def _warm(client, warm_log: Path | None) -> None:
    """Every worker imports the job and reviews one log outside the timed set (first-call costs)."""
    if warm_log is not None:
        client.run(review_log, str(warm_log))


def timed_run(client, workers: int, logs: list[Path], db: Path, mapping,
              quiet: tuple[float, float] = (0.0, 0.0)) -> tuple[object, dict]:
    """One review of ``logs`` into a fresh history ``db`` on a warmed cluster, timed; with ``quiet`` =
    (idle share, max wait s) started once the machine is that idle."""
    idle = wait_quiet(*quiet)
    before = load_avg()
    t0, c0 = time.perf_counter(), time.process_time()
    summary = run_review(client, logs, db, airframes=mapping)
    wall, client_cpu = time.perf_counter() - t0, time.process_time() - c0
    after = load_avg()
    with closing(fleet_db.connect(db, read_only=True)) as con:
        rows = fleet_db.flight_rows(con)
    per_worker: dict[str, float] = {}
    for r in rows:
        if r.get("worker") and r.get("worker_peak_rss_MB") is not None:
            per_worker[r["worker"]] = max(per_worker.get(r["worker"], 0.0), r["worker_peak_rss_MB"])
    flight_min = summary.flight_seconds / 60.0
    return summary, {"workers": workers, "wall_s": wall, "idle_before": idle,
                     "client_cpu_ms_per_log": 1000.0 * client_cpu / max(summary.progress.done, 1),
                     "logs_per_s": summary.progress.done / wall,
                     "load_before": before, "load_after": after, "rss_MB": per_worker, "rows": rows,
                     "worker_s_per_flight_min": workers * wall / flight_min if flight_min else float("nan"),
                     "cpu_s_per_flight_min": summary.log_cpu_seconds / flight_min if flight_min else float("nan"),
                     "cpu_share": summary.log_cpu_seconds / summary.log_seconds if summary.log_seconds
                     else float("nan")}


def throughput(clients: dict, logs: list[Path], mapping, repeats: int, tmp: Path,
               quiet: tuple[float, float]) -> list[tuple[dict, dict]]:
    """``repeats`` pairs of (1 worker, 2 workers) runs on the same logs, on two warmed clusters that
    stay up (the idle one costs < 2 % of a core), back to back in the order 1 2 | 2 1 | 1 2 ...,
    so that a change of the shared machine's load hits both sides alike."""
    pairs = []
    for k in range(repeats):
        runs = {}
        for w in ((1, 2) if k % 2 == 0 else (2, 1)):
            runs[w] = timed_run(clients[w], w, logs, tmp / f"tp-{k}-{w}.sqlite", mapping, quiet)[1]
            print(f"repeat {k + 1}, {w} worker(s): {runs[w]['logs_per_s']:.3f} logs/s, load "
                  f"{runs[w]['load_before']} -> {runs[w]['load_after']}", file=sys.stderr)
        pairs.append((runs[1], runs[2]))
    return pairs


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


def score_rows(score: dict, full: tuple) -> list[tuple[str, str, str, str]]:
    d, p, s, i, c, f = (score[k] for k in ("drift", "payload", "anomaly_sites", "interference", "corrupt", "fit"))
    sf, mf = full
    return [
        ("planted drifts found", f"{d['found']}/{d['planted']}", "all", verdict(d["found"] == d["planted"])),
        ("false drift alerts on steady airframes", f"{len(d['false'])}/{d['steady_airframes']}", "0",
         verdict(not d["false"])),
        ("payload changes found (flight error)", f"{p['found']}/{p['planted']} ({p['flight_error']})", "all",
         verdict(p["found"] == p["planted"] and not p["false"])),
        ("anomaly sites found / false", f"{s['found']}/{s['planted']} / {len(s['false'])}", "all / 0",
         verdict(s["found"] == s["planted"] and not s["false"])),
        ("interference events found", f"{i['found']}/{i['planted']} (median delay {i['median_delay_s']:.1f} s)"
         if i["median_delay_s"] is not None else f"{i['found']}/{i['planted']}", "all",
         verdict(i["found"] == i["planted"])),
        ("clean flights with an alarm", f"{i['false_alarm_flights']}/{i['clean_flights']}", "(reported)", ""),
        ("damaged files reported, run not stopped", f"{c['reported']}/{c['planted']}, {sf.progress.done} logs done",
         "all", verdict(c["reported"] == c["planted"] and sf.progress.left == 0)),
        ("whole fleet, 2 workers", f"{mf['logs_per_s']:.2f} logs/s ({mf['wall_s']:.0f} s; workers got "
         f"{100 * mf['cpu_share']:.0f} % CPU; load {mf['load_before']} -> {mf['load_after']})", "", ""),
        ("fitted offsets error median / p90", f"{f['offset_error_median_mG']:.1f} / {f['offset_error_p90_mG']:.1f} mG",
         "(reported)", ""),
        ("motor field per A error, median", f"{100 * f['motor_rel_error_median']:.1f} %", "(reported)", ""),
    ]


def _pct(x: float | None) -> str:
    return "?" if x is None else f"{100 * x:.0f} %"


def throughput_rows(pairs: list[tuple[dict, dict]], serial: dict, timed_logs: int) -> list[tuple[str, str, str, str]]:
    rows = [("serial loop, no Dask (peer)", f"{serial['logs_per_s']:.2f} logs/s ({serial['logs']} logs, load "
             f"{serial['load_before']} -> {serial['load_after']})", "", ""),
            ("in-flight WMM fit, serial loop: offsets median / p90, motor",
             f"{serial['ofs_med']:.1f} / {serial['ofs_p90']:.1f} mG, {100 * serial['motor_med']:.1f} % "
             f"({serial['fitted']} flights)", "(reported)", "")]
    speedups = []
    for k, (one, two) in enumerate(pairs):
        speedups.append(two["logs_per_s"] / one["logs_per_s"])
        for m in (one, two):
            rows.append((f"repeat {k + 1}: {m['workers']} worker(s), {timed_logs} logs",
                         f"{m['logs_per_s']:.3f} logs/s ({m['wall_s']:.0f} s; workers got {100 * m['cpu_share']:.0f} % "
                         f"CPU; machine {_pct(m['idle_before'])} idle before; load {m['load_before']} -> "
                         f"{m['load_after']})", "", ""))
        rows.append((f"repeat {k + 1}: 2 workers / 1 worker", f"{speedups[-1]:.2f}x", "", ""))
    med = float(np.median(speedups))
    fed = [x for x, (one, two) in zip(speedups, pairs) if min(one["cpu_share"], two["cpu_share"]) >= FED_SHARE]
    one_all = [p[0] for p in pairs]
    two_all = [p[1] for p in pairs]
    rss = [v for m in one_all + two_all for v in m["rss_MB"].values()]
    rows += [
        ("2 workers / 1 worker", f"{med:.2f}x (median of {len(pairs)}; {', '.join(f'{x:.2f}' for x in speedups)})",
         f">= {TARGET_SPEEDUP}x", verdict(med >= TARGET_SPEEDUP)),
        (f"2 workers / 1 worker, pairs whose jobs got >= {100 * FED_SHARE:.0f} % CPU in both runs",
         f"{', '.join(f'{x:.2f}x' for x in fed) or 'none'} ({len(fed)} of {len(pairs)} pairs)", "(reported)", ""),
        ("per-log cost, 1 / 2 workers (worker-seconds per flight-minute)",
         f"{np.median([m['worker_s_per_flight_min'] for m in one_all]):.3f} / "
         f"{np.median([m['worker_s_per_flight_min'] for m in two_all]):.3f} s", "(reported)", ""),
        ("per-log CPU, 1 / 2 workers (CPU seconds per flight-minute)",
         f"{np.median([m['cpu_s_per_flight_min'] for m in one_all]):.3f} / "
         f"{np.median([m['cpu_s_per_flight_min'] for m in two_all]):.3f} s", "(reported)", ""),
        ("client + scheduler + nannies (this process), CPU per log, 1 / 2 workers",
         f"{np.median([m['client_cpu_ms_per_log'] for m in one_all]):.0f} / "
         f"{np.median([m['client_cpu_ms_per_log'] for m in two_all]):.0f} ms", "(reported)", ""),
        ("serial peer cost", f"{serial['s_per_flight_min']:.3f} s per flight-minute", "(reported)", ""),
        ("peak memory per worker (1 / 2 workers)", f"{max(one_all[0]['rss_MB'].values()):.0f} / "
         f"{', '.join(f'{v:.0f}' for v in two_all[0]['rss_MB'].values())} MB (max over runs {max(rss):.0f})",
         "bounded (< 2 GiB limit)", verdict(max(rss) < 2048)),
    ]
    return rows


def table(rows: list[tuple[str, str, str, str]], heading: str) -> list[str]:
    out = [heading, "| metric | ours | target | verdict |", "|---|---|---|---|"]
    return out + [f"| {a} | {b} | {t} | {v} |" for a, b, t, v in rows]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--vehicles", type=int, default=20)
    ap.add_argument("--flights", type=int, default=50)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--fleet", type=Path, help="fleet folder (default: a temp folder per size, reused)")
    ap.add_argument("--serial-logs", type=int, default=20, help="logs in the no-Dask peer loop")
    ap.add_argument("--max-logs", type=int, help="review only the first N logs (smoke runs; findings then incomplete)")
    ap.add_argument("--throughput-logs", type=int, default=40, help="logs timed with 1 and with 2 workers")
    ap.add_argument("--repeats", type=int, default=5, help="pairs of 1- and 2-worker runs")
    ap.add_argument("--no-score", action="store_true", help="skip the scored review of the whole fleet")
    ap.add_argument("--quiet-idle", type=float, default=0.0,
                    help="start each timed run once the machine is this idle (0..1; shared machines)")
    ap.add_argument("--quiet-wait-s", type=float, default=300.0, help="... waiting at most this long")
    a = ap.parse_args(argv)
    fleet = a.fleet or Path(tempfile.gettempdir()) / f"magstation-fleet-{a.vehicles}x{a.flights}-s{a.seed}"
    truth, generated_s = ensure_fleet(fleet, a.vehicles, a.flights, a.seed)
    mapping = load_airframes(fleet / "airframes.json")
    logs = discover_logs([fleet])[: a.max_logs]
    flights = [p for p in logs if p.name.startswith("flight-")]
    subset, warm_log = flights[: a.throughput_logs], flights[-1] if len(flights) > a.throughput_logs else None
    serial = serial_peer(flights[: a.serial_logs], truth)
    with tempfile.TemporaryDirectory() as tmp, fleet_client(workers=1) as (one, _), \
            fleet_client(workers=2) as (two, _):
        _warm(one, warm_log)
        _warm(two, warm_log)
        pairs = throughput({1: one, 2: two}, subset, mapping, a.repeats, Path(tmp), (a.quiet_idle, a.quiet_wait_s))
        lines = [f"fleet: {len(truth['flights'])} flights + {len(truth['corrupt'])} damaged files"
                 + (f", generated in {generated_s:.0f} s" if generated_s else " (reused)"), ""]
        lines += table(throughput_rows(pairs, serial, len(subset)), "throughput (machine: "
                       f"{os.cpu_count()} cores, shared; load average 1/5/15 min beside each run)")
        score = None
        if not a.no_score:
            full = timed_run(two, 2, logs, Path(tmp) / "full.sqlite", mapping)
            with closing(fleet_db.connect(Path(tmp) / "full.sqlite", read_only=True)) as con:
                alerts = fleet_db.alert_rows(con)
            score = score_review(truth, full[1]["rows"], alerts)
            lines += [""] + table(score_rows(score, full), f"findings against the truth ({len(logs)} logs, 2 workers)")
    print("\n".join(lines))
    missed = {k: v for k, v in (score or {}).items() if isinstance(v, dict) and (v.get("missed") or v.get("false")
                                                                                 or v.get("not_reported"))}
    if missed:
        print("details: " + json.dumps(missed))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
