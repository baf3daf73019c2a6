"""Calibration windows of one compass: onboard-calibration markers or rotation segmentation, each
window fitted and judged (estimators.cal_windows), plus the sensor-to-body misalignment of the
chosen one when the attitude and the WMM allow it (seed 004, estimators.calibration)."""
from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from estimators.cal_windows import CalWindow, WindowSearch, field_direction_rate_deg_s, find_calibration_windows, judge_window
from estimators.calibration import apply_calibration, estimate_misalignment
from groundstation.jobs.compass_raw import CompassField
from groundstation.samples import FlightLog

from .context import LogContext, attitude_for, marker_spans
from .settings import CalibrateSettings

__all__ = ["WindowStep", "window_step", "window_dicts", "window_dict", "window_mask", "misalignment",
           "MIN_MISALIGNMENT_SAMPLES"]

MIN_MISALIGNMENT_SAMPLES = 50


@dataclass(frozen=True)
class WindowStep:
    search: WindowSearch
    markers: list


def _rate(log: FlightLog, cf: CompassField, field_strength_mG: float) -> np.ndarray:
    """Attitude rotation rate at the samples; the field-direction rate where there is no attitude."""
    proxy = field_direction_rate_deg_s(cf.t_s, cf.raw_mG, field_strength_mG)
    if len(log.attitude) < 2:
        return proxy
    rate = attitude_for(log, cf.t_s).rate_deg_s
    return np.where(np.isfinite(rate), rate, proxy)


def window_mask(cf: CompassField, window) -> np.ndarray:
    """The compass's samples inside a window's time span (the samples its fit was given)."""
    return (cf.t_s >= window.start_s) & (cf.t_s <= window.end_s)


def misalignment(log: FlightLog, cf: CompassField, ctx: LogContext, window, mask: np.ndarray, C: np.ndarray,
                 settings: CalibrateSettings) -> tuple[np.ndarray | None, list | None, str]:
    """Sensor-to-body rotation of the window's calibrated samples from the attitude and the WMM
    (seed 004 step 2): (R, angles deg, note); R None when not estimated or not small (a rotation
    beyond ``max_misalignment_deg`` is a mounting orientation, the orientation check's business).
    ``mask``: the samples the window's fit was given (``window_mask``, or a subset of it)."""
    if ctx.field is None or len(log.attitude) < 2 or window is None:
        return None, None, ""
    finite = mask & cf.valid
    t = cf.t_s[finite][window.fit.inliers]
    cal = apply_calibration(cf.raw_mG[finite][window.fit.inliers], window.fit.offsets_mG, C)
    att = attitude_for(log, t)
    inside = att.valid
    if inside.sum() < MIN_MISALIGNMENT_SAMPLES:
        return None, None, ""
    mis = estimate_misalignment(cal[inside], att.roll_rad[inside], att.pitch_rad[inside], att.yaw_rad[inside],
                                ctx.field.field_ned_mG, t_s=t[inside])
    if mis.ok and not mis.significant:     # within the fit's own noise (timing jitter, attitude errors)
        angle, sd = float(np.linalg.norm(mis.angles_deg)), float(np.linalg.norm(mis.angles_sd_deg))
        return None, None, (f"no misalignment beyond the noise ({angle:.2f} deg, sd {sd:.2f} deg, "
                            f"attitude lag {mis.lag_s * 1e3:.0f} ms)")
    angle = float(np.linalg.norm(mis.angles_deg)) if mis.ok else float("nan")
    if mis.ok and mis.residual_deg <= settings.max_misalignment_residual_deg and angle <= settings.max_misalignment_deg:
        return mis.rotation, [round(float(a), 3) for a in mis.angles_deg], \
            f"misalignment from attitude (residual {mis.residual_deg:.2f} deg)"
    if mis.ok and angle > settings.max_misalignment_deg:
        return None, None, f"misalignment not applied: {angle:.0f} deg is a mounting rotation, not a misalignment"
    return None, None, "misalignment not estimated: " + (mis.reason or f"attitude/field residual {mis.residual_deg:.1f} deg too large")


WHOLE_LOG_SHARE = 0.7      # windows covering this share of the log: the log is a dance, judge it whole too


def _with_whole_log(cf: CompassField, search: WindowSearch, ws) -> WindowSearch:
    """The whole log judged as one window, when no window is sufficient (a log that is all dance,
    shorter than the segmentation's minimum span or rotating slowly, as the calibration wizard
    records) or when the windows cover most of the log without markers (a dance with pauses: all
    its samples together beat its best part).  Chosen when sufficient and at least as certain."""
    t = cf.t_s
    span = float(t[-1] - t[0]) if len(t) > 1 else 0.0
    covered = sum(max(0.0, min(w.end_s, t[-1]) - max(w.start_s, t[0])) for w in search.windows)
    markers = any("marker" in w.source for w in search.windows)
    if search.chosen is not None and (markers or span <= 0 or covered < WHOLE_LOG_SHARE * span):
        return search
    whole = judge_window(float(t[0]), float(t[-1]), "whole_log", cf.raw_mG, ws)
    windows = search.windows + (whole,)
    best = search.chosen_window
    if not whole.sufficient or (best is not None and np.max(whole.offsets_sd_mG) > np.max(best.offsets_sd_mG)):
        return replace(search, windows=windows)
    return WindowSearch("ok", f"the whole log as one window ({whole.n_samples} samples, {whole.model}, coverage "
                        f"{whole.coverage:.0%}); {search.message}", windows, len(windows) - 1, search.settings)


def window_step(log: FlightLog, cf: CompassField, ctx: LogContext, settings: CalibrateSettings) -> WindowStep:
    """Find, fit and judge this compass's calibration windows."""
    ws = settings.windows
    if ctx.field is not None:
        ws = replace(ws, field_strength_mG=float(ctx.field.field_strength_mG))
    markers = marker_spans(log.mag_cal, cf.compass)
    search = find_calibration_windows(cf.t_s, cf.raw_mG, rate_deg_s=_rate(log, cf, ws.field_strength_mG),
                                      marker_spans_s=markers, settings=ws)
    if search.status != "no_data":
        search = _with_whole_log(cf, search, ws)
    return WindowStep(search, markers)


def _num(v, nd=2):
    v = float(v)
    return round(v, nd) if np.isfinite(v) else None


def window_dict(w: CalWindow, chosen: bool, t_s: np.ndarray) -> dict:
    """One window, JSON-ready (bounds clipped to the compass's samples ``t_s``)."""
    lo, hi = (float(t_s[0]), float(t_s[-1])) if len(t_s) else (0.0, 0.0)
    fit = w.fit if w.fit is not None and w.fit.ok else None
    return {"start_s": _num(max(w.start_s, lo)), "end_s": _num(min(w.end_s, hi)), "source": w.source, "samples": w.n_samples,
            "model": w.model or None, "coverage": _num(w.coverage, 3), "planarity": _num(w.planarity, 3),
            "offsets_mG": [_num(v, 1) for v in fit.offsets_mG] if fit else None,
            "offsets_sd_mG": [_num(v, 2) for v in w.offsets_sd_mG],
            "residual_rms_mG": _num(fit.residual_rms_mG) if fit else None,
            "field_strength_mG": _num(fit.field_strength_mG, 1) if fit else None,
            "axis_ratio": _num(w.axis_ratio, 3), "sufficient": bool(w.sufficient), "reason": w.reason,
            "chosen": bool(chosen)}


def window_dicts(search: WindowSearch, t_s: np.ndarray) -> list[dict]:
    """Every window found (``window_dict``); ``chosen`` marks the one the parameters come from."""
    return [window_dict(w, i == search.chosen, t_s) for i, w in enumerate(search.windows)]
