"""Every compass of a log as the raw body-frame field, the autopilot's corrections un-applied as
they were in force at each sample (shared by calibrate and analyze).

ArduPilot streams and logs the corrected field and changes the corrections during a log (onboard
calibration, COMPASS_LEARN, parameter writes), so raw is rebuilt per sample from the parameter
history (FlightLog.param_history: PARAM_VALUE / PARM, SENSOR_OFFSETS, DataFlash MAG Ofs*) with
estimators.compass_corrections, motor compensation included (COMPASS_MOT* with the log's current
or throttle as COMPASS_MOTCT says, or the compensation the DataFlash log recorded).  PX4's
sensor_mag is raw sensor output (only rotated to the body frame here); vehicle_magnetometer is
corrected (CAL_MAGn_* un-applied per parameter segment).  A value first reported after the log
started is taken as in force from the start (what the vehicle was using before it said so).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estimators.compass_corrections import (ardupilot_param_names, apply_ardupilot_corrections, changes_summary,
                                            correction_matrices, corrections_from_param_changes,
                                            unapply_ardupilot_corrections)
from estimators.log_alignment import interp_series
from groundstation.io.params import (apply_px4, ardupilot_orientation, detect_autopilot, params_at, px4_matrix,
                                     px4_slot, unapply_px4)
from groundstation.samples import CompassTable, FlightLog

__all__ = ["CompassField", "compass_field", "compass_fields", "motor_signals", "reconciled_history", "MOTOR_SIGNAL_GAP_S"]

MOTOR_SIGNAL_GAP_S = 2.0     # current / throttle interpolated across gaps up to this long


@dataclass(frozen=True)
class CompassField:
    """One compass, raw and as the autopilot used it, on its own sample times.

    offsets_in_force_mG: (N,3) the autopilot's offsets in our convention (raw − b): ArduPilot
    −COMPASS_OFS, PX4 R·CAL_MAGn_OFF; nominal_matrix: the correction matrix in force at the end
    (ArduPilot DIA/ODI · SCALE, PX4 R S Rᵀ).  status: ok | partial (some samples without known
    corrections) | no_parameters (ArduPilot's corrected field but no COMPASS_OFS anywhere: raw
    cannot be rebuilt, the logged field stands in for it) | raw (no calibration parameters at all:
    the samples are taken as raw) | no_data.
    """
    compass: int
    source: str
    device_id: int | None
    autopilot: str | None
    t_s: np.ndarray
    logged_mG: np.ndarray
    raw_mG: np.ndarray
    in_force_mG: np.ndarray
    offsets_in_force_mG: np.ndarray
    nominal_matrix: np.ndarray
    status: str
    note: str
    changes: list               # [(t_s, offsets in the autopilot's convention)] when the offsets changed
    orientation_id: int | None  # COMPASS_ORIENTn / CAL_MAGn_ROT in use (ROTATION_* enum)
    px4_slot: int | None
    motor_in_force: dict        # {"type": COMPASS_MOTCT, "per_unit": COMPASS_MOT* at the end} (ArduPilot)

    @property
    def valid(self) -> np.ndarray:
        return np.all(np.isfinite(self.raw_mG), axis=1)


def motor_signals(log: FlightLog, t_s: np.ndarray) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(current A, throttle 0..1) at t_s (NaN in gaps > MOTOR_SIGNAL_GAP_S), None when not logged."""
    out = []
    for table in (log.battery, log.throttle):
        table = np.asarray(table, float).reshape(-1, 2)
        if len(table) < 2:
            out.append(None)
            continue
        v, _ = interp_series(t_s, table[:, 0], table[:, 1], max_gap_s=MOTOR_SIGNAL_GAP_S)
        out.append(v[:, 0])
    return out[0], out[1]


def reconciled_history(log: FlightLog) -> list[tuple[float, str, float]]:
    """The parameter history, reconciled with ``log.params``: a name the table holds but the history
    does not (a log built in memory), or with a value the history never had (the table edited after
    reading), takes the table's value throughout.  (The table holds the last PARAM_VALUE / PARM;
    a later SENSOR_OFFSETS report in the history is not a contradiction.)"""
    hist = list(log.param_history)
    values: dict[str, set] = {}
    for _, name, value in hist:
        values.setdefault(name, set()).add(value)
    override = {n: v for n, v in (log.params or {}).items() if n not in values or v not in values[n]}
    if override:
        hist = [h for h in hist if h[1] not in override] + [(-np.inf, n, v) for n, v in override.items()]
        hist.sort(key=lambda h: h[0])
    return hist


def _backfilled(hist: list[tuple[float, str, float]]) -> list[tuple[float, str, float]]:
    """Each name's first value moved to −inf: in force from the start of the log."""
    seen: set[str] = set()
    out = []
    for t, name, value in hist:
        out.append((-np.inf if name not in seen else t, name, value))
        seen.add(name)
    return out


def _field(table: CompassTable, autopilot, raw, in_force, ofs, M, status, note, changes=(), orient=None, slot=None,
           motor=None) -> CompassField:
    f = table.field
    return CompassField(table.compass, table.source, table.device_id, autopilot, f[:, 0].copy(), f[:, 1:4].copy(),
                        raw, in_force, ofs, M, status, note, list(changes), orient, slot, motor or {})


def _ardupilot(log: FlightLog, table: CompassTable, hist: list) -> CompassField:
    k = table.compass
    t, logged = table.field[:, 0], table.field[:, 1:4]
    names = ardupilot_param_names(k)
    params = dict(log.params)
    seen = {h[1] for h in hist}
    missing = [n for n in names["offsets"] if n not in seen]      # a partial set: the others are 0 (as ArduPilot's default)
    corr = corrections_from_param_changes(t, hist + [(-np.inf, n, 0.0) for n in missing], k)
    current, throttle = motor_signals(log, t)
    after = any(name.startswith("COMPASS_SCALE") for name in params) or not params
    if table.calibration_applied is False:
        raw = logged.copy()
        in_force = apply_ardupilot_corrections(raw, corr, current, throttle, after)
        status, note = "ok", "raw sensor samples; ArduPilot's corrections applied to show the field it used"
    else:
        rebuilt = unapply_ardupilot_corrections(logged, corr, current, throttle, table.motor_offset_mG, after)
        raw, in_force, status = rebuilt.raw_mG, logged.copy(), rebuilt.status
        ofs_txt = np.round(corr.offsets_mG[-1], 1).tolist() if len(t) else []
        note = (f"un-applied ArduPilot {names['offsets'][0][:-2]} (last {ofs_txt} mG), DIA/ODI, SCALE and motor "
                f"compensation as in force at each sample ({rebuilt.message})")
        if missing:
            note += f"; {', '.join(missing)} not in the log, taken as 0"
    n_changes = changes_summary(corr, t)
    if len(n_changes) > 1:
        note += f"; offsets changed {len(n_changes) - 1} time(s) during the log"
    M = correction_matrices(corr.diag[-1:], corr.offdiag[-1:])[0] if len(t) else np.eye(3)
    scale = float(corr.scale[-1]) if len(t) and np.isfinite(corr.scale[-1]) and corr.scale[-1] > 0 else 1.0
    motor = {"type": int(corr.motor_type[-1]) if len(t) else 0,
             "per_unit": corr.motor_per_unit[-1].tolist() if len(t) else [0.0, 0.0, 0.0]}
    return _field(table, "ardupilot", raw, in_force, -corr.offsets_mG, M * scale, status, note, n_changes,
                  ardupilot_orientation(params, k), None, motor)


def _px4_segments(log: FlightLog, t: np.ndarray, slot: int) -> list[tuple[np.ndarray, dict]]:
    """(sample mask, parameters in force) per stretch between changes of the slot's parameters."""
    prefix = (f"CAL_MAG{slot}_", "SENS_BOARD_")
    hist = reconciled_history(log)
    times = sorted({h[0] for h in hist if h[0] > 0 and h[1].startswith(prefix)})
    edges = [-np.inf] + times + [np.inf]
    out = []
    for a, b in zip(edges[:-1], edges[1:]):
        sel = (t >= a) & (t < b)
        if sel.any():
            out.append((sel, params_at(hist, max(a, 0.0), log.params)))
    return out


def _px4(log: FlightLog, table: CompassTable) -> CompassField:
    t, logged = table.field[:, 0], table.field[:, 1:4]
    slot = px4_slot(log.params, table.device_id, table.compass)
    raw, in_force, ofs = (np.full_like(logged, np.nan) for _ in range(3))
    M = np.eye(3)
    for sel, params in _px4_segments(log, t, slot):
        off, S, R = px4_matrix(params, slot)
        if table.calibration_applied is False:
            raw[sel] = logged[sel] @ R.T
            in_force[sel] = apply_px4(logged[sel], params, slot)
        else:
            raw[sel] = unapply_px4(logged[sel], params, slot)
            in_force[sel] = logged[sel]
        ofs[sel] = R @ off * 1000.0
        M = R @ S @ R.T
    rot = int(log.params.get(f"CAL_MAG{slot}_ROT", -1))
    orient = int(log.params.get("SENS_BOARD_ROT", 0)) if rot < 0 else (rot if rot != 100 else None)
    what = ("raw sensor samples rotated to the body frame" if table.calibration_applied is False
            else "un-applied PX4 offsets and scale matrix")
    return _field(table, "px4", raw, in_force, ofs, M, "ok", f"{what} (CAL_MAG{slot}, parameters in force per segment)",
                  orient=orient, slot=slot)


def _plain(log: FlightLog, table: CompassTable, autopilot, status: str, note: str) -> CompassField:
    f = table.field[:, 1:4]
    return _field(table, autopilot, f.copy(), f.copy(), np.zeros_like(f), np.eye(3), status, note)


def compass_field(log: FlightLog, table: CompassTable) -> CompassField:
    """One compass's raw field with the corrections in force un-applied (see the module docstring)."""
    params = log.params or {}
    ap = log.autopilot or detect_autopilot(params)
    hist = _backfilled(reconciled_history(log))
    if not len(table.field):
        return _plain(log, table, ap, "no_data", "no samples")
    if ap == "ardupilot" and any(h[1] in ardupilot_param_names(table.compass)["offsets"] for h in hist):
        return _ardupilot(log, table, hist)
    if ap == "px4" and any(k.startswith("CAL_MAG") for k in params):
        return _px4(log, table)
    if ap == "ardupilot" and table.calibration_applied:
        return _plain(log, table, ap, "no_parameters",
                      f"ArduPilot logs the corrected field but the log holds no "
                      f"{ardupilot_param_names(table.compass)['offsets'][0][:-2]}_* values: raw cannot be rebuilt")
    return _plain(log, table, ap, "raw", "no onboard calibration parameters found; samples used as raw")


def compass_fields(log: FlightLog) -> list[CompassField]:
    """Every compass of the log (FlightLog.compass_tables), in compass order."""
    return [compass_field(log, table) for table in sorted(log.compass_tables(), key=lambda c: c.compass)]
