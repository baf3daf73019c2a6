"""Interference detection benchmark: latency after onset against false alarms, per detector variant.

Each flight is end to end: simulate -> write .tlog -> read_log -> calibrate (the same seed's
calibration dance) -> detection inputs (groundstation.jobs.inputs, with the field-vector test) ->
the detector with each variant's settings.  Every variant sees the same flights (one run).

    .venv/bin/python benchmarks/detection.py                    # 10 seeds, 5 outage flights, real logs
    .venv/bin/python benchmarks/detection.py --seeds 20 --png out.png
    .venv/bin/python benchmarks/detection.py --quick            # smoke run (1 seed, fast ramp, 1 clean flight)
    .venv/bin/python benchmarks/detection.py --population 200 --per-kind 50   # issue 30's population

``--population N``: N clean flights and ``--per-kind`` flights of each disturbance kind drawn from
the wide priors of groundstation/sim/population.py (seed ``--pop-seed``), each end to end through a
.tlog with no calibration but the vehicle's own; the table at the default thresholds, a sweep of
every threshold x0.6-1.6 and the ROC-style chart (false alarms per flight-hour vs median latency)
in benchmarks/results/detection_population.png.  ``--kinds`` and ``--json`` split one run over
processes, ``--merge`` prints the merged table (docs/detection.md).

Scenarios: fast ramp (60 mG/s), slow ramp (12.5 mG/s), step (150 mG), bump (250 mG over 60 s);
clean missions with a payload switching 10 A on top of the motor current (mission-motor, >= 8 A
variation) and GPS-outage missions (80 s outage, 0.5 deg/s gyro bias), no interference; the real
logs in ../shared/data (dronekit ArduCopter tlog, PX4 ulogs), analysed without a calibration.
Targets (issue "Interference detection, second generation"): first combined alarm after onset,
median over the seeds: fast <= 1.5 s, slow <= 3.5 s, worst <= 1.5 x median; zero false alarms on
the clean, outage and real flights.
"""
from __future__ import annotations

import argparse
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from estimators.detection import DetectionSettings, alarm_intervals, detect  # noqa: E402
from groundstation.io.logs import read_log  # noqa: E402
from groundstation.jobs.calibrate import calibrate_log  # noqa: E402
from groundstation.jobs.inputs import detection_inputs  # noqa: E402
from groundstation.sim.scenarios import simulate  # noqa: E402

SHARED = Path(__file__).resolve().parents[2] / "shared" / "data"
REAL_LOGS = ("dronekit/flight_replay_flight.tlog", "px4-pyulog/sample_log_small.ulg",
             "px4-pyulog/sample_px4_events.ulg", "px4-pyulog/sample.ulg")
BASE = DetectionSettings()
VARIANTS = {
    "seed 002 + sector field check": replace(BASE, use_vector=False),
    "+ field vector, corroborated": replace(BASE, vector_alone=float("inf"), vector_gate=float("-inf")),
    "+ field vector alone, no gate": replace(BASE, vector_gate=float("-inf")),
    "+ field vector alone, gating the others (default)": BASE,
}
RAMPS = (("fast", "mission-fast"), ("slow", "mission-slow"), ("step", "mission-step"), ("bump", "mission-bump"))
TARGET_S = {"fast": 1.5, "slow": 3.5}


def combined_alarms(x: dict, settings: DetectionSettings) -> list[tuple[float, float | None]]:
    """(start, end) of the combined alarms of one flight's inputs under one variant."""
    ef = x["ef"]
    det = detect(x["t"], x["e"], x["d"], x["trusted"], x["strength"], x["incl"], x["heading"], x["yaw_rate"],
                 ef.field_strength_mG if ef else np.nan, ef.inclination_deg if ef else np.nan, settings,
                 z_vector=x["z_vector"])
    return [(a[0], a[1]) for a in alarm_intervals(x["t"], det.combined)]


def latency_s(alarms: list, onset_s: float) -> float | None:
    """First combined alarm at or after onset (an alarm already on 0.5 s before counts from onset)."""
    starts = [max(a, onset_s) for a, b in alarms if (b is None or b >= onset_s - 0.5) and a >= onset_s - 0.5]
    return min(starts) - onset_s if starts else None


def end_delay_s(alarms: list, onset_s: float, end_s: float | None) -> float | None:
    """Last combined alarm's end after the disturbance's end [s] (inf: still on at the end of the
    flight; None: no alarm or no end)."""
    after = [b for a, b in alarms if b is None or b >= onset_s - 0.5]
    if end_s is None or not after:
        return None
    return np.inf if after[-1] is None else after[-1] - end_s


def _flight(scenario: str, seed: int, tmp: Path, **over):
    sim = simulate(scenario, seed, **over)
    return read_log(sim.write(tmp / f"{scenario}-{seed}.tlog")), sim.truth


def run(seeds: list[int], outage_seeds: list[int], clean_s: float, ramps, real: bool) -> dict:
    """Latencies and false alarms per variant: {variant: {"lat": {case: [...]}, "fa": {group: n}}}."""
    out = {v: {"lat": {k: [] for k, _ in ramps}, "end": {k: [] for k, _ in ramps},
               "fa": {"clean-motor": 0, "outage": 0, "real": 0}, "pre_onset": 0} for v in VARIANTS}
    counts = {"clean-motor": 0, "outage": 0, "real": 0}
    with tempfile.TemporaryDirectory() as tmpd:
        tmp = Path(tmpd)
        for seed in seeds:
            cal = calibrate_log(_flight("calibration", seed, tmp)[0])
            cal = cal if cal.get("status") == "ok" else None
            for key, scen in ramps:
                log, truth = _flight(scen, seed, tmp)
                x = detection_inputs(log, cal)
                onset, end = truth["interference"]["onset_s"], truth["interference"].get("end_s")
                for v, st in VARIANTS.items():
                    alarms = combined_alarms(x, st)
                    out[v]["lat"][key].append(latency_s(alarms, onset))
                    out[v]["end"][key].append(end_delay_s(alarms, onset, end))
                    out[v]["pre_onset"] += sum(1 for a, b in alarms if b is not None and b < onset - 0.5)
            groups = [("clean-motor", "mission-motor", {"duration_s": clean_s})]
            if seed in outage_seeds:
                groups.append(("outage", "gps-outage", {}))
            for group, scen, over in groups:
                log, _ = _flight(scen, seed, tmp, **over)
                x = detection_inputs(log, cal)
                counts[group] += 1
                for v, st in VARIANTS.items():
                    out[v]["fa"][group] += len(combined_alarms(x, st))
        for rel in REAL_LOGS if real else ():
            path = SHARED / rel
            if not path.exists():
                continue
            x = detection_inputs(read_log(path))
            counts["real"] += 1
            for v, st in VARIANTS.items():
                out[v]["fa"]["real"] += len(combined_alarms(x, st))
    return {"variants": out, "counts": counts}


def _stats(values: list) -> tuple[float, float, int]:
    got = [v for v in values if v is not None]
    missed = len(values) - len(got)
    if not got:
        return np.nan, np.nan, missed
    return float(np.median(got)), float(np.max(got)), missed


def verdicts(res: dict) -> dict:
    """Per variant: all targets met?"""
    ok = {}
    for v, r in res["variants"].items():
        good = sum(r["fa"].values()) == 0
        for case, target in TARGET_S.items():
            if case not in r["lat"]:
                continue
            med, worst, missed = _stats(r["lat"][case])
            good &= missed == 0 and med <= target and worst <= 1.5 * med
        ok[v] = bool(good)
    return ok


def print_table(res: dict, n_seeds: int) -> None:
    c = res["counts"]
    print(f"Interference detection: {n_seeds} seeds per scenario; first combined alarm after onset [s] "
          "(median / worst / missed); last alarm's end after the disturbance's end [s] (median / worst / "
          "still on at the end of the flight)")
    for v, r in res["variants"].items():
        print(f"\n{v}")
        for case, lat in r["lat"].items():
            med, worst, missed = _stats(lat)
            target = TARGET_S.get(case)
            verdict = ""
            if target is not None:
                met = missed == 0 and med <= target and worst <= 1.5 * med
                verdict = (f"target median <= {target:g} s, worst <= 1.5x median: "
                           f"{'met' if met else 'NOT met'}")
            ends = [e for e in r["end"].get(case, []) if e is not None]
            fin = [e for e in ends if np.isfinite(e)]
            end_txt = (f"end {np.median(fin):6.2f} {max(fin):6.2f} {len(ends) - len(fin):3d}" if fin
                       else f"end    nan    nan {len(ends):3d}")
            print(f"  {case:5s} {med:6.2f} {worst:6.2f} {missed:3d}   {end_txt}   {verdict}")
        fa = r["fa"]
        print(f"  false alarms: clean motor-current {fa['clean-motor']} / {c['clean-motor']} flights, "
              f"GPS outage {fa['outage']} / {c['outage']}, real logs {fa['real']} / {c['real']} "
              f"(target 0); alarms ending before onset in interference flights {r['pre_onset']}")
    print()
    for v, ok in verdicts(res).items():
        print(f"{v}: {'all targets met' if ok else 'TARGETS NOT MET'}")


def _pyplot():
    """matplotlib.pyplot on the Agg backend, or None (said) when it cannot be imported."""
    try:
        import matplotlib
        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        print("matplotlib cannot be imported: no chart written")
        return None
    return plt


def _save(plt, fig, path: str) -> None:
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    print(f"wrote {path}")


def write_png(res: dict, path: str) -> None:
    """Latency (median fast and slow ramp) against false alarms, one point per variant."""
    plt = _pyplot()
    if plt is None:
        return
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    for (v, r), mark in zip(res["variants"].items(), "osD^"):
        fa = sum(r["fa"].values())
        for case, color in (("fast", "tab:red"), ("slow", "tab:blue")):
            if case in r["lat"]:
                med = _stats(r["lat"][case])[0]
                ax.scatter(fa, med, marker=mark, color=color, s=60, label=f"{v} ({case})")
    for case, target in TARGET_S.items():
        ax.axhline(target, ls=":", color="tab:red" if case == "fast" else "tab:blue")
    ax.set_xlabel("false alarms (clean motor-current + outage + real flights)")
    ax.set_ylabel("median first-alarm latency [s]")
    ax.set_title("Interference detection: latency vs false alarms")
    ax.legend(fontsize=7)
    _save(plt, fig, path)


# ----------------------------------------------------------------------------- population (issue 30)
POP_SCALES = (0.6, 0.8, 1.0, 1.25, 1.6)     # threshold multipliers of the ROC-style sweep (1.0: the default)
POP_TARGET_S = {"fast": 1.5, "slow": 3.5}
MIN_TURN_DEG = 5.0                          # detection-rate target: disturbances that turn the heading this far


def scaled(x: dict, m: float) -> tuple[dict, DetectionSettings]:
    """The detector with every threshold multiplied by ``m`` (heading 5σ, field floors, the
    field-vector score's levels), for the ROC-style sweep; m = 1 is the default."""
    st = replace(BASE, sigma_k=BASE.sigma_k * m, strength_floor_mG=BASE.strength_floor_mG * m,
                 inclination_floor_deg=BASE.inclination_floor_deg * m, path_threshold_m=BASE.path_threshold_m * m)
    return dict(x, z_vector=np.asarray(x["z_vector"], dtype=float) / m), st


def population_flight(draw, tmp: Path) -> dict:
    """One population flight end to end (write .tlog -> read_log -> detection inputs -> detector
    at each threshold scale): its alarms and truth."""
    from groundstation.sim.population import write_flight
    path, truth = write_flight(draw, tmp / f"{draw.label()}.tlog")
    x = detection_inputs(read_log(path))
    path.unlink()
    row = {"kind": draw.kind, "index": draw.index, "hours": truth["flight_hours"], "onset": truth["onset_s"],
           "end": truth["end_s"],
           "turn_deg": truth["max_heading_turn_deg"], "imu_hz": draw.imu_rate_hz, "mode": draw.attitude_mode,
           "tests_on": x["heading_test"] == "on", "heading_test": x["heading_test"], "alarms": {}}
    for m in POP_SCALES:
        xs, st = scaled(x, m)
        row["alarms"][m] = combined_alarms(xs, st)
    return row


def population_run(n_clean: int, n_kind: int, seed: int, kinds=None, log=print, out_json: str | None = None,
                   first: int = 0) -> list[dict]:
    """The population's flights (indices ``first`` up to n_clean / n_kind), round robin over the
    kinds (clean first), so a run cut short still covers every kind; with ``out_json`` the rows so
    far are written after every flight."""
    from groundstation.sim.population import DISTURBANCES, draw_flight
    kinds = DISTURBANCES if kinds is None else kinds
    plan = [(k, i) for i in range(first, max(n_clean, n_kind)) for k in ("clean", *kinds)
            if i < (n_clean if k == "clean" else n_kind)]
    rows = []
    t0 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmpd:
        for j, (kind, i) in enumerate(plan):
            rows.append(population_flight(draw_flight(i, seed, kind), Path(tmpd)))
            if out_json:
                import json
                Path(out_json).parent.mkdir(parents=True, exist_ok=True)
                Path(out_json).write_text(json.dumps(rows, default=str))
            if (j + 1) % 25 == 0:
                log(f"  {j + 1}/{len(plan)} flights ({time.perf_counter() - t0:.0f} s)", flush=True)
    return rows


DETECT_AFTER_END_S = 5.0     # a population alarm detects the disturbance when it starts before its end + this


def _pop_latency(row: dict, m: float) -> float | None:
    """First combined alarm after onset that starts before the disturbance's end (+ DETECT_AFTER_END_S)."""
    if row["onset"] is None:
        return None
    end = row["end"] if row.get("end") is not None else np.inf
    alarms = [(a, b) for a, b in row["alarms"][m] if a <= end + DETECT_AFTER_END_S]
    return latency_s(alarms, row["onset"])


def population_summary(rows: list[dict], m: float = 1.0) -> dict:
    """Per kind at threshold scale m: flights, false alarms (clean: every alarm; disturbed: alarms
    ending before onset), detections and latencies (all flights and those with the tests on)."""
    out: dict = {}
    for kind in dict.fromkeys(r["kind"] for r in rows):
        rs = [r for r in rows if r["kind"] == kind]
        s = {"flights": len(rs), "hours": sum(r["hours"] for r in rs), "tests_on": sum(r["tests_on"] for r in rs)}
        if kind == "clean":
            s["false_alarms"] = sum(len(r["alarms"][m]) for r in rs)
            s["flights_alarmed"] = sum(bool(r["alarms"][m]) for r in rs)
            s["alarmed_by_mode"] = {}
            for r in rs:
                if r["alarms"][m]:
                    s["alarmed_by_mode"][r["mode"]] = s["alarmed_by_mode"].get(r["mode"], 0) + 1
        else:
            s["pre_onset"] = sum(1 for r in rs for a, b in r["alarms"][m]
                                 if r["onset"] is not None and b is not None and b < r["onset"] - 0.5)
            for name, sel in (("all", rs), ("on", [r for r in rs if r["tests_on"]])):
                big = [r for r in sel if r["turn_deg"] >= MIN_TURN_DEG and r["onset"] is not None]
                lat = [_pop_latency(r, m) for r in big]
                got = [v for v in lat if v is not None]
                s[name] = {"n5": len(big), "detected5": len(got),
                           "median_s": float(np.median(got)) if got else float("nan"),
                           "worst_s": float(np.max(got)) if got else float("nan")}
        out[kind] = s
    return out


def print_population(rows: list[dict], seed: int) -> dict:
    """The population table (default thresholds) and the sweep; returns {scale: summary}."""
    sums = {m: population_summary(rows, m) for m in POP_SCALES}
    s = sums[1.0]
    print(f"Population benchmark (groundstation/sim/population.py, seed {seed}): {len(rows)} flights; "
          "default thresholds")
    c = s.get("clean")
    if c:
        print(f"  clean: {c['flights']} flights, {c['hours']:.2f} flight-hours ({c['tests_on']} with the heading "
              f"and field-vector tests on): combined false alarms {c['false_alarms']} on {c['flights_alarmed']} "
              f"flights {c['alarmed_by_mode'] or ''} (target 0)")
    print(f"  {'kind':8s} {'flights':>7s} | tests on (IMU >= 10 Hz): {'turn>=5':>7s} {'detected':>8s} {'median':>6s} "
          f"{'worst':>6s} | all flights: {'turn>=5':>7s} {'detected':>8s} | pre-onset alarms")
    for kind, k in s.items():
        if kind == "clean":
            continue
        on, al = k["on"], k["all"]
        tgt = POP_TARGET_S.get(kind)
        verdict = ""
        if tgt is not None and on["detected5"]:
            met = on["median_s"] <= tgt and on["worst_s"] <= 2 * on["median_s"]
            verdict = f"  median <= {tgt:g} s, worst <= 2x median: {'met' if met else 'NOT met'}"
        rate = 100.0 * on["detected5"] / on["n5"] if on["n5"] else float("nan")
        print(f"  {kind:8s} {k['flights']:7d} | {on['n5']:32d} {on['detected5']:8d} {on['median_s']:6.2f} "
              f"{on['worst_s']:6.2f} | {al['n5']:19d} {al['detected5']:8d} | {k['pre_onset']:3d}   "
              f"detected {rate:.1f} % (target 99 %){verdict}")
    print("\n  threshold sweep (x default): clean false alarms per flight-hour; median latency fast / slow [s]; "
          "detected (turn >= 5 deg, tests on)")
    for m, sm in sums.items():
        c = sm.get("clean", {"false_alarms": 0, "hours": float("nan")})
        fph = c["false_alarms"] / c["hours"] if c.get("hours") else float("nan")
        det = sum(v["on"]["detected5"] for k, v in sm.items() if k != "clean")
        n5 = sum(v["on"]["n5"] for k, v in sm.items() if k != "clean")
        lat = {k: sm[k]["on"]["median_s"] if k in sm else float("nan") for k in ("fast", "slow")}
        print(f"  x{m:<5g} {fph:6.3f} /h   fast {lat['fast']:5.2f}  slow {lat['slow']:5.2f}   detected {det}/{n5}")
    return sums


def write_population_png(sums: dict, path: str) -> None:
    """ROC-style: false alarms per flight-hour (clean population) against median latency, one
    point per threshold scale, for the fast and slow ramps."""
    plt = _pyplot()
    if plt is None:
        return
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    for case, color in (("fast", "tab:red"), ("slow", "tab:blue")):
        xs, ys, labels = [], [], []
        for m, sm in sums.items():
            c = sm.get("clean")
            if not c or case not in sm:
                continue
            xs.append(c["false_alarms"] / c["hours"])
            ys.append(sm[case]["on"]["median_s"])
            labels.append(m)
        ax.plot(xs, ys, "o-", color=color, label=f"{case} ramp (median latency)")
        for x_, y_, m in zip(xs, ys, labels):
            ax.annotate(f"x{m:g}", (x_, y_), fontsize=7, xytext=(3, 3), textcoords="offset points")
        ax.axhline(POP_TARGET_S[case], ls=":", color=color)
    ax.set_xlabel("combined false alarms per flight-hour (clean population flights)")
    ax.set_ylabel("median first-alarm latency [s]")
    ax.set_title("Population: false alarms vs latency (threshold scale)")
    ax.legend(fontsize=8)
    _save(plt, fig, path)


def main(argv: list[str] | None = None) -> int:
    """Print the table (and write the chart); return 0 when the default variant meets every target."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--outage-seeds", type=int, default=5)
    ap.add_argument("--png", default="benchmarks/results/detection_benchmark.png",
                    help="the latency-versus-false-alarm chart (default: benchmarks/results/, not tracked)")
    ap.add_argument("--quick", action="store_true", help="1 seed, fast ramp, one 90 s clean flight, no real logs")
    ap.add_argument("--population", type=int, metavar="N", help="N clean population flights "
                    "(groundstation/sim/population.py) and --per-kind disturbed flights of each kind")
    ap.add_argument("--per-kind", type=int, default=50, help="population flights per disturbance kind")
    ap.add_argument("--pop-seed", type=int, default=0, help="the population's seed (fixed per run)")
    ap.add_argument("--json", help="population: write the per-flight rows here")
    ap.add_argument("--kinds", help="population: only these kinds, comma-separated (clean,fast,slow,step,bump,"
                    "payload,anomaly), to split one run over processes")
    ap.add_argument("--first-index", type=int, default=0, help="population: start at this flight index (split "
                    "one run over processes: --population 100, and --population 200 --first-index 100)")
    ap.add_argument("--merge", nargs="+", metavar="JSON", help="population: print the table and chart of rows "
                    "written by --json runs (one run split by --kinds) instead of flying")
    a = ap.parse_args(argv)
    t0 = time.perf_counter()
    if a.population is not None or a.merge:
        if a.merge:
            import json
            rows = [r for f in a.merge for r in json.loads(Path(f).read_text())]
            for r in rows:
                r["alarms"] = {float(k): v for k, v in r["alarms"].items()}
        else:
            kinds = a.kinds.split(",") if a.kinds else None
            rows = population_run(a.population if (kinds is None or "clean" in kinds) else 0, a.per_kind, a.pop_seed,
                                  [k for k in kinds if k != "clean"] if kinds else None, out_json=a.json,
                                  first=a.first_index)
        sums = print_population(rows, a.pop_seed)
        if a.png:
            png = a.png if a.png != ap.get_default("png") else "benchmarks/results/detection_population.png"
            write_population_png(sums, png)
        print(f"(benchmark wall time {time.perf_counter() - t0:.0f} s)")
        c = sums[1.0].get("clean", {"false_alarms": 0})
        return 0 if c["false_alarms"] == 0 else 1
    if a.quick:
        res = run([0], [], 90.0, RAMPS[:1], real=False)
        n = 1
    else:
        res = run(list(range(a.seeds)), list(range(a.outage_seeds)), 200.0, RAMPS, real=True)
        n = a.seeds
    print_table(res, n)
    if a.png:
        write_png(res, a.png)
    print(f"(benchmark wall time {time.perf_counter() - t0:.0f} s)")
    return 0 if verdicts(res)[next(reversed(VARIANTS))] else 1


if __name__ == "__main__":
    raise SystemExit(main())
