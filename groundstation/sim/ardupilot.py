"""ArduPilot-realistic simulated logs: what a real vehicle streams and records, with known truth.

``simulate_ardupilot(ArduSimConfig(...)) -> ArduSim``; ``ArduSim.write_tlog(path)`` writes a
MAVLink telemetry log, ``ArduSim.write_bin(path, layout)`` the DataFlash log of the same flight
(layouts in groundstation.sim.dataflash_writer: "timems" 2014-style, "timeus_split" MAG/MAG2/MAG3,
"timeus_instance" MAG with an instance column), each with ``<stem>.truth.json`` beside it.

What makes it ArduPilot-like (and unlike groundstation.sim.scenarios):
* three compasses with their own hard/soft iron, mounting rotation (COMPASS_ORIENTn), motor field
  per ampere and noise; the streamed field (RAW_IMU = compass 0, SCALED_IMU2 = 1, SCALED_IMU3 = 2)
  and the logged one (MAG*) are the *corrected* field, ``AP_Compass_Backend::correct_field`` with
  the values in force at each sample (estimators.compass_corrections);
* stale offsets before the flight, then an onboard calibration (MAV_CMD_DO_START_MAG_CAL) during a
  handheld dance: MAG_CAL_PROGRESS at 1 Hz, MAG_CAL_REPORT with the vehicle's own fit (a robust
  ellipsoid fit of 300 full-rate rotated-raw samples, scale factor to the WMM strength), then
  PARAM_VALUE / PARM and SENSOR_OFFSETS with the new values, used from then on;
* low telemetry rates (IMU 1.5–4 Hz), latency jitter and dropped packets; the motor current in
  SYS_STATUS (and CURR/BAT), throttle in VFR_HUD (and CTUN); COMPASS_MOT compensation in force
  (COMPASS_MOTCT = 2) at a fraction of the true motor field; an optional compass drop-out;
* an EKF-like yaw computed from compass 0 (or an independent yaw source).
"""
from __future__ import annotations

import calendar
import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from estimators.calibration import fit_ellipsoid_robust
from estimators.compass_corrections import CorrectionsInForce, apply_ardupilot_corrections, motor_offset_mG
from estimators.geomag import decimal_year_from_unix, earth_field
from estimators.detection import lla_from_ned
from groundstation.io.params import rotation_enum_matrix
from groundstation.sim.ardupilot_flight import FlightPlan, FlightTruth, autopilot_attitude, fly
from groundstation.sim.ardupilot_telemetry import pack_telemetry, write_dataflash

__all__ = ["CompassSpec", "ArduSimConfig", "ArduSim", "simulate_ardupilot", "default_compasses", "truth_path"]

START_UNIX_S = float(calendar.timegm((2026, 4, 18, 9, 30, 0)))


def truth_path(log_path: str | Path) -> Path:
    p = Path(log_path)
    return p.with_name(p.stem + ".truth.json")


@dataclass(frozen=True)
class CompassSpec:
    """One magnetometer: m_s = A R_mountᵀ (h + f I) + b + noise (sensor frame s)."""
    offsets_sensor_mG: tuple[float, float, float]
    soft_iron: tuple[tuple[float, ...], ...]
    mount_rotation: int = 0            # physical mounting (ArduPilot ROTATION_*)
    orient_param: int = 0              # COMPASS_ORIENTn as configured
    motor_mG_per_A: tuple[float, float, float] = (0.0, 0.0, 0.0)
    noise_mG: float = 2.0
    external: bool = True
    stale_error_mG: tuple[float, float, float] = (0.0, 0.0, 0.0)   # COMPASS_OFS error before the onboard calibration
    motor_comp_fraction: float = 0.0   # COMPASS_MOT in force = −fraction · f (0: none)


def default_compasses(rng: np.random.Generator) -> tuple[CompassSpec, ...]:
    """External GPS/compass (yaw-180 mount), internal board compass near the wiring, second external."""
    def soft(scale: float, off: float) -> tuple:
        d = 1.0 + rng.uniform(-scale, scale, 3)
        o = rng.uniform(-off, off, 3)
        return ((d[0], o[0], o[1]), (o[0], d[1], o[2]), (o[1], o[2], d[2]))
    return (
        CompassSpec(tuple(rng.uniform(-120, 120, 3)), soft(0.04, 0.02), 4, 4, (0.6, -0.4, 1.1), 1.5, True,
                    tuple(rng.uniform(-60, 60, 3)), 0.0),
        CompassSpec(tuple(rng.uniform(-300, 300, 3)), soft(0.08, 0.04), 0, 0, (2.5, 1.8, -3.2), 3.0, False,
                    tuple(rng.uniform(-80, 80, 3)), 0.5),
        CompassSpec(tuple(rng.uniform(-150, 150, 3)), soft(0.05, 0.03), 0, 0, (0.3, 0.2, -0.5), 2.0, True,
                    tuple(rng.uniform(-40, 40, 3)), 0.0),
    )


@dataclass(frozen=True)
class ArduSimConfig:
    seed: int = 0
    imu_rate_hz: float = 2.0
    attitude_rate_hz: float = 4.0
    gps_rate_hz: float = 2.0
    status_rate_hz: float = 2.0
    drop_fraction: float = 0.02
    plan: FlightPlan = field(default_factory=FlightPlan)
    compasses: tuple[CompassSpec, ...] | None = None     # None: default_compasses(seed)
    yaw_source: str = "compass"                           # "compass" | "independent"
    dropout_compass: int | None = None                    # this compass stops during the flight
    dropout_after_s: float = 200.0
    origin: tuple[float, float, float] = (-35.363, 149.165, 584.0)   # Canberra, like the dronekit log
    start_unix_s: float = START_UNIX_S


@dataclass
class CompassRecord:
    """Per-compass arrays on the log grid and the truth of that compass."""
    spec: CompassSpec
    raw_rot_mG: np.ndarray            # ArduPilot's rotated raw (before correct_field)
    corrected_mG: np.ndarray          # what is streamed and logged
    corrections: CorrectionsInForce
    motor_offset_mG: np.ndarray
    present: np.ndarray               # False after a drop-out
    report: dict                      # the vehicle's MAG_CAL_REPORT (empty without a dance)
    truth: dict


@dataclass
class ArduSim:
    config: ArduSimConfig
    flight: FlightTruth
    attitude: np.ndarray              # (N,3) what the autopilot reports
    compasses: list[CompassRecord]
    field_ned_mG: np.ndarray
    declination_deg: float
    cal_applied_s: float | None
    truth: dict

    def write_tlog(self, path: str | Path) -> Path:
        from groundstation.io.mavlink import TlogWriter, new_encoder
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.unlink(missing_ok=True)
        gcs = new_encoder(255, 190)            # commands come from the ground station
        with TlogWriter(path) as w:
            for unix_s, msg in pack_telemetry(self):
                if msg.get_type() == "COMMAND_LONG":
                    w.write_packet(bytes(msg.pack(gcs)), unix_s)
                else:
                    w.write_message(msg, unix_s)
        truth_path(path).write_text(json.dumps(dict(self.truth, file=path.name, format="tlog"), indent=1))
        return path

    def write_bin(self, path: str | Path, layout: str = "timeus_split") -> Path:
        path = write_dataflash(self, Path(path), layout)
        truth_path(path).write_text(json.dumps(dict(self.truth, file=path.name, format=f"bin/{layout}"), indent=1))
        return path


def _onboard_calibration(raw_rot: np.ndarray, dance: np.ndarray, strength_mG: float, rng) -> dict:
    """The vehicle's own calibration: robust ellipsoid fit of ≤300 full-rate dance samples."""
    idx = np.nonzero(dance)[0]
    idx = idx[np.linspace(0, len(idx) - 1, min(300, len(idx))).astype(int)]
    fit = fit_ellipsoid_robust(raw_rot[idx])
    if not fit.ok:
        return {}
    M = fit.matrix
    return {"ofs_mG": (-fit.offsets_mG).tolist(), "diag": np.diag(M).tolist(),
            "offdiag": [float(M[0, 1]), float(M[0, 2]), float(M[1, 2])],
            "scale_factor": float(strength_mG / fit.field_strength_mG), "fitness_mG": float(fit.residual_rms_mG),
            "n_samples": int(len(idx))}


def _corrections(spec: CompassSpec, truth_b_rot: np.ndarray, report: dict, t: np.ndarray, t_apply: float | None,
                 motor_f_rot: np.ndarray) -> CorrectionsInForce:
    """Stale values before ``t_apply``, the report's values from then on."""
    n = len(t)
    stale = CorrectionsInForce.constant(n, -(truth_b_rot + np.asarray(spec.stale_error_mG)),
                                        motor_per_unit=-spec.motor_comp_fraction * motor_f_rot,
                                        motor_type=2 if spec.motor_comp_fraction else 0)
    if not report or t_apply is None:
        return stale
    after = t >= t_apply
    ofs, dia, odi, sc = (stale.offsets_mG.copy(), stale.diag.copy(), stale.offdiag.copy(), stale.scale.copy())
    ofs[after], dia[after], odi[after], sc[after] = report["ofs_mG"], report["diag"], report["offdiag"], report["scale_factor"]
    return CorrectionsInForce(ofs, dia, odi, sc, stale.motor_per_unit, stale.motor_type, stale.known)


def _compass(k: int, spec: CompassSpec, fl: FlightTruth, H: np.ndarray, dance: np.ndarray, t_apply: float | None,
             present: np.ndarray, rng) -> CompassRecord:
    Rm, Rp = rotation_enum_matrix(spec.mount_rotation), rotation_enum_matrix(spec.orient_param)
    A = np.asarray(spec.soft_iron, float)
    b = np.asarray(spec.offsets_sensor_mG, float)
    f = np.asarray(spec.motor_mG_per_A, float)
    h = np.einsum("nji,j->ni", fl.dcm(), H)
    sensor = (h + fl.current_A[:, None] * f) @ (A @ Rm.T).T + b + rng.normal(0, spec.noise_mG, h.shape)
    raw_rot = sensor @ Rp.T
    A_rot, b_rot = Rp @ A @ Rm.T, Rp @ b
    f_rot = f                                      # the motor field is a body-frame field: h + f I
    report = _onboard_calibration(raw_rot, dance, float(np.linalg.norm(H)), rng) if dance.any() else {}
    corr = _corrections(spec, b_rot, report, fl.t_s, t_apply, f_rot)
    corrected = apply_ardupilot_corrections(raw_rot, corr, current_A=fl.current_A)
    mot = motor_offset_mG(corr, current_A=fl.current_A)
    truth = {"instance": k, "mount_rotation": spec.mount_rotation, "orient_param": spec.orient_param,
             "external": spec.external, "noise_mG": spec.noise_mG,
             "model": "m_rotraw = A_rot (h_body + motor_mG_per_A * I) + offsets_rot_mG + noise",
             "A_rot": A_rot.tolist(), "offsets_rot_mG": b_rot.tolist(), "motor_mG_per_A": f.tolist(),
             "ideal": {"COMPASS_OFS": (-b_rot).tolist(), "matrix": np.linalg.inv(A_rot).tolist(),
                       "COMPASS_MOT": (-f).tolist()},
             "stale_COMPASS_OFS": corr.offsets_mG[0].tolist(),
             "COMPASS_MOT_in_force": corr.motor_per_unit[0].tolist(), "mag_cal_report": report}
    return CompassRecord(spec, raw_rot, corrected, corr, mot, present, report, truth)


def simulate_ardupilot(config: ArduSimConfig = ArduSimConfig()) -> ArduSim:
    """Run the flight, the three compasses, the onboard calibration and the autopilot attitude."""
    rng = np.random.default_rng(config.seed)
    fl = fly(config.plan, rng)
    lat, lon, alt = config.origin
    ef = earth_field(lat, lon, alt, decimal_year_from_unix(config.start_unix_s))
    H = np.asarray(ef.field_ned_mG, float)
    specs = config.compasses or default_compasses(np.random.default_rng([config.seed, 5]))
    dance = np.zeros(len(fl.t_s), bool)
    t_apply = None
    if "dance" in fl.events:
        d0, d1 = fl.events["dance"]
        dance = (fl.t_s >= d0) & (fl.t_s < d1)
        t_apply = d1 + 1.0
    recs = []
    for k, spec in enumerate(specs):
        present = np.ones(len(fl.t_s), bool)
        if config.dropout_compass == k:
            present = fl.t_s < config.dropout_after_s
        recs.append(_compass(k, spec, fl, H, dance, t_apply, present, rng))
    att = autopilot_attitude(fl, recs[0].corrected_mG, math.radians(ef.declination_deg), config.yaw_source, rng)
    truth = {"start_unix_s": config.start_unix_s, "seed": config.seed,
             "origin": {"lat_deg": lat, "lon_deg": lon, "alt_m": alt},
             "earth_field": {"field_ned_mG": H.tolist(), "field_strength_mG": float(ef.field_strength_mG),
                             "declination_deg": float(ef.declination_deg), "inclination_deg": float(ef.inclination_deg)},
             "rates_hz": {"imu": config.imu_rate_hz, "attitude": config.attitude_rate_hz, "gps": config.gps_rate_hz,
                          "status": config.status_rate_hz, "log": config.plan.log_rate_hz},
             "yaw_source": config.yaw_source, "events_s": fl.events, "calibration_applied_s": t_apply,
             "dropout": {"compass": config.dropout_compass, "after_s": config.dropout_after_s}
             if config.dropout_compass is not None else None,
             "current_A": {"max": float(fl.current_A.max()), "mean_flying": float(fl.current_A[fl.armed].mean())
                           if fl.armed.any() else 0.0},
             "compasses": [r.truth for r in recs],
             "time_base": "seconds from the first record of the log (t_s of groundstation.samples)"}
    return ArduSim(config, fl, att, recs, H, float(ef.declination_deg), t_apply, truth)


def positions_lla(sim: ArduSim) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(lat_deg, lon_deg, alt_m AMSL) of the flight."""
    lat0, lon0, alt0 = sim.config.origin
    lat, lon = lla_from_ned(sim.flight.pos_ned_m[:, 0], sim.flight.pos_ned_m[:, 1], lat0, lon0)
    return np.asarray(lat), np.asarray(lon), alt0 - sim.flight.pos_ned_m[:, 2]


def main(argv: list[str] | None = None) -> int:
    """python -m groundstation.sim.ardupilot --seed 1 --out flight.tlog [--bin timeus_split] [--no-dance]"""
    import argparse
    from dataclasses import replace

    from groundstation.sim.dataflash_writer import LAYOUTS
    ap = argparse.ArgumentParser(prog="python -m groundstation.sim.ardupilot", description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="ardupilot-sim.tlog", help="telemetry log to write (truth JSON beside it)")
    ap.add_argument("--bin", choices=sorted(LAYOUTS), help="also write the DataFlash log in this layout")
    ap.add_argument("--imu-rate", type=float, default=2.0, help="telemetry IMU rate [Hz]")
    ap.add_argument("--no-dance", action="store_true", help="no onboard calibration: stale offsets throughout")
    ap.add_argument("--independent-yaw", action="store_true", help="attitude yaw independent of the compasses")
    ap.add_argument("--dropout", type=int, choices=[0, 1, 2], help="this compass drops out after 200 s")
    a = ap.parse_args(argv)
    cfg = ArduSimConfig(seed=a.seed, imu_rate_hz=a.imu_rate, plan=replace(FlightPlan(), dance=not a.no_dance),
                        yaw_source="independent" if a.independent_yaw else "compass", dropout_compass=a.dropout)
    sim = simulate_ardupilot(cfg)
    p = sim.write_tlog(a.out)
    print(f"wrote {p} and {truth_path(p)} ({sim.flight.t_s[-1]:.0f} s)")
    if a.bin:
        out = Path(a.out)
        b = sim.write_bin(out.with_name(f"{out.stem}-{a.bin}.bin"), a.bin)     # its own truth JSON
        print(f"wrote {b} and {truth_path(b)}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
