"""The reference field's inclination refined from the flight itself (issue 28).

The in-flight fit (estimators.wmm_fit) takes the WMM field as the truth.  Two parts of a field
error act on the offsets differently:

* its **magnitude** trades with the compass's scale: with the diagonal terms fitted, a field k times
  larger gives a matrix k times smaller and the same offsets;
* its **direction** does not: in level flight the body z axis sees the vertical field D at one
  level, b_z = mean m_z − a_z·D, and a_z is measured through the horizontal field tilting into z.
  An inclination error of δ mG across the field moves b_z by ~1.3 mG per mG (measured on ArduPilot
  SITL at Canberra, I ≈ −66°: the SITL's own field table lies 2.8 mG from WMM2025 across the field,
  and the three compasses' z offsets were all 6.5–9 mG off).

A direction error is observable from the flight when the vehicle banks and turns: the field's tilt
into the body axes then depends on the heading, which no body-fixed matrix absorbs.  Each compass's
fit gives the profile of its cost over shifts of the reference along e_I, the unit vector of the
field's inclination (``inclination_direction``): −2 log L per shift, from the robust cost at a
fixed residual scale, divided by the residual's autocorrelation time (estimators.wmm_fit.
field_direction_nll).  ``refine_field`` takes the mean of the compasses' profiles (they share one
attitude, whose slow errors dominate: counted as one measurement, not n), fits a parabola to find
the flight's estimate y and its 1σ, and combines it with the WMM's error model as a prior: a Kalman
update of the NED field with the one measurement eᵀ δH = y (Gelb 1974, ch. 4).  Refused (the prior
kept) when no profile has a minimum inside its shifts with a positive curvature.

Units: mG.  Pure numpy.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["FieldRefinement", "inclination_rad", "inclination_direction", "profile_minimum", "refine_field"]


@dataclass(frozen=True)
class FieldRefinement:
    """The reference field after the flight: WMM + ``shift_ned_mG``, with ``covariance_ned_mG2``."""
    shift_ned_mG: np.ndarray          # (3,) added to the WMM field (zeros: the prior kept)
    covariance_ned_mG2: np.ndarray    # (3,3) the refined field's covariance
    direction_ned: np.ndarray         # (3,) e_I
    measured_mG: float                # the flight's estimate along e_I (NaN: no usable profile)
    measured_sd_mG: float
    prior_sd_mG: float                # the WMM's 1σ along e_I
    profiles: int                     # profiles used
    reason: str = ""                  # why the prior was kept (empty when refined)

    @property
    def refined(self) -> bool:
        return bool(np.isfinite(self.measured_mG))

    def measured_mg_text(self) -> str:
        """The flight's estimate in words: "+2.1 ± 0.6 mG across the field, the WMM's 1σ 1.4 mG"."""
        return (f"{self.measured_mG:+.1f} ± {self.measured_sd_mG:.1f} mG across the field, "
                f"the WMM's 1σ {self.prior_sd_mG:.1f} mG")


def inclination_rad(field_ned_mG: np.ndarray) -> float:
    """The inclination atan2(D, |N, E|) of the mean of the fields given ((3,) or (N,3)) [rad]."""
    H = np.atleast_2d(np.asarray(field_ned_mG, float)).mean(axis=0)
    return float(np.arctan2(H[2], np.hypot(H[0], H[1])))


def inclination_direction(field_ned_mG: np.ndarray) -> np.ndarray:
    """e_I (3,): the unit NED vector in which a field turns when its inclination grows, ∂B̂/∂I, for
    the mean of the fields given ((3,) or (N,3))."""
    H = np.atleast_2d(np.asarray(field_ned_mG, float)).mean(axis=0)
    h = float(np.hypot(H[0], H[1]))
    inc = inclination_rad(H)
    north, east = (H[0] / h, H[1] / h) if h > 0 else (1.0, 0.0)
    return np.array([-np.sin(inc) * north, -np.sin(inc) * east, np.cos(inc)])


def profile_minimum(shifts_mG: np.ndarray, nll: np.ndarray) -> tuple[float, float]:
    """(mode, 1σ) of a −2 log-likelihood profile from the parabola through its lowest point and its two
    neighbours; (NaN, NaN) when the lowest point is at an end, the profile is not finite or the
    curvature is not positive."""
    x, y = np.asarray(shifts_mG, float), np.asarray(nll, float)
    if len(x) < 3 or not np.all(np.isfinite(y)):
        return float("nan"), float("nan")
    k = int(np.argmin(y))
    if k in (0, len(x) - 1):
        return float("nan"), float("nan")
    c2, c1, _ = np.polyfit(x[k - 1:k + 2], y[k - 1:k + 2], 2)
    if not c2 > 0:
        return float("nan"), float("nan")
    return float(-c1 / (2 * c2)), float(1.0 / np.sqrt(c2))      # −2 log L = (y − ŷ)²/σ² + const


def refine_field(field_ned_mG: np.ndarray, prior_sd_ned_mG, shifts_mG: np.ndarray,
                 profiles: list[np.ndarray], attitude_tilt_sd_deg: float) -> FieldRefinement:
    """The reference field after the flight (module docstring).  field_ned_mG: the WMM (3,) or (N,3);
    prior_sd_ned_mG (3,): the WMM's 1σ per NED component; profiles: −2 log L over ``shifts_mG``, one
    per compass (NaN-free; others are left out); attitude_tilt_sd_deg: a tilt error of the attitude
    common to the whole flight turns the field seen as a field direction error would, and no residual
    shows it: |B|·σ_tilt is added in quadrature to the flight's 1σ (0.1° is 1 mG at 580 mG).  Measured
    on ten ArduPilot SITL route flights (five sites, `.BIN` and `.tlog`, 20 estimates): the flight's
    estimate lay 0.0–1.2 mG (RMS 0.6) from the SITL's own field table along e_I, within this 1σ 18
    times in 20 (docs/inflight-calibration.md)."""
    e = inclination_direction(field_ned_mG)
    P0 = np.diag(np.square(np.asarray(prior_sd_ned_mG, float)))
    prior_sd = float(np.sqrt(e @ P0 @ e))
    good = [np.asarray(p, float) for p in profiles if p is not None and np.all(np.isfinite(p))]
    mean = np.mean(good, axis=0) if good else None
    y, sd = profile_minimum(shifts_mG, mean) if good else (float("nan"), float("nan"))
    if not (np.isfinite(y) and np.isfinite(sd) and sd > 0):
        c2 = np.polyfit(np.asarray(shifts_mG, float), mean, 2)[0] if good and np.all(np.isfinite(mean)) else 0.0
        if not good:
            why = "no compass fit gave a profile"
        elif int(np.argmin(mean)) in (0, len(mean) - 1) and c2 > 0 and 1.0 / np.sqrt(c2) < max(np.abs(shifts_mG)):
            why = (f"the flight's best field lies beyond ±{max(np.abs(shifts_mG)):.0f} mG of the WMM across it "
                   "(a local anomaly or an attitude error), not used")
        else:
            why = "the flight does not pin the inclination down"
        return FieldRefinement(np.zeros(3), P0, e, float("nan"), float("nan"), prior_sd, len(good), why)
    B = np.atleast_2d(np.asarray(field_ned_mG, float)).mean(axis=0)
    sd = float(np.hypot(sd, np.linalg.norm(B) * np.radians(attitude_tilt_sd_deg)))
    gain = P0 @ e / (prior_sd ** 2 + sd ** 2)
    cov = P0 - np.outer(gain, e @ P0)
    return FieldRefinement(gain * y, (cov + cov.T) / 2, e, y, sd, prior_sd, len(good))
