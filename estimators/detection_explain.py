"""What an alarm looks like: the disturbance vector, its growth, the tests that fired, its likely kind.

``explain_alarm`` works on per-step arrays of one flight (the field-vector test's residual r̄ in
the body frame [mG], the motor signal, the position, the test scores) and an alarm's index span.
The likely kind, by the first rule that holds:
* "moving with current" (motor, payload): over the alarm and the ``lead_s`` before it, |r̄|
  follows the motor signal (Pearson r ≥ ``current_corr``) and the signal varies by at least
  ``current_min_span`` (A, or throttle %);
* "fixed in place" (an environmental anomaly): |r̄| rose and fell again around its peak as the
  vehicle flew past: both crossings of half the peak are seen (the rise up to ``shape_s`` before
  the alarm, the fall before its end) and the ground track flown from one to the other is between
  ``place_min_m`` and ``place_max_m``.  A magnetised mass on the ground is a dipole whose field
  falls with the cube of the distance (Jackson, Classical Electrodynamics, eq. 5.56): passing at
  height h within h to the side, |B| stays above half its peak over 1.3–3.0 h of track (computed
  over dipole orientations), so 60 m holds masses up to ~20–45 m below.  A disturbance that varies
  in time spans the track flown meanwhile (seed 002's ramps and bump: 90–140 m at 6 m/s), or
  none when the vehicle hovers.  Or, flown down onto the place and up again (a mass below a
  hover; ArduPilot SITL's SIM_MAG_ALY, whose field depends on the height alone): over at most
  ``place_max_m`` of track between the crossings, the vehicle came down by ``place_min_climb_m``
  or more to the peak and rose again as much after it, the peak at its lowest (``_down_and_up``):
  a field that varies in time does not peak where a descent turns into a climb but by chance.
  Or, flown down onto the place to stay there (a landing, a hover low): the height fell by
  ``place_min_climb_m`` or more while |r̄| rose through half its peak, and once the descent ended
  (the height within ``rest_band_m`` of the peak's) |r̄| held steady: after ``settle_s`` (r̄'s own
  lag) and for at least ``rest_min_s``, its slope at most ``rest_slope_ratio`` of the slope over the
  ``lead_s`` before the descent ended (``_came_down_onto``).  A field that varies in time goes on
  varying when the vehicle stops; a place's field stops with it.
  Its position is that of the peak;
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
    shape_s: float = 20.0            # before the alarm: where the rise of a field tied to a place is looked for
    place_min_m: float = 10.0        # ground track flown between the half-peak crossings (module docstring)
    place_max_m: float = 60.0
    place_min_climb_m: float = 2.0   # a descent onto a place and the climb off it (module docstring)
    rest_band_m: float = 0.5         # a descent onto a place to stay: "stopped" = within this of the peak's height
    settle_s: float = 2.0            # ... r̄'s lag after the vehicle stops
    rest_min_s: float = 1.5          # ... steady for at least this long after settle_s
    rest_slope_ratio: float = 0.25   # ... its slope at rest over the slope as it came down


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


def _half_peak_crossings(size: np.ndarray, lo: int, k: int, hi: int) -> tuple[int, int] | None:
    """(the last step below half of ``size[k]`` before k, from ``lo``; the first after k, up to
    ``hi``); None when either side never falls to half."""
    if not np.isfinite(size[k]):
        return None
    low = np.flatnonzero(size[lo:hi + 1] < 0.5 * size[k]) + lo
    before, after = low[low < k], low[low > k]
    if not len(before) or not len(after):
        return None
    return int(before[-1]), int(after[0])


def _track_m(t: np.ndarray, north_m: np.ndarray, east_m: np.ndarray, a: int, b: int) -> float:
    """Ground track flown [m] from step a to step b, from fixes 1 s apart (GPS noise adds little)."""
    fixes = np.unique(np.r_[np.searchsorted(t, np.arange(t[a], t[b], 1.0)), b])
    return float(np.nansum(np.hypot(np.diff(north_m[fixes]), np.diff(east_m[fixes]))))


def _smoothed(x: np.ndarray, half: int) -> np.ndarray:
    """Mean of the finite values within ``half`` steps either side (GPS height noise)."""
    ok = np.isfinite(x)
    c = np.r_[0.0, np.cumsum(np.where(ok, x, 0.0))]
    m = np.r_[0, np.cumsum(ok)]
    i = np.arange(len(x))
    lo, hi = np.maximum(i - half, 0), np.minimum(i + half + 1, len(x))
    count = m[hi] - m[lo]
    return np.where(count > 0, (c[hi] - c[lo]) / np.maximum(count, 1), np.nan)


def _down_and_up(up_m: np.ndarray, lo: int, k: int, hi: int, least_m: float) -> bool:
    """The vehicle came down to the peak (step k) and rose again: in steps lo..hi (the alarm and
    the ``shape_s`` before it) the height (smoothed over 1/40 of the span either side) fell by at
    least ``least_m`` before k and rose by as much after it, and at k it was within
    max(1 m, a quarter of that) of its lowest.  (|r̄| lags the field by its averaging, so the
    half-peak crossings themselves lie closer to the peak's height than the field's do.)"""
    h = _smoothed(np.asarray(up_m, dtype=float)[lo:hi + 1], max(1, (hi - lo) // 40))
    j = k - lo
    if not (0 < j < len(h) - 1 and np.isfinite(h[j])):
        return False
    fell, rose = np.nanmax(h[:j + 1]) - h[j], np.nanmax(h[j:]) - h[j]
    return bool(min(fell, rose) >= least_m and h[j] - np.nanmin(h) <= max(1.0, 0.25 * min(fell, rose)))


def _came_down_onto(t: np.ndarray, size: np.ndarray, up_m: np.ndarray, lo: int, k: int, hi: int,
                    s: "ExplainSettings") -> int | None:
    """The vehicle came down onto the place of the peak (step k) and stayed (module docstring): in
    steps lo..hi (the ``shape_s`` before the alarm and the alarm) the height (smoothed as in
    ``_down_and_up``) fell by ``place_min_climb_m`` or more to the peak's; the descent ended at the
    last step before k higher than ``rest_band_m`` above the peak's height, with |r̄| already at half
    its peak or more and below half somewhere before in the window; the height stayed within
    ``rest_band_m`` from there to hi, over at least ``settle_s + rest_min_s``; and |r̄|'s slope after
    ``settle_s`` is at most ``rest_slope_ratio`` of its slope over the ``lead_s`` before the descent
    ended (which must be rising).  Returns the step where |r̄| first rose through half its peak (the
    track is measured from there), or None."""
    h = _smoothed(np.asarray(up_m, dtype=float)[lo:hi + 1], max(1, (hi - lo) // 40))
    j = k - lo
    if not (0 < j < len(h) and np.isfinite(h[j]) and np.isfinite(size[k])):
        return None
    if np.nanmax(h[:j + 1]) - h[j] < s.place_min_climb_m:
        return None
    above = np.flatnonzero(h[:j] > h[j] + s.rest_band_m)
    if not len(above):
        return None
    rest = lo + int(above[-1]) + 1                      # the descent's end
    if np.nanmax(np.abs(h[rest - lo:] - h[j])) > s.rest_band_m:
        return None                                     # did not stay down
    half = 0.5 * size[k]
    below = np.flatnonzero(size[lo:rest] < half)
    if not len(below) or not size[rest] >= half:
        return None                                     # |r̄| did not rise through half its peak coming down
    settled = int(np.searchsorted(t, t[rest] + s.settle_s))
    if settled >= hi or t[hi] - t[settled] < s.rest_min_s:
        return None
    before = int(np.searchsorted(t, t[rest] - s.lead_s))
    coming = _slope(t[before:rest + 1], size[before:rest + 1])
    at_rest = _slope(t[settled:hi + 1], size[settled:hi + 1])
    if not (np.isfinite(coming) and coming > 0 and np.isfinite(at_rest)
            and abs(at_rest) <= s.rest_slope_ratio * coming):
        return None
    return lo + int(below[-1])


def explain_alarm(t_s, residual_mG, motor_signal, north_m, east_m, lat_deg, lon_deg, scores: dict,
                  i0: int, i1: int, settings: ExplainSettings | None = None, up_m=None) -> dict:
    """One alarm (steps i0..i1) in numbers: disturbance_mG (body, at the largest |r̄|),
    growth_mG_s, tests (names whose score reached 1), kind, position (of the peak, when fixed in
    place), current_correlation.  ``up_m``: the height [m, any datum] per step, or None."""
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
    shape_start = int(np.searchsorted(t, t[i0] - s.shape_s))
    crossings = _half_peak_crossings(size, shape_start, k, i1)
    placed = False
    if crossings is not None:
        a, b = crossings
        width_m = _track_m(t, np.asarray(north_m, dtype=float), np.asarray(east_m, dtype=float), a, b)
        placed = s.place_min_m <= width_m <= s.place_max_m or (
            up_m is not None and width_m <= s.place_max_m
            and _down_and_up(up_m, shape_start, k, i1, s.place_min_climb_m))
    if not placed and up_m is not None:
        a = _came_down_onto(t, size, up_m, shape_start, k, i1, s)
        placed = a is not None and _track_m(t, np.asarray(north_m, dtype=float), np.asarray(east_m, dtype=float),
                                            a, i1) <= s.place_max_m
    if placed:
        out["kind"] = KINDS[1]
        la, lo = float(np.asarray(lat_deg, float)[k]), float(np.asarray(lon_deg, float)[k])
        out["position"] = {"lat": round(la, 7), "lon": round(lo, 7)} if np.isfinite(la) and np.isfinite(lo) else None
    return out
