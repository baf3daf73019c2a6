"""Autopilot compass-calibration parameter conventions (ArduPilot COMPASS_*, PX4 CAL_MAGn_*).

Our calibration:  m_cal = C · (m_raw − b)   (field in mG, C dimensionless).

ArduPilot (AP_Compass_Backend::correct_field, read in the ArduPilot source):
    the driver first rotates the sensor reading into the body frame (COMPASS_ORIENT, board
    orientation), then  corrected = M · (SCALE · (rot_raw + OFS)),
    M = [[DIA_X, ODI_X, ODI_Y], [ODI_X, DIA_Y, ODI_Z], [ODI_Y, ODI_Z, DIA_Z]],
    OFS in mG and *added*; SCALE (COMPASS_SCALE) used only when set (> 0); DIA all zero means 1.
    Motor compensation (COMPASS_MOT_*) is not modelled here.
    Our "raw" for ArduPilot is rot_raw (orientation applied, calibration not), so
    OFS = −b,  M = k·S (symmetric part of C, scaled),  SCALE = 1.  COMPASS_ORIENT is left as it is.

PX4 (calibration::Magnetometer::Correct in the PX4 source):
    corrected = R · (S · (raw − off)),  raw and off in gauss, S = [[XSCALE, XODIAG, YODIAG],
    [XODIAG, YSCALE, ZODIAG], [YODIAG, ZODIAG, ZSCALE]], R from CAL_MAGn_ROT (enum; 100 =
    custom CAL_MAGn_ROLL/PITCH/YAW in degrees; −1 = internal sensor: board rotation
    SENS_BOARD_ROT with SENS_BOARD_X/Y/Z_OFF).  Power compensation (CAL_MAGn_*COMP) is ignored.
    Our "raw" for PX4 is R·raw (body-aligned, uncalibrated): raw_ours = R S⁻¹ Rᵀ m_corr + R off.
    Export: off = Rᵀ b / 1000 (gauss), S = Rᵀ C_sym R, so R·S·(raw − off) = C_sym (raw_ours − b).

Field scale (``wmm_scale``): our fit normalises C to determinant 1, so |C (raw − b)| is the fitted
radius, not the Earth's field.  ArduPilot's calibrator scales its result to the WMM intensity at the
vehicle (CompassCalibrator::fix_radius: scale = WMM intensity / fitted radius, refused outside
COMPASS_MIN/MAX_SCALE_FACTOR 1/1.5 … 1.5, left unscaled without a position); the export does the
same, k = WMM / radius, folded into DIA/ODI (and PX4's *SCALE/*ODIAG) with COMPASS_SCALE 1, so the
corrected field's length is the WMM intensity and DIA/ODI equal the true soft-iron matrix.

If C is not symmetric (misalignment estimated), C = R_mis · S (``polar_decomposition``):
S goes to DIA/ODI or SCALE/ODIAG, R_mis is reported separately (misalignment) and is *not*
folded silently into the symmetric parameters.
"""
from __future__ import annotations

import math
import re

import numpy as np

from estimators.calibration import polar_decomposition
from estimators.compass_corrections import ardupilot_param_names
from estimators.rotations import dcm_body_to_ned

MG_PER_GAUSS = 1000.0
SCALE_FACTOR_LIMITS = (1.0 / 1.5, 1.5)    # ArduPilot COMPASS_MIN/MAX_SCALE_FACTOR (AP_Compass_config.h)

# PX4 / ArduPilot rotation enum -> (roll, pitch, yaw) in degrees; both share 0..37.
_ROTATIONS_DEG = [
    (0, 0, 0), (0, 0, 45), (0, 0, 90), (0, 0, 135), (0, 0, 180), (0, 0, 225), (0, 0, 270), (0, 0, 315),
    (180, 0, 0), (180, 0, 45), (180, 0, 90), (180, 0, 135), (0, 180, 0), (180, 0, 225), (180, 0, 270),
    (180, 0, 315), (90, 0, 0), (90, 0, 45), (90, 0, 90), (90, 0, 135), (270, 0, 0), (270, 0, 45),
    (270, 0, 90), (270, 0, 135), (0, 90, 0), (0, 270, 0), (0, 180, 90), (0, 180, 270), (90, 90, 0),
    (180, 90, 0), (270, 90, 0), (90, 180, 0), (270, 180, 0), (90, 270, 0), (180, 270, 0), (270, 270, 0),
    (90, 180, 90), (90, 0, 270),
]


# ------------------------------------------------------------------------- trusted values
# One table of the values a compass parameter can hold: (pattern, low, high, also allowed, source).
# ArduPilot (AP_Compass.cpp @Range, CompassCalibrator.cpp): COMPASS_OFS* documents ±400 mG, but the
# vehicle's own calibrator stores offsets up to COMPASS_OFFS_MAX, whose documented range ends at 3000;
# DIA 0.2–5 and ODI ±1 are CompassCalibrator::fit_acceptable's limits (DIA 0 means "unset" = 1);
# COMPASS_SCALE 0 (unused) or up to COMPASS_MAX_SCALE_FACTOR 1.5; COMPASS_MOT* ±1000 mG/A;
# COMPASS_DEC ±3.142 rad; COMPASS_ORIENT* the ROTATION_* values 0–43 and 100–102.
# PX4 (CAL_MAGn_*) documents no bounds for its calibration values; the same physical limits are used
# in its units (gauss): offsets ±3 G, scales 0.2–5, off-diagonals ±1, CAL_MAGn_ROT −1 (internal) to 100.
PARAM_RANGES: tuple[tuple[str, float, float, tuple[float, ...], str], ...] = (
    (r"COMPASS_OFS[23]?_[XYZ]", -3000.0, 3000.0, (), "mG, up to COMPASS_OFFS_MAX's 3000"),
    (r"COMPASS_DIA[23]?_[XYZ]", 0.2, 5.0, (0.0,), "CompassCalibrator fit_acceptable"),
    (r"COMPASS_ODI[23]?_[XYZ]", -1.0, 1.0, (), "CompassCalibrator fit_acceptable"),
    (r"COMPASS_SCALE[23]?", SCALE_FACTOR_LIMITS[0], SCALE_FACTOR_LIMITS[1], (0.0,), "COMPASS_MAX_SCALE_FACTOR"),
    (r"COMPASS_MOT[23]?_[XYZ]", -1000.0, 1000.0, (), "mG/A, AP_Compass @Range"),
    (r"COMPASS_DEC", -3.142, 3.142, (), "rad, AP_Compass @Range"),
    (r"COMPASS_ORIENT[23]?", 0.0, 43.0, (100.0, 101.0, 102.0), "ROTATION_* values"),
    (r"CAL_MAG\d_[XYZ]OFF", -3.0, 3.0, (), "gauss"),
    (r"CAL_MAG\d_[XYZ]SCALE", 0.2, 5.0, (), "scale factor"),
    (r"CAL_MAG\d_[XYZ]ODIAG", -1.0, 1.0, (), "off-diagonal"),
    (r"CAL_MAG\d_ROT", -1.0, 100.0, (), "rotation enum, -1 internal"),
)
_RANGES = [(re.compile(p + r"\Z"), lo, hi, extra, src) for p, lo, hi, extra, src in PARAM_RANGES]


def param_value_problem(name: str, value) -> str | None:
    """Why a parameter value cannot be true (None: it can): not a number, NaN or infinite (any
    parameter), or outside ``PARAM_RANGES`` (compass parameters).  The one check used for the live
    parameter cache, the parameters read from logs and ``.param`` files, and ``info``."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        return f"{name}: not a number ({value!r})"
    if not math.isfinite(v):
        return f"{name}: {v} is not a finite number"
    if abs(v) >= 1e30:                 # 3.4e38 is float32's largest: an unset or corrupted value
        return f"{name}: {v:.3g} is absurd"
    for pattern, lo, hi, extra, src in _RANGES:
        if pattern.match(name):
            if not (lo <= v <= hi or v in extra):
                return f"{name}: {v:.6g} is outside {lo:g}…{hi:g} ({src})"
            return None
    return None


def trusted_params(params: dict[str, float]) -> tuple[dict[str, float], list[str]]:
    """(the values ``param_value_problem`` accepts, one line per value refused)."""
    kept, refused = {}, []
    for name, value in params.items():
        problem = param_value_problem(name, value)
        if problem is None:
            kept[name] = float(value)
        else:
            refused.append(problem)
    return kept, refused


def _rpy_matrix(rpy_deg) -> np.ndarray:
    r, p, y = np.radians(rpy_deg)
    R = dcm_body_to_ned(r, p, y)
    return np.where(np.abs(R) < 1e-12, 0.0, R)


def _read_only(m: np.ndarray) -> np.ndarray:
    m.flags.writeable = False
    return m


# the table's matrices, made once: the fake autopilot turns every sample of every compass by one
_ENUM_MATRICES = tuple(_read_only(_rpy_matrix(rpy)) for rpy in _ROTATIONS_DEG)


def rotation_enum_matrix(rot: int, custom_rpy_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> np.ndarray:
    """Rotation matrix of a PX4/ArduPilot ``Rotation`` enum (v' = R v, R = Rz(yaw) Ry(pitch) Rx(roll)),
    read-only.  100 = custom roll/pitch/yaw.  Raises ValueError for enums not in the table."""
    rot = int(rot)
    if rot == 100:
        return _read_only(_rpy_matrix(custom_rpy_deg))
    if 0 <= rot < len(_ENUM_MATRICES):
        return _ENUM_MATRICES[rot]
    raise ValueError(f"unsupported rotation enum {rot}")


def detect_autopilot(params: dict[str, float]) -> str | None:
    if any(k.startswith("COMPASS_") for k in params):
        return "ardupilot"
    if any(k.startswith("CAL_MAG") for k in params):
        return "px4"
    return None


def wmm_scale(fitted_field_mG: float | None, expected_field_mG: float | None) -> float:
    """k = WMM intensity / fitted radius (ArduPilot's fix_radius), the factor the exported soft-iron
    matrix takes so the corrected field has the WMM's length; 1.0 when either is unknown or not
    finite, or k is outside ``SCALE_FACTOR_LIMITS`` (ArduPilot refuses such a radius: the
    calibration's own checks report it, the export does not hide it in a scale)."""
    try:
        fitted, expected = float(fitted_field_mG), float(expected_field_mG)
    except (TypeError, ValueError):
        return 1.0
    if not (np.isfinite(fitted) and np.isfinite(expected)) or fitted <= 0 or expected <= 0:
        return 1.0
    k = expected / fitted
    return k if SCALE_FACTOR_LIMITS[0] <= k <= SCALE_FACTOR_LIMITS[1] else 1.0


# ------------------------------------------------------------------------------------ ArduPilot

def ardupilot_never_calibrated(params: dict[str, float]) -> bool:
    """COMPASS_OFS_X/Y/Z all present and 0: the compass was never calibrated (a calibrated one
    has non-zero offsets), so ArduPilot's 'corrected' field is the raw sensor output."""
    ofs = [params.get(f"COMPASS_OFS_{a}") for a in "XYZ"]
    return all(v is not None and v == 0.0 for v in ofs)


def ardupilot_matrix(params: dict[str, float], instance: int = 0) -> tuple[np.ndarray, np.ndarray, float]:
    """(OFS mG, M, SCALE) of compass ``instance`` (0 = COMPASS_OFS_*, 1 = COMPASS_OFS2_* ...; the
    names of estimators.compass_corrections.ardupilot_param_names, the one definition)."""
    names = ardupilot_param_names(instance)
    ofs = np.array([float(params.get(k, 0.0)) for k in names["offsets"]])
    dia = np.array([float(params.get(k, 0.0)) for k in names["diag"]])
    odi = np.array([float(params.get(k, 0.0)) for k in names["offdiag"]])
    if np.all(dia == 0):
        dia = np.ones(3)
    M = np.array([[dia[0], odi[0], odi[1]], [odi[0], dia[1], odi[2]], [odi[1], odi[2], dia[2]]])
    scale = float(params.get(names["scale"][0], 0.0))
    return ofs, M, (scale if scale > 0 else 1.0)


def ardupilot_orientation(params: dict[str, float], instance: int = 0) -> int:
    """COMPASS_ORIENT / COMPASS_ORIENT2 / ... of compass ``instance`` (ROTATION_* enum, default 0)."""
    return int(params.get("COMPASS_ORIENT" + ("" if instance == 0 else str(instance + 1)), 0))


def ardupilot_has_offsets(params: dict[str, float], instance: int = 0) -> bool:
    return all(k in params for k in ardupilot_param_names(instance)["offsets"])


def apply_ardupilot(raw_mG: np.ndarray, params: dict[str, float], instance: int = 0) -> np.ndarray:
    """ArduPilot's correction: M · (SCALE · (raw + OFS))."""
    ofs, M, scale = ardupilot_matrix(params, instance)
    return (scale * (np.asarray(raw_mG, float) + ofs)) @ M.T


def unapply_ardupilot(corrected_mG: np.ndarray, params: dict[str, float], instance: int = 0) -> np.ndarray:
    """Inverse of ``apply_ardupilot``: raw = M⁻¹ corrected / SCALE − OFS."""
    ofs, M, scale = ardupilot_matrix(params, instance)
    return np.asarray(corrected_mG, float) @ np.linalg.inv(M).T / scale - ofs


def ardupilot_params_from_calibration(offsets_mG: np.ndarray, matrix: np.ndarray, instance: int = 0,
                                      scale: float = 1.0) -> dict[str, float]:
    """COMPASS_OFS/DIA/ODI/SCALE for m_cal = scale · S (raw − b) (``scale``: ``wmm_scale``); the
    rotation part of a non-symmetric C is dropped here (report it as misalignment)."""
    _, S = polar_decomposition(matrix)
    S = float(scale) * S
    names = ardupilot_param_names(instance)
    b = np.asarray(offsets_mG, float)
    out: dict[str, float] = {}
    for i, k in enumerate(names["offsets"]):
        out[k] = float(-b[i])
    for i, k in enumerate(names["diag"]):
        out[k] = float(S[i, i])
    for k, (i, j) in zip(names["offdiag"], ((0, 1), (0, 2), (1, 2))):
        out[k] = float(S[i, j])
    out[names["scale"][0]] = 1.0
    return out


# ------------------------------------------------------------------------------------------ PX4

def px4_slot(params: dict[str, float], device_id: int | None = None, default: int = 0) -> int:
    """Calibration slot n of CAL_MAGn_*: the one whose CAL_MAGn_ID matches ``device_id`` or
    CAL_MAG_PRIME, else ``default``."""
    want = device_id if device_id is not None else params.get("CAL_MAG_PRIME")
    if want:
        for n in range(4):
            if int(params.get(f"CAL_MAG{n}_ID", -1)) == int(want):
                return n
    return default


def px4_rotation(params: dict[str, float], slot: int = 0) -> np.ndarray:
    rot = int(params.get(f"CAL_MAG{slot}_ROT", -1))
    if rot < 0:  # internal sensor: board rotation
        R = rotation_enum_matrix(int(params.get("SENS_BOARD_ROT", 0)))
        off = np.radians([float(params.get(f"SENS_BOARD_{a}_OFF", 0.0)) for a in "XYZ"])
        return dcm_body_to_ned(*off) @ R
    custom = tuple(float(params.get(f"CAL_MAG{slot}_{a}", 0.0)) for a in ("ROLL", "PITCH", "YAW"))
    return rotation_enum_matrix(rot, custom)


def px4_matrix(params: dict[str, float], slot: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(offsets gauss, S, R) of slot n."""
    p = lambda k, d: float(params.get(f"CAL_MAG{slot}_{k}", d))
    off = np.array([p("XOFF", 0.0), p("YOFF", 0.0), p("ZOFF", 0.0)])
    d = [p("XSCALE", 1.0), p("YSCALE", 1.0), p("ZSCALE", 1.0)]
    o = [p("XODIAG", 0.0), p("YODIAG", 0.0), p("ZODIAG", 0.0)]
    S = np.array([[d[0], o[0], o[1]], [o[0], d[1], o[2]], [o[1], o[2], d[2]]])
    return off, S, px4_rotation(params, slot)


def apply_px4(raw_sensor_mG: np.ndarray, params: dict[str, float], slot: int = 0) -> np.ndarray:
    """PX4's correction on a sensor-frame reading: R · S · (raw − off), in mG."""
    off, S, R = px4_matrix(params, slot)
    return (np.asarray(raw_sensor_mG, float) / MG_PER_GAUSS - off) @ (R @ S).T * MG_PER_GAUSS


def unapply_px4(corrected_mG: np.ndarray, params: dict[str, float], slot: int = 0) -> np.ndarray:
    """Recover body-aligned raw (R · raw_sensor, mG) from PX4-corrected samples:
    R (S⁻¹ Rᵀ m + off)."""
    off, S, R = px4_matrix(params, slot)
    m = np.asarray(corrected_mG, float) / MG_PER_GAUSS
    raw_sensor = m @ (np.linalg.inv(S) @ R.T).T + off
    return raw_sensor @ R.T * MG_PER_GAUSS


def px4_params_from_calibration(offsets_mG: np.ndarray, matrix: np.ndarray, slot: int = 0,
                                rotation: np.ndarray | None = None, scale: float = 1.0) -> dict[str, float]:
    """CAL_MAGn_{X,Y,Z}OFF (gauss), *SCALE, *ODIAG for m_cal = scale · S (raw_body − b), raw_body =
    R raw_sensor (``scale``: ``wmm_scale``).  The rotation part of a non-symmetric C is dropped
    (report it as misalignment)."""
    _, S = polar_decomposition(matrix)
    S = float(scale) * S
    R = np.eye(3) if rotation is None else np.asarray(rotation, float)
    off = R.T @ np.asarray(offsets_mG, float) / MG_PER_GAUSS
    Ss = R.T @ S @ R
    out: dict[str, float] = {}
    for i, a in enumerate("XYZ"):
        out[f"CAL_MAG{slot}_{a}OFF"] = float(off[i])
    for i, a in enumerate("XYZ"):
        out[f"CAL_MAG{slot}_{a}SCALE"] = float(Ss[i, i])
    out[f"CAL_MAG{slot}_XODIAG"] = float(Ss[0, 1])
    out[f"CAL_MAG{slot}_YODIAG"] = float(Ss[0, 2])
    out[f"CAL_MAG{slot}_ZODIAG"] = float(Ss[1, 2])
    return out


# ------------------------------------------------------------------------------------- generic

def unapply_onboard_calibration(mag_mG: np.ndarray, params: dict[str, float], autopilot: str | None = None,
                                applied: bool | None = None) -> tuple[np.ndarray, str]:
    """Log samples -> body-aligned raw samples, with a one-line note of what was done.

    ``applied`` is FlightLog.mag_calibration_applied: True (corrected field: un-apply), False
    (raw sensor output: PX4 sensor_mag is only rotated into the body frame by CAL_MAGn_ROT /
    board rotation), None (unknown: un-apply when calibration parameters are present).
    """
    ap = autopilot or detect_autopilot(params)
    if applied is False:
        if ap == "px4" and any(k.startswith("CAL_MAG") for k in params):
            slot = px4_slot(params)
            R = px4_rotation(params, slot)
            return np.asarray(mag_mG, float) @ R.T, f"raw sensor samples rotated to body frame (CAL_MAG{slot})"
        return np.asarray(mag_mG, float), "raw sensor samples"
    if ap == "ardupilot" and any(k.startswith("COMPASS_OFS") for k in params):
        ofs, M, scale = ardupilot_matrix(params)
        return unapply_ardupilot(mag_mG, params), (
            f"un-applied ArduPilot COMPASS_OFS {np.round(ofs, 1).tolist()} mG, DIA/ODI, SCALE {scale:g}")
    if ap == "px4" and any(k.startswith("CAL_MAG") for k in params):
        slot = px4_slot(params)
        off, S, R = px4_matrix(params, slot)
        return unapply_px4(mag_mG, params, slot), (
            f"un-applied PX4 CAL_MAG{slot} offsets {np.round(off * MG_PER_GAUSS, 1).tolist()} mG and scale matrix")
    return np.asarray(mag_mG, float), "no onboard calibration parameters found; samples used as raw"


def export_params(offsets_mG: np.ndarray, matrix: np.ndarray, params: dict[str, float] | None = None, *,
                  compass: int = 0, device_id: int | None = None, scale: float = 1.0
                  ) -> tuple[dict[str, float], dict[str, float]]:
    """(ArduPilot params, PX4 params) for a calibration in the body-aligned raw frame of compass
    ``compass`` (COMPASS_OFS{n}_*); the PX4 slot (CAL_MAG{slot}_*: the one whose CAL_MAGn_ID is the
    device id, else the compass number) and sensor rotation follow the log's parameters.
    ``scale``: ``wmm_scale`` of the fit (the corrected field's length becomes the WMM's)."""
    params = params or {}
    ap = ardupilot_params_from_calibration(offsets_mG, matrix, compass, scale)
    has_px4 = any(k.startswith("CAL_MAG") for k in params)
    if device_id is not None or compass:
        slot = px4_slot(params, device_id, compass) if has_px4 else compass
    else:
        slot = px4_slot(params) if has_px4 else 0
    try:
        R = px4_rotation(params, slot) if has_px4 else np.eye(3)
    except ValueError:
        R = np.eye(3)
    return ap, px4_params_from_calibration(offsets_mG, matrix, slot, R, scale)


def format_param_file(values: dict[str, float], style: str = "comma") -> str:
    """``NAME,VALUE`` lines (style "comma", MAVProxy/ArduPilot .param) or ``NAME VALUE``
    (style "space", Mission Planner)."""
    sep = "," if style == "comma" else " "
    return "".join(f"{k}{sep}{v:.7g}\n" for k, v in sorted(values.items()))


def params_at(history: list[tuple[float, str, float]], t_s: float, base: dict[str, float] | None = None
              ) -> dict[str, float]:
    """The parameters in force at t_s: ``base`` (e.g. FlightLog.params) overlaid with every
    history value set at or before t_s; a name first seen later keeps its first value (the best
    knowledge of what was in force before it was reported)."""
    out = dict(base or {})
    seen: set[str] = set()
    for t, name, value in sorted(history, key=lambda h: h[0]):
        if t <= t_s or name not in seen:
            out[name] = value
            seen.add(name)
    return out
