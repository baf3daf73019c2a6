"""What an alarm looks like: the disturbance vector, its growth, the tests that fired, its likely kind.

``explain_alarm`` works on per-step arrays of one flight (the field-vector test's residual r̄ in
the body frame [mG], the motor signal, the position, the test scores) and an alarm's index span.
The likely kind, by the first rule that holds:
* "moving with current" (motor, payload): over the alarm and the ``lead_s`` before it, |r̄|
  follows the motor signal (Pearson r ≥ ``current_corr``) and the signal varies by at least
  ``current_min_span`` (A, or throttle %);
* "fixed in place" (an environmental anomaly): the vehicle moved between ``place_min_m`` and
  ``place_max_m`` during the alarm and |r̄| rose and fell again inside it (peak at least
  ``place_peak_ratio`` times both ends, near the peak (≥ 0.8 of it) less than ``place_flat_max`` of
  the alarm's time): a field tied to a place the vehicle passed (a dipole's field falls with the
  cube of the distance: a peak, not a plateau, over tens of metres); its position is that of the peak;
* "rising with time" (a ramp, a step): otherwise.
Growth rate: the least-squares slope of |r̄| over the ``lead_s`` up to the alarm's start [mG/s].
Units: mG, s, m, degrees of latitude/longitude.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["ExplainSettings", "explain_alarm", "KINDS"]

KINDS = ("moving with current", "fixed in place", "rising with time")


@dataclass(frozen=True)
class ExplainSettings:
    lead_s: float = 3.0              # before the alarm: growth rate and current correlation window
    current_corr: float = 0.7
    current_min_span: float = 2.0    # A (or throttle %)
    place_min_m: float = 20.0
    place_peak_ratio: float = 1.5
    place_max_m: float = 150.0
    place_flat_max: float = 0.5


def _slope(t: np.ndarray, y: np.ndarray) -> float:
    ok = np.isfinite(t) & np.isfinite(y)
    if ok.sum() < 3 or np.ptp(t[ok]) <= 0:
        return float("nan")
    return float(np.polyfit(t[ok], y[ok], 1)[0])


def _corr(a: np.ndarray, b: np.ndarray) -> float:
    ok = np.isfinite(a) & np.isfinite(b)
    if ok.sum() < 5 or np.std(a[ok]) == 0 or np.std(b[ok]) == 0:
        return float("nan")
    return float(np.corrcoef(a[ok], b[ok])[0, 1])


def explain_alarm(t_s, residual_mG, motor_signal, north_m, east_m, lat_deg, lon_deg, scores: dict,
                  i0: int, i1: int, settings: ExplainSettings | None = None) -> dict:
    """One alarm (steps i0..i1) in numbers: disturbance_mG (body, at the largest |r̄|),
    growth_mG_s, tests (names whose score reached 1), kind, position (of the peak, when fixed in
    place), current_correlation."""
    s = settings or ExplainSettings()
    t = np.asarray(t_s, dtype=float)
    r = np.asarray(residual_mG, dtype=float).reshape(-1, 3)
    size = np.linalg.norm(r, axis=1)
    lead = int(np.searchsorted(t, t[i0] - s.lead_s))
    span = slice(i0, i1 + 1)
    finite = np.isfinite(size[span])
    k = i0 + int(np.nanargmax(np.where(finite, size[span], -np.inf))) if finite.any() else i0
    out = {"disturbance_mG": [round(float(v), 1) for v in r[k]] if np.isfinite(r[k]).all() else None,
           "disturbance_size_mG": round(float(size[k]), 1) if np.isfinite(size[k]) else None,
           "growth_mG_s": None, "tests": [name for name, z in scores.items()
                                           if np.nanmax(np.r_[np.asarray(z, float)[span], -np.inf]) >= 1.0],
           "kind": KINDS[2], "position": None, "current_correlation": None}
    g = _slope(t[lead:i0 + 1], size[lead:i0 + 1])
    out["growth_mG_s"] = round(g, 1) if np.isfinite(g) else None
    x = np.asarray(motor_signal, dtype=float)
    window = slice(lead, i1 + 1)
    c = _corr(size[window], x[window])
    out["current_correlation"] = round(c, 2) if np.isfinite(c) else None
    xs = x[window][np.isfinite(x[window])]
    if np.isfinite(c) and c >= s.current_corr and len(xs) and np.ptp(xs) >= s.current_min_span:
        out["kind"] = KINDS[0]
        return out
    n, e = np.asarray(north_m, dtype=float), np.asarray(east_m, dtype=float)
    moved = np.hypot(n[i1] - n[i0], e[i1] - e[i0])
    ends = np.fmax(size[i0], size[i1])
    near_peak = float(np.mean(size[span] >= 0.8 * size[k])) if np.isfinite(size[k]) else 1.0
    if (np.isfinite(moved) and s.place_min_m <= moved <= s.place_max_m and np.isfinite(size[k])
            and size[k] >= s.place_peak_ratio * ends and near_peak < s.place_flat_max):
        out["kind"] = KINDS[1]
        la, lo = float(np.asarray(lat_deg, float)[k]), float(np.asarray(lon_deg, float)[k])
        out["position"] = {"lat": round(la, 7), "lon": round(lo, 7)} if np.isfinite(la) and np.isfinite(lo) else None
    return out
