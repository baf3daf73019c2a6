"""Thresholds of the guided calibration, with units, in one frozen dataclass (recorded in results).

Fitness levels are ArduPilot's COMPASS_CAL_FIT values (AP_Compass.cpp parameter table:
4 Very Strict, 8 Strict, 16 Default, 32 Relaxed): the largest RMS residual, in mG, of the
calibrated field about the fitted sphere that still passes.  ArduPilot applies the value to the
first compass when it is external and twice the value to every other compass
(AP_Compass_Calibration.cpp, internal compasses being noisier); we do the same.
"""
from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from functools import lru_cache

__all__ = ["WizardSettings", "DEFAULT_SETTINGS", "FITNESS_LEVELS", "fitness_threshold_mG"]

FITNESS_LEVELS: dict[str, float] = {"very_strict": 4.0, "strict": 8.0, "default": 16.0, "relaxed": 32.0}


def fitness_threshold_mG(level: str, compass: int) -> float:
    """COMPASS_CAL_FIT of ``level`` for compass index ``compass`` (doubled after the first)."""
    base = FITNESS_LEVELS.get(level, FITNESS_LEVELS["default"])
    return base if compass == 0 else 2.0 * base


@dataclass(frozen=True)
class WizardSettings:
    """Guided-calibration thresholds (units in the names)."""
    turn_target_deg: float = 360.0          # net rotation about the step's body axis ...
    turn_tolerance_deg: float = 15.0        # ... less this much (a turn by hand is never exact)
    tumble_coverage: float = 0.60           # fraction of the 100 equal-area field-direction cells
    too_fast_deg_s: float = 172.0           # |gyro| above this: samples sparse, IMU/mag timing skews
    still_rate_deg_s: float = 4.0           # attitude rate below this for still_window_s: "no motion"
    still_window_s: float = 2.0
    resume_max_gap_s: float = 30.0          # link back within this: the step resumes; else it restarts
    disturbance_fraction: float = 0.12      # |m_cal| off the live sphere by this fraction: disturbance
    live_fit_every_s: float = 3.0           # the live robust fit is redone this often (sample time)
    live_fit_points: int = 400              # ... on at most this many (decimated) points
    trust_min_samples: int = 300            # the live field is judged only with this many samples,
    trust_coverage: float = 0.40            # ... this direction coverage,
    trust_planarity: float = 0.25           # ... and this thickness ratio (sqrt λmin/λmax)
    wmm_mismatch_fraction: float = 0.15     # |F_fit − F_WMM| / F_WMM above this: field hypothesis
    radius_min_mG: float = 150.0            # ArduPilot's fit_acceptable radius range
    radius_max_mG: float = 950.0
    offsets_max_mG: float = 1800.0          # ArduPilot's COMPASS_OFFS_MAX default
    consistency_angle_deg: float = 5.0      # calibrated compasses should agree within this (median)
    fitness_level: str = "default"

    @property
    def too_fast_rad_s(self) -> float:
        return math.radians(self.too_fast_deg_s)

    def as_dict(self) -> dict:
        return dict(_as_dict(self))


@lru_cache(maxsize=16)
def _as_dict(settings: WizardSettings) -> dict:
    return asdict(settings)


DEFAULT_SETTINGS = WizardSettings()
