"""Real and simulated ArduPilot logs: our calibration pieces against the vehicle and pymavlink's magfit_WMM.

    .venv/bin/python benchmarks/real_logs.py            # 3 seeds + magfit_WMM side by side (~20 min: magfit
                                                        # takes 3.5-8 min per 2,900-record log on this box)
    .venv/bin/python benchmarks/real_logs.py --quick    # one seed, magfit on every 10th record (~1 min)
    .venv/bin/python benchmarks/real_logs.py --quick --no-magfit   # the smoke run of the tests (~10 s)
magfit_WMM needs the "bench" extra (scipy, matplotlib).

For each simulated flight (groundstation.sim.ardupilot: three compasses, stale offsets, an onboard
calibration dance inside a 1.5 Hz telemetry log, a polygon mission with motor current):
1. the calibration window found in the telemetry log vs the vehicle's own MAG_CAL_REPORT
   (target: within 20 mG);
2. the in-flight fit against the WMM (estimators.wmm_fit) on the mission, vs truth (target 5 mG);
3. the motor field per ampere (estimators.motor_field) vs truth (target 10 %);
4. the same in-flight fit on the DataFlash .bin of the flight, next to pymavlink's
   tools/magfit_WMM.py on the same file (offsets error vs truth, runtime; ours must be faster and at
   least as accurate).
The extraction helpers (``extract_tlog``, ``extract_bin``) read a log with pymavlink into arrays
per compass; the later ingest work replaces them with groundstation's readers and extends this
table to the real logs in ../shared/data.
"""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import argparse  # noqa: E402
import re  # noqa: E402
import subprocess  # noqa: E402
import sys  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from dataclasses import dataclass, field  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

import groundstation  # noqa: E402,F401  (selects MAVLink 2 before pymavlink loads)

MAG_MESSAGES = {"RAW_IMU": 0, "SCALED_IMU2": 1, "SCALED_IMU3": 2}


@dataclass
class LogArrays:
    """A log as arrays per compass (times in s from the first record)."""
    mag: dict = field(default_factory=dict)          # compass -> (t_s (N,), corrected (N,3), logged motor offset or None)
    params: list = field(default_factory=list)       # (t_s, name, value)
    attitude: np.ndarray = field(default_factory=lambda: np.empty((0, 4)))
    gps: np.ndarray = field(default_factory=lambda: np.empty((0, 6)))   # t, lat, lon, alt, vn, ve
    current: np.ndarray = field(default_factory=lambda: np.empty((0, 2)))
    cal_progress: dict = field(default_factory=dict)  # compass -> [t_s...]
    cal_report: dict = field(default_factory=dict)    # compass -> (t_s, ofs (3,), fitness)


def _finish(rows: dict, out: LogArrays, t0: float) -> LogArrays:
    for k, r in rows["mag"].items():
        a = np.array(r, float)
        out.mag[k] = (a[:, 0] - t0, a[:, 1:4], a[:, 4:7] if a.shape[1] >= 7 else None)
    out.params = [(t - t0, n, v) for t, n, v in rows["params"]]
    for name in ("attitude", "gps", "current"):
        a = np.array(rows[name], float).reshape(-1, {"attitude": 4, "gps": 6, "current": 2}[name])
        a[:, 0] -= t0
        setattr(out, name, a)
    out.cal_progress = {k: [t - t0 for t in v] for k, v in rows["progress"].items()}
    out.cal_report = {k: (t - t0, o, f) for k, (t, o, f) in rows["report"].items()}
    return out


def _new_rows() -> dict:
    return {"mag": {}, "params": [], "attitude": [], "gps": [], "current": [], "progress": {}, "report": {}}


def extract_tlog(path: str | Path) -> LogArrays:
    """Telemetry log -> arrays (arrival times; GCS traffic ignored)."""
    from pymavlink import mavutil
    conn = mavutil.mavlink_connection(str(path), robust_parsing=True)
    rows, t0 = _new_rows(), None
    while (m := conn.recv_msg()) is not None:
        typ = m.get_type()
        if typ == "BAD_DATA" or m.get_srcSystem() == 255:
            continue
        t = float(m._timestamp)
        t0 = t if t0 is None else t0
        if typ in MAG_MESSAGES and (m.xmag, m.ymag, m.zmag) != (0, 0, 0):
            rows["mag"].setdefault(MAG_MESSAGES[typ], []).append((t, m.xmag, m.ymag, m.zmag))
        elif typ == "ATTITUDE":
            rows["attitude"].append((t, m.roll, m.pitch, m.yaw))
        elif typ == "GPS_RAW_INT" and m.fix_type >= 3:
            c = np.radians(m.cog / 100.0)
            rows["gps"].append((t, m.lat * 1e-7, m.lon * 1e-7, m.alt * 1e-3, m.vel / 100 * np.cos(c), m.vel / 100 * np.sin(c)))
        elif typ == "SYS_STATUS" and m.current_battery >= 0:
            rows["current"].append((t, m.current_battery / 100.0))
        elif typ == "PARAM_VALUE":
            rows["params"].append((t, m.param_id.rstrip("\x00"), float(m.param_value)))
        elif typ == "SENSOR_OFFSETS":
            rows["params"] += [(t, f"COMPASS_OFS_{a}", float(v)) for a, v in zip("XYZ", (m.mag_ofs_x, m.mag_ofs_y, m.mag_ofs_z))]
        elif typ == "MAG_CAL_PROGRESS":
            rows["progress"].setdefault(m.compass_id, []).append(t)
        elif typ == "MAG_CAL_REPORT":
            rows["report"][m.compass_id] = (t, np.array([m.ofs_x, m.ofs_y, m.ofs_z]), float(m.fitness))
    conn.close()
    return _finish(rows, LogArrays(), t0 or 0.0)


def extract_bin(path: str | Path) -> LogArrays:
    """DataFlash log -> arrays (MAG/MAG2/MAG3 or MAG with I; MAG.Ofs* as offset history of each compass)."""
    from pymavlink import mavutil
    conn = mavutil.mavlink_connection(str(path))
    rows, t0 = _new_rows(), None
    while (m := conn.recv_match(type=["MAG", "MAG2", "MAG3", "ATT", "GPS", "BAT", "CURR", "PARM"])) is not None:
        typ, t = m.get_type(), float(m._timestamp)
        t0 = t if t0 is None else t0
        if typ.startswith("MAG"):
            k = int(getattr(m, "I", 0)) if typ == "MAG" else int(typ[3]) - 1
            mo = (getattr(m, "MOX", getattr(m, "MOfsX", 0)), getattr(m, "MOY", getattr(m, "MOfsY", 0)),
                  getattr(m, "MOZ", getattr(m, "MOfsZ", 0)))
            rows["mag"].setdefault(k, []).append((t, m.MagX, m.MagY, m.MagZ, *mo))
            n = "" if k == 0 else str(k + 1)
            rows["params"] += [(t, f"COMPASS_OFS{n}_{a}", float(v)) for a, v in zip("XYZ", (m.OfsX, m.OfsY, m.OfsZ))]
        elif typ == "ATT":
            rows["attitude"].append((t, *np.radians([m.Roll, m.Pitch, m.Yaw])))
        elif typ == "GPS" and m.Status >= 3:
            c = np.radians(m.GCrs)
            rows["gps"].append((t, m.Lat, m.Lng, m.Alt, m.Spd * np.cos(c), m.Spd * np.sin(c)))
        elif typ in ("BAT", "CURR") and int(getattr(m, "Inst", 0)) == 0:
            rows["current"].append((t, m.Curr / (100.0 if typ == "CURR" else 1.0)))
        elif typ == "PARM":
            rows["params"].append((t, m.Name, float(m.Value)))
    conn.close()
    return _finish(rows, LogArrays(), t0 or 0.0)


# ------------------------------------------------------------------------------------ pipeline

def raw_field(arr: LogArrays, k: int):
    """(t_s, raw (N,3), corrected (N,3), corrections) of compass k with the corrections in force rebuilt."""
    from estimators.compass_corrections import corrections_from_param_changes, unapply_ardupilot_corrections
    t, corrected, logged_mot = arr.mag[k]
    corr = corrections_from_param_changes(t, arr.params, k)
    cur = np.interp(t, arr.current[:, 0], arr.current[:, 1]) if len(arr.current) else None
    rebuilt = unapply_ardupilot_corrections(corrected, corr, current_A=cur, logged_motor_offset_mG=logged_mot)
    return t, rebuilt.raw_mG, corrected, corr


def flight_inputs(arr: LogArrays, t: np.ndarray):
    """Attitude (with rate), GPS velocity and current at the field times."""
    from estimators.log_alignment import attitude_at, interp_series
    att = attitude_at(t, arr.attitude[:, 0], arr.attitude[:, 1], arr.attitude[:, 2], arr.attitude[:, 3])
    vel, _ = interp_series(t, arr.gps[:, 0], arr.gps[:, 4:6], max_gap_s=2.0)
    cur, _ = interp_series(t, arr.current[:, 0], arr.current[:, 1], max_gap_s=2.0)
    return att, vel, cur[:, 0]


def expected_field(arr: LogArrays, start_unix_s: float):
    from estimators.geomag import decimal_year_from_unix, earth_field
    lat, lon, alt = arr.gps[0, 1:4]
    return earth_field(lat, lon, alt, decimal_year_from_unix(start_unix_s))


def window_offsets(arr: LogArrays, k: int):
    """The chosen calibration window's ArduPilot offsets (COMPASS_OFS = −b) and the search result."""
    from estimators.cal_windows import find_calibration_windows
    from estimators.log_alignment import attitude_at
    t, raw, _, _ = raw_field(arr, k)
    att = attitude_at(t, arr.attitude[:, 0], arr.attitude[:, 1], arr.attitude[:, 2], arr.attitude[:, 3])
    marks = [(min(v), max(v + [arr.cal_report[k][0]] if k in arr.cal_report else v))
             for kk, v in arr.cal_progress.items() if kk == k and v]
    res = find_calibration_windows(t, raw, rate_deg_s=att.rate_deg_s, marker_spans_s=marks)
    w = res.chosen_window
    return (None if w is None else -w.fit.offsets_mG), res


def wmm_fit_compass(arr: LogArrays, k: int, field_ned_mG: np.ndarray, settings=None):
    from estimators.wmm_fit import WmmFitSettings, fit_wmm
    t, raw, corrected, corr = raw_field(arr, k)
    att, vel, cur = flight_inputs(arr, t)
    from estimators.compass_corrections import correction_matrices
    return fit_wmm(t, raw, att.roll_rad, att.pitch_rad, att.yaw_rad, field_ned_mG, attitude_rate_deg_s=att.rate_deg_s,
                   motor_signal=cur, gps_vel_ne_mps=vel, corrected_in_force_mG=corrected,
                   nominal_matrix=correction_matrices(corr.diag[-1:], corr.offdiag[-1:])[0], settings=settings or WmmFitSettings())


def motor_fit_compass(arr: LogArrays, k: int, field_ned_mG: np.ndarray):
    from estimators.compass_corrections import correction_matrices
    from estimators.motor_field import fit_motor_field
    t, raw, corrected, corr = raw_field(arr, k)
    att, vel, cur = flight_inputs(arr, t)
    return fit_motor_field(t, raw, att.roll_rad, att.pitch_rad, att.yaw_rad, field_ned_mG, cur,
                           attitude_rate_deg_s=att.rate_deg_s, gps_vel_ne_mps=vel, corrected_in_force_mG=corrected,
                           nominal_matrix=correction_matrices(corr.diag[-1:], corr.offdiag[-1:])[0])


# ------------------------------------------------------------------------------------ peers

MAGFIT = Path(__import__("pymavlink").__file__).parent / "tools" / "magfit_WMM.py"


def run_magfit(path: Path, mag: int = 1, reduce: int = 1, timeout_s: float = 900.0) -> dict:
    """pymavlink's magfit_WMM.py on a DataFlash log (same model as ours: --elliptical --cmot).
    Returns {"ofs": COMPASS_OFS (3,), "cmot": (3,), "runtime_s", "error"}."""
    try:
        import scipy  # noqa: F401  (magfit_WMM needs scipy and matplotlib: the "bench" extra)
        import matplotlib  # noqa: F401
    except ImportError as err:
        return {"error": f"magfit_WMM needs {err.name}"}
    cmd = [sys.executable, str(MAGFIT), "--att-source", "ATT", "--mag", str(mag), "--elliptical", "--cmot",
           "--reduce", str(reduce), str(path)]
    t0 = time.perf_counter()
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout_s, env=dict(os.environ, MPLBACKEND="Agg"))
    except subprocess.TimeoutExpired:
        return {"error": f"timeout after {timeout_s:.0f} s", "runtime_s": timeout_s}
    dt = time.perf_counter() - t0
    m = re.search(r"New: Vector3\(([-\d.]+), ([-\d.]+), ([-\d.]+)\).*cmot: Vector3\(([-\d.]+), ([-\d.]+), ([-\d.]+)\)",
                  out.stdout)
    if not m:
        return {"error": (out.stderr.strip().splitlines() or ["no result"])[-1], "runtime_s": dt}
    v = np.array([float(x) for x in m.groups()])
    return {"ofs": v[:3], "cmot": v[3:], "runtime_s": dt}


# ------------------------------------------------------------------------------------ table

def _verdict(ok: bool) -> str:
    return "PASS" if ok else "FAIL"


def bench_windows(seed: int, tmp: Path) -> list[str]:
    from groundstation.sim.ardupilot import ArduSimConfig, simulate_ardupilot
    sim = simulate_ardupilot(ArduSimConfig(seed=seed, imu_rate_hz=1.5))
    arr = extract_tlog(sim.write_tlog(tmp / f"dance-{seed}.tlog"))
    rows = []
    for k in sorted(arr.mag):
        ofs, res = window_offsets(arr, k)
        w = res.chosen_window
        err = float(np.max(np.abs(ofs - arr.cal_report[k][1]))) if ofs is not None else float("nan")
        rows.append(f"  seed {seed} compass {k}: {res.status:22s} {w.n_samples if w else 0:3d} samples "
                    f"{w.model if w else '-':9s} max |ours - MAG_CAL_REPORT| {err:5.1f} mG   target 20   {_verdict(err <= 20)}")
    return rows


def bench_inflight(seed: int, tmp: Path, magfit_reduce: int | None) -> list[str]:
    from groundstation.sim.ardupilot import ArduSimConfig, simulate_ardupilot
    from groundstation.sim.ardupilot_flight import FlightPlan
    sim = simulate_ardupilot(ArduSimConfig(seed=seed, imu_rate_hz=2.0, plan=FlightPlan(dance=False, legs=6)))
    arr = extract_tlog(sim.write_tlog(tmp / f"flight-{seed}.tlog"))
    H = np.asarray(expected_field(arr, sim.config.start_unix_s).field_ned_mG)
    rows = []
    for k in sorted(arr.mag):
        tr = sim.truth["compasses"][k]
        t0 = time.perf_counter()
        fit = wmm_fit_compass(arr, k, H)
        dt = time.perf_counter() - t0
        err = float(np.max(np.abs(fit.offsets_mG - tr["offsets_rot_mG"])))
        mot = motor_fit_compass(arr, k, H)
        f = np.asarray(tr["motor_mG_per_A"])
        rel = 100 * float(np.linalg.norm(mot.motor_mG_per_unit - f) / np.linalg.norm(f))
        rows.append(f"  seed {seed} compass {k}: {fit.status:3s} {fit.model:8s} offsets max err {err:4.1f} mG (target 5) "
                    f"{_verdict(err <= 5)} | motor {np.linalg.norm(f):.2f} mG/A err {rel:4.1f} % (target 10) "
                    f"{_verdict(rel <= 10)} | {1e3 * dt:4.0f} ms")
    bin_path = sim.write_bin(tmp / f"flight-{seed}.bin", "timeus_split")
    t0 = time.perf_counter()
    arr_b = extract_bin(bin_path)
    t_read = time.perf_counter() - t0
    fit = wmm_fit_compass(arr_b, 0, H)
    t_all = time.perf_counter() - t0
    truth0 = np.asarray(sim.truth["compasses"][0]["offsets_rot_mG"])
    ours = float(np.max(np.abs(fit.offsets_mG - truth0)))
    rows.append(f"  seed {seed} .bin compass 0 ({len(arr_b.mag[0][0])} MAG records): ours max err {ours:4.1f} mG, "
                f"{t_all:5.2f} s (read {t_read:.2f} s + fit {t_all - t_read:.2f} s)")
    if magfit_reduce is not None:
        mf = run_magfit(bin_path, 1, magfit_reduce)
        if "error" in mf:
            rows.append(f"  seed {seed} magfit_WMM: {mf['error']}")
        else:
            theirs = float(np.max(np.abs(-mf["ofs"] - truth0)))
            faster = mf["runtime_s"] / t_all
            rows.append(f"  seed {seed} magfit_WMM --elliptical --cmot --reduce {magfit_reduce}: max err {theirs:4.1f} mG, "
                        f"{mf['runtime_s']:6.1f} s  ->  ours {faster:5.0f}x faster {_verdict(faster > 1)}, "
                        f"accuracy {'at least as good' if ours <= theirs + 0.5 else 'worse'} {_verdict(ours <= theirs + 0.5)}")
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="one seed; magfit_WMM on every 10th record")
    ap.add_argument("--seeds", type=int, default=3)
    ap.add_argument("--no-magfit", action="store_true")
    a = ap.parse_args(argv)
    seeds = [1] if a.quick else list(range(1, a.seeds + 1))
    reduce = None if a.no_magfit else (10 if a.quick else 1)
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        print("1. onboard calibration window in a 1.5 Hz telemetry log vs the vehicle's MAG_CAL_REPORT")
        for s in seeds:
            print("\n".join(bench_windows(s, tmp)))
        print("2-4. in-flight WMM fit (no dance, 2 Hz telemetry; yaw from compass 0's EKF-like heading), "
              "motor field per ampere, and the same fit on the DataFlash log vs magfit_WMM")
        for s in seeds:
            print("\n".join(bench_inflight(s, tmp, reduce)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
