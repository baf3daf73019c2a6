"""Heading/attitude benchmark next to the seeds' figures (issue 4).

1. Static heading protocol of seed 000 table 1: 8 headings 45° apart, each level and rolled −20°,
   simulated IMU + magnetometer time series (hard iron + per-axis scale, the seed's model (1)),
   calibrated with estimators.calibration (seed 000 RLS ellipsoid on a full-rotation data set),
   the whole chain (gravity + field vector filters, tilt compensation, WMM declination) run over
   it; readings are the mean heading over the last 2 s of each 10 s hold.
2. GPS outage of 80 s with gyro bias 0.5°/s per axis during manoeuvring flight (seed 003):
   open-loop INS vs field-vector feedback (seed 003's PI law, PI + gravity, the Kalman-gain
   feedback that is our default, and the same tuned for a sudden bias change, which is fragile
   on flights with a motor-current field: see estimators/ins_gps.py); two cases: the bias is there all flight (the Kalman filter
   learns it while GPS is good) and the bias appears at the outage start (unseen).  Bias signs
   (+,+,+) on odd seeds, (+,−,+) on even seeds.  "hdg max all" runs from 20 s to the end; in the step case the bias
   vanishes again when GPS returns (a second unseen step), and that column includes it.
3. Speed of the batch chain (IMU samples/s) and of the per-sample chain.

Run:  .venv/bin/python benchmarks/heading.py [--quick]
"""
from __future__ import annotations

import argparse
import pathlib
import sys
import time

import numpy as np

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parents[1]))

from estimators.rotations import dcm_body_to_ned  # noqa: E402
from estimators.calibration import RlsEllipsoidCalibrator, apply_calibration  # noqa: E402
from estimators.geomag import earth_field  # noqa: E402
from estimators.heading import HeadingChain, run_heading_chain  # noqa: E402
from estimators.rotations import wrap_angle_deg  # noqa: E402
from estimators.ins_gps import InsGpsSettings, attitude_errors_deg, run_ins_gps  # noqa: E402
from groundstation.sim.truth import simulate_manoeuvring_flight  # noqa: E402

G = 9.80665


# ----------------------------------------------------------------------------- 1. static protocol

def _smooth_step(n: int) -> np.ndarray:
    return 0.5 - 0.5 * np.cos(np.linspace(0.0, np.pi, n))


def static_protocol_sequence(rate_hz: float = 100.0, hold_s: float = 10.0, move_s: float = 3.0):
    """Euler angles (N,3) and the read-out windows [(i0, i1, heading_index, rolled)]."""
    hold, move = int(hold_s * rate_hz), int(move_s * rate_hz)
    roll, yaw, windows = [], [], []
    y0 = np.radians(10.0)                           # start off a cardinal direction
    n = 0
    for k in range(8):
        yk = y0 + np.radians(45.0) * k
        for rolled in (False, True):
            r = np.radians(-20.0) if rolled else 0.0
            roll.append(np.full(hold, r)); yaw.append(np.full(hold, yk))
            windows.append((n + hold - int(2 * rate_hz), n + hold, k, rolled))
            n += hold
            nxt = 0.0 if rolled else np.radians(-20.0)
            roll.append(r + (nxt - r) * _smooth_step(move)); yaw.append(np.full(move, yk))
            n += move
        roll.append(np.zeros(move)); yaw.append(yk + np.radians(45.0) * _smooth_step(move))
        n += move
    roll, yaw = np.concatenate(roll), np.concatenate(yaw)
    return np.c_[roll, np.zeros_like(roll), yaw], windows


def _body_rates(euler: np.ndarray, dt: float) -> np.ndarray:
    r, p, y = euler.T
    dr, dp, dy = (np.gradient(a, dt) for a in (r, p, y))
    return np.c_[dr - dy * np.sin(p), dp * np.cos(r) + dy * np.cos(p) * np.sin(r),
                 -dp * np.sin(r) + dy * np.cos(p) * np.cos(r)]


def static_protocol(sensors: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    ef = earth_field(30.26, 120.12, 10.0, 2026.5)            # Hangzhou, where seed 000 flew
    h_n, F = ef.field_ned_mG, ef.field_strength_mG
    rate = 100.0
    euler, windows = static_protocol_sequence(rate)
    n = len(euler)
    t = np.arange(n) / rate
    C = dcm_body_to_ned(*euler.T)
    truth_body = np.einsum("nji,j->ni", C, h_n)
    steps, diffs, static = [], [], []
    for _ in range(sensors):
        s = rng.uniform(0.85, 1.15, 3)
        b = rng.uniform(-0.3, 0.3, 3) * F
        # calibration: 5000 samples over the whole sphere, seed 000 RLS (step 1-5)
        m = 5000
        att = np.c_[rng.uniform(-np.pi, np.pi, m), np.arcsin(rng.uniform(-1, 1, m)), rng.uniform(-np.pi, np.pi, m)]
        raw_cal = np.einsum("nji,j->ni", dcm_body_to_ned(*att.T), h_n) * s + b + rng.normal(0, 1.0, (m, 3))
        rls = RlsEllipsoidCalibrator(F)
        rls.update_batch(raw_cal)
        # static protocol time series
        gyro = _body_rates(euler, 1.0 / rate) + np.radians(0.05) + rng.normal(0, 0.003, (n, 3))
        acc = np.einsum("nji,j->ni", C, [0.0, 0.0, -G]) + rng.normal(0, 0.02, (n, 3))
        raw = truth_body * s + b + rng.normal(0, 1.0, (n, 3))
        mi = np.arange(0, n, 2)                                   # magnetometer at 50 Hz
        mag_cal = np.c_[t[mi], apply_calibration(raw[mi], rls.offsets_mG, rls.matrix)]
        res = run_heading_chain(np.c_[t, gyro, acc], mag_cal, ef.declination_deg)
        read = np.zeros((8, 2))
        for i0, i1, k, rolled in windows:
            h = res.heading_true_rad[i0:i1]
            read[k, int(rolled)] = np.degrees(np.angle(np.mean(np.exp(1j * h))))
            static.append(float(wrap_angle_deg(read[k, int(rolled)] - np.degrees(euler[i1 - 1, 2]))))
        for col in range(2):
            steps.extend(wrap_angle_deg(np.diff(np.r_[read[:, col], read[0, col]]) - 45.0))
        diffs.extend(wrap_angle_deg(read[:, 1] - read[:, 0]))
    steps, diffs, static = map(np.asarray, (steps, diffs, static))
    rms = lambda a: float(np.sqrt(np.mean(a ** 2)))
    return dict(step_rms=rms(steps), step_max=float(np.abs(steps).max()), roll_rms=rms(diffs),
                roll_max=float(np.abs(diffs).max()), static_max=float(np.abs(static).max()),
                static_rms=rms(static), sensors=sensors, declination=ef.declination_deg)


# ----------------------------------------------------------------------------- 2. GPS outage

def outage_case(case: str, seeds: list[int], duration_s: float, outage: tuple[float, float], rate_hz: float):
    b = np.radians(0.5)
    configs = {"open-loop INS": dict(field_feedback=False),
               "field feedback, PI (seed 003)": dict(feedback_law="pi"),
               "PI + gravity on field line": dict(feedback_law="pi", gravity_kp_per_s=0.2),
               "field feedback, Kalman (default)": dict(),
               "Kalman tuned for a bias step": dict(outage_gyro_bias_sigma_rad_s=0.001, outage_field_walk_mG=0.0)}
    rows = {k: dict(att_rms=[], att_max=[], head_max=[], head_max_all=[]) for k in configs}
    for sd in seeds:
        bias = (b, -b if sd % 2 == 0 else b, b)              # sign pattern varies with the seed
        tr = simulate_manoeuvring_flight(
            duration_s=duration_s, imu_rate_hz=rate_hz, outage=outage, seed=sd,
            gyro_bias_rad_s=bias if case == "bias all flight" else (0.0, 0.0, 0.0),
            outage_gyro_bias_rad_s=bias if case == "bias step at outage" else (0.0, 0.0, 0.0))
        dec = float(np.degrees(np.arctan2(tr.field_ned_mG[1], tr.field_ned_mG[0])))
        inside = (tr.t_s >= outage[0]) & (tr.t_s < outage[1])
        after_align = tr.t_s >= 20.0
        for name, kw in configs.items():
            res = run_ins_gps(tr.imu, tr.gps_ned, tr.mag, InsGpsSettings(declination_deg=dec, **kw))
            ang, hd = attitude_errors_deg(res, tr)
            r = rows[name]
            r["att_rms"].append(np.sqrt(np.mean(ang[inside] ** 2)))
            r["att_max"].append(ang[inside].max())
            r["head_max"].append(np.abs(hd[inside]).max())
            r["head_max_all"].append(np.abs(hd[after_align]).max())
    return {k: {m: float(np.mean(v)) if m == "att_rms" else float(np.max(v)) for m, v in r.items()}
            for k, r in rows.items()}


# ----------------------------------------------------------------------------- 3. speed

def speed(n: int, n_live: int):
    rng = np.random.default_rng(3)
    t = np.arange(n) * 0.0025                                   # 400 Hz IMU, 100 Hz magnetometer
    imu = np.c_[t, rng.normal(0, 0.3, (n, 3)), np.array([0.3, -0.2, -9.7]) + rng.normal(0, 0.1, (n, 3))]
    mag = np.c_[t[::4], np.array([220.0, 20.0, 420.0]) + rng.normal(0, 2, (len(t[::4]), 3))]
    t0 = time.perf_counter()
    run_heading_chain(imu, mag, 3.0)
    batch = n / (time.perf_counter() - t0)
    chain = HeadingChain(3.0)
    t0 = time.perf_counter()
    j = 0
    for i in range(n_live):
        if i % 4 == 0:
            chain.update_mag(mag[j, 0], mag[j, 1:4])
            j += 1
        chain.update_imu(imu[i, 0], imu[i, 1:4], imu[i, 4:7])
    live = n_live / (time.perf_counter() - t0)
    return batch, live


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small smoke run")
    a = ap.parse_args(argv)
    q = a.quick
    st = static_protocol(sensors=2 if q else 20)
    print("\n1. Static heading protocol (seed 000 table 1), %d simulated sensors, whole chain, "
          "seed-000 RLS calibration, WMM declination %.2f deg" % (st["sensors"], st["declination"]))
    print(f"{'metric':42s} {'ours':>8s} {'target':>10s} {'seed 000':>9s}")
    for name, v, tgt, seedv in (("45 deg step error RMS [deg]", st["step_rms"], "<= 0.5", "1.41"),
                                ("45 deg step error max [deg]", st["step_max"], "", "2.42"),
                                ("level vs -20 deg roll RMS [deg]", st["roll_rms"], "<= 0.3", "0.30"),
                                ("level vs -20 deg roll max [deg]", st["roll_max"], "", "0.58"),
                                ("static true-heading error max [deg]", st["static_max"], "< 1.5", "< 1.5"),
                                ("static true-heading error RMS [deg]", st["static_rms"], "", "")):
        print(f"{name:42s} {v:8.3f} {tgt:>10s} {seedv:>9s}")

    seeds = [1] if q else [1, 2, 3, 4, 5]
    dur, out_ = (130.0, (40.0, 120.0)) if q else (200.0, (90.0, 170.0))
    rate = 50.0 if q else 100.0
    print(f"\n2. GPS outage {out_[1] - out_[0]:.0f} s, gyro bias 0.5 deg/s per axis, manoeuvring flight "
          f"({len(seeds)} seeds, IMU {rate:.0f} Hz; RMS averaged, max over seeds)")
    print("   target: attitude error with field feedback <= 1/3 of open loop; heading error < 2 deg "
          "throughout; seed 003 reports closed loop < open loop")
    checks = [("static 45 deg step RMS <= 0.5 deg", st["step_rms"] <= 0.5),
              ("static level-vs-roll RMS <= 0.3 deg", st["roll_rms"] <= 0.3),
              ("static true-heading error max < 1.5 deg", st["static_max"] < 1.5)]
    for case in ("bias all flight", "bias step at outage"):
        res = outage_case(case, seeds, dur, out_, rate)
        ol = res["open-loop INS"]["att_rms"]
        ours = res["field feedback, Kalman (default)"]
        checks += [(f"outage, {case}: attitude RMS <= 1/3 open loop", ours["att_rms"] <= ol / 3.0),
                   (f"outage, {case}: heading error < 2 deg", ours["head_max"] < 2.0)]
        print(f"  case: {case}")
        print(f"  {'estimator':34s} {'att RMS':>8s} {'att max':>8s} {'ratio':>6s} {'hdg max out':>11s} {'hdg max all':>11s}")
        for name, r in res.items():
            print(f"  {name:34s} {r['att_rms']:8.2f} {r['att_max']:8.2f} {r['att_rms'] / ol:6.2f} "
                  f"{r['head_max']:11.2f} {r['head_max_all']:11.2f}")

    batch, live = speed(200_000 if q else 1_000_000, 5_000 if q else 20_000)
    print("\n3. Speed")
    print(f"  batch run_heading_chain   {batch:12,.0f} IMU samples/s   (target >= 100,000)")
    print(f"  per-sample HeadingChain   {live:12,.0f} IMU samples/s   (live path)")
    checks.append(("batch chain >= 100,000 IMU samples/s", batch >= 100_000))
    print("\n4. Targets (default estimator)")
    for name, ok in checks:
        print(f"  {'met   ' if ok else 'MISSED'}  {name}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
