"""Alarm explanations from per-step arrays, the same for analyze, replay and a live link.

``explain_span(steps, start_s, end_s)`` runs ``estimators.detection_explain.explain_alarm`` on
the steps of one alarm (and the ``shape_s`` before it): steps is a dict of equal-length arrays
(``STEP_KEYS``: t_s, the field-vector test's residual r̄ [mG, body], the motor signal, the held
GPS lat/lon [deg] and altitude [m] and the four test scores).  North/east are metres from the first fix inside
that window, so a live history that has dropped its oldest steps explains an alarm exactly as the
whole log does.  ``ExplainHistory`` keeps those arrays for a live link (bounded);
``explanation_text`` says an explanation in words for the page and the events.
"""
from __future__ import annotations

import numpy as np

from estimators.detection import ned_from_lla
from estimators.detection_explain import ExplainSettings, explain_alarm
from groundstation.jobs.words import score_name

__all__ = ["STEP_KEYS", "SCORE_NAMES", "explain_span", "explanation_text", "ExplainHistory"]

SCORE_NAMES = ("heading_difference", "path_deviation", "field_strength_inclination", "field_vector")
STEP_KEYS = ("t_s", "rx", "ry", "rz", "motor", "lat_deg", "lon_deg", "alt_m") + SCORE_NAMES


def explain_span(steps: dict, start_s: float, end_s: float | None,
                 settings: ExplainSettings | None = None) -> dict | None:
    """The explanation of the alarm from ``start_s`` to ``end_s`` (None: the last step); None when
    the steps do not reach the alarm."""
    s = settings or ExplainSettings()
    t = np.asarray(steps["t_s"], dtype=float)
    if not len(t) or t[-1] < start_s:
        return None
    lo = int(np.searchsorted(t, start_s - max(s.lead_s, s.shape_s) - 1e-6))
    hi = len(t) if end_s is None else int(min(np.searchsorted(t, end_s + 1e-6, side="right"), len(t)))
    w = {k: np.asarray(steps[k], dtype=float)[lo:hi] for k in STEP_KEYS}
    tw = w["t_s"]
    i0 = int(min(np.searchsorted(tw, start_s - 1e-6), len(tw) - 1))
    i1 = len(tw) - 1
    lat, lon = w["lat_deg"], w["lon_deg"]
    ok = np.flatnonzero(np.isfinite(lat) & np.isfinite(lon))
    north, east = (ned_from_lla(lat, lon, lat[ok[0]], lon[ok[0]]) if len(ok)
                   else (np.full(len(tw), np.nan), np.full(len(tw), np.nan)))
    residual = np.c_[w["rx"], w["ry"], w["rz"]]
    return explain_alarm(tw, residual, w["motor"], north, east, lat, lon, {k: w[k] for k in SCORE_NAMES},
                         i0, i1, s, up_m=w["alt_m"])


def explanation_text(e: dict | None, signal: str = "current_A") -> str:
    """An alarm's explanation in words, for people ("" without one)."""
    if not e:
        return ""
    parts = [f"likely {e['kind']}"]
    if e.get("position"):
        parts[0] += f" at {e['position']['lat']:.6f}, {e['position']['lon']:.6f}"
    if e.get("disturbance_size_mG") is not None:
        v = e["disturbance_mG"]
        parts.append(f"disturbance {e['disturbance_size_mG']:.0f} mG "
                     f"(body x {v[0]:+.0f}, y {v[1]:+.0f}, z {v[2]:+.0f})")
    if e.get("growth_mG_s") is not None:
        parts.append(f"growing {e['growth_mG_s']:+.1f} mG/s before the alarm")
    if e["kind"] == "moving with current" and e.get("current_correlation") is not None:
        what = "current" if signal == "current_A" else "throttle"
        parts.append(f"follows the {what} (r = {e['current_correlation']:.2f})")
    if e.get("tests"):
        parts.append("tests: " + ", ".join(score_name(k) for k in e["tests"]))
    return "; ".join(parts)


class ExplainHistory:
    """The per-step explanation inputs of a live link, appended chunk by chunk; at most
    ``max_steps`` (the oldest quarter goes first when full)."""

    def __init__(self, max_steps: int = 360_000) -> None:
        self.max_steps = max_steps
        self._a = np.zeros((1024, len(STEP_KEYS)))
        self.n = 0

    def append(self, **cols) -> None:
        """Arrays of one chunk, by ``STEP_KEYS`` name (all the same length)."""
        block = np.column_stack([np.asarray(cols[k], dtype=float) for k in STEP_KEYS])
        if self.n + len(block) > self.max_steps:
            drop = min(self.n, max(self.max_steps // 4, self.n + len(block) - self.max_steps))
            self._a[:self.n - drop] = self._a[drop:self.n]
            self.n -= drop
        if self.n + len(block) > len(self._a):
            grown = np.zeros((max(2 * len(self._a), self.n + len(block)), len(STEP_KEYS)))
            grown[:self.n] = self._a[:self.n]
            self._a = grown
        self._a[self.n:self.n + len(block)] = block
        self.n += len(block)

    def steps(self) -> dict:
        return {k: self._a[:self.n, j] for j, k in enumerate(STEP_KEYS)}

    def explain(self, start_s: float, end_s: float | None) -> dict | None:
        return explain_span(self.steps(), start_s, end_s)
