"""In-flight compass fit against the World Magnetic Model, for logs without a calibration dance.

With the autopilot's attitude and the WMM field at the flight's position and date the body-frame
field is predicted, so offsets are observable from ordinary flight (the idea of pymavlink's
``tools/magfit_WMM.py``).  Done here (see estimators/field_model.py for the model and solver):

* samples are gated first: NaN rows, attitude rotating faster than ``max_rate_deg_s`` (at 1–4 Hz
  telemetry the attitude interpolated to a field sample is off by rate × timing error), and — when
  the yaw is used — stretches where the attitude heading disagrees with the GPS course while moving
  straight and fast (a bad attitude source);
* the fit is a closed-form start + robust Gauss–Newton with priors (magfit_WMM: SLSQP on numerical
  gradients of a Python loop, L1 cost, no uncertainty), Huber-weighted first and with outliers
  rejected only from that answer, so the result does not depend on the start: offsets always; diagonal and motor terms
  element by element only where the data supports them (posterior sd < ``supported_ratio`` × prior
  sd, else held at nominal), within ArduPilot/magfit bounds; the covariance is returned;
* the heading source: ArduPilot's EKF yaw is computed from the compass, and a vector fit that uses
  it is pulled toward the offsets the EKF was using (and 1° of yaw error is ~4 mG of horizontal
  offset error).  So "auto" (and "compass") fit yaw-free: the attitude's heading is not used at
  all, the horizontal offsets are observed through heading changes, and when too few headings were
  flown (largest offset sd > ``max_offset_sd_mG``) the status is ``attitude_depends_on_compass``
  (or ``insufficient_data`` when the yaw demonstrably does not follow this compass).  The yaw is
  diagnosed, never trusted unasked: the RMS disagreement between the attitude yaw and the fitted
  compass heading, and the slope of (attitude yaw − fitted heading) on (in-force heading − fitted
  heading): ≈ 1 when the attitude follows this compass, ≈ 0 when not.
* too few headings (fewer than ``min_heading_coverage`` of the 12 30° sectors, e.g. a there-and-back
  mission) is never ``ok``: the covariance, linearised at the solution, then hides the trade
  between the across-track offset and the soft-iron terms (measured: 2 mG sd reported, 176 mG
  error on a simulated two-heading mission).  A caller that knows the
  yaw is independent and accurate (GPS yaw, EK3_SRC1_YAW) asks for "independent": the full-vector
  residual, with the GPS-course gate.

An answer with its quality (issue 28): the offsets' covariance is marginal over the terms held at
nominal by this fit's choice, each variance raised to its jackknife variance (time blocks, heading
sectors), plus the reference field's own uncertainty carried through the fit (``field_model_sd_mG``, the WMM's
error model, or ``field_cov_ned_mG2``, the covariance of the field refined from the flight by
estimators.field_refine from the profiles ``field_direction_nll`` gives) and the attitude's common tilt error (``attitude_tilt_sd_deg``); a flight dominated by one line flown both ways (``heading_imbalance`` > 0.9) holds soft
iron at nominal with its prior in the 1σ.  ``recommended`` when the worst 1σ ≤ ``max_offset_sd_mG``;
else status "weak" (offsets, 1σ, the reason and the flight that would pin them down); refused only
when unobservable (< ``min_heading_coverage`` of the headings, 1σ > ``max_answer_sd_mG``).
``heading_change_deg``: the new calibration's heading against the corrections in force.  Sphere
cells (``sphere_cell_weights``, off by default: measured to add error here, docs/inflight-calibration.md).

Statuses: ok | weak | attitude_depends_on_compass | insufficient_data | no_attitude | no_expected_field |
offsets_out_of_range.  Units: mG, rad, A (or throttle 0..1), m/s.  Pure numpy.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from estimators.geomag import WMM_ERROR_NED_mG
from estimators.field_model import (PARAM_NAMES, FieldData, Solution, SolverOptions, corrected_field,
                                    matrix_from_params, model_terms, nominal_params, residuals, solve, stack_rows)
from estimators.field_model_groups import solve_groups
from estimators.rotations import dcm_body_to_ned, wrap_angle_rad

__all__ = ["WmmFitSettings", "WmmFit", "fit_wmm", "heldout_residual_mG", "field_direction_nll", "course_check", "straight_and_fast", "compass_heading_rad", "sphere_cell_index", "sphere_cell_weights", "heading_imbalance",
           "FLY_FOR_HEADINGS"]


@dataclass(frozen=True)
class WmmFitSettings:
    """In-flight fit settings (units in the names).  Bounds follow magfit_WMM.py's defaults
    (diag 0.8–1.2, off-diagonal ±0.2) and ArduPilot's COMPASS_OFFS_MAX (1800 mG)."""
    yaw_source: str = "auto"                  # "auto"/"compass": yaw-free | "independent": vector
    fit_diagonal: bool | None = None          # None: each element kept when supported
    fit_offdiagonal: bool = True              # True: each element kept when supported
    fit_motor: bool | None = None             # None: when the motor signal varies enough
    min_motor_signal_std: float = 1.0         # [A] (use ~0.05 for throttle)
    max_rate_deg_s: float = 20.0
    course_min_speed_mps: float = 4.0
    max_course_turn_deg_s: float = 5.0
    max_course_disagreement_deg: float = 30.0
    course_check_min_speed_mps: float = 5.0       # the GPS-course check of the heading change (course_check)
    course_check_max_roll_deg: float = 10.0
    course_check_min_samples: int = 20
    offset_limit_mG: float = 1800.0
    diag_limits: tuple[float, float] = (0.8, 1.2)
    offdiag_limit: float = 0.2
    motor_limit_mG_per_unit: float = 20.0
    offset_prior_sd_mG: float = 1000.0
    diag_prior_sd: float = 0.1
    offdiag_prior_sd: float = 0.05
    motor_prior_sd_mG_per_unit: float = 5.0
    supported_ratio: float = 0.3
    huber_k: float = 1.345
    outlier_sigma: float = 5.0
    max_iter: int = 25
    max_offset_sd_mG: float = 5.0
    min_samples: int = 30
    yaw_dependence_slope: float = 0.5
    min_heading_spread_deg: float = 1.0
    min_heading_coverage: float = 4 / 12          # of 12 30-degree heading sectors, among the used samples
    max_answer_sd_mG: float = 150.0               # worst-axis 1σ beyond this: unobservable, no answer
    max_heading_imbalance: float = 0.9            # above: soft iron held at nominal (its prior in the 1σ)
    cell_weighting: bool | None = False           # sphere cells, rare directions weighted up (None: when soft iron is
                                                  # held).  Off: measured to add bias here (docs/inflight-calibration.md)
    jackknife_blocks: int = 8                     # contiguous time blocks for the jackknife 1σ (0: none)
    # the reference field's own 1σ per NED component [mG], in the stated 1σ (``_with_flight_wide_errors``): WMM2025's
    # error model as wmm-calculator ships it (``geomag.WMM_ERROR_NED_mG``: 1.37, 0.89, 1.41 mG);
    # (0, 0, 0): the reference taken as exact
    field_model_sd_mG: tuple[float, float, float] = WMM_ERROR_NED_mG
    # shifts of the reference field along its inclination for the profile of estimators.field_refine [mG]
    field_profile_shifts_mG: tuple[float, ...] = (-6.0, -3.0, 0.0, 3.0, 6.0)   # (9 points at 2 mG: within 0.15 mG)
    # the attitude's tilt error, common to the flight, that no residual shows [deg]: in the offsets' 1σ
    # (``_with_flight_wide_errors``) and the refined field's (estimators.field_refine).  Measured on ArduCopter
    # SITL (EKF3's ATT against the simulator's SIM, seeds 13, 15, 16, 17, 20): +0.06…+0.08° roll and
    # +0.07…+0.09° pitch, mean over each flight
    attitude_tilt_sd_deg: float = 0.10
    sphere_bands: int = 8                         # equal-area cells: bands of equal Δz × sectors per band
    sphere_sectors: int = 10


@dataclass(frozen=True)
class WmmFit:
    """Result of ``fit_wmm``.  Calibration: m_cal = matrix · (m_raw − offsets_mG) − motor · x.
    ArduPilot export: COMPASS_OFS = −offsets_mG, DIA/ODI from matrix, COMPASS_MOT = −motor."""
    status: str
    message: str
    model: str                                # "vector" | "yaw_free" | ""
    yaw_used: bool                            # the attitude's yaw entered the fit (vector model)
    offsets_mG: np.ndarray
    matrix: np.ndarray
    motor_mG_per_unit: np.ndarray
    covariance: np.ndarray                    # (12,12) over field_model.PARAM_NAMES (b, A = M⁻¹, f)
    offsets_sd_mG: np.ndarray
    motor_sd_mG_per_unit: np.ndarray
    fitted: tuple[str, ...]                   # PARAM_NAMES entries that were fitted
    residual_rms_mG: float
    n_used: int
    n_input: int
    rejected: dict
    heading_coverage: float                   # fraction of 12 heading sectors visited (used samples)
    yaw_dependence: float                     # slope, NaN when not determinable
    yaw_disagreement_deg: float               # RMS(attitude yaw − fitted compass heading)
    recommended: bool = False                 # offsets precise enough to write (status "ok")
    reason: str = ""                          # why (not) recommended, or what flight would make it observable
    heading_change_deg: tuple[float, float] = (float("nan"), float("nan"))   # (RMS, max |Δψ|) new vs in force
    sphere_coverage: float = 0.0              # fraction of the sphere cells holding a used field direction
    course: dict | None = None                # course_check of the heading change (None: no GPS velocity or in-force field)
    field_profile_nll: np.ndarray | None = None   # −2 log L over settings.field_profile_shifts_mG along the direction asked
    settings: WmmFitSettings = field(default_factory=WmmFitSettings)


FLY_FOR_HEADINGS = ("fly two full yaw turns (360° each) at 20–30° bank, or legs in four or more directions, "
                    "then fit that flight")


def _failed(status: str, message: str, n: int, rejected: dict, settings: WmmFitSettings, reason: str = "",
            coverage: float = 0.0) -> WmmFit:
    nan3 = np.full(3, np.nan)
    return WmmFit(status, message, "", False, nan3, np.full((3, 3), np.nan), nan3.copy(), np.full((12, 12), np.nan),
                  nan3.copy(), nan3.copy(), (), float("nan"), 0, n, rejected, coverage, float("nan"), float("nan"),
                  False, reason or message, settings=settings)


def sphere_cell_index(directions: np.ndarray, bands: int = 8, sectors: int = 10) -> np.ndarray:
    """Equal-area cell (0 … bands·sectors − 1) of each direction (N,3): bands of equal Δz on the unit
    sphere have equal area (Archimedes' hat-box theorem), split into equal longitude sectors."""
    u = np.asarray(directions, float).reshape(-1, 3)
    u = u / np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-12)
    band = np.clip(((u[:, 2] + 1.0) / 2.0 * bands).astype(int), 0, bands - 1)
    sector = np.clip(((np.arctan2(u[:, 1], u[:, 0]) + np.pi) / (2 * np.pi) * sectors).astype(int), 0, sectors - 1)
    return band * sectors + sector


def sphere_cell_weights(directions: np.ndarray, bands: int = 8, sectors: int = 10) -> tuple[np.ndarray, float]:
    """(per-sample weights with mean 1, fraction of cells occupied).  MAGFit's idea: a direction flown
    for most of the flight must not outvote the rare ones.  Here a cell holding n samples counts as
    min(n, n_med) samples (n_med: the median count of the occupied cells), i.e. w = min(1, n_med / n):
    crowded cells are weighted down to the typical one, and no sample is weighted above the others
    (a lone sample does not steer the fit, its noise is not amplified).  Used as prior weights in the
    least squares, with the sandwich covariance (estimators.field_model.solve)."""
    cell = sphere_cell_index(directions, bands, sectors)
    if len(cell) == 0:
        return np.ones(0), 0.0
    counts = np.bincount(cell, minlength=bands * sectors)
    n_med = float(np.median(counts[counts > 0]))
    w = np.minimum(1.0, n_med / counts[cell])
    return w / w.mean(), float(np.count_nonzero(counts) / (bands * sectors))


def compass_heading_rad(corrected_mG: np.ndarray, roll_rad, pitch_rad, field_ned_mG) -> np.ndarray:
    """Tilt-compensated heading (true, rad) of corrected body fields, declination from the field:
    l = Ry(θ)Rx(φ) c,  ψ = atan2(−l_y, l_x) + atan2(H_E, H_N)."""
    T = dcm_body_to_ned(np.asarray(roll_rad, float), np.asarray(pitch_rad, float), np.zeros(np.shape(roll_rad)))
    lv = np.einsum("nij,nj->ni", T, np.asarray(corrected_mG, float))
    H = np.asarray(field_ned_mG, float)          # (3,) or (N,3)
    return wrap_angle_rad(np.arctan2(-lv[:, 1], lv[:, 0]) + np.arctan2(H[..., 1], H[..., 0]))


def straight_and_fast(t_s, vel_ne_mps, min_speed_mps: float, max_turn_deg_s: float) -> tuple[np.ndarray, np.ndarray]:
    """(mask, GPS course rad): samples moving faster than ``min_speed_mps`` on a steady course (its
    rate of change, by central differences over the fast samples, below ``max_turn_deg_s``)."""
    v = np.asarray(vel_ne_mps, float).reshape(-1, 2)
    speed = np.hypot(v[:, 0], v[:, 1])
    fast = np.isfinite(speed) & (speed >= min_speed_mps)
    course = np.arctan2(v[:, 1], v[:, 0])
    if fast.sum() < 3:
        return np.zeros(len(speed), bool), course
    tc, cc = np.asarray(t_s, float)[fast], np.unwrap(course[fast])
    turn = np.full(len(speed), np.inf)
    if np.all(np.diff(tc) > 0):
        turn[fast] = np.degrees(np.abs(np.gradient(cc, tc)))
    return fast & (turn <= max_turn_deg_s), course


def _course_disagrees(t_s, yaw_rad, vel_ne_mps, s: WmmFitSettings) -> np.ndarray:
    """True where moving straight and fast while the attitude heading is far from the GPS course."""
    straight, course = straight_and_fast(t_s, vel_ne_mps, s.course_min_speed_mps, s.max_course_turn_deg_s)
    out = np.zeros(len(course), bool)
    diff = np.degrees(np.abs(wrap_angle_rad(np.asarray(yaw_rad, float) - course)))
    out[straight] = diff[straight] > s.max_course_disagreement_deg
    return out


def course_check(t_s, heading_new_rad, heading_old_rad, vel_ne_mps, roll_rad,
                 s: WmmFitSettings = WmmFitSettings()) -> dict:
    """The GPS course over ground as an independent yaw reference, to check a heading change.

    In straight, level (|roll| < ``course_check_max_roll_deg``), fast (> ``course_check_min_speed_mps``)
    flight the heading minus the course is the crab angle (wind, a vehicle that does not face its way),
    roughly constant, so a compass error shows as the spread of δ = ψ − course about its circular
    mean.  For the compass heading with the corrections in force (old) and with the new calibration
    (new): mean and RMS spread of δ [deg]; ``slope``: of (course − ψ_old) on (ψ_new − ψ_old), both
    less their means: ≈ 1 when the course confirms the fitted heading change, ≈ 0 when it does not
    see it (NaN when the heading change does not vary).  Needs ≥ ``course_check_min_samples``
    samples in ≥ 2 of 12 course sectors (one course cannot tell a compass error from crab).
    Returns a JSON-ready dict with ``status`` ok | too_little_straight_flight, and ``verdict``."""
    t = np.asarray(t_s, float).ravel()
    straight, course = straight_and_fast(t, vel_ne_mps, s.course_check_min_speed_mps, s.max_course_turn_deg_s)
    new, old = np.asarray(heading_new_rad, float).ravel(), np.asarray(heading_old_rad, float).ravel()
    use = straight & (np.abs(np.degrees(np.asarray(roll_rad, float).ravel())) < s.course_check_max_roll_deg) \
        & np.isfinite(new) & np.isfinite(old)
    sectors = len(np.unique((np.mod(course[use], 2 * np.pi) / (2 * np.pi) * 12).astype(int)))
    out: dict = {"samples": int(use.sum()), "course_sectors": sectors, "min_speed_mps": s.course_check_min_speed_mps}
    if use.sum() < s.course_check_min_samples or sectors < 2:
        out.update(status="too_little_straight_flight",
                   verdict=f"not checked: {int(use.sum())} samples of straight, level flight faster than "
                           f"{s.course_check_min_speed_mps:g} m/s in {sectors} course sector(s) "
                           f"(need {s.course_check_min_samples} in 2 or more)")
        return out

    def spread(psi):
        d = wrap_angle_rad(psi[use] - course[use])
        mean = float(np.angle(np.mean(np.exp(1j * d))))
        dev = wrap_angle_rad(d - mean)
        return d, mean, dev, float(np.degrees(np.sqrt(np.mean(dev ** 2))))

    _, m_old, dev_old, sd_old = spread(old)
    _, m_new, _, sd_new = spread(new)
    change = wrap_angle_rad(new[use] - old[use])
    change = change - change.mean()
    slope = float(np.dot(change, -dev_old) / np.dot(change, change)) if np.degrees(np.std(change)) > 0.2 else float("nan")
    better = sd_new < sd_old - 0.5
    worse = sd_new > sd_old + 0.5
    verdict = ("the GPS course agrees better with the new calibration" if better else
               "the GPS course agrees worse with the new calibration" if worse else
               "the GPS course does not tell the two apart")
    out.update(status="ok", old={"mean_deg": round(float(np.degrees(m_old)), 2), "spread_deg": round(sd_old, 2)},
               new={"mean_deg": round(float(np.degrees(m_new)), 2), "spread_deg": round(sd_new, 2)},
               slope=round(slope, 2) if np.isfinite(slope) else None,
               verdict=verdict + f" (heading − course spread {sd_old:.1f}° in force, {sd_new:.1f}° new"
                       + (f"; the course sees {slope:.0%} of the fitted heading change" if np.isfinite(slope) else "")
                       + ")")
    return out


def _gate(t_s, raw, roll, pitch, yaw, rate_deg_s, s: WmmFitSettings) -> tuple[np.ndarray, dict]:
    """Mask of usable samples and the counts of each rejection reason (yaw-independent gates)."""
    att = np.column_stack([roll, pitch, yaw])
    finite_mag = np.all(np.isfinite(raw), axis=1) & np.isfinite(t_s)
    finite_att = np.all(np.isfinite(att), axis=1)
    rate = np.asarray(rate_deg_s, float) if rate_deg_s is not None else np.zeros(len(raw))
    fast = finite_att & np.isfinite(rate) & (rate > s.max_rate_deg_s)
    rej = {"non_finite_field": int((~finite_mag).sum()), "no_attitude": int((finite_mag & ~finite_att).sum()),
           "fast_rotation": int((finite_mag & fast).sum())}
    return finite_mag & finite_att & ~fast, rej


def _heading_coverage(yaw_rad: np.ndarray, sectors: int = 12) -> float:
    y = np.mod(np.asarray(yaw_rad, float), 2 * np.pi)
    y = y[np.isfinite(y)]
    if len(y) == 0:
        return 0.0
    return float(len(np.unique((y / (2 * np.pi) * sectors).astype(int) % sectors)) / sectors)


def heading_imbalance(yaw_rad: np.ndarray) -> float:
    """|mean e^{2iψ}| over the samples: 1 when one line flown both ways (or one heading) carries the
    flight, the degeneracy of the offsets with the soft-iron terms in the second harmonic of the
    heading; 0 for headings spread evenly (a square, three legs at 120°, full turns).  The real
    dronekit flight (mostly one heading, turns all round): 0.76; simulated A–B missions: 0.9998."""
    y = np.asarray(yaw_rad, float)
    y = y[np.isfinite(y)]
    return float(abs(np.mean(np.exp(2j * y)))) if len(y) else 1.0


def _options(model: str, active: np.ndarray, s: WmmFitSettings) -> SolverOptions:
    prior = np.array([s.offset_prior_sd_mG] * 3 + [s.diag_prior_sd] * 3 + [s.offdiag_prior_sd] * 3
                     + [s.motor_prior_sd_mG_per_unit] * 3)
    return SolverOptions(model, active, prior, s.huber_k, s.outlier_sigma, s.max_iter)


def _initial_offsets(data: FieldData, M: np.ndarray) -> np.ndarray:
    """Closed-form start: b = median(m − A h), A = M⁻¹ (exact when the yaw and M are right)."""
    return np.median(data.mag_raw_mG - data.expected_body_mG() @ np.linalg.inv(M).T, axis=0)


def _fit_terms(data: FieldData, model: str, p0: np.ndarray, auto: np.ndarray, forced: np.ndarray,
               s: WmmFitSettings, held: np.ndarray | None = None, field_cov_ned_mG2: np.ndarray | None = None
               ) -> tuple[Solution, np.ndarray]:
    """Fit with forced + auto terms; drop auto elements whose posterior sd is not well below the
    prior sd; clamp to bounds.  Returns the final solution and the active mask."""
    prior = _options(model, forced | auto, s).prior_sd
    active = forced | auto
    p_init = p0.copy()
    p_init[:3] = _initial_offsets(data, matrix_from_params(p0))
    # Huber weights alone first, hard rejection from that answer: rejection judged at the start (the
    # motor term at 0, the matrix in force) dropped the high-current samples for good when the start
    # fitted the rest well, e.g. from the true DIA/ODI (SITL seed 13: motor field 5 % off, 9 mG)
    sol = solve(data, p_init, p0, replace(_options(model, active, s), outlier_sigma=np.inf))
    sol = solve(data, sol.params, p0, _options(model, active, s))
    for _ in range(3):
        sd = np.sqrt(np.clip(np.diag(sol.support_covariance), 0, None))
        weak = auto & active & ~(sd < s.supported_ratio * prior)
        if not weak.any():
            break
        active = active & ~weak
        sol = solve(data, np.where(active, sol.params, p0), p0, _options(model, active, s))
    # diag_limits bound the correction matrix M = A⁻¹: A's diagonal within [1/hi, 1/lo]
    lo = np.array([-np.inf] * 3 + [1.0 / s.diag_limits[1]] * 3 + [-s.offdiag_limit] * 3 + [-s.motor_limit_mG_per_unit] * 3)
    hi = -lo
    hi[3:6] = 1.0 / s.diag_limits[0]
    clamped = active & ((sol.params < lo) | (sol.params > hi))
    clamped[:3] = False
    if clamped.any():
        p_fix = np.where(clamped, np.clip(sol.params, lo, hi), sol.params)
        active = active & ~clamped
        sol = solve(data, p_fix, np.where(clamped, p_fix, p0), _options(model, active, s))
    # the covariance stated is the marginal over every candidate term: a term held at nominal because
    # the data barely constrain it still trades against the offsets within its prior (measured on
    # simulated A–B missions: the conditional covariance covered the true error 0 times in 4)
    every = forced | auto | (np.zeros(12, bool) if held is None else held)   # + terms the fit chose to hold
    marginal = solve(data, sol.params, p0, replace(_options(model, every, s), max_iter=0))
    cov = _with_jackknife(marginal.covariance, data, sol, active, p0, model, s)
    return replace(sol, covariance=_with_flight_wide_errors(cov, data, sol, active, p0, model, s, field_cov_ned_mG2)), active


def _field_shifts(s: WmmFitSettings, field_cov_ned_mG2: np.ndarray | None) -> list[np.ndarray]:
    """1σ shifts of the reference field (NED, mG) spanning its uncertainty: along N, E, D by
    ``field_model_sd_mG`` when no covariance is given (or it is diagonal), else along the covariance's
    principal axes by the square roots of their variances."""
    if field_cov_ned_mG2 is None:
        C = np.diag(np.square(np.asarray(s.field_model_sd_mG, float)))
    else:
        C = np.asarray(field_cov_ned_mG2, float)
    if not np.all(np.isfinite(C)):
        return []
    if not np.any(C - np.diag(np.diag(C))):
        sd = np.sqrt(np.clip(np.diag(C), 0, None))
        return [sd[j] * np.eye(3)[j] for j in range(3) if sd[j] > 0]
    lam, V = np.linalg.eigh((C + C.T) / 2)
    return [np.sqrt(v) * V[:, j] for j, v in enumerate(lam) if v > 1e-12]


def _with_flight_wide_errors(cov: np.ndarray, data: FieldData, sol: Solution, active: np.ndarray, p0: np.ndarray,
                      model: str, s: WmmFitSettings, field_cov_ned_mG2: np.ndarray | None = None) -> np.ndarray:
    """The covariance plus the errors common to the whole flight that no residual and no resampling of
    the samples sees: cov + S Sᵀ, S the change of the solution per 1σ of each, re-solved from ``sol``
    in lockstep (estimators.field_model_groups).

    * The reference field's: each 1σ shift of ``_field_shifts`` (the WMM's error model,
      ``field_model_sd_mG``, or the covariance of the field refined from the flight,
      estimators.field_refine).  In level flight the body z axis sees the vertical field D at one
      level: b_z = mean m_z − a_z·D, and a_z is measured through the horizontal field H tilting into z,
      so it scales with the model's H.  Measured on the ArduPilot SITL route flight at Canberra (seed
      15, D ≈ −530 mG, H ≈ 235 mG, compass 1): the reference's N +3 mG moves every diagonal term
      −1.2 % and b_z −8.2 mG; D +3 / −3 mG moves b_z −4.4 / +7.9 mG.  The three compasses' z offsets
      were all −8.7 mG off against our WMM and −3 to −4 mG against SITL's own field table, with a
      stated 1σ of 3 mG.
    * The attitude's tilt: roll, then pitch, off by ``attitude_tilt_sd_deg``.  A body tilt δ turns the
      expected field by δ × h, and its mean over the flight, δ × (0, 0, D) in level flight, is an
      offset (0.1° is 0.8 mG of x and y at D = 470 mG; re-solved, 0.8–1.9 mG on the SITL route
      flights).  The yaw-free fit absorbs a yaw error."""
    H = np.asarray(data.field_ned_mG, float)
    variants = [data.with_field(H + d) for d in _field_shifts(s, field_cov_ned_mG2)]
    tilt = np.radians(s.attitude_tilt_sd_deg)
    if tilt > 0:
        variants += [replace(data, roll_rad=data.roll_rad + tilt), replace(data, pitch_rad=data.pitch_rad + tilt)]
    if not variants or not np.all(np.isfinite(cov)):
        return cov
    P, _ = _solved_in_lockstep([data] + variants, sol, active, p0, model, s)   # as given, then under each error
    S = (P[1:] - P[0]).T
    return cov + S @ S.T


def _solved_in_lockstep(variants: list[FieldData], sol: Solution, active: np.ndarray, p0: np.ndarray,
                        model: str, s: WmmFitSettings):
    """(P (G,12), rows): the fit of ``sol``'s terms re-solved from ``sol`` on each of ``variants`` (the
    same samples under a shifted reference field or a tilted attitude), in lockstep
    (estimators.field_model_groups), and their stacked rows."""
    rows = stack_rows(variants)
    P = solve_groups(rows, sol.params, p0, replace(_options(model, active, s), max_iter=8),
                     weight=variants[0].weight).params
    return P, rows


def field_direction_nll(data: FieldData, sol: Solution, active: np.ndarray, p0: np.ndarray, model: str,
                        s: WmmFitSettings, direction_ned: np.ndarray, shifts_mG) -> np.ndarray:
    """−2 log L of the fit over shifts of the reference field along ``direction_ned`` (the profile of
    estimators.field_refine): each shift re-solved with the terms of ``sol`` (in lockstep), its
    residual scored at ``sol``'s scale σ on ``sol``'s inliers, Σ ρ(|r|/σ) with ρ(u) = u² (Huber's
    linear tail beyond the solver's threshold), divided by the residual's autocorrelation time τ
    (slow attitude errors: the samples are not independent).  Minimum 0.  (G,) over the shifts."""
    e = np.asarray(direction_ned, float)
    H = np.asarray(data.field_ned_mG, float)
    P, rows = _solved_in_lockstep([data.with_field(H + d * e) for d in shifts_mG], sol, active, p0, model, s)
    r, _ = model_terms(P, rows, model)
    u = np.sqrt(np.sum(r * r, axis=1)) / max(sol.sigma_mG, 1e-9)
    c = s.huber_k * np.sqrt(2.0)         # the solver's threshold, |r|/√2 ≤ k·σ
    loss = np.where(u <= c, u * u, 2 * c * u - c * c)
    if data.weight is not None:
        loss = loss * data.weight
    nll = np.sum(loss[:, sol.inliers], axis=1) / max(sol.autocorr, 1.0)
    return nll - nll.min()


def _with_jackknife(cov: np.ndarray, data: FieldData, sol: Solution, active: np.ndarray, p0: np.ndarray,
                    model: str, s: WmmFitSettings) -> np.ndarray:
    """The covariance, each parameter's variance raised to at least its delete-one-block jackknife
    variance, the larger of two: delete one of K contiguous time blocks, and delete one heading sector
    (of 12) flown (v = (k−1)/k Σ (p₋ₖ − p̄)², k groups), correlations kept.  The jackknife sees what
    the linearised covariance does not: slow attitude errors (time blocks) and the trade between the
    offsets and the soft-iron terms when few headings carry the fit (sectors) (Efron & Stein 1981).
    The refits of one kind are solved in lockstep (estimators.field_model_groups.solve_groups: each
    the solve of its own rows, tested equal to it)."""
    K = int(s.jackknife_blocks)
    n = len(data.roll_rad)
    if K < 3 or n < K * 10 or not np.all(np.isfinite(cov)):
        return cov
    var = np.zeros(12)
    sector = (np.mod(data.yaw_rad, 2 * np.pi) / (2 * np.pi) * 12).astype(int) % 12
    for block in (np.minimum((np.arange(n) * K) // n, K - 1), sector):
        groups = [g for g in np.unique(block) if (block == g).sum() >= max(10, n // 50)]
        if len(groups) < 3:
            continue
        keep = np.asarray([block != g for g in groups])          # each refit without one group, in lockstep
        P = solve_groups(data.rows(), sol.params, p0, replace(_options(model, active, s), max_iter=8), keep,
                         data.weight).params
        k = len(groups)
        var = np.maximum(var, (k - 1) / k * np.sum((P - P.mean(axis=0)) ** 2, axis=0))
    sd_a = np.sqrt(np.clip(np.diag(cov), 0, None))
    scale = np.where(sd_a > 0, np.sqrt(np.maximum(1.0, var / np.where(sd_a > 0, sd_a ** 2, 1.0))), 1.0)
    return cov * np.outer(scale, scale)


def _yaw_checks(data: FieldData, p: np.ndarray, corrected_in_force: np.ndarray | None,
                s: WmmFitSettings) -> tuple[float, float]:
    """(dependence slope, disagreement RMS deg) of the attitude yaw against the yaw-free fit.

    disagreement: RMS of (attitude yaw − heading of the fitted compass); small only when the yaw
    is right (whatever its source), so the full-vector residual may use it.
    slope: of (attitude yaw − fitted heading) on (in-force heading − fitted heading): ≈ 1 when the
    attitude follows this compass with its in-force corrections, ≈ 0 when it does not; NaN when the
    in-force corrections are unknown or give the same headings (spread < min_heading_spread_deg)."""
    psi_fit = compass_heading_rad(corrected_field(p, data), data.roll_rad, data.pitch_rad, data.field_ned_mG)
    d_att = wrap_angle_rad(data.yaw_rad - psi_fit)
    rms = float(np.degrees(np.sqrt(np.mean(d_att ** 2))))
    if corrected_in_force is None:
        return float("nan"), rms
    psi_in = compass_heading_rad(corrected_in_force, data.roll_rad, data.pitch_rad, data.field_ned_mG)
    d_in = wrap_angle_rad(psi_in - psi_fit)
    good = np.isfinite(d_in) & np.isfinite(d_att)
    if good.sum() < 10:
        return float("nan"), rms
    x, y = d_in[good] - d_in[good].mean(), d_att[good] - d_att[good].mean()
    if np.degrees(np.std(x)) < s.min_heading_spread_deg:
        return float("nan"), rms
    return float(np.dot(x, y) / np.dot(x, x)), rms


def _term_masks(s: WmmFitSettings, use_motor: bool, motor_forced: bool) -> tuple[np.ndarray, np.ndarray]:
    """(forced, auto) masks over PARAM_NAMES."""
    forced = np.zeros(12, bool)
    auto = np.zeros(12, bool)
    forced[:3] = True
    if s.fit_diagonal is True:
        forced[3:6] = True
    elif s.fit_diagonal is None:
        auto[3:6] = True
    if s.fit_offdiagonal:
        auto[6:9] = True
    if use_motor:
        (forced if motor_forced else auto)[9:12] = True
    return forced, auto


def _motor_choice(signal, ok, s: WmmFitSettings) -> tuple[bool, bool, str]:
    """(use motor term, forced, note)."""
    if signal is None or s.fit_motor is False:
        return False, False, ""
    fin = ok & np.isfinite(signal)
    sd = float(np.std(signal[fin])) if fin.sum() > 1 else 0.0
    if s.fit_motor is True:
        return True, True, ""
    if sd >= s.min_motor_signal_std:
        return True, False, ""
    return False, False, f"motor term not fitted: signal varies by {sd:.2f} (sd) only"


def _worst_offset_sd(cov: np.ndarray) -> float:
    c = cov[:3, :3]
    return float(np.sqrt(max(np.linalg.eigvalsh(c)[-1], 0.0))) if np.all(np.isfinite(c)) else float("inf")


def _heading_change(data: FieldData, p: np.ndarray, corrected_in_force: np.ndarray | None) -> tuple[float, float]:
    """(RMS, max |Δψ|) deg of the tilt-compensated heading with the new calibration against the one
    with the corrections in force (NaN when those are not known)."""
    if corrected_in_force is None or len(corrected_in_force) != len(data.roll_rad):
        return float("nan"), float("nan")
    new = compass_heading_rad(corrected_field(p, data), data.roll_rad, data.pitch_rad, data.field_ned_mG)
    old = compass_heading_rad(corrected_in_force, data.roll_rad, data.pitch_rad, data.field_ned_mG)
    d = np.degrees(np.abs(wrap_angle_rad(new - old)))
    d = d[np.isfinite(d)]
    return (float(np.sqrt(np.mean(d ** 2))), float(np.max(d))) if len(d) else (float("nan"), float("nan"))


def _result(sol: Solution, active: np.ndarray, model: str, yaw: tuple[float, float], data: FieldData,
            n_in: int, rej: dict, notes: list[str], s: WmmFitSettings, heading_change: tuple[float, float],
            sphere_coverage: float) -> WmmFit:
    """Status: ok (recommended) | weak (an answer with its 1σ, not recommended) | a refusal when the
    offsets are unobservable (too few headings, 1σ beyond ``max_answer_sd_mG``) or out of range."""
    p, cov = sol.params, sol.covariance
    slope, disagree = yaw
    sd = np.sqrt(np.clip(np.diag(cov), 0, None))
    worst_sd = _worst_offset_sd(cov)
    rej = dict(rej, outliers=int((~sol.inliers).sum()))
    coverage = _heading_coverage(data.yaw_rad[sol.inliers])
    sectors = int(round(coverage * 12))
    depends = model == "yaw_free" and not (np.isfinite(slope) and slope < s.yaw_dependence_slope)
    refused = "attitude_depends_on_compass" if depends else "insufficient_data"
    indep = ("; if the attitude's yaw is independent and accurate (GPS yaw), fit with yaw_source 'independent'"
             if model == "yaw_free" else "")
    recommended, reason = False, ""
    if np.any(np.abs(p[:3]) > s.offset_limit_mG):
        status = "offsets_out_of_range"
        notes.append(f"offsets beyond ±{s.offset_limit_mG:.0f} mG")
        reason = f"offsets beyond ±{s.offset_limit_mG:.0f} mG: check the compass orientation and the log's corrections"
    elif coverage < s.min_heading_coverage:
        # Few headings (a there-and-back mission): the covariance, linearised at the solution, does
        # not show the trade between the offset across track and the soft-iron terms; measured on a
        # two-heading simulated mission: sd 2 mG reported, 176 mG error.
        status = refused
        notes.append(f"offsets unobservable: {sectors} of 12 heading sectors flown "
                     f"(need {int(np.ceil(s.min_heading_coverage * 12))})" + indep)
        reason = f"unobservable from {sectors} of 12 headings: {FLY_FOR_HEADINGS}"
    elif not worst_sd <= s.max_answer_sd_mG:
        status = refused
        notes.append(f"offsets unobservable: 1σ up to {worst_sd:.0f} mG" + indep)
        reason = f"unobservable (1σ up to {worst_sd:.0f} mG): {FLY_FOR_HEADINGS}"
    elif worst_sd > s.max_offset_sd_mG:
        status = "weak"
        reason = (f"not recommended: offsets uncertain by up to {worst_sd:.1f} mG (1σ, limit {s.max_offset_sd_mG:.0f}) "
                  f"from {sectors} of 12 headings" + (" and the attitude's yaw may follow this compass" if depends else "")
                  + f"; to pin them down {FLY_FOR_HEADINGS}")
        notes.append(reason + indep)
    else:
        status, recommended = "ok", True
        reason = f"recommended: offsets known to {worst_sd:.1f} mG (1σ, worst axis) from {sectors} of 12 headings"
    if status in ("ok", "weak") and np.isfinite(heading_change[1]):
        reason += f"; the heading changes by {heading_change[0]:.1f}° RMS, up to {heading_change[1]:.1f}°"
    head = f"{model} fit of {int(sol.inliers.sum())} samples, residual RMS {sol.residual_rms_mG:.1f} mG"
    fitted = tuple(n for n, a in zip(PARAM_NAMES, active) if a)
    return WmmFit(status, "; ".join([head] + notes), model, model == "vector", p[:3].copy(), matrix_from_params(p),
                  p[9:12].copy(), cov, sd[:3], sd[9:12], fitted, sol.residual_rms_mG, int(sol.inliers.sum()), n_in,
                  rej, coverage, slope, disagree, recommended, reason, heading_change, sphere_coverage, settings=s)


def fit_wmm(t_s, mag_raw_mG, roll_rad, pitch_rad, yaw_rad, field_ned_mG, *, attitude_rate_deg_s=None,
            motor_signal=None, gps_vel_ne_mps=None, corrected_in_force_mG=None, nominal_matrix=None,
            field_cov_ned_mG2=None, profile_direction_ned=None, settings: WmmFitSettings = WmmFitSettings()) -> WmmFit:
    """Fit offsets (and supported diagonal / motor terms) of one compass against the WMM.

    Args (N samples on the field's time base; use estimators.log_alignment to get there):
        t_s (N,) s; mag_raw_mG (N,3) raw body field (corrections in force un-applied,
        estimators.compass_corrections); roll/pitch/yaw_rad (N,) autopilot attitude (NaN: none);
        field_ned_mG (3,) WMM field, or (N,3) the WMM at each sample's position, altitude and date
        (estimators.geomag.field_along_path); attitude_rate_deg_s (N,) from ``attitude_at`` (rate gate);
        motor_signal (N,) current A or throttle 0..1; gps_vel_ne_mps (N,2) GPS velocity (course gate);
        corrected_in_force_mG (N,3) the logged corrected field (yaw-dependence test);
        nominal_matrix (3,3) M held where not fitted (e.g. the DIA/ODI in force);
        field_cov_ned_mG2 (3,3) the reference field's covariance in the stated 1σ (None: the WMM's
        error model, ``field_model_sd_mG``; estimators.field_refine gives the refined field's);
        profile_direction_ned (3,): also return the fit's −2 log L over shifts of the reference along
        it (``field_profile_nll``, for estimators.field_refine), when the fit answers.
    Returns a ``WmmFit``; never raises on bad input (status and message say what was wrong).
    """
    s = settings
    raw = np.asarray(mag_raw_mG, float).reshape(-1, 3)
    n = len(raw)
    H = np.asarray(field_ned_mG, float)
    H = H.ravel() if H.size == 3 else H
    if H.shape not in ((3,), (n, 3)) or not np.all(np.isfinite(H)) or np.any(np.linalg.norm(H, axis=-1) <= 0):
        return _failed("no_expected_field", "no finite WMM field given (one (3,) or one per sample (N,3))", n, {}, s)
    cols = [np.full(n, np.nan) if a is None else np.asarray(a, float).ravel() for a in (roll_rad, pitch_rad, yaw_rad)]
    if any(len(c) != n for c in cols) or not np.any(np.all(np.isfinite(np.column_stack(cols)), axis=1)):
        return _failed("no_attitude", "no attitude at the field samples", n, {"no_attitude": n}, s)
    t = np.asarray(t_s, float).ravel()
    signal = None if motor_signal is None else np.asarray(motor_signal, float).ravel()
    ok, rej = _gate(t, raw, *cols, attitude_rate_deg_s, s)
    use_motor, motor_forced, motor_note = _motor_choice(signal, ok, s)
    if use_motor:
        rej["no_motor_signal"] = int((ok & ~np.isfinite(signal)).sum())
        ok &= np.isfinite(signal)
    notes = [motor_note] if motor_note else []
    if ok.sum() < s.min_samples:
        return _failed("insufficient_data", f"{int(ok.sum())} usable samples of {n} (need {s.min_samples}); "
                       "rejected: " + (", ".join(f"{k.replace('_', ' ')} {v}" for k, v in rej.items() if v) or "none"), n, rej, s)
    flown = _heading_coverage(cols[2][ok])
    if flown < s.min_heading_coverage:          # the attitude's headings, before any fit: no point solving
        k = int(round(flown * 12))
        return _failed("insufficient_data", f"offsets unobservable: {k} of 12 heading sectors "
                       f"flown (need {int(np.ceil(s.min_heading_coverage * 12))})", n, rej, s,
                       f"unobservable from {k} of 12 headings: {FLY_FOR_HEADINGS}", flown)
    M0 = np.eye(3) if nominal_matrix is None else np.asarray(nominal_matrix, float)
    p0 = nominal_params(M0)
    imbalance = heading_imbalance(cols[2][ok])
    few = imbalance > s.max_heading_imbalance
    if few:     # one heading (line) dominates: the soft-iron terms would trade against the offsets (measured
        # on simulated A–B missions: 1σ covered the error 5 times in 12 with them fitted, 11 in 12 held)
        notes.append(f"one heading line dominates the flight (imbalance {imbalance:.2f}): soft iron held at "
                     "nominal, its uncertainty included in the offsets' 1σ")
    forced, auto = _term_masks(replace(s, fit_diagonal=False, fit_offdiagonal=False) if few else s,
                               use_motor, motor_forced)
    wanted_f, wanted_a = _term_masks(s, use_motor, motor_forced)
    held = (wanted_f | wanted_a) & ~(forced | auto)     # held by this fit's choice: their prior enters the 1σ
    sig = signal if use_motor else np.zeros(n)

    cover = [0.0]

    def data_for(mask):
        d = FieldData(raw[mask], cols[0][mask], cols[1][mask], cols[2][mask], sig[mask], H if H.ndim == 1 else H[mask])
        w, cover[0] = sphere_cell_weights(d.expected_body_mG(), s.sphere_bands, s.sphere_sectors)
        return replace(d, weight=w) if (few if s.cell_weighting is None else s.cell_weighting) else d

    model = "vector" if s.yaw_source == "independent" else "yaw_free"
    data = data_for(ok)
    sol, active = _fit_terms(data, model, p0, auto, forced, s, held, field_cov_ned_mG2)
    cin = None if corrected_in_force_mG is None else np.asarray(corrected_in_force_mG, float).reshape(-1, 3)[ok]
    slope, disagree = _yaw_checks(data, sol.params, cin, s)
    notes.append(f"attitude yaw vs fitted heading: {disagree:.1f} deg RMS"
                 + (f", dependence on this compass: slope {slope:.2f}" if np.isfinite(slope) else ""))
    if model == "vector" and gps_vel_ne_mps is not None:
        bad = ok & _course_disagrees(t, cols[2], gps_vel_ne_mps, s)
        rej["course_disagreement"] = int(bad.sum())
        ok &= ~bad
        if ok.sum() < s.min_samples:
            return _failed("insufficient_data", f"{int(ok.sum())} samples left after the course check", n, rej, s)
        data = data_for(ok)
    if model == "vector" and gps_vel_ne_mps is not None:
        sol, active = _fit_terms(data, model, p0, auto, forced, s, held, field_cov_ned_mG2)   # refit without the gated samples
    cin_used = None if corrected_in_force_mG is None else np.asarray(corrected_in_force_mG, float).reshape(-1, 3)[ok]
    fit = _result(sol, active, model, (slope, disagree), data, n, rej, notes, s,
                  _heading_change(data, sol.params, cin_used), cover[0])
    if gps_vel_ne_mps is not None and cin_used is not None and fit.status in ("ok", "weak"):
        Hs = data.field_ned_mG
        new = compass_heading_rad(corrected_field(sol.params, data), data.roll_rad, data.pitch_rad, Hs)
        old = compass_heading_rad(cin_used, data.roll_rad, data.pitch_rad, Hs)
        fit = replace(fit, course=course_check(t[ok], new, old, np.asarray(gps_vel_ne_mps, float).reshape(-1, 2)[ok],
                                               data.roll_rad, s))
    if profile_direction_ned is not None and fit.status in ("ok", "weak"):
        fit = replace(fit, field_profile_nll=field_direction_nll(data, sol, active, p0, model, s, profile_direction_ned,
                                                                 s.field_profile_shifts_mG))
    return fit


def heldout_residual_mG(t_s, mag_raw_mG, roll_rad, pitch_rad, yaw_rad, field_ned_mG, *, attitude_rate_deg_s=None,
                        motor_signal=None, nominal_matrix=None, settings: WmmFitSettings = WmmFitSettings(),
                        block_samples: int = 20) -> tuple[float, int]:
    """How well an attitude source explains a compass: the held-out residual of the in-flight fit.

    Two-fold cross-validation over interleaved time blocks of ``block_samples`` samples (even blocks
    fit, odd blocks judged, and back; short blocks so that each half flies the headings of the
    whole): each half is fitted with ``fit_wmm`` (no jackknife, no observability refusal: the
    score asks how consistent the data are, not whether the offsets are pinned down) and the residual
    r = m − A(h + f·x) − b (estimators.field_model.residuals, the fit's model) is taken on the other
    half's samples that pass the same gates.  Returns (RMS |r| [mG] over the held-out samples with
    |r| below 5 × their median, samples judged); (NaN, 0) when a half cannot be fitted.  A held-out
    residual does not reward a source for the terms it lets the fit bend to (unlike the residual
    after the fit), and an attitude that is late, noisy or wrong in tilt shows in it directly.
    """
    s = replace(settings, jackknife_blocks=0, field_model_sd_mG=(0.0, 0.0, 0.0), min_heading_coverage=0.0,
                max_answer_sd_mG=float("inf"))
    raw = np.asarray(mag_raw_mG, float).reshape(-1, 3)
    n = len(raw)
    cols = [np.asarray(a, float).ravel() for a in (roll_rad, pitch_rad, yaw_rad)]
    H = np.asarray(field_ned_mG, float)
    H = H.ravel() if H.size == 3 else H
    t = np.asarray(t_s, float).ravel()
    rate = None if attitude_rate_deg_s is None else np.asarray(attitude_rate_deg_s, float).ravel()
    sig = None if motor_signal is None else np.asarray(motor_signal, float).ravel()
    if n < 4 * block_samples or any(len(c) != n for c in cols):
        return float("nan"), 0
    fold = (np.arange(n) // max(1, int(block_samples))) % 2
    ok, _ = _gate(t, raw, *cols, rate, s)
    errs = []
    for k in (0, 1):
        train = fold != k
        pick = lambda a: None if a is None else a[train]  # noqa: E731
        fit = fit_wmm(t[train], raw[train], *(c[train] for c in cols), H if H.ndim == 1 else H[train],
                      attitude_rate_deg_s=pick(rate), motor_signal=pick(sig), nominal_matrix=nominal_matrix, settings=s)
        if fit.status not in ("ok", "weak", "attitude_depends_on_compass") or not np.all(np.isfinite(fit.offsets_mG)):
            return float("nan"), 0
        p = nominal_params(fit.matrix, fit.offsets_mG)
        f = fit.motor_mG_per_unit
        p[9:12] = np.where(np.isfinite(f), f, 0.0)
        test = (fold == k) & ok & (np.isfinite(sig) if sig is not None else True)
        x = np.zeros(int(test.sum())) if sig is None else np.nan_to_num(sig[test])
        data = FieldData(raw[test], cols[0][test], cols[1][test], cols[2][test], x, H if H.ndim == 1 else H[test])
        errs.append(np.linalg.norm(residuals(p, data, fit.model or "yaw_free"), axis=1))
    e = np.concatenate(errs)
    if len(e) == 0:
        return float("nan"), 0
    e = e[e <= 5 * np.median(e)]
    return float(np.sqrt(np.mean(e ** 2))), int(len(e))
