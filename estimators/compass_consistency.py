"""Consistency of up to three compasses, as ArduPilot's pre-arm check does it, over a whole log.

ArduPilot (Compass::consistent, AP_Compass source, 4.x): every compass used for yaw is compared
with the primary's corrected body-frame field; it is inconsistent when
  * the angle between the 3-D fields exceeds AP_COMPASS_MAX_XYZ_ANG_DIFF = 90°,
  * the angle between their XY (body-frame horizontal) parts exceeds AP_COMPASS_MAX_XY_ANG_DIFF = 60°,
  * or the length of the difference of the XY parts exceeds AP_COMPASS_MAX_XY_LENGTH_DIFF = 200 mG
(3.x firmware used 50°, 30° and 100 mG).  Those limits only catch gross faults, so every pair is
also summarised (median and 95th percentile of the 3-D angle and of the field-strength difference)
and the compass that disagrees is named: with three compasses, the one whose median angle to both
others exceeds ``name_angle_deg`` while the other two agree within that and within a third of it
(likewise for the field strength: beyond ``name_strength_mG``, the other two within half of it); with two, the one
whose field strength is farther from the WMM strength when that is given, else none.

Statuses: ok | inconsistent (a pair fails ArduPilot's check on more than ``fail_fraction`` of the
common samples) | insufficient_data.  Units: mG, deg.  Pure numpy.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

__all__ = ["ConsistencySettings", "PairConsistency", "ConsistencyReport", "compass_consistency"]


@dataclass(frozen=True)
class ConsistencySettings:
    max_xyz_angle_deg: float = 90.0
    max_xy_angle_deg: float = 60.0
    max_xy_length_diff_mG: float = 200.0
    fail_fraction: float = 0.05
    name_angle_deg: float = 5.0
    name_strength_mG: float = 30.0
    min_samples: int = 10


@dataclass(frozen=True)
class PairConsistency:
    a: int
    b: int
    n: int
    angle_median_deg: float
    angle_p95_deg: float
    xy_angle_median_deg: float
    xy_length_diff_median_mG: float
    strength_diff_median_mG: float      # |m_b| − |m_a|
    fail_fraction: float                # of samples failing ArduPilot's check
    ardupilot_consistent: bool


@dataclass(frozen=True)
class ConsistencyReport:
    status: str
    message: str
    pairs: tuple[PairConsistency, ...]
    disagreeing: int | None             # compass index named as the odd one out
    strength_median_mG: tuple[float, ...]


def _angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    na, nb = np.linalg.norm(a, axis=1), np.linalg.norm(b, axis=1)
    ok = (na > 0) & (nb > 0)
    cos = np.where(ok, np.sum(a * b, axis=1) / np.where(ok, na * nb, 1.0), 1.0)
    return np.where(ok, np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))), 180.0)


def _pair(i: int, j: int, a: np.ndarray, b: np.ndarray, s: ConsistencySettings) -> PairConsistency | None:
    good = np.all(np.isfinite(a), axis=1) & np.all(np.isfinite(b), axis=1)
    n = int(good.sum())
    if n < s.min_samples:
        return None
    a, b = a[good], b[good]
    ang = _angle_deg(a, b)
    xy = _angle_deg(np.column_stack([a[:, :2], np.zeros(n)]), np.column_stack([b[:, :2], np.zeros(n)]))
    xy_len = np.linalg.norm(a[:, :2] - b[:, :2], axis=1)
    fails = (ang > s.max_xyz_angle_deg) | (xy > s.max_xy_angle_deg) | (xy_len > s.max_xy_length_diff_mG)
    frac = float(fails.mean())
    return PairConsistency(i, j, n, float(np.median(ang)), float(np.percentile(ang, 95)), float(np.median(xy)),
                           float(np.median(xy_len)),
                           float(np.median(np.linalg.norm(b, axis=1) - np.linalg.norm(a, axis=1))),
                           frac, frac <= s.fail_fraction)


def _odd_one(pairs: list[PairConsistency], k: int, strengths: list[float], expected: float | None,
             s: ConsistencySettings) -> int | None:
    if k == 3 and len(pairs) == 3:
        for c in range(3):
            mine = [p for p in pairs if c in (p.a, p.b)]
            rest = [p for p in pairs if c not in (p.a, p.b)][0]
            ang = min(p.angle_median_deg for p in mine)
            if ang > s.name_angle_deg and rest.angle_median_deg <= min(s.name_angle_deg, ang / 3):
                return c
            dif = min(abs(p.strength_diff_median_mG) for p in mine)
            if dif > s.name_strength_mG and abs(rest.strength_diff_median_mG) <= min(s.name_strength_mG, dif / 2):
                return c
    if len(pairs) == 1 and expected is not None and np.isfinite(expected):
        p = pairs[0]
        if p.angle_median_deg > s.name_angle_deg or abs(p.strength_diff_median_mG) > s.name_strength_mG:
            dev = [abs(strengths[p.a] - expected), abs(strengths[p.b] - expected)]
            if abs(dev[0] - dev[1]) > s.name_strength_mG / 2:
                return p.a if dev[0] > dev[1] else p.b
    return None


def compass_consistency(fields_mG: Sequence[np.ndarray | None], *, expected_strength_mG: float | None = None,
                        settings: ConsistencySettings = ConsistencySettings()) -> ConsistencyReport:
    """Compare compasses on a common time base.

    Args:
        fields_mG: per compass (N,3) corrected body-frame field on the same N sample times (NaN
            where that compass has no sample, e.g. after it dropped out), or None for an absent one.
        expected_strength_mG: WMM field strength (names the odd one of two compasses).
    """
    s = settings
    arrs = [None if f is None else np.asarray(f, float).reshape(-1, 3) for f in fields_mG]
    idx = [i for i, f in enumerate(arrs) if f is not None and np.any(np.all(np.isfinite(f), axis=1))]
    strengths = [float(np.nanmedian(np.linalg.norm(f, axis=1))) if f is not None and
                 np.any(np.all(np.isfinite(f), axis=1)) else float("nan") for f in arrs]
    if len(idx) < 2:
        return ConsistencyReport("insufficient_data", f"{len(idx)} compass(es) with data: nothing to compare",
                                 (), None, tuple(strengths))
    pairs = [p for i in idx for j in idx if i < j for p in [_pair(i, j, arrs[i], arrs[j], s)] if p is not None]
    if not pairs:
        return ConsistencyReport("insufficient_data", f"fewer than {s.min_samples} common samples for every pair",
                                 (), None, tuple(strengths))
    odd = _odd_one(pairs, len(idx), strengths, expected_strength_mG, s)
    bad = [p for p in pairs if not p.ardupilot_consistent]
    status = "inconsistent" if bad else "ok"
    text = ", ".join(f"{p.a}-{p.b}: {p.angle_median_deg:.1f} deg, {p.strength_diff_median_mG:+.0f} mG"
                     f"{' (fails ArduPilot check)' if not p.ardupilot_consistent else ''}" for p in pairs)
    if odd is not None:
        text += f"; compass {odd} disagrees with the others"
    return ConsistencyReport(status, text, tuple(pairs), odd, tuple(strengths))
