"""Calibration quality as numbers and words people understand.

* **Fitness** — the RMS residual of the calibrated field about the fitted sphere, in mG: the same
  quantity ArduPilot's calibrator calls fitness (CompassCalibrator: RMS of radius − |corrected|)
  and compares with COMPASS_CAL_FIT (``settings.FITNESS_LEVELS``).
* **Predicted heading error** — a residual r (mG, any direction) turns the horizontal field
  H_h by at most atan(r / H_h): the worst case of one sample, H_h from the WMM (or 60° inclination).
* **Pass / fail with the reason in words** — planar or too few samples, radius out of ArduPilot's
  150–950 mG, offsets beyond COMPASS_OFFS_MAX, fitness above the threshold, orientation
  ambiguous or wrong; cautions (not failures): field far from the WMM (worded as a hypothesis),
  disturbances during the dance.
* **Disturbances need evidence** (``confirmed_disturbances``): the live count flags samples off a
  fit still being learnt; the caution counts only episodes the final fit confirms — the
  calibrated field's length off the fitted sphere by more than ``DISTURBANCE_FRACTION`` of it and
  more than ``DISTURBANCE_SIGMAS`` × the fit's own robust residual σ (1.4826·MAD), for at least
  ``DISTURBANCE_MIN_SAMPLES`` samples in a row (one odd sample is a glitch, a magnet moved stays).
"""
from __future__ import annotations

import math

import numpy as np

from groundstation.samples import finite_or_none
from groundstation.station.wizard.settings import FITNESS_LEVELS, WizardSettings, fitness_threshold_mG

__all__ = ["judge", "predicted_heading_error_deg", "field_hypothesis", "confirmed_disturbances"]

DEFAULT_INCLINATION_DEG = 60.0
DISTURBANCE_SIGMAS = 8.0
DISTURBANCE_FRACTION = 0.05     # and at least this share of the field (25 mG at 490 mG)
DISTURBANCE_MIN_SAMPLES = 3
DISTURBANCE_GAP_S = 1.0


def confirmed_disturbances(t_s: np.ndarray, cal_mG: np.ndarray, settings: WizardSettings) -> tuple[int, float]:
    """(episodes, largest departure in mG) of the calibrated field's length leaving its sphere
    beyond max(DISTURBANCE_FRACTION·F, DISTURBANCE_SIGMAS·σ) for DISTURBANCE_MIN_SAMPLES samples
    in a row; episodes closer than DISTURBANCE_GAP_S are one."""
    r = np.linalg.norm(np.asarray(cal_mG, float), axis=1)
    ok = np.isfinite(r)
    if ok.sum() < 10:
        return 0, 0.0
    F = float(np.median(r[ok]))
    e = np.where(ok, r - F, 0.0)
    sigma = 1.4826 * float(np.median(np.abs(e[ok])))
    off = np.abs(e) > max(DISTURBANCE_FRACTION * F, DISTURBANCE_SIGMAS * sigma)
    edges = np.flatnonzero(np.diff(np.concatenate([[0], off.astype(int), [0]])))
    runs = [(a, b) for a, b in zip(edges[::2], edges[1::2]) if b - a >= DISTURBANCE_MIN_SAMPLES]
    episodes, last_end = 0, -np.inf
    for a, b in runs:
        if t_s[a] - last_end > DISTURBANCE_GAP_S:
            episodes += 1
        last_end = t_s[b - 1]
    worst = max((float(np.max(np.abs(e[a:b]))) for a, b in runs), default=0.0)
    return episodes, worst


def predicted_heading_error_deg(residual_mG: float | None, field_mG: float | None,
                                field_ned_mG: np.ndarray | None) -> float | None:
    r, f = finite_or_none(residual_mG), finite_or_none(field_mG)
    if field_ned_mG is not None and np.all(np.isfinite(field_ned_mG)):
        horizontal = float(np.hypot(field_ned_mG[0], field_ned_mG[1]))
    elif f:
        horizontal = f * math.cos(math.radians(DEFAULT_INCLINATION_DEG))
    else:
        return None
    if r is None or horizontal <= 0:
        return None
    return round(math.degrees(math.atan2(r, horizontal)), 2)


def field_hypothesis(field_mG: float, expected_mG: float, who: str = "The fitted field") -> str:
    pct = 100.0 * (field_mG - expected_mG) / expected_mG
    return (f"{who} ({field_mG:.0f} mG) is {abs(pct):.0f} % {'weaker' if pct < 0 else 'stronger'} than the "
            f"WMM predicts here ({expected_mG:.0f} mG). Possibly iron nearby (car, steel table, "
            "reinforced floor) or a wrong sensor scale: try again a few metres away.")


def _failure_reasons(result: dict, k: int, orientation: dict | None, s: WizardSettings) -> list[str]:
    status = result.get("status")
    if status != "ok":
        msg = result.get("message") or status or "fit failed"
        if "planar" in msg:
            return ["The turns stayed in one plane: turn the vehicle about all three axes."]
        if "cover" in msg or "too few" in msg or "only" in msg:
            return ["Too few directions were covered: " + msg.split(";")[0] + "."]
        return ["The fit failed: " + msg.split(";")[0] + "."]
    reasons = []
    field = finite_or_none(result.get("field_strength_mG"))
    if field is not None and not s.radius_min_mG < field < s.radius_max_mG:
        reasons.append(f"Field strength {field:.0f} mG is outside {s.radius_min_mG:.0f}–{s.radius_max_mG:.0f} mG "
                       "(ArduPilot's limit): wrong sensor scale or a strong disturbance.")
    ofs = result.get("offsets_mG") or []
    big = max((abs(v) for v in ofs if v is not None), default=0.0)
    if big > s.offsets_max_mG:
        reasons.append(f"Offset {big:.0f} mG exceeds COMPASS_OFFS_MAX {s.offsets_max_mG:.0f} mG: the compass "
                       "sits too close to iron or a magnet.")
    fit, thr = finite_or_none(result.get("residual_rms_mG")), fitness_threshold_mG(s.fitness_level, k)
    if fit is not None and fit > thr:
        reasons.append(f"Fitness {fit:.1f} mG is above the {thr:g} mG threshold ({s.fitness_level.replace('_', ' ')}): "
                       "the samples do not lie on one ellipsoid (a disturbance, or turning too fast).")
    if orientation is not None and orientation["status"] == "ambiguous" and orientation["detected"] != orientation["current"]:
        reasons.append("Orientation ambiguous: two mounting rotations fit about equally; turn the vehicle about "
                       "more axes and redo.")
    return reasons


def judge(result: dict, k: int, orientation: dict | None, disturbances: int, settings: WizardSettings,
          field_ned_mG: np.ndarray | None = None) -> dict:
    """Quality fields of one compass result: fitness, threshold, pass, reasons, cautions, heading error."""
    s = settings
    fit = finite_or_none(result.get("residual_rms_mG"))
    reasons = _failure_reasons(result, k, orientation, s)
    cautions = []
    field, expected = finite_or_none(result.get("field_strength_mG")), finite_or_none(result.get("expected_field_mG"))
    if field and expected and abs(field - expected) > s.wmm_mismatch_fraction * expected:
        cautions.append(field_hypothesis(field, expected))
    if disturbances:
        worst = finite_or_none(result.get("disturbance_max_mG"))
        cautions.append(f"The field left the fitted sphere {disturbances} time(s) during the dance"
                        + (f" (by up to {worst:.0f} mG, well beyond the fit's noise)" if worst else "")
                        + ": something magnetic moved near the vehicle.")
    return {
        "fitness_mG": fit, "fitness_level": s.fitness_level,
        "fitness_threshold_mG": fitness_threshold_mG(s.fitness_level, k),
        "fitness_levels_mG": dict(FITNESS_LEVELS),
        "pass": not reasons, "reasons": reasons, "cautions": cautions,
        "heading_error_deg": predicted_heading_error_deg(fit, field, field_ned_mG),
    }
