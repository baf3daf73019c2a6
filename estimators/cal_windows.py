"""Calibration windows: the stretches of a log where the vehicle was turned through enough of the sphere.

A real log may hold a 30 s onboard-calibration dance (MAV_CMD_DO_START_MAG_CAL, marked by
MAG_CAL_PROGRESS / MAG_CAL_REPORT) inside a 15-minute flight, at 1–4 Hz telemetry: 40–60 field
samples.  ``find_calibration_windows``:

1. candidate spans — the marker spans the caller passes (padded by ``marker_pad_s``) and the
   stretches where the rotation rate (attitude/gyro rate when given, else the rate of change of the
   field direction) stays above ``min_rate_deg_s`` for at least ``min_span_s``, with pauses up to
   ``merge_gap_s`` bridged; overlapping spans are merged (source "marker+motion");
2. each span is fitted: the robust sphere (as ArduPilot's calibrator starts with a sphere fit) and,
   from ``ellipsoid_min_samples`` on, the robust ellipsoid (estimators.calibration), kept when its
   shape is credible and it explains clearly more than the sphere;
3. sufficiency is judged by what the samples *say*, not by their count: direction coverage of the
   calibrated field (``coverage_bands`` × ``coverage_sectors`` equal-area cells, coarse enough for a
   45-sample dance), the offsets' standard deviation from the fit covariance, the residual RMS
   relative to the field, and the ellipsoid axis ratio;
4. every window is returned with its quality; the chosen one is the sufficient window with the
   smallest offsets sd.

Statuses: ok | insufficient_coverage (windows found, none sufficient) | no_window | no_data.
Units: s, mG, deg/s.  Pure numpy.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from estimators.calibration import (EllipsoidFit, apply_calibration, fit_ellipsoid_robust, fit_sphere_robust,
                                    planarity_ratio, sphere_coverage)

__all__ = ["WindowSettings", "CalWindow", "WindowSearch", "find_calibration_windows", "field_direction_rate_deg_s",
           "fit_window", "judge_window"]


@dataclass(frozen=True)
class WindowSettings:
    """Window search and acceptance settings (units in the names)."""
    min_rate_deg_s: float = 20.0
    merge_gap_s: float = 6.0
    min_span_s: float = 8.0
    marker_pad_s: float = 2.0
    min_samples: int = 15
    ellipsoid_min_samples: int = 30
    ellipsoid_gain: float = 0.8
    max_axis_ratio: float = 2.5
    coverage_bands: int = 5
    coverage_sectors: int = 6
    min_coverage: float = 0.45
    max_offset_sd_mG: float = 8.0
    max_residual_fraction: float = 0.05
    field_strength_mG: float = 500.0      # for the field-only rate proxy (the WMM strength when known)


@dataclass(frozen=True)
class CalWindow:
    """One candidate window and its fit.  ``sufficient`` False -> ``reason`` says why."""
    start_s: float
    end_s: float
    source: str                       # "marker" | "motion" | "marker+motion"
    n_samples: int
    model: str                        # "ellipsoid" | "sphere" | ""
    fit: EllipsoidFit | None
    coverage: float
    planarity: float
    offsets_sd_mG: np.ndarray
    axis_ratio: float
    sufficient: bool
    reason: str


@dataclass(frozen=True)
class WindowSearch:
    status: str
    message: str
    windows: tuple[CalWindow, ...] = ()
    chosen: int | None = None
    settings: WindowSettings = field(default_factory=WindowSettings)

    @property
    def chosen_window(self) -> CalWindow | None:
        return None if self.chosen is None else self.windows[self.chosen]


def field_direction_rate_deg_s(t_s: np.ndarray, mag_mG: np.ndarray, field_strength_mG: float = 500.0) -> np.ndarray:
    """Rotation-rate proxy from the field alone (deg/s) when no attitude is logged: the chord between
    consecutive samples on a sphere of radius F, 2·asin(|Δm| / 2F) / Δt.  Offsets cancel in Δm, noise
    adds ~|Δε|/F (a few tenths of a degree per sample).  NaN where a neighbour is missing; assigned
    to the later sample."""
    m = np.asarray(mag_mG, float).reshape(-1, 3)
    t = np.asarray(t_s, float).ravel()
    out = np.full(len(m), np.nan)
    good = np.all(np.isfinite(m), axis=1) & np.isfinite(t)
    if good.sum() < 2:
        return out
    chord = np.linalg.norm(np.diff(m[good], axis=0), axis=1)
    ang = np.degrees(2.0 * np.arcsin(np.clip(chord / (2.0 * field_strength_mG), 0.0, 1.0)))
    dt = np.diff(t[good])
    idx = np.nonzero(good)[0][1:]
    out[idx] = np.where(dt > 0, ang / np.where(dt > 0, dt, 1.0), np.nan)
    return out


def _motion_spans(t: np.ndarray, rate: np.ndarray, s: WindowSettings) -> list[tuple[float, float]]:
    active = np.isfinite(rate) & (rate >= s.min_rate_deg_s)
    spans: list[list[float]] = []
    for ti in t[active]:
        if spans and ti - spans[-1][1] <= s.merge_gap_s:
            spans[-1][1] = ti
        else:
            spans.append([ti, ti])
    return [(a, b) for a, b in spans if b - a >= s.min_span_s]


def _merge(spans: list[tuple[float, float, str]]) -> list[tuple[float, float, str]]:
    out: list[list] = []
    for a, b, src in sorted(spans):
        if out and a <= out[-1][1]:
            out[-1][1] = max(out[-1][1], b)
            if src not in out[-1][2]:
                out[-1][2] = "marker+motion"
        else:
            out.append([a, b, src])
    return [(a, b, src) for a, b, src in out]


def _axis_ratio(C: np.ndarray) -> float:
    sv = np.linalg.svd(C, compute_uv=False)
    return float(sv[0] / sv[-1]) if sv[-1] > 0 else float("inf")


def fit_window(mag_raw_mG: np.ndarray, settings: WindowSettings = WindowSettings()) -> tuple[str, EllipsoidFit | None]:
    """(model, fit) for one window's samples; ("", None) below ``min_samples`` finite samples.

    The sphere (4 parameters) is always fitted; from ``ellipsoid_min_samples`` on the ellipsoid
    (9 parameters) too, and it is kept when its shape is credible and it explains clearly more
    (residual below ``ellipsoid_gain`` × the sphere's: real soft iron, not noise fitting)."""
    m = np.asarray(mag_raw_mG, float).reshape(-1, 3)
    m = m[np.all(np.isfinite(m), axis=1)]
    if len(m) < settings.min_samples:
        return "", None
    sphere = fit_sphere_robust(m)
    if len(m) >= settings.ellipsoid_min_samples:
        ell = fit_ellipsoid_robust(m)
        if ell.ok and _axis_ratio(ell.matrix) <= settings.max_axis_ratio and (
                not sphere.ok or ell.residual_rms_mG < settings.ellipsoid_gain * sphere.residual_rms_mG):
            return "ellipsoid", ell
    return "sphere", sphere


def judge_window(t0: float, t1: float, src: str, m: np.ndarray, s: WindowSettings = WindowSettings()) -> CalWindow:
    """Fit one window's raw samples (N,3) and judge its sufficiency (step 3 of the module docstring)."""
    nan3 = np.full(3, np.nan)
    n = int(np.all(np.isfinite(m), axis=1).sum())
    model, fit = fit_window(m, s)
    if fit is None or not fit.ok:
        why = f"only {n} finite samples (need {s.min_samples})" if fit is None else fit.reason
        return CalWindow(t0, t1, src, n, model, fit, 0.0, planarity_ratio(m) if n >= 4 else 0.0, nan3, float("nan"),
                         False, why)
    good = m[np.all(np.isfinite(m), axis=1)][fit.inliers]
    cal = apply_calibration(good, fit.offsets_mG, fit.matrix)
    cov = sphere_coverage(cal, s.coverage_bands, s.coverage_sectors)
    sd = np.sqrt(np.clip(np.diag(fit.offsets_cov_mG2), 0, None)) if fit.offsets_cov_mG2 is not None else nan3
    ratio = _axis_ratio(fit.matrix)
    resid = fit.residual_rms_mG / fit.field_strength_mG
    reasons = []
    if cov < s.min_coverage:
        reasons.append(f"directions cover {cov:.0%} of the sphere (need {s.min_coverage:.0%})")
    if not np.all(sd <= s.max_offset_sd_mG):
        reasons.append(f"offsets sd up to {np.nanmax(sd):.1f} mG (limit {s.max_offset_sd_mG:.0f})")
    if not resid <= s.max_residual_fraction:
        reasons.append(f"residual {100 * resid:.1f} % of the field (limit {100 * s.max_residual_fraction:.0f} %)")
    if ratio > s.max_axis_ratio:
        reasons.append(f"axis ratio {ratio:.2f} not credible")
    return CalWindow(t0, t1, src, n, model, fit, cov, planarity_ratio(good), sd, ratio, not reasons, "; ".join(reasons))


def find_calibration_windows(t_s: np.ndarray, mag_raw_mG: np.ndarray, *, rate_deg_s: np.ndarray | None = None,
                             marker_spans_s: Sequence[tuple[float, float]] = (),
                             settings: WindowSettings = WindowSettings()) -> WindowSearch:
    """Find, fit and judge calibration windows in one compass's raw field.

    Args:
        t_s (N,) s; mag_raw_mG (N,3) raw body field (corrections in force un-applied; inside an
        onboard dance the old corrections are still in force, so any consistent frame works);
        rate_deg_s (N,) rotation rate at the samples (``log_alignment.attitude_at(...).rate_deg_s``
        or the gyro norm); None -> the field-direction rate; marker_spans_s [(start, end)] of
        MAG_CAL_PROGRESS/REPORT (or any caller-known dance).
    """
    s = settings
    t = np.asarray(t_s, float).ravel()
    m = np.asarray(mag_raw_mG, float).reshape(-1, 3)
    finite = np.all(np.isfinite(m), axis=1) & np.isfinite(t)
    if len(m) != len(t) or finite.sum() == 0:
        return WindowSearch("no_data", "no finite field samples", (), None, s)
    rate = field_direction_rate_deg_s(t, m, s.field_strength_mG) if rate_deg_s is None else np.asarray(rate_deg_s, float).ravel()
    spans = [(a, b, "motion") for a, b in _motion_spans(t[finite], rate[finite], s)]
    spans += [(float(a) - s.marker_pad_s, float(b) + s.marker_pad_s, "marker") for a, b in marker_spans_s
              if np.isfinite(a) and np.isfinite(b) and b >= a]
    if not spans:
        return WindowSearch("no_window", f"no stretch rotating faster than {s.min_rate_deg_s:.0f} deg/s for "
                            f"{s.min_span_s:.0f} s and no calibration markers", (), None, s)
    windows = tuple(judge_window(a, b, src, m[(t >= a) & (t <= b)], s) for a, b, src in _merge(spans))
    ok = [i for i, w in enumerate(windows) if w.sufficient]
    if not ok:
        why = "; ".join(f"{w.start_s:.0f}–{w.end_s:.0f} s: {w.reason}" for w in windows)
        return WindowSearch("insufficient_coverage", f"{len(windows)} window(s), none sufficient ({why})", windows, None, s)
    best = min(ok, key=lambda i: float(np.max(windows[i].offsets_sd_mG)))
    w = windows[best]
    return WindowSearch("ok", f"{len(windows)} window(s), {len(ok)} sufficient; chosen {w.start_s:.0f}–{w.end_s:.0f} s "
                        f"({w.source}, {w.n_samples} samples, {w.model}, coverage {w.coverage:.0%}, offsets sd "
                        f"{np.max(w.offsets_sd_mG):.1f} mG)", windows, best, s)
