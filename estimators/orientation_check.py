"""Compass orientation check, as ArduPilot's COMPASS_AUTO_ROT does it.

ArduPilot (CompassCalibrator::calculate_orientation, AP_Compass source): for every candidate
rotation r, each calibrated sample is taken back to the sensor frame (inverse of the orientation in
use), rotated by r, and rotated into the earth frame with the attitude of that sample; a correct
orientation gives the same earth field for every sample.  The score is the variance of those
implied earth fields about their mean; the best rotation passes when it is the one in use, or when
the second best (among rotations not equivalent to it) has at least twice its variance
(``variance_threshold`` 2.0, the ``_orientation_confidence`` of MAG_CAL_REPORT).

Here: ``reference`` "mean" is ArduPilot's score; "expected" scores against the WMM field instead
(mean squared error to H_ned), which also tells apart rotations about the vertical when the yaw is
independent of this compass — with exactly level yaw turns every rotation about the body Z axis
gives a constant implied field, so "mean" cannot separate them (ambiguous, as it should say); a few
degrees of tilt, as in real flight, already do.

Statuses: confirmed (best = the rotation in use, clearly) | rotation_found (another rotation clearly
best) | ambiguous | insufficient_data | no_attitude.  Units: mG, rad.  Pure numpy.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from estimators.rotations import dcm_body_to_ned

__all__ = ["OrientationSettings", "OrientationCheck", "check_orientation"]


@dataclass(frozen=True)
class OrientationSettings:
    reference: str = "mean"            # "mean" (ArduPilot) | "expected" (needs field_ned_mG)
    variance_threshold: float = 2.0    # second best / best (ArduPilot's pass ratio)
    min_samples: int = 20
    equal_tolerance: float = 1e-3      # rotations closer than this (|R1 v − R2 v| for v=(1,2,3)/|.|) are the same


@dataclass(frozen=True)
class OrientationCheck:
    status: str
    message: str
    best_id: int | None                # caller's id of the best candidate
    second_id: int | None
    confidence: float                  # second best score / best score
    scores_mG2: dict                   # id -> score (variance or mean squared error)
    current_id: int | None
    n_used: int


def _same(R1: np.ndarray, R2: np.ndarray, tol: float) -> bool:
    """ArduPilot's rotation_equal: both rotations map (1,2,3) to the same vector."""
    v = np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)
    return float(np.linalg.norm(R1 @ v - R2 @ v)) < tol


def check_orientation(mag_cal_mG: np.ndarray, roll_rad, pitch_rad, yaw_rad,
                      candidates: Sequence[tuple[int, np.ndarray]], current_id: int, *,
                      field_ned_mG: np.ndarray | None = None,
                      settings: OrientationSettings = OrientationSettings()) -> OrientationCheck:
    """Score candidate sensor rotations of one compass.

    Args:
        mag_cal_mG (N,3): calibrated field (offsets/soft iron removed) in the body frame given by the
            orientation in use (ArduPilot's corrected field is that; a PX4 one too).
        roll/pitch/yaw_rad (N,): attitude at the samples.
        candidates: (id, R) pairs, R = the rotation enum's matrix (sensor -> body, v_body = R v_sensor),
            e.g. ArduPilot's ROTATION_* from groundstation.io.params.rotation_enum_matrix.
        current_id: the id in use (COMPASS_ORIENTn); must be among the candidates.
        field_ned_mG: WMM field, needed for reference "expected".
    """
    s = settings
    m = np.asarray(mag_cal_mG, float).reshape(-1, 3)
    att = np.column_stack([np.ravel(np.asarray(a, float)) if a is not None else np.full(len(m), np.nan)
                           for a in (roll_rad, pitch_rad, yaw_rad)])
    cand = {int(i): np.asarray(R, float) for i, R in candidates}

    def fail(status: str, msg: str, n: int = 0) -> OrientationCheck:
        return OrientationCheck(status, msg, None, None, float("nan"), {}, current_id, n)

    if current_id not in cand:
        return fail("insufficient_data", f"rotation in use ({current_id}) is not among the candidates")
    if len(att) != len(m) or not np.any(np.all(np.isfinite(att), axis=1)):
        return fail("no_attitude", "no attitude at the field samples")
    good = np.all(np.isfinite(m), axis=1) & np.all(np.isfinite(att), axis=1)
    n = int(good.sum())
    if n < s.min_samples:
        return fail("insufficient_data", f"{n} samples with attitude (need {s.min_samples})", n)
    use_expected = s.reference == "expected"
    if use_expected and (field_ned_mG is None or not np.all(np.isfinite(field_ned_mG))):
        return fail("insufficient_data", "reference 'expected' needs the WMM field", n)
    C = dcm_body_to_ned(att[good, 0], att[good, 1], att[good, 2])
    sensor = m[good] @ cand[current_id]                    # R_curᵀ v, row-wise
    scores = {}
    for i, R in cand.items():
        e = np.einsum("nij,nj->ni", C, sensor @ R.T)       # C_bn · R · v_sensor
        ref = np.asarray(field_ned_mG, float) if use_expected else e.mean(axis=0)
        scores[i] = float(np.mean(np.sum((e - ref) ** 2, axis=1)))
    best = min(scores, key=scores.get)
    others = [i for i in scores if not _same(cand[i], cand[best], s.equal_tolerance)]
    if not others:
        return OrientationCheck("ambiguous", "a single candidate rotation", best, None, float("nan"), scores, current_id, n)
    second = min(others, key=scores.get)
    conf = scores[second] / max(scores[best], 1e-12)
    is_current = _same(cand[best], cand[current_id], s.equal_tolerance)
    ties = sorted(i for i in others if scores[i] <= s.variance_threshold * scores[best])
    if conf <= s.variance_threshold:
        msg = (f"ambiguous: rotations {best} and {ties} fit within a factor {s.variance_threshold:g} "
               f"(confidence {conf:.2f}); rotate the vehicle about more axes")
        return OrientationCheck("ambiguous", msg, best, second, conf, scores, current_id, n)
    if is_current:
        return OrientationCheck("confirmed", f"rotation in use ({current_id}) fits best, confidence {conf:.1f}",
                                best, second, conf, scores, current_id, n)
    return OrientationCheck("rotation_found", f"rotation {best} fits clearly best (in use: {current_id}), "
                            f"confidence {conf:.1f}", best, second, conf, scores, current_id, n)
