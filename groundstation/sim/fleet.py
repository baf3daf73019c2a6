"""A simulated fleet of logs with known truth, for `magstation review` (`magstation simulate fleet`).

``simulate_fleet(out_dir, FleetSettings(...))`` writes ``<out>/<airframe>/flight-NNN.tlog`` for every
vehicle and flight, ``<out>/airframes.json`` (the operator's mapping: board serial -> airframe name
and payload) and ``<out>/fleet.truth.json`` (everything planted).  Each flight is a short closed-loop
mission of ``groundstation.sim.scenarios.simulate("mission-clean", ...)`` (the nose turning at
``yaw_sweep_deg_s`` so that the in-flight WMM fit sees every heading) with the vehicle's own
sensor errors, re-shaped the way an ArduPilot vehicle would log it:

* the streamed field is the *corrected* one, with the calibration in force (COMPASS_OFS/DIA/ODI
  from the vehicle's last calibration, done before the first flight) written in the parameters;
  ``BRD_SERIAL_NUM`` and ``SYSID_THISMAV`` identify the vehicle (every sysid is the default 1);
* dates: flight k of every vehicle is on day k after ``FLEET_START_UNIX_S``;
* planted: slow hard-iron drift on ``drift_vehicles`` airframes (``drift_total_mG`` over the fleet's
  flights, constant direction), a payload change on ``payload_vehicles`` airframes (a motor-current
  field of ``payload_motor_mG_per_A`` added from the middle flight on), an anomaly site (a constant
  extra field ``anomaly_ned_mG`` in NED wherever a vehicle flies there), interference events
  (a step or ramp on the sensor during a fraction of flights) and ``corrupt_files`` damaged logs.

Limits: the simulator's autopilot heading uses the vehicle's true calibration (its yaw does not
follow a drifting offset or the site anomaly), so attitude-based fits see an independent yaw.
Units: mG, mG/A, s, deg.
"""
from __future__ import annotations

import calendar
import json
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from estimators.rotations import dcm_body_to_ned
from groundstation.io.mavlink import TlogWriter
from groundstation.io.params import apply_ardupilot, ardupilot_params_from_calibration
from groundstation.sim import flight_sim as fs
from groundstation.sim.scenarios import START_UNIX_S, simulate

__all__ = ["FleetSettings", "FlightPlan", "plan_fleet", "simulate_fleet", "write_flight",
           "FLEET_START_UNIX_S", "TRUTH_NAME", "MAPPING_NAME"]

FLEET_START_UNIX_S = float(calendar.timegm((2026, 1, 5, 8, 0, 0)))
TRUTH_NAME = "fleet.truth.json"
MAPPING_NAME = "airframes.json"
SERIAL_BASE = 7100


@dataclass(frozen=True)
class Site:
    name: str
    lat_deg: float
    lon_deg: float
    anomaly_ned_mG: tuple[float, float, float] | None = None


DEFAULT_SITES = (Site("base", 30.260, 120.120), Site("north-field", 30.420, 120.060),
                 Site("river", 30.180, 120.290), Site("quarry", 30.330, 119.950, (8.0, -6.0, 55.0)))


@dataclass(frozen=True)
class FleetSettings:
    """What the fleet holds.  Units in the names; ``seed`` fixes everything."""
    vehicles: int = 20
    flights: int = 50
    seed: int = 0
    flight_s: tuple[float, float] = (70.0, 100.0)       # flight length range (two legs at least)
    drift_vehicles: int = 3
    drift_total_mG: float = 60.0                        # hard-iron change from first to last flight
    payload_vehicles: int = 1
    payload_motor_mG_per_A: float = 2.5                 # added motor-current field (its norm)
    sites: tuple[Site, ...] = DEFAULT_SITES
    anomaly_visit_fraction: float = 0.25                # share of flights at the anomaly site(s)
    interference_fraction: float = 0.03                 # share of flights with an interference event
    corrupt_files: int = 5
    leg_length_m: float = 100.0
    hover_s: float = 10.0
    yaw_sweep_deg_s: float = 10.0                       # the nose turns through the flight (headings for the WMM fit)

    def __post_init__(self) -> None:
        if self.vehicles < 1 or self.flights < 2:
            raise ValueError("a fleet needs at least 1 vehicle and 2 flights each")
        if self.drift_vehicles + self.payload_vehicles > self.vehicles:
            raise ValueError("more drifting/payload vehicles than vehicles")


@dataclass(frozen=True)
class FlightPlan:
    """Everything one flight needs (picklable; arrays as nested tuples)."""
    airframe: str
    serial: int
    sysid: int
    flight: int
    seed: int
    date_unix_s: float
    duration_s: float
    site: Site
    leg_bearing_deg: float
    wind_mps: tuple[float, float]
    matrix: tuple                        # A (soft iron + misalignment), sensor = A·body
    offsets_mG: tuple[float, float, float]       # true hard iron this flight
    motor_mG_per_A: tuple[float, float, float]   # true motor-current field this flight
    cal_offsets_mG: tuple[float, float, float]   # the calibration in force (raw-frame b)
    cal_matrix: tuple                            # ... and its matrix C (m_cal = C (raw − b))
    interference: dict | None = None
    leg_length_m: float = 150.0
    hover_s: float = 10.0
    yaw_sweep_deg_s: float = 0.0

    @property
    def file(self) -> str:
        return f"{self.airframe}/flight-{self.flight:03d}.tlog"


# ------------------------------------------------------------------------------------ planning
def _vehicle_roles(settings: FleetSettings, rng: np.random.Generator) -> dict[int, str]:
    order = rng.permutation(settings.vehicles)
    roles = {int(v): "steady" for v in order}
    for v in order[:settings.drift_vehicles]:
        roles[int(v)] = "drift"
    for v in order[settings.drift_vehicles:settings.drift_vehicles + settings.payload_vehicles]:
        roles[int(v)] = "payload"
    return roles


def _unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def _site_sequence(settings: FleetSettings, rng: np.random.Generator, home: int) -> list[int]:
    anomalous = [i for i, s in enumerate(settings.sites) if s.anomaly_ned_mG is not None]
    normal = [i for i, s in enumerate(settings.sites) if s.anomaly_ned_mG is None] or [home]
    out = []
    for _ in range(settings.flights):
        if anomalous and rng.random() < settings.anomaly_visit_fraction:
            out.append(int(rng.choice(anomalous)))
        else:
            out.append(home if rng.random() < 0.6 else int(rng.choice(normal)))
    return out


def _interference(rng: np.random.Generator, duration_s: float) -> dict:
    onset = float(rng.uniform(32.0, duration_s - 22.0))
    if rng.random() < 0.5:
        return {"kind": "step", "onset_s": round(onset, 2), "amplitude_mG": 150.0, "duration_s": 15.0,
                "axis": (0.0, 1.0, 0.0)}
    return {"kind": "ramp", "onset_s": round(onset, 2), "rate_mG_s": 40.0, "rise_s": 4.0, "hold_s": 8.0,
            "axis": (0.0, 1.0, 0.0)}


def _vehicle_plans(settings: FleetSettings, v: int, role: str, rng: np.random.Generator) -> list[FlightPlan]:
    mag = fs.MagModel.random(rng)
    motor0 = rng.uniform(0.6, 1.4) * np.array([1.2, 0.8, 2.0]) * rng.choice([-1, 1], 3)
    b0 = mag.offsets_mG
    cal_b = b0 + rng.normal(0.0, 2.0, 3)               # the calibration done before flight 0
    cal_C = np.linalg.inv(mag.matrix)
    drift = _unit(rng) * settings.drift_total_mG / (settings.flights - 1) if role == "drift" else np.zeros(3)
    payload_from = settings.flights // 2 if role == "payload" else settings.flights + 1
    payload = _unit(rng) * settings.payload_motor_mG_per_A
    home = int(rng.integers(0, len(settings.sites)))
    while settings.sites[home].anomaly_ned_mG is not None:
        home = int(rng.integers(0, len(settings.sites)))
    sites = _site_sequence(settings, rng, home)
    name = f"AF-{v + 1:02d}"
    plans = []
    for k in range(settings.flights):
        duration = float(rng.uniform(*settings.flight_s))
        interf = _interference(rng, duration) if rng.random() < settings.interference_fraction else None
        motor = motor0 + (payload if k >= payload_from else 0.0)
        plans.append(FlightPlan(
            airframe=name, serial=SERIAL_BASE + 13 * v, sysid=1, flight=k,
            seed=int(rng.integers(0, 2**31 - 1)),
            date_unix_s=FLEET_START_UNIX_S + 86400.0 * k + float(rng.uniform(0, 8 * 3600)),
            duration_s=round(duration, 1), site=settings.sites[sites[k]],
            leg_bearing_deg=float(rng.uniform(0, 360)), wind_mps=tuple(rng.uniform(-2.0, 2.0, 2).tolist()),
            matrix=tuple(map(tuple, mag.matrix.tolist())), offsets_mG=tuple((b0 + drift * k).tolist()),
            motor_mG_per_A=tuple(np.asarray(motor, float).tolist()), cal_offsets_mG=tuple(cal_b.tolist()),
            cal_matrix=tuple(map(tuple, cal_C.tolist())), interference=interf,
            leg_length_m=settings.leg_length_m, hover_s=settings.hover_s, yaw_sweep_deg_s=settings.yaw_sweep_deg_s))
    return plans


def plan_fleet(settings: FleetSettings) -> tuple[list[FlightPlan], dict]:
    """Every flight's plan and the per-vehicle truth (roles, drift, payload change)."""
    rng = np.random.default_rng([settings.seed, 2026])
    roles = _vehicle_roles(settings, rng)
    plans, vehicles = [], []
    for v in range(settings.vehicles):
        p = _vehicle_plans(settings, v, roles[v], np.random.default_rng([settings.seed, v, 17]))
        plans += p
        first, last = np.array(p[0].offsets_mG), np.array(p[-1].offsets_mG)
        change = next((q.flight for q in p if q.motor_mG_per_A != p[0].motor_mG_per_A), None)
        vehicles.append({
            "airframe": p[0].airframe, "serial": p[0].serial, "sysid": p[0].sysid, "role": roles[v],
            "drift_total_mG": float(np.linalg.norm(last - first)),
            "drift_mG_per_flight": (last - first).tolist() if roles[v] == "drift" else None,
            "payload_change_flight": change,
            "motor_before_mG_per_A": list(p[0].motor_mG_per_A),
            "motor_after_mG_per_A": list(p[-1].motor_mG_per_A) if change is not None else None,
            "calibration_offsets_mG": list(p[0].cal_offsets_mG)})
    return plans, {"vehicles": vehicles}


# ------------------------------------------------------------------------------------ one flight
def _params(plan: FlightPlan) -> list[tuple[str, float]]:
    cal = ardupilot_params_from_calibration(np.array(plan.cal_offsets_mG), np.array(plan.cal_matrix))
    p = [("SYSID_THISMAV", float(plan.sysid)), ("BRD_SERIAL_NUM", float(plan.serial)),
         ("COMPASS_USE", 1.0), ("COMPASS_ORIENT", 0.0), ("COMPASS_EXTERNAL", 1.0), ("COMPASS_MOTCT", 0.0)]
    return p + sorted(cal.items())


def _corrected_field(plan: FlightPlan, sim) -> np.ndarray:
    """What the vehicle streams: ArduPilot's correction with the calibration in force applied to the
    raw field, plus the site's anomaly seen through the sensor (A · C_n^b · ΔH)."""
    r = sim.result
    raw = np.asarray(r.mag_raw_mG, float).copy()
    if plan.site.anomaly_ned_mG is not None:
        c_bn = dcm_body_to_ned(r.roll_rad, r.pitch_rad, r.yaw_rad)
        dh_body = np.einsum("nji,j->ni", c_bn, np.asarray(plan.site.anomaly_ned_mG, float))
        raw += dh_body @ np.asarray(plan.matrix).T
    params = dict(_params(plan))
    return apply_ardupilot(raw, params)


def _vehicle_messages(plan: FlightPlan, sim) -> list:
    """The simulation's messages as this vehicle logs them (see the module docstring)."""
    from groundstation.io.mavlink import mavlink2 as M

    shift = plan.date_unix_s - START_UNIX_S
    corrected = np.clip(np.rint(_corrected_field(plan, sim)), -32768, 32767).astype(int)
    out, k, t0 = [], 0, None
    for unix_s, msg in sim.messages:
        kind = msg.get_type()
        if kind == "PARAM_VALUE":
            t0 = unix_s if t0 is None else t0
            continue
        if kind == "SCALED_IMU":
            msg.xmag, msg.ymag, msg.zmag = (int(v) for v in corrected[k])
            k += 1
        elif kind == "SYSTEM_TIME":
            msg.time_unix_usec = int(msg.time_unix_usec + shift * 1e6)
        out.append((unix_s + shift, msg))
    params = _params(plan)
    base = (t0 if t0 is not None else sim.messages[0][0]) + shift
    for i, (name, value) in enumerate(params):
        out.append((base + i * 1e-3, M.MAVLink_param_value_message(
            name.encode(), float(value), M.MAV_PARAM_TYPE_REAL32, len(params), i)))
    out.sort(key=lambda x: x[0])
    return out


def _flight_truth(plan: FlightPlan, sim) -> dict:
    t = sim.truth
    return {"file": plan.file, "airframe": plan.airframe, "flight": plan.flight, "serial": plan.serial,
            "date_unix_s": plan.date_unix_s, "duration_s": t["duration_s"], "site": plan.site.name,
            "lat_deg": plan.site.lat_deg, "lon_deg": plan.site.lon_deg,
            "offsets_mG": list(plan.offsets_mG), "calibration_offsets_mG": list(plan.cal_offsets_mG),
            "offsets_change_mG": (np.array(plan.offsets_mG) - plan.cal_offsets_mG).tolist(),
            "motor_mG_per_A": list(plan.motor_mG_per_A), "interference": t["interference"]
            if plan.interference else None, "earth_field": t["earth_field"],
            "max_cross_track_m": t.get("max_cross_track_m")}


def write_flight(plan: FlightPlan, out_dir: str | Path) -> dict:
    """Simulate one flight, write its .tlog under ``out_dir``; returns its truth entry."""
    interf = None
    if plan.interference:
        interf = fs.Interference(**{k: (tuple(v) if k == "axis" else v) for k, v in plan.interference.items()})
    mag = fs.MagModel(matrix=np.array(plan.matrix), offsets_mG=np.array(plan.offsets_mG),
                      motor_mG_per_A=np.array(plan.motor_mG_per_A))
    over = dict(duration_s=plan.duration_s, mag=mag, origin_lat_deg=plan.site.lat_deg,
                origin_lon_deg=plan.site.lon_deg, leg_bearing_deg=plan.leg_bearing_deg,
                mean_wind_mps=plan.wind_mps, leg_length_m=plan.leg_length_m, hover_s=plan.hover_s,
                yaw_sweep_deg_s=plan.yaw_sweep_deg_s)
    if interf is not None:
        over["interference"] = interf
    sim = simulate("mission-clean", plan.seed, **over)
    path = Path(out_dir) / plan.file
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.exists():
        path.unlink()
    with TlogWriter(path, system_id=plan.sysid) as w:
        for unix_s, msg in _vehicle_messages(plan, sim):
            w.write_message(msg, unix_s)
    return _flight_truth(plan, sim)


# ------------------------------------------------------------------------------------ damage
CORRUPTIONS = ("truncated", "garbage_inside", "random_bytes", "empty", "not_a_dataflash")


def _inside_a_record(tlog: bytes, near: int) -> int:
    """A cut in the middle of the .tlog record (8-byte stamp + MAVLink packet) around byte ``near``,
    never on a record boundary (a cut there leaves a whole, shorter log)."""
    i = 0
    while i + 10 < len(tlog):
        size = 12 + tlog[i + 9] + (13 if tlog[i + 10] & 1 else 0) if tlog[i + 8] == 0xFD else 8 + tlog[i + 9]
        if i + 8 + size > near:
            return i + 8 + size // 2
        i += 8 + size
    return max(len(tlog) - 1, 0)


def _corrupt(kind: str, source: Path, target: Path, rng: np.random.Generator) -> str:
    """Write a damaged copy; returns what review must say ("error" or "damaged": read with warnings)."""
    data = source.read_bytes() if source.exists() else b""
    if kind == "truncated":
        target.write_bytes(data[:_inside_a_record(data, int(len(data) * 0.6))])
        return "damaged"
    if kind == "garbage_inside":
        buf = bytearray(data)
        for start in rng.integers(1000, max(len(buf) - 5000, 2000), 20):
            buf[int(start):int(start) + 400] = rng.integers(0, 256, 400, dtype=np.uint8).tobytes()
        target.write_bytes(bytes(buf))
        return "damaged"
    if kind == "random_bytes":
        target.write_bytes(rng.integers(0, 256, 200_000, dtype=np.uint8).tobytes())
        return "error"
    if kind == "empty":
        target.write_bytes(b"")
        return "error"
    target.write_text("this is not an ArduPilot DataFlash log\n" * 100)
    return "error"


def _write_corrupt(truth_flights: list[dict], out_dir: Path, count: int, seed: int) -> list[dict]:
    rng = np.random.default_rng([seed, 99])
    out = []
    for i in range(count):
        kind = CORRUPTIONS[i % len(CORRUPTIONS)]
        src = truth_flights[int(rng.integers(0, len(truth_flights)))]
        suffix = ".bin" if kind == "not_a_dataflash" else ".tlog"
        name = f"{src['airframe']}/damaged-{i:02d}-{kind}{suffix}"
        expected = _corrupt(kind, out_dir / src["file"], out_dir / name, rng)
        out.append({"file": name, "kind": kind, "expected": expected, "copy_of": src["file"]})
    return out


# ------------------------------------------------------------------------------------ the fleet
def _mapping(vehicles: list[dict]) -> dict:
    """The operator's airframe list: board serial -> name and payload (as the operator wrote it
    down; the payload change is *not* in it, review has to find it)."""
    return {"airframes": [{"match": {"serial": v["serial"]}, "airframe": v["airframe"],
                           "payload": "survey-camera" if i % 2 == 0 else "lidar"}
                          for i, v in enumerate(vehicles)]}


def simulate_fleet(out_dir: str | Path, settings: FleetSettings = FleetSettings(), *, workers: int | None = None,
                   progress: Callable[[int, int], None] | None = None) -> dict:
    """Write the fleet (logs, ``airframes.json``, ``fleet.truth.json``) in parallel processes;
    returns the truth.  ``progress(done, total)`` is called as flights finish."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    plans, truth = plan_fleet(settings)
    workers = workers or os.cpu_count() or 1
    flights: list[dict] = []
    if workers == 1:
        for plan in plans:
            flights.append(write_flight(plan, out))
            if progress:
                progress(len(flights), len(plans))
    else:
        with ProcessPoolExecutor(max_workers=workers) as pool:
            for entry in pool.map(write_flight, plans, [out] * len(plans), chunksize=4):
                flights.append(entry)
                if progress:
                    progress(len(flights), len(plans))
    sites = [{"name": s.name, "lat_deg": s.lat_deg, "lon_deg": s.lon_deg,
              "anomaly_ned_mG": list(s.anomaly_ned_mG) if s.anomaly_ned_mG else None} for s in settings.sites]
    truth.update(settings={k: v for k, v in asdict(settings).items() if k != "sites"}, sites=sites,
                 flights=flights, corrupt=_write_corrupt(flights, out, settings.corrupt_files, settings.seed),
                 mapping=MAPPING_NAME)
    (out / MAPPING_NAME).write_text(json.dumps(_mapping(truth["vehicles"]), indent=1))
    (out / TRUTH_NAME).write_text(json.dumps(truth, indent=1))
    return truth
