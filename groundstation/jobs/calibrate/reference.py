"""The reference field of a log's in-flight fits: the WMM, its inclination refined from the flight.

Run once per log, after the attitude choice and before the compasses' fits (issue 28).  Each
compass the in-flight fit answers (a quick fit: no jackknife, the field taken as exact) gives the
profile of its cost over shifts of the WMM along the field's inclination; estimators.field_refine
combines them with the WMM's error model as the prior.  The compasses' fits then run against the
WMM plus that shift, with the refined field's covariance in their 1σ.  Every result records it
(``reference_field``), and the message says it in words.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from estimators.field_refine import inclination_direction, inclination_rad, refine_field
from groundstation.jobs.compass_raw import CompassField
from groundstation.samples import FlightLog

from .context import LogContext
from .inflight import flight_inputs, inflight_step
from .settings import CalibrateSettings

__all__ = ["refine_reference"]


def refine_reference(log: FlightLog, fields: list[CompassField], ctx: LogContext, settings: CalibrateSettings
                     ) -> LogContext:
    """ctx with ``field_shift_ned_mG``, ``field_cov_ned_mG2`` and ``field_refinement`` (module docstring);
    ctx unchanged when there is no WMM field or no in-flight fit."""
    if not settings.refine_field or ctx.field is None or not settings.inflight_fit:
        return ctx
    quick = replace(settings, wmm=replace(settings.wmm, jackknife_blocks=0, field_model_sd_mG=(0.0, 0.0, 0.0)))
    wmm = np.asarray(ctx.field.field_ned_mG, float)
    e = inclination_direction(wmm)
    profiles, used = [], []
    for cf in fields:
        x = flight_inputs(log, cf, settings.inflight_max_samples, ctx) if cf.valid.any() else None
        if x is None:
            continue
        fit = inflight_step(cf, x, ctx, quick, profile_direction_ned=e)
        if fit.field_profile_nll is not None:
            profiles.append(fit.field_profile_nll)
            used.append(cf.compass)
    ref = refine_field(wmm, settings.wmm.field_model_sd_mG, np.asarray(settings.wmm.field_profile_shifts_mG), profiles,
                       settings.wmm.attitude_tilt_sd_deg)
    inc0 = float(np.degrees(inclination_rad(wmm)))
    inc = float(np.degrees(inclination_rad(wmm + ref.shift_ned_mG)))
    # 1σ of the inclination: the field's 1σ across it (along e_I) over its magnitude
    sd_deg = float(np.degrees(np.sqrt(ref.direction_ned @ ref.covariance_ned_mG2 @ ref.direction_ned)
                              / np.linalg.norm(wmm)))
    if ref.refined:
        note = (f"reference field: inclination {inc0:.2f}° (WMM) refined to {inc:.2f}° ± {sd_deg:.2f}° from the "
                f"flight (compass{'es' if len(used) > 1 else ''} {', '.join(map(str, used))}: "
                f"{ref.measured_mg_text()})")
    else:
        note = f"reference field: the WMM's ({ref.reason})"
    record = {"wmm_inclination_deg": round(inc0, 3), "inclination_deg": round(inc, 3),
              "inclination_sd_deg": round(sd_deg, 3), "shift_ned_mG": [round(float(v), 2) for v in ref.shift_ned_mG],
              "flight_estimate_mG": None if not ref.refined else round(ref.measured_mG, 2),
              "flight_sd_mG": None if not ref.refined else round(ref.measured_sd_mG, 2),
              "prior_sd_mG": round(ref.prior_sd_mG, 2), "compasses": used, "note": note}
    return replace(ctx, field_shift_ned_mG=ref.shift_ned_mG if ref.refined else None,
                   field_cov_ned_mG2=ref.covariance_ned_mG2, field_refinement=record,
                   field_note="; ".join(x for x in (ctx.field_note, note) if x))
