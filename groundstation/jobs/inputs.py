"""Detector inputs on the IMU time base, one definition for the batch form and the live form.

``detection_inputs(log, calibration, mission, settings)`` is the batch form (a whole FlightLog);
``groundstation.jobs.live.LiveAnalyzer`` is the per-sample form.  Both build their inputs from
the same pieces, so a log gives the same alarms replayed, streamed live or analysed:

* ``field_policy``: what the magnetometer samples are (autopilot-corrected, station-corrected,
  raw) and how they become the calibrated field (un-apply the autopilot's own calibration, then
  apply ours), and whether the field test may run;
* ``gps_rows``: per GPS sample the cross-track to the nearest mission leg (signed, + right of
  A->B), RTK trust, position and velocity;
* ``hold_last``: the latest value at or before each IMU step within a timeout (live: ``Held``
  calls it on its latest value);
* ``imu_rate_hz``: the IMU rate from the median of the last RATE_WINDOW intervals (the heading
  test needs ``min_imu_rate_hz``);
* ``step_inputs``: heading difference, field strength/inclination, steep-attitude gate and
  turn rate on the IMU steps, carrying its gate state (``StepState``) from call to call; the tilt
  of the field tests comes from ``groundstation.jobs.tilt`` (re-exported here).
"""
from __future__ import annotations

import statistics
import time
from dataclasses import dataclass, field

import numpy as np

from estimators.detection import DetectionSettings, cross_track_m, field_inclination_deg, ned_from_lla
from estimators.field_consistency import field_consistency
from estimators.geomag import decimal_year_from_unix, earth_field
from estimators.heading import run_heading_chain
from estimators.low_pass import low_pass_state
from estimators.residual_trackers import MOTOR_TIMEOUT_S   # the one motor-signal timeout
from estimators.rotations import wrap_angle_rad

from groundstation.io.params import ardupilot_never_calibrated, unapply_onboard_calibration
from groundstation.jobs.calibration_check import calibration_arrays
from groundstation.jobs.compass_raw import compass_field
from groundstation.jobs.field_forward import field_at_steps, reading_times
from groundstation.jobs.tilt import TILT_AGREE_DEG, TILT_GAP_S, TILT_JUMP_DEG, brought_forward, checked_tilt
from groundstation.samples import CompassTable, FlightLog, finite_or_none

__all__ = ["detection_inputs", "primary_raw", "primary_field", "mission_legs",
           "cross_track_legs", "hold_last", "Held", "field_reference", "field_policy", "FieldPolicy", "gps_rows",
           "GPS_COLUMNS", "imu_rate_hz", "step_inputs", "StepState", "too_steep", "rotation_rate", "rounded",
           "checked_tilt", "brought_forward", "TILT_AGREE_DEG", "TILT_GAP_S", "TILT_JUMP_DEG",
           "heading_deg", "GPS_TIMEOUT_S", "ATTITUDE_TIMEOUT_S", "RATE_WINDOW", "vector_test_inputs", "earth_prior_mG",
           "motor_signal_table", "MOTOR_TIMEOUT_S"]

GPS_TIMEOUT_S = 1.0          # a GPS or magnetometer value older than this is not used
ATTITUDE_TIMEOUT_S = 0.5     # the autopilot's roll/pitch, for the field inclination and the steep gate
RATE_WINDOW = 25             # IMU intervals in the rolling rate estimate
GPS_COLUMNS = ("cross_track_m", "cross_track_signed_m", "trusted", "lat_deg", "lon_deg", "vn_mps", "ve_mps",
               "fix_type", "alt_m")


def heading_deg(heading_rad) -> np.ndarray:
    """Heading in degrees in [0, 360) (``np.mod(-tiny, 360)`` is 360.0: folded to 0)."""
    d = np.mod(np.degrees(np.asarray(heading_rad, dtype=float)), 360.0)
    return np.where(d >= 360.0, 0.0, d)


def primary_field(log: FlightLog):
    """The primary compass (jobs.compass_raw.CompassField) on the rows of ``log.mag``."""
    mag = np.asarray(log.mag, dtype=float).reshape(-1, 4)
    same = [c for c in log.compasses if c.compass == log.primary_compass and c.field is log.mag]
    table = CompassTable(log.primary_compass, mag, "mag", None, log.mag_calibration_applied,
                         same[0].motor_offset_mG if same else None)
    return compass_field(log, table)


def primary_raw(log: FlightLog) -> np.ndarray:
    """The primary compass's raw field (N,3), corrections in force un-applied (``primary_field``)."""
    return primary_field(log).raw_mG


# ----------------------------------------------------------------------------- the field
@dataclass(frozen=True)
class FieldPolicy:
    """What the magnetometer samples of a source are and what the station does with them.

    correction:  "station" (our calibration, applied to the un-applied raw field),
                 "autopilot" (the autopilot's own calibration, as it sent the field),
                 "raw" (the sensor output: never calibrated, or raw samples), "none" (no field).
    field_test:  "on" or "off: <why>".
    note:        one line for people.
    """
    correction: str
    field_test: str
    note: str
    cal: tuple[np.ndarray, np.ndarray] | None = None
    params: dict = field(default_factory=dict)
    autopilot: str | None = None
    applied: bool | None = None
    affine: tuple[np.ndarray, np.ndarray] | None = None    # (A, b): field = A m + b, None: as sent

    @property
    def field_on(self) -> bool:
        return self.field_test == "on"

    @property
    def heading_usable(self) -> bool:
        """The compass heading can be a test's evidence: never on the raw output of a sensor that
        was never calibrated, whose heading error swings by tens of degrees with the heading (a
        turn would look like interference)."""
        return self.correction not in ("none", "raw")

    def apply(self, mag_mG: np.ndarray) -> np.ndarray:
        """Samples (n, 3) as the source sent them -> the field the estimators use (n, 3)."""
        m = np.asarray(mag_mG, dtype=float).reshape(-1, 3)
        if self.affine is None:
            return m.copy()
        return m @ self.affine[0].T + self.affine[1]


def _station_affine(cal, params, autopilot, applied) -> tuple[np.ndarray, np.ndarray]:
    """Un-applying the autopilot's calibration and applying ours is affine: (A, b) of the whole."""
    basis = np.vstack([np.zeros(3), np.eye(3)])
    raw, _ = unapply_onboard_calibration(basis, params, autopilot, applied)
    out = (raw - cal[0]) @ cal[1].T
    return (out[1:] - out[0]).T.copy(), out[0].copy()


def field_policy(calibration: dict | None, params: dict[str, float], autopilot: str | None,
                 applied: bool | None, has_mag: bool = True) -> FieldPolicy:
    """The one rule for the field of a source (batch: the log's; live: what has arrived so far).

    ``applied`` is FlightLog.mag_calibration_applied (live: True for ArduPilot, which sends the
    corrected field, as ``groundstation.io.logs.tlog`` records it)."""
    cal = calibration_arrays(calibration)
    common = dict(params=dict(params), autopilot=autopilot, applied=applied)
    if not has_mag:
        return FieldPolicy("none", "off: no magnetometer data in the log", "no magnetometer samples", **common)
    if cal is not None:
        return FieldPolicy("station", "on", "station-corrected: this station's calibration, applied to the "
                           "raw field (the autopilot's own calibration un-applied first)", cal=cal,
                           affine=_station_affine(cal, params, autopilot, applied), **common)
    if applied is False or ardupilot_never_calibrated(params):
        return FieldPolicy("raw", "off: magnetometer not calibrated (give a calibration; the source has no "
                           "onboard offsets)", "raw: the sensor's output, no calibration on board or here", **common)
    if applied or autopilot in ("ardupilot", "px4"):
        who = {"ardupilot": "ArduPilot", "px4": "PX4"}.get(autopilot or "", "the autopilot")
        return FieldPolicy("autopilot", "on", f"autopilot-corrected: {who} applies its own compass calibration",
                           **common)
    return FieldPolicy("unknown", "on", "unknown: no autopilot or calibration information yet", **common)


def field_reference(log: FlightLog):
    """WMM at the log's median GPS position and date (None when the position is unknown)."""
    g = log.gps
    if not len(g):
        return None, None
    lat, lon, alt = float(np.median(g[:, 1])), float(np.median(g[:, 2])), float(np.median(g[:, 3]))
    start = log.start_unix_s if log.start_unix_s else time.time()
    try:
        return earth_field(lat, lon, alt, decimal_year_from_unix(start)), (lat, lon, alt)
    except ValueError:
        return None, None


# ----------------------------------------------------------------------------- the path
def mission_legs(points: list | None) -> list[tuple[tuple[float, float], tuple[float, float]]]:
    """Consecutive waypoint pairs [(A, B), ...] as (lat, lon) tuples; empty if fewer than two."""
    pts = [(float(p[0]), float(p[1])) for p in (points or []) if len(p) >= 2
           and np.isfinite(p[0]) and np.isfinite(p[1])]
    return [(pts[k], pts[k + 1]) for k in range(len(pts) - 1) if pts[k] != pts[k + 1]]


def cross_track_legs(lat, lon, legs, origin, signed: bool = False) -> np.ndarray:
    """Horizontal seed 002 eq. (6) distance to the nearest leg (chosen by distance to the
    segment); ``signed``: + right of that leg's A->B."""
    n, e = ned_from_lla(np.atleast_1d(lat), np.atleast_1d(lon), origin[0], origin[1])
    x = np.stack([n, e, np.zeros_like(n)], axis=1)
    best_seg = np.full(len(x), np.inf)
    best_d = np.full(len(x), np.nan)
    for (a, b) in legs:
        an, ae = ned_from_lla(a[0], a[1], origin[0], origin[1])
        bn, be = ned_from_lla(b[0], b[1], origin[0], origin[1])
        A, B = np.array([an, ae, 0.0]), np.array([bn, be, 0.0])
        ab = B - A
        u = np.clip(((x - A) @ ab) / max(ab @ ab, 1e-12), 0.0, 1.0)
        seg = np.linalg.norm(x - (A + u[:, None] * ab), axis=1)
        d = cross_track_m(x, A, B)
        if signed:
            d = np.where(ab[0] * (x[:, 1] - A[1]) - ab[1] * (x[:, 0] - A[0]) < 0, -d, d)
        better = seg < best_seg
        best_seg = np.where(better, seg, best_seg)
        best_d = np.where(better, d, best_d)
    return best_d


def gps_rows(gps: np.ndarray, legs: list, settings: DetectionSettings) -> np.ndarray:
    """GPS table rows [t, lat, lon, alt, vn, ve, vd, fix] -> GPS_COLUMNS per row (same for one
    row live and a whole log)."""
    g = np.asarray(gps, dtype=float).reshape(-1, 8)
    out = np.full((len(g), len(GPS_COLUMNS)), np.nan)
    if not len(g):
        return out
    if legs:
        out[:, 1] = cross_track_legs(g[:, 1], g[:, 2], legs, legs[0][0], signed=True)
        out[:, 0] = np.abs(out[:, 1])
    out[:, 2] = (g[:, 7] >= settings.rtk_min_fix).astype(float)
    out[:, 3:7] = g[:, [1, 2, 4, 5]]
    out[:, 7] = g[:, 7]
    out[:, 8] = g[:, 3]
    return out


# ----------------------------------------------------------------------------- holds and rates
def hold_last(t_src: np.ndarray, v_src: np.ndarray, t: np.ndarray, timeout_s: float) -> np.ndarray:
    """Latest source value at or before each t (NaN when none within timeout)."""
    v_src = np.asarray(v_src, dtype=float)
    out_shape = (len(t),) + v_src.shape[1:]
    if len(t_src) == 0:
        return np.full(out_shape, np.nan)
    idx = np.searchsorted(t_src, t, side="right") - 1
    ok = (idx >= 0) & (t - t_src[np.maximum(idx, 0)] <= timeout_s)
    out = v_src[np.maximum(idx, 0)]          # a new float array (fancy indexing copies): no astype copy
    out[~ok] = np.nan
    return out


class Held:
    """The live form of ``hold_last``: the latest value of one stream, read at a later time (a
    value older than the one held is ignored: it is never the latest at a later step)."""

    def __init__(self, width: int, timeout_s: float) -> None:
        self.timeout_s = timeout_s
        self._t: float | None = None
        self._v = self._nan = np.full((1, width), np.nan)

    def update(self, t_s: float, value) -> None:
        if self._t is not None and float(t_s) < self._t:
            return
        self._t = float(t_s)
        self._v = np.asarray(value, dtype=float).reshape(1, -1)

    def fresh(self, t_s: float) -> bool:
        """A value was received at or before t_s within the timeout (``hold_last``'s rule)."""
        return self._t is not None and self._t <= t_s and t_s - self._t <= self.timeout_s

    def at(self, t_s: float) -> np.ndarray:
        """(1, width): the value if ``fresh`` at t_s, else NaN (``hold_last``'s rule on one value)."""
        return self._v if self.fresh(t_s) else self._nan

    def time_at(self, t_s: float) -> float:
        """The held value's sample time under ``at``'s rule (NaN when ``at`` gives NaN)."""
        return self._t if self.fresh(t_s) else float("nan")


def imu_rate_hz(t_s: np.ndarray, start: int = 0) -> np.ndarray:
    """IMU rate at each step: 1 / median of the last RATE_WINDOW intervals ending there (0 at
    the first step, inf when the intervals are zero).  Returns the steps from ``start`` on (the
    live form passes its last RATE_WINDOW + 1 times before its new steps)."""
    t = np.asarray(t_s, dtype=float)
    n = len(t)
    start = min(max(int(start), 0), n)
    med = np.zeros(n - start)
    dt = np.diff(t)
    small = n - start <= 8                                    # a few live steps: plain Python is faster
    for i in range(start, n if small else min(n, RATE_WINDOW + 1)):
        window = dt[max(0, i - RATE_WINDOW):i].tolist()
        med[i - start] = statistics.median(window) if window else 0.0    # np.median's value, faster on a few
    first = n if small else max(start, RATE_WINDOW + 1)
    if n > first:
        windows = np.lib.stride_tricks.sliding_window_view(dt, RATE_WINDOW)   # windows[k] = dt[k:k+W]
        med[first - start:] = _window_medians(windows[first - RATE_WINDOW:n - RATE_WINDOW])
    idx = np.arange(start, n)
    with np.errstate(divide="ignore"):
        rate = np.where(med > 0, 1.0 / np.maximum(med, 1e-300), np.where(idx == 0, 0.0, np.inf))
    # to 0.01 Hz: a 10 Hz stream is 10 Hz, not 9.9999 Hz below the 10 Hz minimum (its times on
    # the microseconds of a .tlog, or as boot_s + offset in floating point)
    return np.round(rate, 2)


MEDIAN_ROWS = 1 << 16      # windows partitioned at a time: the copy np.partition makes stays bounded


def _window_medians(windows: np.ndarray) -> np.ndarray:
    """np.median(windows, axis=1) for an odd window, a block of rows at a time: the middle element
    after a partial sort (8x faster than np.median on a 2-hour log, and its temporaries a few MB
    instead of one copy of every window); a block holding a NaN goes through np.median itself,
    whose windows with a NaN give NaN (a partial sort would put the NaN last and pass it by)."""
    width = windows.shape[1]
    assert width % 2 == 1, "the middle element is the median only for an odd window"
    out = np.empty(len(windows))
    for lo in range(0, len(windows), MEDIAN_ROWS):
        block = windows[lo:lo + MEDIAN_ROWS]
        if np.isnan(block).any():
            out[lo:lo + MEDIAN_ROWS] = np.median(block, axis=1)
        else:
            out[lo:lo + MEDIAN_ROWS] = np.partition(block, width // 2, axis=1)[:, width // 2]
    return out


def too_steep(roll_rad, pitch_rad, settings: DetectionSettings):
    """Not a flight attitude (calibration dance, vehicle carried): detection does not look there."""
    cos_tilt = np.cos(roll_rad) * np.cos(pitch_rad)
    return ~(cos_tilt >= np.cos(np.radians(settings.max_tilt_deg)))


def rotation_rate(gyro_rad_s: np.ndarray) -> np.ndarray:
    """|ω| [rad/s]: turns and other fast rotations gate the heading-difference evidence."""
    return np.linalg.norm(np.nan_to_num(np.asarray(gyro_rad_s, dtype=float)), axis=-1)


def rounded(x, nd=3):
    v = finite_or_none(x)
    return None if v is None else round(v, nd)


# ----------------------------------------------------------------------------- per IMU step
@dataclass
class StepState:
    """What the per-step gates carry from one call to the next (the live form calls per sample)."""
    last_steep_t: float = -np.inf
    tilt_gap: np.ndarray = field(default_factory=lambda: low_pass_state(2))   # the autopilot-minus-ours
    # tilt gap, low-passed (``checked_tilt``): estimators.low_pass's state
    ours: tuple = (np.zeros(0), np.zeros(0), np.zeros(0))   # our (t, roll, pitch) over the last steps (``brought_forward``)


def step_inputs(t, chain, mag_held, att_rp, gps_held, rate_hz, gyro, policy: FieldPolicy,
                settings: DetectionSettings, state: StepState, att_t=None) -> dict:
    """The detector's inputs on IMU steps (arrays of any length, one for live).

    chain: object with roll_rad, pitch_rad, yaw_rad, mag_heading_rad, valid arrays (our attitude,
    the default AHRS, on these steps); mag_held (n, 3) calibrated field; att_rp (n, 2) the
    autopilot's roll and pitch (``checked_tilt``), att_t (n,) their sample times (``brought_forward``;
    None: used as held); gps_held (n, len(GPS_COLUMNS)); rate_hz (n,) IMU
    rate; gyro (n, 3).  Below ``min_imu_rate_hz`` our attitude
    is not trusted: the heading and field tests are off there.
    Returns e, d, trusted, strength, incl, heading, yaw_rate (the detector's arguments) and
    field_mG, inclination_deg, heading_on, field_on, steep, rate_hz for display.
    """
    t = np.asarray(t, dtype=float)
    valid = np.asarray(chain.valid, dtype=bool)
    if att_t is not None:
        att_rp = brought_forward(t, chain, att_rp, att_t, state)
    roll, pitch = checked_tilt(chain, att_rp, t, state)
    field_mG = np.linalg.norm(mag_held, axis=1)
    incl = field_inclination_deg(mag_held, roll, pitch)
    last = np.maximum.accumulate(np.concatenate([[state.last_steep_t],
                                                 np.where(too_steep(roll, pitch, settings), t, -np.inf)]))
    state.last_steep_t = float(last[-1])
    steep = t - last[1:] <= settings.turn_settle_s
    trusted_rate = np.asarray(rate_hz) >= settings.min_imu_rate_hz
    heading_on = trusted_rate & policy.heading_usable
    e = np.where(valid & heading_on & ~steep, wrap_angle_rad(chain.mag_heading_rad - chain.yaw_rad), np.nan)
    use_field = ~steep & policy.field_on
    tilt_ok = use_field & trusted_rate & valid        # the inclination (and so the sector check) needs our tilt
    return dict(e=e, d=gps_held[:, 0], trusted=gps_held[:, 2] == 1.0,
                strength=np.where(use_field, field_mG, np.nan), incl=np.where(tilt_ok, incl, np.nan),
                heading=np.where(valid, chain.yaw_rad, np.nan), yaw_rate=rotation_rate(gyro),
                field_mG=field_mG, inclination_deg=incl, heading_on=heading_on, field_on=use_field, steep=steep,
                tilt_roll=roll, tilt_pitch=pitch,
                rate_hz=np.asarray(rate_hz, dtype=float))


# ----------------------------------------------------------------------------- the field-vector test
def earth_prior_mG(ef) -> tuple[float, float, float] | None:
    """The WMM field in the magnetic navigation frame (H, 0, Z) [mG], the field test's prior,
    rounded to 1 mG (far below its uncertainty; the live twin's WMM date and position may differ a
    little from the log's)."""
    if ef is None:
        return None
    incl = np.radians(ef.inclination_deg)
    return (round(float(ef.field_strength_mG * np.cos(incl))), 0.0, round(float(ef.field_strength_mG * np.sin(incl))))


def first_fix_prior(log: FlightLog) -> tuple[tuple[float, float, float] | None, float]:
    """(prior, time) from the WMM at the first GPS fix, the live twin's rule (LiveAnalyzer._start)."""
    g = np.asarray(log.gps, dtype=float).reshape(-1, 8)
    ok = np.flatnonzero(np.isfinite(g[:, 1]) & np.isfinite(g[:, 2]) & np.isfinite(g[:, 3]))
    if not len(ok):
        return None, np.inf
    row = g[ok[0]]
    start = log.start_unix_s if log.start_unix_s else time.time() - row[0]
    try:
        return earth_prior_mG(earth_field(row[1], row[2], row[3], decimal_year_from_unix(start + row[0]))), float(row[0])
    except ValueError:
        return None, np.inf


def motor_signal_table(log: FlightLog) -> tuple[np.ndarray, str]:
    """[t, signal] of the motor field's signal: battery current [A] when the log has one that
    varies, else throttle in %, else empty; and its name."""
    bat = np.asarray(log.battery, dtype=float).reshape(-1, 2)
    if len(bat) and np.nanmax(bat[:, 1]) - np.nanmin(bat[:, 1]) > 0.5:
        return bat, "current_A"
    thr = np.asarray(getattr(log, "throttle", np.zeros((0, 2))), dtype=float).reshape(-1, 2)
    if len(thr):
        return np.c_[thr[:, 0], 100.0 * thr[:, 1]], "throttle_pct"
    return np.zeros((0, 2)), "none"


def vector_test_inputs(chain, x: dict, gyro: np.ndarray, steep: np.ndarray):
    """(roll, pitch, attitude_ok, gyro bias-corrected) for the field-vector test: the tilt of
    ``checked_tilt`` (``step_inputs``' x["tilt_roll"], x["tilt_pitch"]) and our attitude's gyro
    bias removed (its heading is the test's own, ψ_f)."""
    roll, pitch = x["tilt_roll"], x["tilt_pitch"]
    ok = np.asarray(chain.valid, dtype=bool) & ~np.asarray(steep, dtype=bool)
    return roll, pitch, ok, np.asarray(gyro, dtype=float) - np.asarray(chain.gyro_bias_rad_s, dtype=float)


def _tests(log_imu_rate: float, n: int, settings: DetectionSettings, legs, g, rtk: bool,
           policy: FieldPolicy) -> tuple[str, str]:
    """(heading_test, path_test) lines of the report."""
    if policy.correction == "none":
        heading = "off: no magnetometer data in the log"
    elif not policy.heading_usable:
        heading = policy.field_test
    elif not n:
        heading = "off: no IMU data"
    elif log_imu_rate < settings.min_imu_rate_hz:
        heading = f"off: IMU rate {log_imu_rate:.1f} Hz < {settings.min_imu_rate_hz:g} Hz: our attitude cannot be trusted"
    else:
        heading = "on"
    path = ("off: no mission" if not legs else "off: no GPS position in the log" if not len(g)
            else "on" if rtk else "untrusted: no RTK fix (fix_type < 5), path deviation never alarms")
    return heading, path


def detection_inputs(log: FlightLog, calibration: dict | None = None, mission: list | None = None,
                     settings: DetectionSettings | None = None) -> dict:
    """Everything the detector needs, on the IMU time base (heading chain, field, cross-track).

    Keys: t, e, d, trusted, strength, incl, heading, yaw_rate (the detector's arguments); ef
    (EarthField or None), pos, chain, valid, g (GPS table), gps (GPS_COLUMNS per GPS row), gps_held
    (the same on the IMU steps), att_held (autopilot roll, pitch, yaw on the steps), d_gps, legs,
    rtk, policy, path_test, heading_test, field_test, imu_rate_hz (log median), rate_hz (per step),
    mag_cal, field_mG, inclination_deg, heading_on, cal.
    """
    settings = settings or DetectionSettings()
    mag = np.asarray(log.mag, dtype=float).reshape(-1, 4)
    imu = np.asarray(log.imu, dtype=float).reshape(-1, 7)
    policy = field_policy(calibration, log.params, log.autopilot, getattr(log, "mag_calibration_applied", None),
                          has_mag=bool(len(mag)))
    if policy.cal is not None:
        # batch: the autopilot's corrections un-applied with the values in force at each sample
        # (parameter history), then ours; the live twin uses the values known so far (policy.apply)
        mag_cal = np.c_[mag[:, :1], (primary_raw(log) - policy.cal[0]) @ policy.cal[1].T]
    else:
        mag_cal = np.c_[mag[:, :1], policy.apply(mag[:, 1:4])]
    ef, pos = field_reference(log)
    chain = run_heading_chain(imu, mag_cal, ef.declination_deg if ef else 0.0)
    t = chain.t_s
    n = len(t)
    att = np.asarray(log.attitude, dtype=float).reshape(-1, 4)
    att_held = hold_last(att[:, 0], att[:, 1:4], t, ATTITUDE_TIMEOUT_S)
    legs = mission_legs(mission if mission else log.mission)
    g = np.asarray(log.gps, dtype=float).reshape(-1, 8)
    gps = gps_rows(g, legs, settings)
    gps_held = hold_last(g[:, 0], gps, t, GPS_TIMEOUT_S)
    rate = imu_rate_hz(t)
    # the compass at each step: the held reading turned by the gyro since it was read (field_forward)
    held = hold_last(mag[:, 0], np.c_[mag_cal[:, 1:4], reading_times(mag[:, 0], mag[:, 1:4])], t, GPS_TIMEOUT_S)
    mag_step = field_at_steps(held[:, :3], t - held[:, 3], imu[:, 1:4] - np.asarray(chain.gyro_bias_rad_s, dtype=float))
    x = step_inputs(t, chain, mag_step, att_held[:, :2],
                    gps_held, rate, imu[:, 1:4], policy, settings, StepState(),
                    att_t=hold_last(att[:, 0], att[:, 0], t, ATTITUDE_TIMEOUT_S))
    motor, motor_name = motor_signal_table(log)
    motor_held = hold_last(motor[:, 0], motor[:, 1], t, MOTOR_TIMEOUT_S)
    roll_v, pitch_v, ok_v, gyro_v = vector_test_inputs(chain, x, imu[:, 1:4], x["steep"])
    vector = field_consistency(t, mag_step, roll_v, pitch_v,
                               ok_v, gyro_v, motor_held, rate, policy.field_on, settings.vector,
                               *first_fix_prior(log))
    med_dt = float(np.median(np.diff(t))) if n > 10 else 0.0
    log_rate = 1.0 / med_dt if med_dt > 0 else 0.0
    rtk = bool(len(g) and np.mean(g[:, 7] >= settings.rtk_min_fix) > 0.5)
    heading_test, path_test = _tests(log_rate, n, settings, legs, g, rtk, policy)
    return dict(x, t=t, ef=ef, pos=pos, chain=chain, valid=chain.valid, g=g, gps=gps, gps_held=gps_held,
                att_held=att_held, d_gps=gps[:, 0] if legs else np.zeros(0), legs=legs, rtk=rtk, policy=policy,
                path_test=path_test, heading_test=heading_test,
                field_test=heading_test if heading_test.startswith("off: IMU rate") else policy.field_test,
                imu_rate_hz=log_rate, mag_cal=mag_cal, cal=policy.cal, vector=vector, z_vector=vector.z,
                motor_held=motor_held, motor_signal=motor_name)
