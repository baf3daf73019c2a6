"""Settings of the calibrate job: one frozen dataclass, its default instance recorded in every result."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

from estimators.cal_windows import WindowSettings
from estimators.compass_consistency import ConsistencySettings
from estimators.orientation_check import OrientationSettings
from estimators.wmm_fit import WmmFitSettings

__all__ = ["CalibrateSettings", "DEFAULT_SETTINGS", "QUICK_SETTINGS", "settings_record"]


@dataclass(frozen=True)
class CalibrateSettings:
    """What the calibrate job tries and what it accepts (units in the names).

    windows: calibration-window search and sufficiency (estimators.cal_windows); wmm: the in-flight
    fit against the WMM (estimators.wmm_fit; also the motor fit's base); orientation /
    consistency: the checks.  ``max_misalignment_residual_deg``: a sensor-to-body rotation estimated
    from the attitude is applied only when it explains the field directions this well and is
    smaller than ``max_misalignment_deg`` (a larger one is a mounting orientation, left to the
    orientation check).
    ``offsets_limit_mG``: ArduPilot's default COMPASS_OFFS_MAX (a note, not a rejection).
    ``consistency_max_dt_s``: compasses are compared at samples this close in time.
    ``orientation_max_rate_deg_s``: the orientation check uses samples rotating slower than this.
    ``attitude_source``: the attitude the in-flight fits use ("auto": chosen by the
    held-out residual, jobs/calibrate/inflight.choose_attitude; or one by name).
    ``window_max_motor_field_mG``: a calibration window whose mean motor field (the in-flight fit's
    motor term × the window's mean current or throttle) exceeds this is fitted again on its samples
    whose motor field is below it, and not used when those are not sufficient.
    ``refine_field``: the in-flight fits' reference field is the WMM with its inclination refined
    from the flight's banked turns (jobs/calibrate/reference.py, estimators.field_refine).
    ``inflight_max_samples``: the in-flight and motor fits take every k-th sample beyond this many
    (attitude errors are slow, so a 50 Hz log holds little more than its 2 Hz subset; the fit's
    covariance already allows for correlated residuals).
    """
    windows: WindowSettings = field(default_factory=WindowSettings)
    wmm: WmmFitSettings = field(default_factory=WmmFitSettings)
    orientation: OrientationSettings = field(default_factory=OrientationSettings)
    consistency: ConsistencySettings = field(default_factory=ConsistencySettings)
    inflight_fit: bool = True
    motor_fit: bool = True
    orientation_check: bool = True
    max_misalignment_residual_deg: float = 10.0
    max_misalignment_deg: float = 15.0
    offsets_limit_mG: float = 1800.0
    consistency_max_dt_s: float = 0.6
    orientation_max_rate_deg_s: float = 60.0
    inflight_max_samples: int = 1500
    window_max_motor_field_mG: float = 5.0   # a window flown with more motor field than this is fitted on its low-current samples (compass.motor_free_window)
    attitude_source: str = "auto"       # "auto": chosen per log by the held-out residual; or a name (ATT, XKF1, ahrs …)
    refine_field: bool = True           # the WMM's inclination refined from the flight (reference.refine_reference)


DEFAULT_SETTINGS = CalibrateSettings()
# offsets and matrix only (windows, else the in-flight fit): what the station waits for before a replay
QUICK_SETTINGS = CalibrateSettings(motor_fit=False, orientation_check=False)


def settings_record(settings: CalibrateSettings) -> dict:
    """The acceptance thresholds a result was judged by (JSON-ready)."""
    w = settings.windows
    return {"window": {"min_coverage": w.min_coverage, "coverage_cells": [w.coverage_bands, w.coverage_sectors],
                       "max_offset_sd_mG": w.max_offset_sd_mG, "max_residual_fraction": w.max_residual_fraction,
                       "max_axis_ratio": w.max_axis_ratio, "min_samples": w.min_samples,
                       "min_rate_deg_s": w.min_rate_deg_s},
            "inflight": {"max_offset_sd_mG": settings.wmm.max_offset_sd_mG, "yaw_source": settings.wmm.yaw_source,
                         "max_rate_deg_s": settings.wmm.max_rate_deg_s, "min_samples": settings.wmm.min_samples},
            "orientation": {"variance_threshold": settings.orientation.variance_threshold,
                            "reference": settings.orientation.reference},
            "consistency": asdict(settings.consistency)}
