"""A population of simulated flights drawn from wide priors, for a detection benchmark nobody
tuned for (issue 30).

``draw_flight(index, seed, kind)`` draws one flight's settings (``FlightDraw``) from the priors
below with a generator seeded by (seed, index, kind), so a run is reproducible and every detector
variant sees the same flights; ``build_flight(draw)`` simulates it (``groundstation.sim.
scenarios``' closed loop and MAVLink packing) and returns the time-ordered messages and the truth.

Priors (uniform unless said; every flight is an ArduPilot multirotor calibrated on board):
* site: latitude/longitude drawn until the WMM inclination is within −60°..78°;
* motor field |f| 0–10 mG/A in a random body direction, the autopilot compensating 50–100 % of
  it (COMPASS_MOT, so the streamed field keeps (1 − c)·f·I) and its own heading filter the same;
* IMU (and compass) telemetry 1–50 Hz (one of 1, 2, 4, 5, 10, 16.7, 25, 50) as RAW_IMU,
  SCALED_IMU or HIGHRES_IMU; ATTITUDE at its own rate (2–50 Hz); battery current at 1–10 Hz
  with a current-sensor lag of 0–0.8 s;
* the autopilot's attitude: good (its GPS-aided estimate), drifting open-loop through a GPS
  outage (yaw 0.1–0.6 °/s, roll/pitch a random walk of a few degrees), or a yaw that follows its
  compass quickly (heading filter gain 2/s, so it turns with any disturbance);
* wind 0–8 m/s mean, gusts σ 0.1–1.5 m/s; route stop-and-go (40–120 m legs at 3–8 m/s) or survey
  (200–600 m legs at 5–12 m/s, sometimes with the nose sweeping); gyro bias up to 0.5 °/s per axis;
* GPS outages (a third of the flights, 20–120 s), telemetry gaps (a third, 1–3 gaps of 0.5–5 s,
  every message lost);
* a disturbance of the chosen kind at a random time after the first 45 s: fast ramp (40–100 mG/s
  for 3–8 s), slow ramp (10–25 mG/s for 15–30 s), step (60–300 mG), bump (100–300 mG over 20–90 s),
  payload (6–15 A on its own lead, 3–10 mG/A, switched on and off), fixed anomaly (a magnetised
  mass beside the route, 20–60 mG... 300 mG at the closest pass), in a random sensor direction.

The truth of a disturbed flight carries its onset (the nominal one; for the payload and the
anomaly the first time the foreign field reaches 20 mG) and the largest heading turn it causes
(the tilt-compensated heading of the true body field with and without it).  Units: deg, mG, A, s.
"""
from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field, replace

import numpy as np

from estimators.geomag import decimal_year_from_unix, earth_field
from estimators.rotations import dcm_body_to_ned, wrap_angle_rad

from groundstation.io.mavlink import mavlink2
from groundstation.sim import flight_sim as fs
from groundstation.sim import scenarios as sc

__all__ = ["KINDS", "DISTURBANCES", "FlightDraw", "draw_flight", "build_flight", "IMU_RATES_HZ"]

_M = mavlink2
DISTURBANCES = ("fast", "slow", "step", "bump", "payload", "anomaly")
KINDS = ("clean",) + DISTURBANCES
IMU_RATES_HZ = (1.0, 2.0, 4.0, 5.0, 10.0, 50.0 / 3.0, 25.0, 50.0)
IMU_MESSAGES = ("RAW_IMU", "SCALED_IMU", "HIGHRES_IMU")
ATTITUDE_MODES = ("good", "drift_in_outage", "yaw_follows_compass")
ONSET_FIELD_MG = 20.0             # payload / anomaly: onset when the foreign field reaches this


@dataclass(frozen=True)
class FlightDraw:
    """One flight of the population (everything needed to build it again)."""
    index: int
    seed: int
    kind: str
    lat_deg: float
    lon_deg: float
    inclination_deg: float
    duration_s: float
    motor_mG_per_A: tuple
    motor_comp: float
    imu_rate_hz: float
    imu_message: str
    attitude_rate_hz: float
    current_rate_hz: float
    current_lag_s: float
    attitude_mode: str
    wind_mps: tuple
    gust_sigma_mps: float
    route: str
    leg_length_m: float
    speed_mps: float
    leg_bearing_deg: float
    yaw_sweep_deg_s: float
    gyro_bias_deg_s: tuple
    gps_outage: tuple | None
    gaps: tuple
    disturbance: dict = field(default_factory=dict)

    def label(self) -> str:
        return f"{self.kind}-{self.index:04d}"


def _rng(seed: int, index: int, kind: str) -> np.random.Generator:
    return np.random.default_rng([seed, index, KINDS.index(kind), 30])


def _site(rng: np.random.Generator) -> tuple[float, float, float]:
    year = decimal_year_from_unix(sc.START_UNIX_S)
    while True:
        lat, lon = float(rng.uniform(-70.0, 78.0)), float(rng.uniform(-180.0, 180.0))
        with warnings.catch_warnings():                 # near the magnetic poles the WMM warns
            warnings.simplefilter("ignore", UserWarning)
            incl = earth_field(lat, lon, 40.0, year).inclination_deg
        if -60.0 <= incl <= 78.0:
            return lat, lon, float(incl)


def _unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def draw_flight(index: int, seed: int = 0, kind: str = "clean") -> FlightDraw:
    """One flight drawn from the priors (module docstring); the same (index, seed, kind) gives
    the same flight."""
    if kind not in KINDS:
        raise ValueError(f"unknown kind {kind!r}; choose from {', '.join(KINDS)}")
    rng = _rng(seed, index, kind)
    lat, lon, incl = _site(rng)
    duration = float(rng.uniform(180.0, 300.0))
    motor = float(rng.uniform(0.0, 10.0)) * _unit(rng)
    route = str(rng.choice(["stop-and-go", "survey"]))
    if route == "stop-and-go":
        leg, speed, sweep = float(rng.uniform(40.0, 120.0)), float(rng.uniform(3.0, 8.0)), 0.0
    else:
        leg, speed = float(rng.uniform(200.0, 600.0)), float(rng.uniform(5.0, 12.0))
        sweep = float(rng.choice([0.0, 0.0, rng.uniform(-3.0, 3.0)]))
    outage = None
    if rng.uniform() < 1 / 3:
        start = float(rng.uniform(40.0, max(41.0, duration - 60.0)))
        outage = (start, min(duration - 5.0, start + float(rng.uniform(20.0, 120.0))))
    mode = str(rng.choice(ATTITUDE_MODES))
    if mode == "drift_in_outage" and outage is None:
        start = float(rng.uniform(40.0, max(41.0, duration - 60.0)))
        outage = (start, min(duration - 5.0, start + float(rng.uniform(30.0, 120.0))))
    gaps: list = []
    if rng.uniform() < 1 / 3:
        for _ in range(int(rng.integers(1, 4))):
            g0 = float(rng.uniform(30.0, duration - 10.0))
            gaps.append((g0, g0 + float(rng.uniform(0.5, 5.0))))
    wind_speed, wind_dir = float(rng.uniform(0.0, 8.0)), float(rng.uniform(0.0, 2 * math.pi))
    dist: dict = {}
    if kind != "clean":
        onset = float(rng.uniform(45.0, duration - 70.0))
        axis = tuple(float(v) for v in _unit(rng))
        if kind == "fast":
            dist = dict(kind="ramp", onset_s=onset, rate_mG_s=float(rng.uniform(40.0, 100.0)),
                        rise_s=float(rng.uniform(3.0, 8.0)), hold_s=float(rng.uniform(5.0, 20.0)), axis=axis)
        elif kind == "slow":
            dist = dict(kind="ramp", onset_s=onset, rate_mG_s=float(rng.uniform(10.0, 25.0)),
                        rise_s=float(rng.uniform(15.0, 30.0)), hold_s=float(rng.uniform(5.0, 20.0)), axis=axis)
        elif kind == "step":
            dist = dict(kind="step", onset_s=onset, amplitude_mG=float(rng.uniform(60.0, 300.0)),
                        duration_s=float(rng.uniform(10.0, 40.0)), axis=axis)
        elif kind == "bump":
            dist = dict(kind="bump", onset_s=onset, amplitude_mG=float(rng.uniform(100.0, 300.0)),
                        duration_s=float(rng.uniform(20.0, 90.0)), axis=axis)
        elif kind == "payload":
            dist = dict(kind="payload", onset_s=onset, current_A=float(rng.uniform(6.0, 15.0)),
                        period_s=float(rng.uniform(10.0, 40.0)),
                        mG_per_A=tuple(float(v) for v in float(rng.uniform(3.0, 10.0)) * _unit(rng)))
        else:
            dist = dict(kind="anomaly", side_m=float(rng.uniform(-6.0, 6.0)), along=float(rng.uniform(0.2, 0.8)),
                        moment_scale=float(rng.uniform(0.5, 3.0)))
    return FlightDraw(
        index=index, seed=seed, kind=kind, lat_deg=lat, lon_deg=lon, inclination_deg=incl, duration_s=duration,
        motor_mG_per_A=tuple(float(v) for v in motor), motor_comp=float(rng.uniform(0.5, 1.0)),
        imu_rate_hz=float(rng.choice(IMU_RATES_HZ)), imu_message=str(rng.choice(IMU_MESSAGES)),
        attitude_rate_hz=float(rng.choice([2.0, 5.0, 10.0, 25.0, 50.0])),
        current_rate_hz=float(rng.choice([1.0, 2.0, 5.0, 10.0])), current_lag_s=float(rng.uniform(0.0, 0.8)),
        attitude_mode=mode, wind_mps=(wind_speed * math.cos(wind_dir), wind_speed * math.sin(wind_dir)),
        gust_sigma_mps=float(rng.uniform(0.1, 1.5)), route=route, leg_length_m=leg, speed_mps=speed,
        leg_bearing_deg=float(rng.uniform(0.0, 360.0)), yaw_sweep_deg_s=sweep,
        gyro_bias_deg_s=tuple(float(v) for v in rng.uniform(-0.5, 0.5, 3)), gps_outage=outage, gaps=tuple(gaps),
        disturbance=dist)


# ----------------------------------------------------------------------------- building
def _config(d: FlightDraw) -> fs.SimConfig:
    rng = np.random.default_rng([d.seed, d.index, KINDS.index(d.kind), 31])
    mag = fs.MagModel.random(rng)
    mag.motor_mG_per_A = np.asarray(d.motor_mG_per_A, dtype=float)
    over = dict(duration_s=d.duration_s, origin_lat_deg=d.lat_deg, origin_lon_deg=d.lon_deg, mag=mag,
                gyro_bias_rad_s=np.radians(d.gyro_bias_deg_s), autopilot_motor_comp=d.motor_comp,
                mean_wind_mps=d.wind_mps, gust_sigma_mps=d.gust_sigma_mps, leg_length_m=d.leg_length_m,
                speed_mps=d.speed_mps, leg_bearing_deg=d.leg_bearing_deg, yaw_sweep_deg_s=d.yaw_sweep_deg_s,
                gps_outage=d.gps_outage, rtk=False)
    if d.attitude_mode == "yaw_follows_compass":
        over["autopilot_mag_gain_per_s"] = 2.0
    dist = dict(d.disturbance)
    kind = dist.pop("kind", None)
    if kind in ("ramp", "step", "bump"):
        over["interference"] = fs.Interference(kind, **dist)
    elif kind == "payload":
        over["payload"] = fs.PayloadLoad(dist["current_A"], dist["period_s"], from_s=dist["onset_s"],
                                         mG_per_A=dist["mG_per_A"])
    cfg = sc._config("mission-clean", d.seed * 100_003 + d.index, over)
    if kind == "anomaly":
        brg = math.radians(d.leg_bearing_deg)
        along, side = dist["along"] * d.leg_length_m, dist["side_m"]
        pos = (along * math.cos(brg) - side * math.sin(brg), along * math.sin(brg) + side * math.cos(brg), 0.0)
        moment = dist["moment_scale"] * sc.ANOMALY_MOMENT_AM2 * cfg.field_ned_mG / np.linalg.norm(cfg.field_ned_mG)
        cfg.anomaly = fs.GroundAnomaly(pos_ned_m=pos, moment_ned_Am2=tuple(float(v) for v in moment))
    return cfg


def _heading_turn_deg(cfg: fs.SimConfig, res: fs.SimResult) -> np.ndarray:
    """Per step: how far the disturbance turns the tilt-compensated heading of the true field [deg]."""
    c = dcm_body_to_ned(res.roll_rad, res.pitch_rad, res.yaw_rad)
    a_inv = np.linalg.inv(cfg.mag.matrix)
    d_ned = np.einsum("nij,nj->ni", c, res.interference_mG @ a_inv.T)      # sensor -> body -> NED
    h = cfg.field_ned_mG
    turned = np.arctan2(h[1] + d_ned[:, 1], h[0] + d_ned[:, 0]) - math.atan2(h[1], h[0])
    return np.abs(np.degrees(np.angle(np.exp(1j * turned))))


def _attitude_errors(d: FlightDraw, t: np.ndarray) -> np.ndarray:
    """(N, 3) roll, pitch, yaw errors [rad] added to the autopilot's ATTITUDE: its open-loop
    drift through the GPS outage (then slowly pulled back), zero otherwise."""
    err = np.zeros((len(t), 3))
    if d.attitude_mode != "drift_in_outage" or d.gps_outage is None:
        return err
    rng = np.random.default_rng([d.seed, d.index, KINDS.index(d.kind), 32])
    a, b = d.gps_outage
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 0.02
    inside = (t >= a) & (t < b)
    yaw_rate = math.radians(rng.uniform(0.1, 0.6)) * rng.choice([-1.0, 1.0])
    walk = np.cumsum(rng.normal(0.0, math.radians(0.08) * math.sqrt(dt), (len(t), 2)) * inside[:, None], axis=0)
    err[:, :2] = walk
    err[:, 2] = np.cumsum(np.where(inside, yaw_rate * dt, 0.0))
    after = t >= b                                    # GPS back: the EKF pulls it in over ~20 s
    if after.any():
        decay = np.exp(-(t[after] - b) / 20.0)
        err[after] = err[np.flatnonzero(after)[0] - 1] * decay[:, None]
    return err


def build_flight(d: FlightDraw) -> tuple[list, dict]:
    """(time-ordered [(unix_s, MAVLink message)], truth) of one drawn flight."""
    cfg = _config(d)
    res = fs.run(cfg)
    truth = sc._truth(d.label(), cfg, res)
    t = res.t_s
    motor = res.motor_current_A[:, None] * np.asarray(d.motor_mG_per_A)[None, :]
    res.mag_raw_mG -= (d.motor_comp * motor) @ cfg.mag.matrix.T       # the autopilot's COMPASS_MOT
    params = sc._params(cfg)
    comp = {f"COMPASS_MOT_{a}": -d.motor_comp * d.motor_mG_per_A[k] for k, a in enumerate("XYZ")}
    params = [(n, v) for n, v in params if n != "COMPASS_MOTCT"] + sorted(comp.items()) + [("COMPASS_MOTCT", 2.0)]
    err = _attitude_errors(d, t)
    res.est_roll_rad = res.est_roll_rad + err[:, 0]
    res.est_pitch_rad = res.est_pitch_rad + err[:, 1]
    res.est_yaw_rad = wrap_angle_rad(res.est_yaw_rad + err[:, 2])
    msgs = sc._pack(cfg, res, sc.START_UNIX_S, sc.BOOT_OFFSET_S, with_mission=True, params=params)
    msgs = _restream(d, cfg, res, msgs, params)
    turn = _heading_turn_deg(cfg, res)
    truth["population"] = {k: v for k, v in d.__dict__.items()}
    onset = None
    if d.kind in ("fast", "slow", "step", "bump"):
        onset = float(d.disturbance["onset_s"])
    elif d.kind in ("payload", "anomaly"):
        over = np.flatnonzero(np.linalg.norm(res.interference_mG, axis=1) >= ONSET_FIELD_MG)
        onset = float(t[over[0]]) if len(over) else None
    truth["onset_s"] = onset
    over = np.flatnonzero(np.linalg.norm(res.interference_mG, axis=1) >= ONSET_FIELD_MG)
    truth["end_s"] = float(t[over[-1]]) if len(over) and onset is not None else None
    truth["max_heading_turn_deg"] = float(np.max(turn)) if len(turn) else 0.0
    truth["max_disturbance_mG"] = float(np.max(np.linalg.norm(res.interference_mG, axis=1)))
    truth["flight_hours"] = float(t[-1] / 3600.0)
    truth["autopilot_yaw_error_max_deg"] = float(np.max(np.abs(np.degrees(wrap_angle_rad(res.est_yaw_rad - res.yaw_rad)))))
    return msgs, truth


def _restream(d: FlightDraw, cfg: fs.SimConfig, res: fs.SimResult, msgs: list, params: list) -> list:
    """The 50 Hz SCALED_IMU / ATTITUDE / 10 Hz SYS_STATUS stream of ``scenarios._pack`` at the
    drawn rates, IMU message and current lag, with the telemetry gaps cut out."""
    start = sc.START_UNIX_S
    imu_every = max(1, int(round(cfg.rate_hz / d.imu_rate_hz)))
    att_every = max(1, int(round(cfg.rate_hz / d.attitude_rate_hz)))
    out: list = []
    k_imu = k_att = 0
    for u, m in msgs:
        typ = m.get_type()
        if typ == "SCALED_IMU":
            k_imu += 1
            if (k_imu - 1) % imu_every:
                continue
            if d.imu_message == "RAW_IMU":
                m = _M.MAVLink_raw_imu_message(int(round((u - start + sc.BOOT_OFFSET_S) * 1e6)), m.xacc, m.yacc,
                                               m.zacc, m.xgyro, m.ygyro, m.zgyro, m.xmag, m.ymag, m.zmag)
            elif d.imu_message == "HIGHRES_IMU":
                g = fs.G / 1000.0
                m = _M.MAVLink_highres_imu_message(
                    int(round((u - start + sc.BOOT_OFFSET_S) * 1e6)), m.xacc * g, m.yacc * g, m.zacc * g,
                    m.xgyro * 1e-3, m.ygyro * 1e-3, m.zgyro * 1e-3, m.xmag * 1e-3, m.ymag * 1e-3, m.zmag * 1e-3,
                    1013.0, 0.0, 40.0, 25.0, 0x1FFF)
        elif typ == "ATTITUDE":
            k_att += 1
            if (k_att - 1) % att_every:
                continue
        elif typ == "SYS_STATUS":
            continue
        out.append((u, m))
    t = res.t_s
    every = max(1, int(round(cfg.rate_hz / d.current_rate_hz)))
    lagged = np.interp(t - d.current_lag_s, t, res.motor_current_A)
    for i in range(0, len(t), every):
        out.append((start + t[i] + 3e-4, _M.MAVLink_sys_status_message(
            0, 0, 0, 300, 15200, int(round(lagged[i] * 100.0)), 70, 0, 0, 0, 0, 0, 0)))
    if d.gaps:
        keep_head = start + 0.5                       # parameters and the mission stay
        out = [(u, m) for u, m in out if u < keep_head or not any(a <= u - start < b for a, b in d.gaps)]
    out.sort(key=lambda x: x[0])
    return out


def write_flight(d: FlightDraw, path) -> tuple:
    """Write the flight's .tlog (and truth JSON beside it); returns (path, truth)."""
    msgs, truth = build_flight(d)
    sim = sc.Simulation(d.label(), d.seed, msgs, truth)
    return sim.write(path), truth


def replace_draw(d: FlightDraw, **changes) -> FlightDraw:
    """A drawn flight with some settings changed (tests, studies of one prior)."""
    return replace(d, **changes)
