"""Pack an ArduSim (groundstation.sim.ardupilot) into MAVLink telemetry and DataFlash records.

Units per the MAVLink XML and ArduPilot's log definitions: RAW_IMU / SCALED_IMU2/3 acc mG (milli-g),
gyro mrad/s, mag mgauss; ATTITUDE rad; GPS_RAW_INT degE7, mm, cm/s, cdeg; SYS_STATUS mV, cA;
SENSOR_OFFSETS mag_ofs in mgauss (COMPASS_OFS of compass 0); DataFlash MAG mgauss, ATT degrees,
CURR volt cV / current cA (2014 layout), BAT volt V / current A.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from groundstation.io.mavlink import mavlink2 as _M
from groundstation.sim.ardupilot_flight import G_MPS2
from groundstation.sim.dataflash_writer import DataFlashWriter

__all__ = ["pack_telemetry", "write_dataflash", "BOOT_OFFSET_S", "param_table"]

BOOT_OFFSET_S = 15.0          # the autopilot booted this long before the log starts
GPS_EPOCH_UNIX = 315964800
GPS_LEAP_S = 18


def _i16(x) -> np.ndarray:
    return np.clip(np.rint(np.asarray(x, float)), -32768, 32767).astype(int)


def _stream(t: np.ndarray, rate_hz: float) -> np.ndarray:
    """Grid indices of a stream at rate_hz (nearest grid sample to each k/rate)."""
    dt = t[1] - t[0]
    want = np.arange(0.0, t[-1], 1.0 / rate_hz)
    return np.unique(np.clip(np.rint(want / dt).astype(int), 0, len(t) - 1))


def _imu(sim) -> tuple[np.ndarray, np.ndarray]:
    """Body specific force [mG] and body rates [mrad/s] on the grid."""
    fl = sim.flight
    dt = fl.t_s[1] - fl.t_s[0]
    C = fl.dcm()
    a_ned = np.gradient(fl.vel_ned_mps, dt, axis=0) - np.array([0.0, 0.0, G_MPS2])
    acc = np.einsum("nji,nj->ni", C, a_ned) / G_MPS2 * 1000.0
    rel = np.einsum("nji,njk->nik", C[:-1], C[1:])
    w = np.column_stack([rel[:, 2, 1] - rel[:, 1, 2], rel[:, 0, 2] - rel[:, 2, 0], rel[:, 1, 0] - rel[:, 0, 1]]) / (2 * dt)
    return acc, np.vstack([w, w[-1:]]) * 1000.0


def param_table(sim, after: bool) -> list[tuple[str, float]]:
    """Every compass parameter as the vehicle holds it before (after=False) or after the onboard calibration."""
    out: list[tuple[str, float]] = [("AHRS_EKF_TYPE", 3.0), ("AHRS_TRIM_X", 0.0), ("AHRS_TRIM_Y", 0.0),
                                    ("AHRS_TRIM_Z", 0.0), ("COMPASS_AUTODEC", 1.0), ("COMPASS_USE", 1.0)]
    motct = 0.0
    for rec in sim.compasses:
        k = rec.truth["instance"]
        n = "" if k == 0 else str(k + 1)
        i = -1 if after and sim.cal_applied_s is not None else 0
        c = rec.corrections
        out += [(f"COMPASS_OFS{n}_{a}", float(c.offsets_mG[i, j])) for j, a in enumerate("XYZ")]
        out += [(f"COMPASS_DIA{n}_{a}", float(c.diag[i, j])) for j, a in enumerate("XYZ")]
        out += [(f"COMPASS_ODI{n}_{a}", float(c.offdiag[i, j])) for j, a in enumerate("XYZ")]
        out += [(f"COMPASS_SCALE{n}", float(c.scale[i])), (f"COMPASS_ORIENT{n}", float(rec.spec.orient_param)),
                (f"COMPASS_EXTERN{n}" if k else "COMPASS_EXTERNAL", float(rec.spec.external))]
        out += [(f"COMPASS_MOT{n}_{a}", float(c.motor_per_unit[0, j])) for j, a in enumerate("XYZ")]
        motct = max(motct, float(c.motor_type[0]))
    out.append(("COMPASS_MOTCT", motct))
    return out


def _params_msgs(sim, t0: float, after: bool) -> list:
    table = param_table(sim, after)
    if after:   # ArduPilot broadcasts only what the calibration changed
        table = [(n, v) for n, v in table if n.startswith(("COMPASS_OFS", "COMPASS_DIA", "COMPASS_ODI", "COMPASS_SCALE"))]
    return [(t0 + 0.002 * k, _M.MAVLink_param_value_message(n.encode(), v, _M.MAV_PARAM_TYPE_REAL32, len(table), k))
            for k, (n, v) in enumerate(table)]


def _mag_cal_msgs(sim) -> list:
    if "dance" not in sim.flight.events:
        return []
    d0, d1 = sim.flight.events["dance"]
    # the ground station starts it: MAV_CMD_DO_START_MAG_CAL (mask 0 = all, autosave), sent by the GCS
    out = [(max(d0 - 0.5, 0.0), _M.MAVLink_command_long_message(1, 1, 42424, 0, 0, 0, 1, 0, 0, 0, 0))]
    for ts in np.arange(d0, d1, 1.0):
        pct = int(min(99, 100 * (ts - d0) / (d1 - d0)))
        for rec in sim.compasses:
            out.append((ts, _M.MAVLink_mag_cal_progress_message(rec.truth["instance"], 7, 3, 1, pct, [255] * 10, 0, 0, 0)))
    for rec in sim.compasses:
        r = rec.report
        if not r:
            continue
        out.append((d1 + 0.5, _M.MAVLink_mag_cal_report_message(
            rec.truth["instance"], 7, _M.MAG_CAL_SUCCESS, 1, r["fitness_mG"], *r["ofs_mG"], *r["diag"], *r["offdiag"],
            10.0, rec.spec.orient_param, rec.spec.orient_param, r["scale_factor"])))
    return out


def _imu_msgs(sim, acc, gyr) -> list:
    t = sim.flight.t_s
    out = []
    makers = (lambda i, m: _M.MAVLink_raw_imu_message(int((t[i] + BOOT_OFFSET_S) * 1e6), *_i16(acc[i]), *_i16(gyr[i]), *m),
              lambda i, m: _M.MAVLink_scaled_imu2_message(int((t[i] + BOOT_OFFSET_S) * 1e3), *_i16(acc[i]), *_i16(gyr[i]), *m),
              lambda i, m: _M.MAVLink_scaled_imu3_message(int((t[i] + BOOT_OFFSET_S) * 1e3), *_i16(acc[i]), *_i16(gyr[i]), *m))
    for i in _stream(t, sim.config.imu_rate_hz):
        for rec, make in zip(sim.compasses, makers):
            mag = _i16(rec.corrected_mG[i]) if rec.present[i] else (0, 0, 0)
            out.append((t[i], make(i, tuple(int(v) for v in mag))))
    return out


def _nav_msgs(sim, gyr) -> list:
    from groundstation.sim.ardupilot import positions_lla
    fl, cfg = sim.flight, sim.config
    t = fl.t_s
    boot = lambda i: int((t[i] + BOOT_OFFSET_S) * 1e3)
    out = []
    for i in _stream(t, cfg.attitude_rate_hz):
        out.append((t[i], _M.MAVLink_attitude_message(boot(i), *map(float, sim.attitude[i]), *map(float, gyr[i] / 1000))))
    lat, lon, alt = positions_lla(sim)
    v = fl.vel_ned_mps
    for i in _stream(t, cfg.gps_rate_hz):
        spd = math.hypot(v[i, 0], v[i, 1])
        cog = int(round(math.degrees(math.atan2(v[i, 1], v[i, 0])) % 360 * 100)) % 36000
        out.append((t[i], _M.MAVLink_gps_raw_int_message(int((t[i] + BOOT_OFFSET_S) * 1e6), 3, int(round(lat[i] * 1e7)),
                                                         int(round(lon[i] * 1e7)), int(round(alt[i] * 1000)), 90, 150,
                                                         int(round(spd * 100)), cog, 12)))
        out.append((t[i], _M.MAVLink_global_position_int_message(
            boot(i), int(round(lat[i] * 1e7)), int(round(lon[i] * 1e7)), int(round(alt[i] * 1000)),
            int(round(-fl.pos_ned_m[i, 2] * 1000)), *(int(round(x * 100)) for x in v[i]),
            int(round(math.degrees(sim.attitude[i, 2]) % 360 * 100)) % 36000)))
    for i in _stream(t, cfg.status_rate_hz):
        cur = float(fl.current_A[i])
        out.append((t[i], _M.MAVLink_sys_status_message(0, 0, 0, 400, int(16000 - 25 * cur), int(round(cur * 100)),
                                                        80, 0, 0, 0, 0, 0, 0)))
        out.append((t[i], _M.MAVLink_vfr_hud_message(0.0, float(math.hypot(v[i, 0], v[i, 1])),
                                                     int(math.degrees(sim.attitude[i, 2]) % 360),
                                                     int(round(fl.throttle[i] * 100)), float(alt[i]), float(-v[i, 2]))))
    return out


def _housekeeping_msgs(sim) -> list:
    fl = sim.flight
    t = fl.t_s
    out = []
    for i in _stream(t, 1.0):
        mode = _M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (_M.MAV_MODE_FLAG_SAFETY_ARMED if fl.armed[i] else 0)
        out.append((t[i], _M.MAVLink_heartbeat_message(_M.MAV_TYPE_QUADROTOR, _M.MAV_AUTOPILOT_ARDUPILOTMEGA, mode,
                                                       3 if fl.armed[i] else 0, _M.MAV_STATE_ACTIVE, 3)))
        out.append((t[i] + 1e-3, _M.MAVLink_system_time_message(int((sim.config.start_unix_s + t[i]) * 1e6),
                                                                int((t[i] + BOOT_OFFSET_S) * 1e3))))
    c0 = sim.compasses[0].corrections
    for i in _stream(t, 0.5):
        out.append((t[i] + 2e-3, _M.MAVLink_sensor_offsets_message(*(int(round(v)) for v in c0.offsets_mG[i]),
                                                                    math.radians(sim.declination_deg), 0, 0,
                                                                    0.0, 0.0, 0.0, 0.0, 0.0, 0.0)))
    return out


def pack_telemetry(sim) -> list:
    """Time-ordered [(unix_s arrival, message)] of the whole flight, with link latency and drops."""
    rng = np.random.default_rng([sim.config.seed, 99])
    acc, gyr = _imu(sim)
    timed = _housekeeping_msgs(sim) + _params_msgs(sim, 0.05, False) + _mag_cal_msgs(sim)
    if sim.cal_applied_s is not None:
        timed += _params_msgs(sim, sim.cal_applied_s, True)
        timed.append((sim.cal_applied_s + 0.5, _M.MAVLink_statustext_message(6, b"Mag calibration successful")))
    lossy = _imu_msgs(sim, acc, gyr) + _nav_msgs(sim, gyr)
    keep = rng.random(len(lossy)) >= sim.config.drop_fraction
    timed += [m for m, k in zip(lossy, keep) if k]
    start = sim.config.start_unix_s
    lat = rng.uniform(0.02, 0.15, len(timed))
    out = [(start + ts + (0.0 if k == 0 else lat[k]), msg) for k, (ts, msg) in enumerate(timed)]
    out.sort(key=lambda x: x[0])
    return out


def _gps_week_ms(unix_s: float) -> tuple[int, int]:
    g = unix_s - GPS_EPOCH_UNIX + GPS_LEAP_S
    return int(g // 604800), int(round((g % 604800) * 1000))


def _df_params(w: DataFlashWriter, sim, t_us: int, after: bool) -> None:
    table = param_table(sim, after)
    for name, v in table:
        if w.layout == "timems":
            w.write("PARM", name, v)
        elif w.layout == "timeus_split":
            w.write("PARM", t_us, name, v)
        else:
            w.write("PARM", t_us, name, v, 0.0)


def _df_mag(w: DataFlashWriter, k: int, rec, i: int, t_us: int) -> None:
    m, o, mo = rec.corrected_mG[i], rec.corrections.offsets_mG[i], rec.motor_offset_mG[i]
    vals = [*_i16(m), *_i16(o), *_i16(mo)]
    if w.layout == "timems":
        w.write(("MAG", "MAG2", "MAG3")[k], t_us // 1000, *vals)
    elif w.layout == "timeus_split":
        w.write(("MAG", "MAG2", "MAG3")[k], t_us, *vals, 1, t_us)
    else:
        w.write("MAG", t_us, k, *vals, 1, t_us)


def _df_nav(w: DataFlashWriter, sim, i: int, t_us: int, lla, gps_row: bool) -> None:
    fl = sim.flight
    r, p, y = (math.degrees(a) for a in sim.attitude[i])
    att = (r, r, p, p, y % 360, y % 360, 0, 0)
    cur, thr = float(fl.current_A[i]), float(fl.throttle[i])
    alt_rel = -fl.pos_ned_m[i, 2]
    if w.layout == "timems":
        w.write("ATT", t_us // 1000, *att)
        w.write("CURR", t_us // 1000, thr * 1000, 0, 1600 - 2.5 * cur, cur * 100, 5000, 0.0)
        w.write("CTUN", t_us // 1000, thr * 1000, 0, thr * 1000, alt_rel, alt_rel, alt_rel, 0, 0, 0, 0)
    else:
        w.write("ATT", t_us, *att, *(() if w.layout == "timeus_split" else (3,)))
        bat = (16.0 - 0.025 * cur, 16.0, cur, 0.0, 0.0, 25.0)
        w.write("BAT", t_us, *bat) if w.layout == "timeus_split" else w.write("BAT", t_us, 0, *bat, 0.0, 80, 1, 100)
        w.write("CTUN", t_us, thr, 0, thr, thr, alt_rel, alt_rel, alt_rel, 0, alt_rel, alt_rel, 0, 0)
    if not gps_row:
        return
    lat, lon, alt = lla
    v = fl.vel_ned_mps[i]
    spd, crs = math.hypot(v[0], v[1]), math.degrees(math.atan2(v[1], v[0])) % 360
    week, ms = _gps_week_ms(sim.config.start_unix_s + fl.t_s[i])
    if w.layout == "timems":
        w.write("GPS", 3, ms, week, 12, 0.9, lat[i], lon[i], alt_rel, alt[i], spd, crs, v[2], t_us // 1000)
    elif w.layout == "timeus_split":
        w.write("GPS", t_us, 3, ms, week, 12, 0.9, lat[i], lon[i], alt[i], spd, crs, v[2], 1)
    else:
        w.write("GPS", t_us, 0, 3, ms, week, 12, 0.9, lat[i], lon[i], alt[i], spd, crs, v[2], 0, 1)


def write_dataflash(sim, path: Path, layout: str) -> Path:
    """The full-rate DataFlash log of the flight (every grid sample; GPS at 5 Hz)."""
    from groundstation.sim.ardupilot import positions_lla
    w = DataFlashWriter(layout)
    fl = sim.flight
    t = fl.t_s
    lla = positions_lla(sim)
    gps_every = max(1, int(round(sim.config.plan.log_rate_hz / 5.0)))
    _df_params(w, sim, int(BOOT_OFFSET_S * 1e6), False)
    applied = False
    for i in range(len(t)):
        t_us = int(round((t[i] + BOOT_OFFSET_S) * 1e6))
        if sim.cal_applied_s is not None and not applied and t[i] >= sim.cal_applied_s:
            _df_params(w, sim, t_us, True)
            applied = True
        _df_nav(w, sim, i, t_us, lla, i % gps_every == 0)
        for k, rec in enumerate(sim.compasses):
            if rec.present[i]:
                _df_mag(w, k, rec, i, t_us)
    return w.save(path)
