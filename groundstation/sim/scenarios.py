"""Simulated flights written as real MAVLink `.tlog` files (issue 5).

``simulate(scenario, seed=0, **overrides) -> Simulation``: runs the closed-loop physics of
``groundstation.sim.flight_sim`` and packs the result into pymavlink message objects exactly as an
ArduPilot multirotor would send them (units per the MAVLink XML: SCALED_IMU acc mG, gyro mrad/s,
mag mgauss; GPS_RAW_INT degE7 / mm / cm/s / cdeg; ...).  ``Simulation.write(path)`` writes the
tlog and a truth JSON beside it (``<stem>.truth.json``).

    python -m groundstation.sim.scenarios mission-slow --seed 3 --out /tmp/slow.tlog
    python -m groundstation.sim.scenarios --make-recordings        # regenerate recordings/
"""
from __future__ import annotations

import argparse
import calendar
import json
import math
from dataclasses import asdict, dataclass, field, fields, replace
from pathlib import Path

import numpy as np

from . import flight_sim as fs
from estimators.geomag import decimal_year_from_unix, earth_field

from groundstation.io.mavlink import TlogWriter, mavlink2
from groundstation.io.params import apply_ardupilot, ardupilot_params_from_calibration
from groundstation.paths import RECORDINGS_DIR

__all__ = ["SCENARIOS", "Simulation", "simulate", "make_recordings", "truth_path"]

SCENARIOS = ("calibration", "static-headings", "mission-clean", "mission-slow", "mission-fast",
             "mission-step", "mission-bump", "mission-motor", "mission-payload", "mission-anomaly", "gps-outage",
             "demo")

ORIGIN = (30.26, 120.12, 20.0)              # near Hangzhou: lat, lon, ground alt AMSL [m]
START_UNIX_S = float(calendar.timegm((2026, 6, 15, 2, 0, 0)))   # 2026-06-15 02:00 UTC
BOOT_OFFSET_S = 12.0                        # the autopilot booted this long before the log starts

_M = mavlink2
PAYLOAD_LEAD_MG_PER_A = 6.0                 # a power lead past the compass: 72 mG at 12 A
ANOMALY_MOMENT_AM2 = 4.0e5                  # a large steel mass: ~100 mG at 20 m (B ≈ 2m/r³ above it)


def truth_path(tlog_path: str | Path) -> Path:
    p = Path(tlog_path)
    return p.with_name(p.stem + ".truth.json")


@dataclass
class Simulation:
    """A simulated log: time-ordered (unix_s, message) pairs and the truth behind them."""
    scenario: str
    seed: int
    messages: list = field(default_factory=list)
    truth: dict = field(default_factory=dict)
    result: fs.SimResult | None = None      # the raw arrays (last part for concatenations)

    @property
    def duration_s(self) -> float:
        return self.messages[-1][0] - self.messages[0][0] if self.messages else 0.0

    def write(self, path: str | Path) -> Path:
        """Write the .tlog (overwrites) and the truth JSON beside it; returns the tlog path."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        if path.exists():
            path.unlink()
        with TlogWriter(path) as w:
            for unix_s, msg in self.messages:
                w.write_message(msg, unix_s)
        truth_path(path).write_text(json.dumps(self.truth, indent=1))
        return path


# ------------------------------------------------------------------------------ scenarios
def _hardware(seed: int) -> tuple[fs.MagModel, np.ndarray]:
    """The vehicle's sensor errors: the same for every scenario of one seed (so a calibration
    flight of seed s calibrates the missions of seed s)."""
    rng = np.random.default_rng([seed, 7])
    mag = fs.MagModel.random(rng)
    mag.motor_mG_per_A = rng.uniform(0.6, 1.4) * np.array([1.2, 0.8, 2.0]) * rng.choice([-1, 1], 3)
    bias = rng.uniform(-0.05, 0.05, 3) * math.pi / 180
    return mag, bias


def _config(scenario: str, seed: int, overrides: dict) -> fs.SimConfig:
    mag, bias = _hardware(seed)
    rng = np.random.default_rng([seed, 11])
    lat, lon, ground = ORIGIN
    base = dict(seed=seed, origin_lat_deg=lat, origin_lon_deg=lon, ground_alt_m=ground, mag=mag,
                gyro_bias_rad_s=bias)
    if scenario == "calibration":
        base.update(kind="dance", duration_s=80.0, flight_alt_m=1.0)
    elif scenario == "static-headings":
        base.update(kind="headings", flight_alt_m=1.0)
    elif scenario.startswith("mission") or scenario == "gps-outage":
        base.update(kind="mission", duration_s=300.0,
                    mean_wind_mps=tuple(rng.uniform(-2.0, 2.0, 2)))
        onset = 60.0 + rng.uniform(-5.0, 5.0)
        if scenario == "mission-slow":
            base.update(duration_s=150.0, interference=fs.Interference(
                "ramp", onset, rate_mG_s=12.5, rise_s=20.0, hold_s=10.0))
        elif scenario == "mission-fast":
            base.update(duration_s=150.0, interference=fs.Interference(
                "ramp", onset, rate_mG_s=60.0, rise_s=5.0, hold_s=10.0))
        elif scenario == "mission-step":
            base.update(duration_s=150.0, interference=fs.Interference(
                "step", onset, amplitude_mG=150.0, duration_s=20.0))
        elif scenario == "mission-bump":      # seed 002 sec. 4: slowly rising then falling, horizontal
            base.update(duration_s=200.0, interference=fs.Interference(
                "bump", onset, axis=(0.7071, 0.7071, 0.0), amplitude_mG=250.0, duration_s=60.0))
        elif scenario == "mission-motor":     # clean, with a payload switching 10 A every 10 s
            base.update(payload=fs.PayloadLoad(10.0, 20.0, from_s=fs.SimConfig.hover_s))
        elif scenario == "mission-payload":   # from the onset, a payload on its own lead past the compass
            lead = rng.normal(size=3)
            lead_mG_per_A = tuple(float(v) for v in PAYLOAD_LEAD_MG_PER_A * lead / np.linalg.norm(lead))
            base.update(duration_s=150.0, payload=fs.PayloadLoad(12.0, 16.0, from_s=onset, mG_per_A=lead_mG_per_A))
        elif scenario == "mission-anomaly":   # a magnetised mass on the ground beside the middle of the leg
            base.update(duration_s=200.0, anomaly=fs.GroundAnomaly(pos_ned_m=_beside_mid_leg(base, rng)))
        elif scenario == "gps-outage":
            base.update(gps_outage=(100.0, 180.0), gyro_bias_rad_s=np.radians([0.5, 0.5, 0.5]))
        elif scenario != "mission-clean":
            raise ValueError(f"unknown scenario {scenario!r}; choose from {', '.join(SCENARIOS)}")
    else:
        raise ValueError(f"unknown scenario {scenario!r}; choose from {', '.join(SCENARIOS)}")
    names = {f.name for f in fields(fs.SimConfig)}
    interf = overrides.pop("interference", None)
    bad = set(overrides) - names
    if bad:
        raise TypeError(f"unknown simulate() overrides: {sorted(bad)}")
    base.update(overrides)
    cfg = fs.SimConfig(**base)
    if isinstance(interf, dict):
        cfg.interference = replace(cfg.interference, **interf)
    elif interf is not None:
        cfg.interference = interf
    year = decimal_year_from_unix(START_UNIX_S)
    ef = earth_field(cfg.origin_lat_deg, cfg.origin_lon_deg, cfg.ground_alt_m + cfg.flight_alt_m, year)
    cfg.field_ned_mG = np.array(ef.field_ned_mG)
    cfg.declination_deg = ef.declination_deg
    if cfg.anomaly is not None and not any(cfg.anomaly.moment_ned_Am2):    # induced: along the Earth field
        moment = ANOMALY_MOMENT_AM2 * cfg.field_ned_mG / np.linalg.norm(cfg.field_ned_mG)
        cfg.anomaly = replace(cfg.anomaly, moment_ned_Am2=tuple(float(v) for v in moment))
    return cfg


def _beside_mid_leg(base: dict, rng: np.random.Generator) -> tuple[float, float, float]:
    """On the ground under the middle of the mission leg, a few metres to one side [m, NED]."""
    brg = math.radians(base.get("leg_bearing_deg", fs.SimConfig.leg_bearing_deg))
    along, side = 0.5 * fs.SimConfig.leg_length_m, rng.uniform(-6.0, 6.0)
    return (along * math.cos(brg) - side * math.sin(brg), along * math.sin(brg) + side * math.cos(brg), 0.0)


def simulate(scenario: str, seed: int = 0, **overrides) -> Simulation:
    """Run one scenario (see ``SCENARIOS``); ``overrides`` are ``SimConfig`` fields
    (e.g. duration_s=120, rtk=False, leg_bearing_deg=90, interference=dict(rate_mG_s=30)).

    "demo" = the calibration dance followed (after a short gap) by mission-slow, or by the mission
    scenario given as ``mission=`` (e.g. simulate("demo", 1, mission="mission-anomaly")).
    ``onboard_calibration=True``: the vehicle was calibrated on board with its true hard and soft
    iron (the symmetric part ArduPilot's OFS/DIA/ODI hold), streams the corrected field and reports
    those parameters; by default it streams the raw sensor with an identity (never run) calibration.
    """
    overrides = dict(overrides)
    onboard = overrides.pop("onboard_calibration", False)
    if scenario == "demo":
        cal = simulate("calibration", seed, onboard_calibration=onboard)
        mis = simulate(overrides.pop("mission", "mission-slow"), seed, onboard_calibration=onboard, **overrides)
        return _concat("demo", seed, [cal, mis], gap_s=5.0)
    cfg = _config(scenario, seed, overrides)
    res = fs.run(cfg)
    truth = _truth(scenario, cfg, res)
    params = _params(cfg if onboard else None)
    truth["onboard_calibration"] = {k: v for k, v in params if k.startswith("COMPASS_")} if onboard else None
    msgs = _pack(cfg, res, START_UNIX_S, BOOT_OFFSET_S, with_mission=cfg.kind == "mission", params=params)
    return Simulation(scenario, seed, msgs, truth, res)


def _concat(name: str, seed: int, parts: list[Simulation], gap_s: float) -> Simulation:
    msgs: list = []
    truths = []
    shift = 0.0
    for k, p in enumerate(parts):
        if k:
            shift = msgs[-1][0] + gap_s - p.messages[0][0]
        offset = shift
        # keep the boot clock monotonic: rebuild the part's messages with shifted times
        for unix_s, m in p.messages:
            if hasattr(m, "time_boot_ms"):
                m.time_boot_ms = int(m.time_boot_ms + offset * 1000)
            if hasattr(m, "time_usec"):
                m.time_usec = int(m.time_usec + offset * 1e6)
            if hasattr(m, "time_unix_usec"):
                m.time_unix_usec = int(m.time_unix_usec + offset * 1e6)
            msgs.append((unix_s + offset, m))
        t = dict(p.truth)
        t["log_offset_s"] = round(p.messages[0][0] + offset - parts[0].messages[0][0], 3)
        truths.append(t)
    truth = {"scenario": name, "seed": seed, "parts": truths, "start_unix_s": truths[0]["start_unix_s"]}
    # interference times on the combined log's time base (for benchmarks / tests)
    for t in truths:
        if t.get("interference", {}).get("onset_s") is not None:
            truth["interference_onset_s"] = round(t["interference"]["onset_s"] + t["log_offset_s"], 3)
    return Simulation(name, seed, msgs, truth, parts[-1].result)


def _truth(scenario: str, cfg: fs.SimConfig, res: fs.SimResult) -> dict:
    intf = cfg.interference
    lat0, lon0 = cfg.origin_lat_deg, cfg.origin_lon_deg
    t = {
        "scenario": scenario, "seed": cfg.seed, "start_unix_s": START_UNIX_S,
        "duration_s": float(res.t_s[-1]),
        "origin": {"lat_deg": lat0, "lon_deg": lon0, "ground_alt_m": cfg.ground_alt_m},
        "earth_field": {"declination_deg": cfg.declination_deg,
                        "field_ned_mG": [float(v) for v in cfg.field_ned_mG],
                        "field_strength_mG": float(np.linalg.norm(cfg.field_ned_mG)),
                        "inclination_deg": float(np.degrees(np.arctan2(
                            cfg.field_ned_mG[2], np.hypot(cfg.field_ned_mG[0], cfg.field_ned_mG[1]))))},
        "mag": {"model": "m_raw = A (m_body + motor_mG_per_A * I) + offsets + interference + noise",
                "A": cfg.mag.matrix.tolist(), "offsets_mG": cfg.mag.offsets_mG.tolist(),
                "calibration_matrix": np.linalg.inv(cfg.mag.matrix).tolist(),
                "misalignment_deg": np.asarray(cfg.mag.misalignment_deg).tolist(),
                "noise_mG": cfg.mag.noise_mG,
                "motor_mG_per_A": np.asarray(cfg.mag.motor_mG_per_A).tolist(),
                "current_range_A": [float(np.min(res.motor_current_A)), float(np.max(res.motor_current_A))],
                "payload_current_A": cfg.payload.current_A if cfg.payload else 0.0},
        "payload": asdict(cfg.payload) if cfg.payload else None,
        "anomaly": _anomaly_truth(cfg, res),
        "gyro_bias_rad_s": np.asarray(cfg.gyro_bias_rad_s).tolist(),
        "rtk": bool(cfg.rtk), "fix_type": 6 if cfg.rtk else 3,
        "gps_outage_s": list(cfg.gps_outage) if cfg.gps_outage else None,
        "interference": {"kind": intf.kind, "axis_sensor": list(intf.axis),
                         "onset_s": intf.onset_s if intf.kind != "none" else None,
                         "end_s": intf.end_s, "rate_mG_s": intf.rate_mG_s,
                         "rise_s": intf.rise_s, "hold_s": intf.hold_s, "amplitude_mG": intf.amplitude_mG},
        "events": res.events,
    }
    if res.mission_ned_m is not None:
        lat, lon = fs.lla_from_ned(res.mission_ned_m[:, 0], res.mission_ned_m[:, 1], lat0, lon0)
        alt = cfg.ground_alt_m + cfg.flight_alt_m
        t["mission"] = {"A": [float(lat[0]), float(lon[0]), alt], "B": [float(lat[1]), float(lon[1]), alt]}
        t["leg_bearing_deg"] = cfg.leg_bearing_deg
        t["wind_mean_ne_mps"] = list(cfg.mean_wind_mps)
        d = res.cross_track_m
        onset = intf.onset_s if intf.kind != "none" else res.t_s[-1] + 1
        pre = (res.t_s > cfg.hover_s) & (res.t_s < onset)
        t["max_cross_track_m"] = float(np.nanmax(d))
        t["max_cross_track_clean_m"] = float(np.nanmax(d[pre])) if pre.any() else None
        over = np.nonzero((res.t_s >= onset) & (d > 1.0))[0]
        t["first_cross_track_over_1m_s"] = float(res.t_s[over[0]]) if len(over) else None
        dy = np.degrees(np.angle(np.exp(1j * (res.est_yaw_rad - res.yaw_rad))))
        t["max_autopilot_yaw_error_deg"] = float(np.max(np.abs(dy)))
    return t


def _anomaly_truth(cfg: fs.SimConfig, res: fs.SimResult) -> dict | None:
    """Where the ground anomaly is and when the vehicle passed nearest to it (within 30 m)."""
    a = cfg.anomaly
    if a is None:
        return None
    lat, lon = fs.lla_from_ned(np.array([a.pos_ned_m[0]]), np.array([a.pos_ned_m[1]]),
                               cfg.origin_lat_deg, cfg.origin_lon_deg)
    dist = np.hypot(res.pos_ned_m[:, 0] - a.pos_ned_m[0], res.pos_ned_m[:, 1] - a.pos_ned_m[1])
    near = np.r_[False, dist < 30.0, False].astype(int)
    starts, ends = np.flatnonzero(np.diff(near) == 1), np.flatnonzero(np.diff(near) == -1)
    passes = [float(res.t_s[i + int(np.argmin(dist[i:j]))]) for i, j in zip(starts, ends)]
    return {"lat_deg": float(lat[0]), "lon_deg": float(lon[0]), "pos_ned_m": list(a.pos_ned_m),
            "moment_ned_Am2": list(a.moment_ned_Am2), "passes_s": [round(p, 2) for p in passes],
            "closest_m": [round(float(np.min(dist[i:j])), 2) for i, j in zip(starts, ends)]}


# ------------------------------------------------------------------------------ packing
def _i(x) -> np.ndarray:
    return np.rint(np.asarray(x, dtype=float)).astype(np.int64)


def _params(cfg: fs.SimConfig | None = None) -> list[tuple[str, float]]:
    """The vehicle's compass parameters: identity (never calibrated: SCALED_IMU carries the raw
    sensor field), or with ``cfg`` the onboard calibration of its true hard and soft iron."""
    p = [("COMPASS_USE", 1.0), ("COMPASS_ORIENT", 0.0), ("COMPASS_EXTERNAL", 1.0)]
    if cfg is not None:
        cal = ardupilot_params_from_calibration(cfg.mag.offsets_mG, np.linalg.inv(cfg.mag.matrix))
        return p + sorted(cal.items()) + [("COMPASS_MOTCT", 0.0)]
    p += [(f"COMPASS_OFS_{a}", 0.0) for a in "XYZ"]
    p += [(f"COMPASS_DIA_{a}", 1.0) for a in "XYZ"]
    p += [(f"COMPASS_ODI_{a}", 0.0) for a in "XYZ"]
    p += [("COMPASS_SCALE", 1.0), ("COMPASS_MOTCT", 0.0)]
    return p


def _pack(cfg: fs.SimConfig, r: fs.SimResult, start_unix: float, boot_offset: float,
          with_mission: bool, params: list[tuple[str, float]] | None = None) -> list:
    """SimResult -> time-ordered [(unix_s, MAVLink message)]; the field streamed is ArduPilot's
    correction with ``params`` (default identity) applied to the raw sensor."""
    t = r.t_s
    n = len(t)
    boot_ms = _i((t + boot_offset) * 1000)
    acc = _i(r.accel_mps2 / fs.G * 1000.0)
    gyr = _i(r.gyro_rad_s * 1000.0)
    params = params or _params()
    mag = _i(apply_ardupilot(r.mag_raw_mG, dict(params)))
    np.clip(acc, -32768, 32767, out=acc)
    np.clip(gyr, -32768, 32767, out=gyr)
    np.clip(mag, -32768, 32767, out=mag)
    est_rate = r.gyro_rad_s - cfg.gyro_bias_rad_s
    out: list = []
    # 1 Hz heartbeat and system time, parameters and the mission at the start
    base_mode = _M.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | _M.MAV_MODE_FLAG_STABILIZE_ENABLED | (
        _M.MAV_MODE_FLAG_SAFETY_ARMED if cfg.kind == "mission" else 0)
    custom = 3 if cfg.kind == "mission" else 0   # AUTO / STABILIZE
    step1 = int(round(cfg.rate_hz))
    for i in range(0, n, step1):
        u = start_unix + t[i]
        out.append((u, _M.MAVLink_heartbeat_message(_M.MAV_TYPE_QUADROTOR, _M.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                                    base_mode, custom, _M.MAV_STATE_ACTIVE, 3)))
        out.append((u + 1e-4, _M.MAVLink_system_time_message(int(round(u * 1e6)), int(boot_ms[i]))))
    for k, (name, val) in enumerate(params):
        out.append((start_unix + 0.01 + k * 1e-3, _M.MAVLink_param_value_message(
            name.encode(), float(val), _M.MAV_PARAM_TYPE_REAL32, len(params), k)))
    lat0, lon0 = cfg.origin_lat_deg, cfg.origin_lon_deg
    alt_flight = cfg.ground_alt_m + cfg.flight_alt_m
    if with_mission and r.mission_ned_m is not None:
        lat, lon = fs.lla_from_ned(r.mission_ned_m[:, 0], r.mission_ned_m[:, 1], lat0, lon0)
        items = [(lat[0], lon[0], cfg.ground_alt_m), (lat[0], lon[0], alt_flight), (lat[1], lon[1], alt_flight)]
        u = start_unix + 0.05
        out.append((u, _M.MAVLink_mission_count_message(255, 190, len(items), 0)))
        for seq, (la, lo, al) in enumerate(items):   # seq 0 = home (ArduPilot convention)
            out.append((u + 1e-3 * (seq + 1), _M.MAVLink_mission_item_int_message(
                255, 190, seq, _M.MAV_FRAME_GLOBAL_INT, _M.MAV_CMD_NAV_WAYPOINT, int(seq == 1), 1,
                0.0, 0.0, 0.0, float("nan"), int(round(la * 1e7)), int(round(lo * 1e7)), float(al), 0)))
    # 50 Hz: SCALED_IMU + ATTITUDE
    yaw_est = np.asarray(r.est_yaw_rad)
    for i in range(n):
        u = start_unix + t[i]
        out.append((u, _M.MAVLink_scaled_imu_message(
            int(boot_ms[i]), int(acc[i, 0]), int(acc[i, 1]), int(acc[i, 2]), int(gyr[i, 0]), int(gyr[i, 1]),
            int(gyr[i, 2]), int(mag[i, 0]), int(mag[i, 1]), int(mag[i, 2]), 3500)))
        out.append((u + 2e-4, _M.MAVLink_attitude_message(
            int(boot_ms[i]), float(r.est_roll_rad[i]), float(r.est_pitch_rad[i]), float(yaw_est[i]),
            float(est_rate[i, 0]), float(est_rate[i, 1]), float(est_rate[i, 2]))))
    # 10 Hz SYS_STATUS: battery voltage and the motor current (cA), whose field the compass sees
    for i in range(0, n, max(1, int(round(cfg.rate_hz / 10.0)))):
        out.append((start_unix + t[i] + 3e-4, _M.MAVLink_sys_status_message(
            0, 0, 0, 300, 15200, int(round(r.motor_current_A[i] * 100.0)), 70, 0, 0, 0, 0, 0, 0)))
    out += _gps_messages(cfg, r, start_unix, boot_offset, boot_ms)
    out.sort(key=lambda x: x[0])
    return out


def _gps_messages(cfg: fs.SimConfig, r: fs.SimResult, start_unix: float, boot_offset: float,
                  boot_ms: np.ndarray) -> list:
    """GPS rows as GPS_RAW_INT (the receiver) + GLOBAL_POSITION_INT (the autopilot's estimate)."""
    t = r.t_s
    yaw_est = np.asarray(r.est_yaw_rad)
    lat0, lon0 = cfg.origin_lat_deg, cfg.origin_lon_deg
    out: list = []
    gi = r.gps_idx
    glat, glon = fs.lla_from_ned(r.gps_pos_ned_m[:, 0], r.gps_pos_ned_m[:, 1], lat0, lon0)
    galt = cfg.ground_alt_m - r.gps_pos_ned_m[:, 2]
    gv = r.gps_vel_ned_mps
    speed = np.hypot(gv[:, 0], gv[:, 1])
    cog = np.degrees(np.arctan2(gv[:, 1], gv[:, 0])) % 360.0
    elat, elon = fs.lla_from_ned(r.est_pos_ned_m[gi, 0], r.est_pos_ned_m[gi, 1], lat0, lon0)
    ev = r.est_vel_ned_mps[gi]
    hdg = (np.degrees(yaw_est[gi]) % 360.0) * 100
    for k, i in enumerate(gi):
        u = start_unix + t[i] + 5e-4
        fix = int(r.gps_fix_type[k])
        if fix >= 2:
            eph = 2 if fix >= 5 else 120
            msg = _M.MAVLink_gps_raw_int_message(
                int((t[i] + boot_offset) * 1e6), fix, int(round(glat[k] * 1e7)), int(round(glon[k] * 1e7)),
                int(round(galt[k] * 1000)), eph, eph * 2, int(round(speed[k] * 100)),
                int(round(cog[k] * 100)) % 36000, 22 if fix >= 5 else 12)
        else:
            msg = _M.MAVLink_gps_raw_int_message(int((t[i] + boot_offset) * 1e6), fix, 0, 0, 0,
                                                 65535, 65535, 0, 65535, 3)
        out.append((u, msg))
        out.append((u + 1e-4, _M.MAVLink_global_position_int_message(
            int(boot_ms[i]), int(round(elat[k] * 1e7)), int(round(elon[k] * 1e7)),
            int(round((cfg.ground_alt_m - r.est_pos_ned_m[i, 2]) * 1000)),
            int(round(-r.est_pos_ned_m[i, 2] * 1000)), int(round(ev[k, 0] * 100)), int(round(ev[k, 1] * 100)),
            int(round(ev[k, 2] * 100)), int(round(hdg[k])) % 36000)))
    return out


# ------------------------------------------------------------------------------ recordings
RECORDINGS = {"demo.tlog": ("demo", 1), "mission-fast.tlog": ("mission-fast", 2),
              "mission-clean.tlog": ("mission-clean", 3)}


def make_recordings(directory: str | Path = RECORDINGS_DIR) -> list[Path]:
    """Regenerate the bundled logs in recordings/ (deterministic)."""
    directory = Path(directory)
    paths = []
    for name, (scenario, seed) in RECORDINGS.items():
        over = {"duration_s": 150.0} if scenario == "mission-clean" else {}
        paths.append(simulate(scenario, seed, **over).write(directory / name))
    return paths


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m groundstation.sim.scenarios", description=__doc__.split("\n")[0])
    ap.add_argument("scenario", nargs="?", choices=SCENARIOS)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", help="output .tlog (default <scenario>-<seed>.tlog)")
    ap.add_argument("--duration", type=float, help="override duration_s (not for calibration/demo)")
    ap.add_argument("--no-rtk", action="store_true", help="plain 3-D fix GPS instead of RTK")
    ap.add_argument("--make-recordings", action="store_true", help="regenerate recordings/")
    a = ap.parse_args(argv)
    if a.make_recordings:
        for p in make_recordings():
            print(f"wrote {p} ({p.stat().st_size / 1e6:.2f} MB)")
        return 0
    if not a.scenario:
        ap.error("give a scenario or --make-recordings")
    over = {}
    if a.duration:
        over["duration_s"] = a.duration
    if a.no_rtk:
        over["rtk"] = False
    sim = simulate(a.scenario, a.seed, **over)
    out = a.out or f"{a.scenario}-{a.seed}.tlog"
    p = sim.write(out)
    print(f"wrote {p} and {truth_path(p)}: {len(sim.messages)} messages, {sim.duration_s:.1f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
