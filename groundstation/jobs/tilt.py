"""The tilt the field tests use: the autopilot's GPS-aided roll and pitch, brought forward to each
IMU step by our AHRS's change since their sample (``brought_forward``), where their lasting gap to
our AHRS's is small (``checked_tilt``); else ours.  Split from ``groundstation.jobs.inputs``
(``step_inputs`` calls both; ``StepState`` carries their state from call to call, live).  Units:
rad, s (degrees where named).
"""
from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from estimators.low_pass import low_pass_from_rest
from estimators.rotations import wrap_angle_rad

if TYPE_CHECKING:
    from groundstation.jobs.inputs import StepState

__all__ = ["brought_forward", "checked_tilt", "TILT_AGREE_DEG", "TILT_GAP_S", "TILT_JUMP_DEG", "TILT_REF_S",
           "TILT_HISTORY_S"]

TILT_AGREE_DEG = 8.0         # the autopilot's roll/pitch count only while their lasting gap to ours is this small
TILT_GAP_S = 10.0            # the gap is low-passed with this time constant (ours errs for seconds, a drift lasts)
TILT_JUMP_DEG = 20.0         # ... and a gap this large at any one step (a jump of the autopilot) counts at once
TILT_REF_S = 0.5             # the autopilot's tilt is brought forward from our step at most this before its sample
TILT_HISTORY_S = 2.0         # ... kept from call to call this long (> ATTITUDE_TIMEOUT_S + TILT_REF_S)


def brought_forward(t_s, chain, att_rp: np.ndarray, att_t_s, state: "StepState") -> np.ndarray:
    """(n, 2) the autopilot's roll and pitch brought forward from their sample time t_k to each
    step t by our AHRS's change over that interval: a + (ours(t) − ours(t_k)), ours(t_k) our
    attitude at t_k, interpolated between the last step at or before t_k (within TILT_REF_S; else
    no change) and the step after it (at or before t).  Taken at the step before t_k, the change
    over the up to one step between them was counted twice: 0.2-0.6° in the SITL's 30° rolls
    (.BIN: 10 Hz ATT between 25 Hz IMU steps; population flight pop0_1, 2026-12-06).

    A 2 Hz ATTITUDE stream is held up to 0.5 s: in a manoeuvre at 30°/s of roll or pitch the held
    value was 7-8° stale (population clean flights 5 and 189, seed 0: 50-60 mG of field-vector
    residual, 6σ, in turns), while the autopilot's own estimate was within 0.5°.  Our AHRS's
    change over half a second is good (the gyro); its lasting tilt error cancels.  ``state``
    carries our last TILT_HISTORY_S of steps from call to call (the live form calls per sample),
    so batch and live find the same step."""
    t = np.asarray(t_s, dtype=float)
    att = np.asarray(att_rp, dtype=float).reshape(len(t), 2)
    tk = np.asarray(att_t_s, dtype=float)
    ht, hr, hp = state.ours
    tt = np.concatenate([ht, t])
    rr = np.concatenate([hr, np.asarray(chain.roll_rad, dtype=float)])
    pp = np.concatenate([hp, np.asarray(chain.pitch_rad, dtype=float)])
    keep = tt >= (t[-1] if len(t) else -np.inf) - TILT_HISTORY_S
    state.ours = (tt[keep], rr[keep], pp[keep])
    if not len(t):
        return att
    j = np.searchsorted(tt, np.nan_to_num(tk, nan=-np.inf), side="right") - 1
    jj = np.maximum(j, 0)
    i = len(ht) + np.arange(len(t))
    # ours at t_k itself: between the step at or before it and the next one (at or before t, so
    # live has it too); from the step before alone, the change over [t_j, t_k] was counted twice
    j1 = np.minimum(jj + 1, i)
    with np.errstate(invalid="ignore", divide="ignore"):
        span = tt[j1] - tt[jj]
        w = np.where(span > 0, np.clip((tk - tt[jj]) / np.where(span > 0, span, 1.0), 0.0, 1.0), 0.0)
        ok = np.isfinite(tk) & (j >= 0) & (tk - tt[jj] <= TILT_REF_S)
        r_k = rr[jj] + w * wrap_angle_rad(rr[j1] - rr[jj])
        p_k = pp[jj] + w * (pp[j1] - pp[jj])
        dr = wrap_angle_rad(rr[i] - r_k)
        dp = pp[i] - p_k
        ok &= np.isfinite(dr) & np.isfinite(dp)
    return np.c_[np.where(ok, wrap_angle_rad(att[:, 0] + np.where(ok, dr, 0.0)), att[:, 0]),
                 np.where(ok, att[:, 1] + np.where(ok, dp, 0.0), att[:, 1])]


# One attitude (issues 27, 30): the detector's reference is the default AHRS, the attitude shown;
# the field tests take its tilt or the autopilot's where ours confirms it (``checked_tilt``), never
# the autopilot's heading.  Below ``min_imu_rate_hz`` the attitude-based tests are off and say why.
def checked_tilt(chain, att_rp: np.ndarray, t_s=None, state: "StepState | None" = None) -> tuple[np.ndarray, np.ndarray]:
    """(roll, pitch) [rad] for the field tests: the autopilot's GPS-aided roll and pitch where fresh
    and their lasting gap to our AHRS's is within TILT_AGREE_DEG, else ours.

    Our AHRS tilts by 5-10° for a second or two in a hard manoeuvre (a 50-80 mG field-vector
    residual), the GPS-aided autopilot does not; an autopilot drifting open-loop in a GPS outage
    drifts for tens of seconds.  So the gap g = autopilot − ours is low-passed with TILT_GAP_S,
    ḡ ← ḡ + (1 − e^(−Δt/τ)) (g − ḡ) on the steps where the autopilot is fresh (held otherwise), and
    the autopilot counts while |ḡ| ≤ TILT_AGREE_DEG and |g| ≤ TILT_JUMP_DEG on both axes (a jump of
    its estimate counts at once; our AHRS's manoeuvre errors measured up to 13°, population clean
    flight 173).  ``t_s`` and ``state``
    (``StepState``, carried from call to call live) give the steps' times and the filter's state;
    without them each step is judged on its own gap (|g|)."""
    roll, pitch = np.asarray(chain.roll_rad, dtype=float), np.asarray(chain.pitch_rad, dtype=float)
    ar, ap = np.asarray(att_rp[:, 0], dtype=float), np.asarray(att_rp[:, 1], dtype=float)
    lim = np.radians(TILT_AGREE_DEG)
    with np.errstate(invalid="ignore"):
        gr, gp = wrap_angle_rad(ar - roll), ap - pitch
        jump = np.radians(TILT_JUMP_DEG)
        agree = np.isfinite(ar) & np.isfinite(ap) & (np.abs(gr) <= jump) & (np.abs(gp) <= jump)
    if t_s is not None and state is not None:
        gr, gp = _lasting_gap(np.asarray(t_s, dtype=float), gr, gp, state)
    with np.errstate(invalid="ignore"):
        agree &= (np.abs(gr) <= lim) & (np.abs(gp) <= lim)
    return np.where(agree, ar, roll), np.where(agree, ap, pitch)


def _lasting_gap(t: np.ndarray, gr: np.ndarray, gp: np.ndarray, state: "StepState") -> tuple[np.ndarray, np.ndarray]:
    """The autopilot-minus-ours tilt gap low-passed with TILT_GAP_S (``checked_tilt``), per step.
    The gap starts from agreement, not from its first value: at the start our AHRS may not have
    converged (10° of pitch in a climb, population slow 2), and a first gap held for TILT_GAP_S
    put our wrong tilt into the whole learning time; an autopilot drifting open-loop drifts away
    from agreement."""
    gap = low_pass_from_rest(np.ascontiguousarray(t, dtype=float), np.column_stack((gr, gp)), TILT_GAP_S,
                             state.tilt_gap)
    return gap[:, 0], gap[:, 1]
