"""Magnetic interference detection (seed 002) with field checks and a combined decision.

Tests, each reduced to a score z (z ≥ 1 = the test's own alarm threshold):

1. Heading difference (seed 002 sec. 1): e = ψ_m − ψ̂, the tilt-compensated magnetic heading
   (seed 000 eqs. 11–13) minus the attitude filter's heading (seed 000 eq. 9/10).  The filter's
   heading follows the magnetometer only through k/(s+k), so a fast change of the field shows up
   in e.  Alarm |e − ē| > 5σ, σ learned (median/MAD) over the clean start of the flight or set.
2. Path deviation (seed 002 sec. 3, eq. 6): d = |(X − A) × (B − A)| / |B − A| in a local NED frame.
   Alarm d > 1 m, only with an RTK fix (fix_type ≥ 5); otherwise the test is untrusted (z = NaN).
3. Field checks (beyond the seed): measured field strength |m| and inclination
   atan2(m_down, m_horizontal) against the WMM.  The seed rejected the magnitude test because the
   motor-current field makes |m| change when the vehicle turns (a body-fixed field adds to the
   Earth field differently on each heading).  So the offset from the WMM is learned per heading
   sector (8 × 45°, from the attitude filter's heading) the first time the vehicle has spent
   ``field_learn_s`` in that sector, and each sample is compared with its own sector's offset;
   a running mean over ``field_window_s`` averages out throttle transients; the threshold is
   max(floor, 5σ) with σ from the same sector's learning samples.
4. Combined decision.  A test only raises the combined alarm when it is corroborated:
     heading:  z_H ≥ strong held for ``heading_hold_s``, or z_H ≥ 1 held and (z_P ≥ ½ or z_F ≥ ½),
               not during a turn or ``turn_settle_s`` after it (|yaw rate| > ``turn_rate_deg_s``:
               the compass deviation changes with heading faster than the filter follows)
               → keeps test 1's fast response on steps and fast ramps (strong and sustained);
     path:     z_P ≥ 1 and (z_H ≥ ½ or z_F ≥ ½)   (supporting evidence held ``corroborate_hold_s``)
               → keeps test 2's early response on slow ramps, but a gust that pushes the
                 track off the line with a healthy compass does not alarm;
     field:    z_F ≥ strong held for ``field_hold_s``, or z_F ≥ 1 held and (z_H ≥ ½ or z_P ≥ ½).
     vector:   z_V ≥ ``vector_alone``, or z_V ≥ 1 and (z_H ≥ ½ or z_P ≥ ½ held): the field-vector
               consistency test (estimators.field_consistency, a CUSUM that already integrates,
               so no hold), reported as field evidence.
   Gate: where the field-vector test is on (finite z_V), the heading, path and sector-field rules
   fire only while z_V ≥ ``vector_gate``: a compass heading that moves with the motor current
   (explained by the learned field per ampere) is not evidence of interference.
   The alarm stays on ``release_s`` after the last trigger.  Every step names its evidence.
5. A gap in the data longer than ``segment_gap_s`` starts a new segment that learns everything
   again (a calibration dance and a flight in one log).

``detect`` (batch, vectorised over a flight) and ``InterferenceDetector.update`` (per sample, live)
give the same results.  Inputs are on one time base (the IMU steps).  Units: rad, deg where named,
mG, m, s.
"""
from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

import math

import numpy as np

from estimators.field_consistency import FieldConsistencySettings

__all__ = ["ned_from_lla", "lla_from_ned", "DetectionSettings", "DetectionResult", "detect", "InterferenceDetector", "DetectorStep",
           "cross_track_m", "field_inclination_deg", "alarm_intervals", "EVIDENCE"]

EVIDENCE = ("heading_difference", "path_deviation", "field_anomaly")
_MAD = 1.4826
EARTH_RADIUS_M = 6378137.0        # WGS84
_E2 = 6.69437999014e-3


# ----------------------------------------------------------------------------- local tangent plane
def _radii(lat_deg: float) -> tuple[float, float]:
    s = math.sin(math.radians(lat_deg))
    rn = EARTH_RADIUS_M / math.sqrt(1 - _E2 * s * s)
    rm = rn * (1 - _E2) / (1 - _E2 * s * s)
    return rm, rn


def ned_from_lla(lat_deg, lon_deg, lat0_deg: float, lon0_deg: float):
    """North/east metres of lat/lon relative to an origin (local tangent plane, equirectangular)."""
    rm, rn = _radii(lat0_deg)
    n = np.radians(np.asarray(lat_deg, dtype=float) - lat0_deg) * rm
    e = np.radians(np.asarray(lon_deg, dtype=float) - lon0_deg) * rn * math.cos(math.radians(lat0_deg))
    return n, e


def lla_from_ned(n_m, e_m, lat0_deg: float, lon0_deg: float):
    """Inverse of ``ned_from_lla``."""
    rm, rn = _radii(lat0_deg)
    lat = lat0_deg + np.degrees(np.asarray(n_m, dtype=float) / rm)
    lon = lon0_deg + np.degrees(np.asarray(e_m, dtype=float) / (rn * math.cos(math.radians(lat0_deg))))
    return lat, lon


@dataclass(frozen=True)
class DetectionSettings:
    learn_s: float = 20.0                 # clean start used to learn the heading-difference σ
    sigma_k: float = 5.0                  # seed 002: alarm above 5σ
    heading_sigma_deg: float | None = None  # set σ instead of learning it
    min_heading_sigma_deg: float = 0.3
    path_threshold_m: float = 1.0         # seed 002: 1 m
    rtk_min_fix: int = 5
    field_window_s: float = 1.0
    field_learn_s: float = 5.0            # time in a heading sector before its field offset is known
    sectors: int = 8
    turn_rate_deg_s: float = 15.0
    turn_settle_s: float = 4.0
    strength_floor_mG: float = 30.0
    inclination_floor_deg: float = 3.0
    heading_hold_s: float = 0.5
    field_hold_s: float = 1.0
    corroborate: float = 0.5              # supporting evidence: z ≥ ½ ...
    corroborate_hold_s: float = 0.5       # ... held this long (a single noisy sample is no evidence)
    strong: float = 2.0
    release_s: float = 2.0
    segment_gap_s: float = 4.5            # a longer gap in the data starts a new segment (re-learn)
    max_tilt_deg: float = 45.0            # callers blank steeper attitudes (hand-held dance, tumbling)
    min_imu_rate_hz: float = 10.0         # callers skip the heading test on slower IMU data (telemetry)
    vector: FieldConsistencySettings = field(default_factory=FieldConsistencySettings)  # field-vector test
    vector_alone: float = 1.0             # field-vector score that alarms on its own (inf: only corroborated)
    use_vector: bool = True               # False: the seed-002 tests and the sector field check only
    vector_gate: float = 0.3              # where the field-vector test is on, the other tests count only
                                          # while its score is at least this (inf: no gate)


@dataclass
class DetectionResult:
    """Per-step arrays (length N) of a flight."""
    t_s: np.ndarray
    z_heading: np.ndarray        # |e − ē| / (kσ); NaN before learning / invalid
    z_path: np.ndarray           # d / threshold; NaN when untrusted or no mission
    z_field: np.ndarray          # max of strength / inclination scores; NaN before learning
    heading_alarm: np.ndarray    # test 1 alone (seed threshold method)
    path_alarm: np.ndarray       # test 2 alone (trusted only)
    field_alarm: np.ndarray      # test 3 alone (held field_hold_s)
    combined: np.ndarray         # combined decision (with release)
    trigger: np.ndarray          # (N, 3) bool: which corroborated rule fired (heading, path, field)
    heading_sigma_deg: float
    heading_mean_deg: float
    sector_offsets: dict          # sector -> (t learned, strength offset mG, σ, inclination offset deg, σ)
    z_strength: np.ndarray        # running-mean strength deviation / its threshold
    z_inclination: np.ndarray
    z_vector: np.ndarray = field(default_factory=lambda: np.zeros(0))   # field-vector CUSUM score (NaN: off)

    def evidence_at(self, i: int) -> list[str]:
        return [EVIDENCE[k] for k in range(3) if self.trigger[i, k]]


# ----------------------------------------------------------------------------- helpers
def cross_track_m(pos_ned_m: np.ndarray, a_ned_m: np.ndarray, b_ned_m: np.ndarray) -> np.ndarray:
    """Seed 002 eq. (6): d = |(X − A) × (B − A)| / |B − A| (vectorised over X rows)."""
    x = np.asarray(pos_ned_m, dtype=float).reshape(-1, 3)
    a = np.asarray(a_ned_m, dtype=float)
    ab = np.asarray(b_ned_m, dtype=float) - a
    length = np.linalg.norm(ab)
    if not length > 0:
        return np.linalg.norm(x - a, axis=1)
    return np.linalg.norm(np.cross(x - a, ab), axis=1) / length


def field_inclination_deg(mag_body_mG: np.ndarray, roll_rad, pitch_rad) -> np.ndarray:
    """Inclination of a body-frame field given roll/pitch: atan2(m_down, |m_horizontal|) [deg].

    m_down = −sin θ m_x + sin φ cos θ m_y + cos φ cos θ m_z (third row of C_b^n).
    """
    m = np.asarray(mag_body_mG, dtype=float)
    r, p = np.asarray(roll_rad, dtype=float), np.asarray(pitch_rad, dtype=float)
    down = -np.sin(p) * m[..., 0] + np.sin(r) * np.cos(p) * m[..., 1] + np.cos(r) * np.cos(p) * m[..., 2]
    total2 = np.einsum("...i,...i->...", m, m)
    horiz = np.sqrt(np.maximum(total2 - down * down, 0.0))
    return np.degrees(np.arctan2(down, horiz))


def _robust(x: np.ndarray) -> tuple[float, float]:
    x = x[np.isfinite(x)]
    if len(x) == 0:
        return float("nan"), float("nan")
    med = float(np.median(x))
    return med, float(_MAD * np.median(np.abs(x - med)))


def _held_since(t: np.ndarray, cond: np.ndarray) -> np.ndarray:
    """Time since the current run of ``cond`` began (NaN where cond is False)."""
    start = np.where(cond & ~np.concatenate([[False], cond[:-1]]), t, -np.inf)
    start = np.maximum.accumulate(start) if len(t) else start
    return np.where(cond, t - start, np.nan)


def _since_last(t: np.ndarray, cond: np.ndarray) -> np.ndarray:
    last = np.maximum.accumulate(np.where(cond, t, -np.inf)) if len(t) else t
    return t - last


def _window_mean(t: np.ndarray, x: np.ndarray, window_s: float) -> np.ndarray:
    """Causal mean of the finite x over (t − window, t] (NaN if none)."""
    ok = np.isfinite(x)
    cs = np.concatenate([[0.0], np.cumsum(np.where(ok, x, 0.0))])
    cn = np.concatenate([[0], np.cumsum(ok)])
    j = np.searchsorted(t, t - window_s, side="right")
    i = np.arange(1, len(t) + 1)
    n = cn[i] - cn[j]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(n > 0, (cs[i] - cs[j]) / np.maximum(n, 1), np.nan)


def _sector(heading_rad, sectors: int):
    h = np.mod(np.nan_to_num(heading_rad, nan=0.0), 2 * np.pi)
    return np.minimum((h / (2 * np.pi) * sectors).astype(int), sectors - 1)


def _sector_thresholds(vals: np.ndarray, s: "DetectionSettings") -> tuple[float, float, float, float]:
    off_s, sig_s = _robust(vals[:, 0])
    off_i, sig_i = _robust(vals[:, 1])
    thr_s = max(s.strength_floor_mG, s.sigma_k * (sig_s if np.isfinite(sig_s) else 0.0))
    thr_i = max(s.inclination_floor_deg, s.sigma_k * (sig_i if np.isfinite(sig_i) else 0.0))
    return off_s, thr_s, off_i, thr_i


def _sector_residuals(t, sector, sd, idv, valid, s):
    """Field deviations normalised by their heading sector's learned offset and threshold."""
    n = len(t)
    q_s = np.full(n, np.nan)
    q_i = np.full(n, np.nan)
    learned = {}
    dt = np.clip(np.diff(t, prepend=t[:1]), 0.0, 0.1) if n else t
    use = valid & np.isfinite(sd) & np.isfinite(idv)
    for k in range(s.sectors):
        m = use & (sector == k)
        if not m.any():
            continue
        cum = np.cumsum(np.where(m, dt, 0.0))
        done = np.flatnonzero(m & (cum >= s.field_learn_s))
        if not len(done):
            continue
        i_k = done[0]
        sel = np.flatnonzero(m[:i_k + 1])
        off_s, thr_s, off_i, thr_i = _sector_thresholds(np.stack([sd[sel], idv[sel]], axis=1), s)
        learned[k] = (float(t[i_k]), off_s, thr_s, off_i, thr_i)
        after = (sector == k) & valid & (np.arange(n) >= i_k)
        q_s[after] = (sd[after] - off_s) / thr_s
        q_i[after] = (idv[after] - off_i) / thr_i
    return q_s, q_i, learned


def _gt(a: np.ndarray, thr: float) -> np.ndarray:
    return np.nan_to_num(a, nan=-np.inf) >= thr


# ----------------------------------------------------------------------------- batch
def detect(t_s, heading_diff_rad, cross_track, path_trusted, strength_mG, inclination_deg,
           heading_rad, yaw_rate_rad_s, strength_ref_mG: float = np.nan, inclination_ref_deg: float = np.nan,
           settings: DetectionSettings | None = None, z_vector=None) -> DetectionResult:
    """Batch detection over a flight (vectorised).  All inputs length N on one time base.

    heading_diff_rad: ψ_m − ψ̂ wrapped to ±π, NaN where the heading chain is not valid.
    cross_track: metres (NaN when no mission / no fresh GPS); path_trusted: RTK fix at that step.
    strength_mG, inclination_deg: measured field; *_ref: WMM (NaN = unknown → 0, learned offset only).
    heading_rad: the attitude filter's heading (for the field sectors); yaw_rate_rad_s: turn rate
    (|yaw rate| or |ω|) for turn gating.
    A time gap longer than ``segment_gap_s`` starts a new segment: everything is learned again
    (e.g. a calibration dance and a flight in one log).  Scalars of the result are the last segment's.
    """
    s = settings or DetectionSettings()
    zv = np.full(len(np.asarray(t_s)), np.nan) if z_vector is None else np.asarray(z_vector, dtype=float)
    args = [np.asarray(a) for a in (t_s, heading_diff_rad, cross_track, path_trusted, strength_mG,
                                     inclination_deg, heading_rad, yaw_rate_rad_s, zv)]
    t = args[0].astype(float)
    cuts = np.flatnonzero(np.diff(t) > s.segment_gap_s) + 1 if len(t) > 1 else np.zeros(0, int)
    if not len(cuts):
        return _detect_segment(*args, strength_ref_mG, inclination_ref_deg, s)
    parts = [_detect_segment(*[a[i:j] for a in args], strength_ref_mG, inclination_ref_deg, s)
             for i, j in zip(np.r_[0, cuts], np.r_[cuts, len(t)])]
    last = parts[-1]
    cat = lambda name: np.concatenate([getattr(p, name) for p in parts])  # noqa: E731
    return DetectionResult(cat("t_s"), cat("z_heading"), cat("z_path"), cat("z_field"), cat("heading_alarm"),
                           cat("path_alarm"), cat("field_alarm"), cat("combined"), cat("trigger"),
                           last.heading_sigma_deg, last.heading_mean_deg, last.sector_offsets,
                           cat("z_strength"), cat("z_inclination"), cat("z_vector"))


def _detect_segment(t_s, heading_diff_rad, cross_track, path_trusted, strength_mG, inclination_deg,
                    heading_rad, yaw_rate_rad_s, z_vector, strength_ref_mG, inclination_ref_deg, s) -> DetectionResult:
    t = np.asarray(t_s, dtype=float)
    e = np.asarray(heading_diff_rad, dtype=float)
    d = np.asarray(cross_track, dtype=float)
    trusted = np.asarray(path_trusted, dtype=bool)
    sd = np.asarray(strength_mG, dtype=float) - (strength_ref_mG if np.isfinite(strength_ref_mG) else 0.0)
    idv = np.asarray(inclination_deg, dtype=float) - (inclination_ref_deg if np.isfinite(inclination_ref_deg) else 0.0)
    n = len(t)
    valid = np.isfinite(e)
    started = valid | np.isfinite(sd)
    t0 = t[started][0] if started.any() else np.inf
    learn = (t >= t0) & (t < t0 + s.learn_s)
    armed = t >= t0 + s.learn_s
    e_deg = np.degrees(e)
    mean_e, sig_e = _robust(e_deg[learn])
    if s.heading_sigma_deg is not None:
        sig_e = s.heading_sigma_deg
    sig_e = max(sig_e if np.isfinite(sig_e) else 0.0, s.min_heading_sigma_deg)
    mean_e = mean_e if np.isfinite(mean_e) else 0.0
    dev_e = np.abs((e_deg - mean_e + 180.0) % 360.0 - 180.0)
    z_h = np.where(armed & valid, dev_e / (s.sigma_k * sig_e), np.nan)

    z_p = np.where(trusted & np.isfinite(d), d / s.path_threshold_m, np.nan)

    sector = _sector(np.asarray(heading_rad, dtype=float), s.sectors)
    q_s, q_i, learned = _sector_residuals(t, sector, sd, idv, np.isfinite(heading_rad), s)
    zs = np.abs(_window_mean(t, q_s, s.field_window_s)) if n else q_s
    zi = np.abs(_window_mean(t, q_i, s.field_window_s)) if n else q_i
    z_f = np.where(armed, np.fmax(zs, zi), np.nan)
    turning = np.abs(np.nan_to_num(np.asarray(yaw_rate_rad_s, dtype=float))) > np.radians(s.turn_rate_deg_s)
    quiet = _since_last(t, turning) > s.turn_settle_s
    z_hq = np.where(quiet, z_h, np.nan)

    def held(cond, hold):
        return np.nan_to_num(_held_since(t, cond), nan=-1.0) >= hold

    hs, cs = s.heading_hold_s, s.corroborate_hold_s
    h_sus, f_sus = held(_gt(z_hq, 1.0), hs), held(_gt(z_f, 1.0), s.field_hold_s)
    hh, ph, fh = (held(_gt(z, s.corroborate), cs) for z in (z_hq, z_p, z_f))
    p1 = _gt(z_p, 1.0)
    zv = np.where(armed, np.asarray(z_vector, dtype=float), np.nan) if s.use_vector else np.full(n, np.nan)
    vec = _gt(zv, s.vector_alone) | (_gt(zv, 1.0) & (hh | ph))
    gate = ~np.isfinite(zv) | (np.nan_to_num(zv) >= s.vector_gate)
    trig = np.stack([gate & (held(_gt(z_hq, s.strong), hs) | (h_sus & (ph | fh))),
                     gate & p1 & (hh | fh),
                     (gate & (held(_gt(z_f, s.strong), s.field_hold_s) | (f_sus & (hh | ph)))) | vec], axis=1)
    any_trig = trig.any(axis=1)
    combined = _since_last(t, any_trig) <= s.release_s
    return DetectionResult(t, z_h, z_p, z_f, _gt(z_h, 1.0), p1, f_sus, combined, trig, float(sig_e),
                           float(mean_e), learned, zs, zi, zv)


# ----------------------------------------------------------------------------- per sample
@dataclass
class DetectorStep:
    t_s: float
    z_heading: float
    z_path: float
    z_field: float
    combined: bool
    evidence: list[str] = field(default_factory=list)
    z_vector: float = float("nan")


class InterferenceDetector:
    """Per-sample form of ``detect`` (same settings, same results), for the live path."""

    def __init__(self, settings: DetectionSettings | None = None, strength_ref_mG: float = np.nan,
                 inclination_ref_deg: float = np.nan) -> None:
        self.s = settings or DetectionSettings()
        self.strength_ref_mG = strength_ref_mG
        self.inclination_ref_deg = inclination_ref_deg
        self.t0: float | None = None
        self._learn: list[float] = []
        self.learned = False
        self.heading_sigma_deg = self.heading_mean_deg = float("nan")
        self._t_prev: float | None = None
        self._sec_time = [0.0] * self.s.sectors
        self._sec_vals: list[list] = [[] for _ in range(self.s.sectors)]
        self.sector_offsets: dict = {}
        self._win: deque = deque()     # (t, q_strength, q_inclination) in the running-mean window
        self._starts: dict[str, float | None] = {}
        self._last_turn = -np.inf
        self._last_trigger = -np.inf
        self.alarm_active = False
        self.alarm_kinds: list[str] = []
        self.peak: float | None = None

    def _finish_learning(self) -> None:
        s = self.s
        mean_e, sig_e = _robust(np.array(self._learn, dtype=float))
        if s.heading_sigma_deg is not None:
            sig_e = s.heading_sigma_deg
        self.heading_sigma_deg = max(sig_e if np.isfinite(sig_e) else 0.0, s.min_heading_sigma_deg)
        self.heading_mean_deg = mean_e if np.isfinite(mean_e) else 0.0
        self.learned = True

    def update(self, t_s: float, heading_diff_rad: float, cross_track: float, path_trusted: bool,
               strength_mG: float, inclination_deg: float, heading_rad: float = np.nan,
               yaw_rate_rad_s: float = 0.0, z_vector: float = np.nan) -> DetectorStep:
        s = self.s
        t = float(t_s)
        if self._t_prev is not None and t - self._t_prev > s.segment_gap_s:
            self.__init__(s, self.strength_ref_mG, self.inclination_ref_deg)   # new segment: learn again
        sd = strength_mG - (self.strength_ref_mG if np.isfinite(self.strength_ref_mG) else 0.0)
        idv = inclination_deg - (self.inclination_ref_deg if np.isfinite(self.inclination_ref_deg) else 0.0)
        e_deg = float(np.degrees(heading_diff_rad))
        valid = bool(np.isfinite(heading_diff_rad))
        if self.t0 is None and (valid or np.isfinite(sd)):
            self.t0 = t
        if self.t0 is not None and not self.learned:
            if t < self.t0 + s.learn_s:
                self._learn.append(e_deg)
            else:
                self._finish_learning()
        # field: per heading-sector offsets, learned on first ``field_learn_s`` in the sector
        dt = 0.0 if self._t_prev is None else min(max(t - self._t_prev, 0.0), 0.1)
        self._t_prev = t
        k = int(_sector(np.array([heading_rad]), s.sectors)[0])
        have_sector = bool(np.isfinite(heading_rad))
        if k not in self.sector_offsets and have_sector and np.isfinite(sd) and np.isfinite(idv):
            self._sec_time[k] += dt
            self._sec_vals[k].append((sd, idv))
            if self._sec_time[k] >= s.field_learn_s:
                off_s, thr_s, off_i, thr_i = _sector_thresholds(np.array(self._sec_vals[k]), s)
                self.sector_offsets[k] = (t, off_s, thr_s, off_i, thr_i)
                self._sec_vals[k] = []
        if have_sector and k in self.sector_offsets:
            _, off_s, thr_s, off_i, thr_i = self.sector_offsets[k]
            q = ((sd - off_s) / thr_s, (idv - off_i) / thr_i)
        else:
            q = (np.nan, np.nan)
        self._win.append((t, q[0], q[1]))
        while self._win and self._win[0][0] <= t - s.field_window_s:
            self._win.popleft()
        if abs(yaw_rate_rad_s if np.isfinite(yaw_rate_rad_s) else 0.0) > np.radians(s.turn_rate_deg_s):
            self._last_turn = t
        quiet = t - self._last_turn > s.turn_settle_s
        armed = self.learned
        z_h = z_f = float("nan")
        if armed and valid:
            dev = abs((e_deg - self.heading_mean_deg + 180.0) % 360.0 - 180.0)
            z_h = dev / (s.sigma_k * self.heading_sigma_deg)
        z_p = cross_track / s.path_threshold_m if (path_trusted and np.isfinite(cross_track)) else float("nan")
        if armed:
            w = np.array([(a, b) for _, a, b in self._win], dtype=float).reshape(-1, 2)
            okw = np.isfinite(w)
            zs = abs(w[okw[:, 0], 0].mean()) if okw[:, 0].any() else np.nan
            zi = abs(w[okw[:, 1], 1].mean()) if okw[:, 1].any() else np.nan
            z_f = float(np.fmax(zs, zi))
        z_hq = z_h if quiet else float("nan")
        ge = lambda z, th: bool(np.isfinite(z) and z >= th)  # noqa: E731
        st = self._starts
        conds = {"h": ge(z_hq, 1.0), "f": ge(z_f, 1.0), "hs": ge(z_hq, s.strong), "fs": ge(z_f, s.strong),
                 "hh": ge(z_hq, s.corroborate), "ph": ge(z_p, s.corroborate), "fh": ge(z_f, s.corroborate)}
        for key, on in conds.items():
            st[key] = (st.get(key) if st.get(key) is not None else t) if on else None
        held = lambda key, hold: st[key] is not None and t - st[key] >= hold  # noqa: E731
        hs, cs = s.heading_hold_s, s.corroborate_hold_s
        h_sus, f_sus = held("h", hs), held("f", s.field_hold_s)
        hh, ph, fh = held("hh", cs), held("ph", cs), held("fh", cs)
        p1 = ge(z_p, 1.0)
        z_v = float(z_vector) if (armed and s.use_vector) else float("nan")
        vec = ge(z_v, s.vector_alone) or (ge(z_v, 1.0) and (hh or ph))
        gate = not np.isfinite(z_v) or z_v >= s.vector_gate
        trig = [gate and (held("hs", hs) or (h_sus and (ph or fh))), gate and p1 and (hh or fh),
                (gate and (held("fs", s.field_hold_s) or (f_sus and (hh or ph)))) or vec]
        if any(trig):
            self._last_trigger = t
            self.alarm_kinds = [EVIDENCE[j] for j in range(3) if trig[j]]
        combined = t - self._last_trigger <= s.release_s
        if combined:
            zmax = float(np.nanmax([z_h, z_p, z_f, 0.0]))
            self.peak = max(self.peak or 0.0, zmax) if self.alarm_active else zmax
        else:
            self.alarm_kinds = []
        self.alarm_active = bool(combined)
        return DetectorStep(t, float(z_h), float(z_p), float(z_f), bool(combined),
                            [EVIDENCE[j] for j in range(3) if trig[j]], z_v)


# ----------------------------------------------------------------------------- reporting
def alarm_intervals(t_s: np.ndarray, flag: np.ndarray, value: np.ndarray | None = None,
                    merge_gap_s: float = 1.0) -> list[tuple[float, float | None, float, int, int]]:
    """Intervals where ``flag`` is on: (start_s, end_s or None if on at the end, peak of value, i0, i1).

    Intervals separated by less than ``merge_gap_s`` are merged.
    """
    t = np.asarray(t_s, dtype=float)
    f = np.asarray(flag, dtype=bool)
    if not f.any():
        return []
    edges = np.diff(np.concatenate([[0], f.astype(np.int8), [0]]))
    starts = np.flatnonzero(edges == 1)
    ends = np.flatnonzero(edges == -1) - 1
    merged: list[list[int]] = []
    for a, b in zip(starts, ends):
        if merged and t[a] - t[merged[-1][1]] < merge_gap_s:
            merged[-1][1] = b
        else:
            merged.append([a, b])
    out = []
    for a, b in merged:
        peak = float(np.nanmax(value[a:b + 1])) if value is not None and np.isfinite(value[a:b + 1]).any() else float("nan")
        end = None if b == len(t) - 1 else float(t[b])
        out.append((float(t[a]), end, peak, int(a), int(b)))
    return out
