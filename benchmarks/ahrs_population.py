"""Held-out check of the default AHRS: a randomised simulated population beside VQF, one run.

The AHRS default (estimators/ahrs.py ``AhrsSettings()``) and the smoother's were tuned on the seven
BROAD trials that benchmarks/ahrs.py scores (docs/attitude.md); BROAD's other 32 trials are not in
../shared.  So this runs ours and VQF, each at its single default, on flights none of them was
tuned on: the closed-loop multirotor missions of the detection population
(groundstation/sim/population.py, kind "clean"), one flight per seed, drawn from its priors —
sites from −60° to 78° inclination, gyro bias up to 0.5 °/s per axis, wind 0–8 m/s with gusts,
stop-and-go or survey routes (sometimes with the nose sweeping), 180–300 s at 50 Hz.  Nothing is
tuned here.

Inputs (the same to every filter): the simulator's 50 Hz gyro and accelerometer (noise, bias) and
the magnetometer calibrated with its true hard and soft iron, in two variants:
  * "motor removed": the motor-current field taken out entirely (the Earth field + noise);
  * "as streamed": the part of the motor field the autopilot does not compensate left in
    ((1 − c)·f·I, c 50–100 %, |f| up to 10 mG/A): a slowly varying body-fixed disturbance.
Truth: the simulated attitude, heading magnetic (declination of the simulated field removed),
as BROAD's truth.  Metric: benchmarks/ahrs.py's (BROAD's: q_err = q_est ⊗ q_ref* in the earth
frame, heading and inclination RMS, no heading offset removed), from 30 s in (every filter starts
from the data) to the end.

Run:  .venv/bin/python benchmarks/ahrs_population.py [--seeds 24] [--quick]
"""
from __future__ import annotations

import argparse
import math
import pathlib
import sys
import time

import numpy as np

_HERE = pathlib.Path(__file__).resolve().parent     # keep this folder off the path (the ``ahrs`` package)
sys.path[:] = [p for p in sys.path if pathlib.Path(p or ".").resolve() != _HERE]
sys.path.insert(0, str(_HERE.parent))

from benchmarks.broad_peers import (SENSOR_TO_FRD, BroadTrial, quat_enu_from_dcm_ned, run_offline_vqf,  # noqa: E402
                                    run_vqf, score_deg)
from estimators.attitude_smoother import smooth_heading_chain  # noqa: E402
from estimators.heading import run_heading_chain  # noqa: E402
from estimators.rotations import dcm_body_to_ned  # noqa: E402
from groundstation.sim import flight_sim as fs  # noqa: E402
from groundstation.sim import population  # noqa: E402

SCORE_FROM_S = 30.0
CAUSAL, OFFLINE, VQF, OFFLINE_VQF = "ours causal", "ours offline", "VQF", "offlineVQF"
COLUMNS = (CAUSAL, OFFLINE, VQF, OFFLINE_VQF)
VARIANTS = ("motor removed", "as streamed")
TOLERANCE_DEG = 0.02


def flight_trials(seed: int, duration_s: float | None = None) -> tuple[dict, list[BroadTrial]]:
    """(the draw's summary, one BroadTrial per VARIANTS) of the population's clean flight of ``seed``."""
    d = population.draw_flight(0, seed=seed, kind="clean")
    if duration_s is not None:
        d = population.replace_draw(d, duration_s=duration_s, gps_outage=None)
    cfg = population._config(d)
    res = fs.run(cfg)
    t = res.t_s
    motor = res.motor_current_A[:, None] * np.asarray(d.motor_mG_per_A)[None, :]
    body = (res.mag_raw_mG - cfg.mag.offsets_mG) @ np.linalg.inv(cfg.mag.matrix).T     # true calibration
    h = cfg.field_ned_mG
    decl = math.atan2(h[1], h[0])
    q_true = quat_enu_from_dcm_ned(dcm_body_to_ned(res.roll_rad, res.pitch_rad, res.yaw_rad - decl))
    fields = {"motor removed": body - motor, "as streamed": body - d.motor_comp * motor}
    rate = 1.0 / float(np.median(np.diff(t)))
    trials = [BroadTrial(f"{d.label()}-s{seed}", rate, res.gyro_rad_s @ SENSOR_TO_FRD, res.accel_mps2 @ SENSOR_TO_FRD,
                         fields[v] @ SENSOR_TO_FRD / 10.0, q_true, t >= SCORE_FROM_S) for v in VARIANTS]
    info = {"seed": seed, "incl": d.inclination_deg, "bias": float(np.max(np.abs(d.gyro_bias_deg_s))),
            "route": d.route, "sweep": d.yaw_sweep_deg_s, "wind": float(np.hypot(*d.wind_mps)),
            "motor": float(np.linalg.norm(d.motor_mG_per_A) * (1.0 - d.motor_comp)), "duration": float(t[-1])}
    return info, trials


def _ours(trial: BroadTrial, offline: bool) -> np.ndarray:
    imu = np.c_[trial.t_s, trial.gyro_rad_s @ SENSOR_TO_FRD, trial.acc_mps2 @ SENSOR_TO_FRD]
    mag = np.c_[trial.t_s, trial.mag_uT @ SENSOR_TO_FRD * 10.0]
    r = (smooth_heading_chain if offline else run_heading_chain)(imu, mag, 0.0)
    return quat_enu_from_dcm_ned(dcm_body_to_ned(r.roll_rad, r.pitch_rad, r.yaw_rad))


RUNNERS = {CAUSAL: lambda tr: _ours(tr, False), OFFLINE: lambda tr: _ours(tr, True), VQF: run_vqf,
           OFFLINE_VQF: run_offline_vqf}


def _yes(ok: bool) -> str:
    return "yes" if ok else "no"


def print_variant(variant: str, infos: list[dict], rows: list[dict]) -> None:
    """One field variant: the per-flight table, mean and median, and the issue-27 comparisons."""
    print(f"\nfield {variant}: heading / inclination RMS [deg] from {SCORE_FROM_S:g} s, BROAD's metric")
    print(f"{'seed':>4s} {'incl':>6s} {'bias':>5s} {'route':>11s} {'resid mG/A':>10s} " +
          " ".join(f"{c:>13s}" for c in COLUMNS))
    for info, row in zip(infos, rows):
        print(f"{info['seed']:4d} {info['incl']:6.1f} {info['bias']:5.2f} {info['route']:>11s} "
              f"{info['motor']:10.2f} " + " ".join(f"{row[c][0]:6.2f}/{row[c][1]:<6.2f}" for c in COLUMNS))
    mean = {c: [float(np.mean([r[c][j] for r in rows])) for j in (0, 1)] for c in COLUMNS}
    med = {c: [float(np.median([r[c][j] for r in rows])) for j in (0, 1)] for c in COLUMNS}
    print(f"{'mean':>40s} " + " ".join(f"{mean[c][0]:6.2f}/{mean[c][1]:<6.2f}" for c in COLUMNS))
    print(f"{'median':>40s} " + " ".join(f"{med[c][0]:6.2f}/{med[c][1]:<6.2f}" for c in COLUMNS))
    for ours, peer in ((CAUSAL, VQF), (OFFLINE, OFFLINE_VQF)):
        k = [sum(r[ours][j] <= r[peer][j] + TOLERANCE_DEG for r in rows) for j in (0, 1)]
        print(f"  {sum(k)} of {2 * len(rows)} flight-metrics: {ours} at or below {peer} (+{TOLERANCE_DEG} deg): "
              f"heading {k[0]} of {len(rows)}, inclination {k[1]} of {len(rows)}")
    m = {c: f"{mean[c][0]:.3f}/{mean[c][1]:.3f}" for c in COLUMNS}
    print(f"  causal means below VQF's: {_yes(all(mean[CAUSAL][j] < mean[VQF][j] for j in (0, 1)))} "
          f"({m[CAUSAL]} vs {m[VQF]})")
    print(f"  offline mean inclination below offlineVQF's: {_yes(mean[OFFLINE][1] < mean[OFFLINE_VQF][1])} "
          f"({mean[OFFLINE][1]:.3f} vs {mean[OFFLINE_VQF][1]:.3f})")
    print(f"  offline mean heading below ours causal: {_yes(mean[OFFLINE][0] < mean[CAUSAL][0])} "
          f"({mean[OFFLINE][0]:.3f} vs {mean[CAUSAL][0]:.3f})")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, default=24, help="flights (seeds 0..N-1; default 24)")
    ap.add_argument("--quick", action="store_true", help="smoke run: 2 seeds of 60 s")
    a = ap.parse_args(argv)
    try:
        import vqf  # noqa: F401
    except ImportError:
        print("missing package vqf: pip install -e .[bench]")
        return 1
    seeds = range(2 if a.quick else a.seeds)
    t0 = time.perf_counter()
    scores = {v: [] for v in VARIANTS}
    infos = []
    for seed in seeds:
        info, trials = flight_trials(seed, 60.0 if a.quick else None)
        infos.append(info)
        for v, tr in zip(VARIANTS, trials):
            scores[v].append({c: score_deg(RUNNERS[c](tr), tr) for c in COLUMNS})
    for v in VARIANTS:
        print_variant(v, infos, scores[v])
    print(f"\nbenchmark wall time {time.perf_counter() - t0:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
