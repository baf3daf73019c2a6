"""One compass during the dance: its samples, a live robust fit, its own coverage, disturbances.

MAVLink carries up to three compasses at once (ArduPilot: RAW_IMU = compass 0, SCALED_IMU2 = 1,
SCALED_IMU3 = 2; the decoder numbers them MagSample.instance 0/11/12, SCALED_IMU 10, PX4
HIGHRES_IMU 20+id).  ``compass_index`` maps an instance to the compass number.

The live fit is the robust ellipsoid of ``estimators.calibration.fit_ellipsoid_robust`` on at most
``live_fit_points`` decimated samples, redone every ``live_fit_every_s`` of sample time (a few ms).
Its field strength is judged against the WMM, and samples against its sphere (disturbances), only
once it is *trustworthy*: enough samples, the directions covering ``trust_coverage`` of the
sphere, a thickness ratio of at least ``trust_planarity``, and the same answer as the previous
live fit (a fit on one or two turns moves a lot when the next turn arrives; that is not a
disturbance and not a field far from the WMM).
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from estimators.calibration import apply_calibration, coverage_cells, fit_ellipsoid_robust, planarity_ratio
from groundstation.station.tables import GrowingTable
from groundstation.station.wizard.settings import WizardSettings

__all__ = ["compass_index", "LiveFit", "CompassTrack", "MAX_POINTS"]

MAX_POINTS = 200_000
_INSTANCE_TO_COMPASS = {0: 0, 10: 0, 20: 0, 11: 1, 21: 1, 12: 2, 22: 2}


def compass_index(instance: int) -> int | None:
    return _INSTANCE_TO_COMPASS.get(int(instance))


@dataclass(frozen=True)
class LiveFit:
    offsets_mG: np.ndarray
    matrix: np.ndarray
    field_mG: float
    coverage: float
    planarity: float
    n: int
    stable: bool      # agrees with the previous live fit (field within 2 %, offsets within 3 % of it)
    rows: tuple       # the matrix as plain floats (the per-sample disturbance check)


class CompassTrack:
    """Samples and live state of compass ``index`` (fed from MagSample ``instance``)."""

    def __init__(self, index: int, instance: int, settings: WizardSettings) -> None:
        self.index = index
        self.instance = instance
        self.settings = settings
        self.mag = GrowingTable(4, MAX_POINTS)        # t_s, mx, my, mz as received (mG)
        self.included = True
        self.live: LiveFit | None = None
        self._trusted = False
        self.cells = np.zeros(100, bool)
        self.disturbances = 0
        self.disturbed_until = -math.inf
        self._fit_at = -math.inf
        self.result: dict | None = None

    @property
    def name(self) -> str:
        return f"compass {self.index + 1}"

    def on_mag(self, t_s: float, m: tuple[float, float, float]) -> None:
        self.mag.append((t_s, *m))
        live = self.live
        if live is not None and self._trusted:
            d = [m[i] - live.offsets_mG[i] for i in range(3)]        # plain floats: per sample, 3x3
            r = math.sqrt(sum((c[0] * d[0] + c[1] * d[1] + c[2] * d[2]) ** 2 for c in live.rows))
            if abs(r - live.field_mG) > self.settings.disturbance_fraction * live.field_mG:
                if t_s >= self.disturbed_until:
                    self.disturbances += 1
                self.disturbed_until = t_s + 1.0
        if t_s - self._fit_at >= self.settings.live_fit_every_s and self.mag.n >= 100:
            self._fit_at = t_s
            self.refit()

    def refit(self) -> None:
        pts = self.mag.view()[:, 1:4]
        step = max(1, len(pts) // self.settings.live_fit_points)
        fit = fit_ellipsoid_robust(pts[::step])
        if not fit.ok or not math.isfinite(fit.field_strength_mG):
            return
        cal = apply_calibration(pts[::step], fit.offsets_mG, fit.matrix)
        self.cells = coverage_cells(cal)
        field, prev = float(fit.field_strength_mG), self.live
        stable = (prev is not None and abs(field - prev.field_mG) < 0.02 * field
                  and float(np.linalg.norm(fit.offsets_mG - prev.offsets_mG)) < 0.03 * field)
        self.live = LiveFit(fit.offsets_mG, fit.matrix, field, float(self.cells.mean()), planarity_ratio(pts[::step]),
                            len(pts), stable, tuple(tuple(float(v) for v in row) for row in fit.matrix))
        self._trusted = self.trusted()

    def trusted(self) -> bool:
        """The live fit is good enough to judge the field strength."""
        s, live = self.settings, self.live
        return (live is not None and live.stable and live.n >= s.trust_min_samples
                and live.coverage >= s.trust_coverage and live.planarity >= s.trust_planarity)

    def disturbed(self, t_s: float) -> bool:
        return t_s < self.disturbed_until

    def snapshot(self) -> dict:
        live = self.live
        return {
            "index": self.index, "name": self.name, "instance": self.instance, "included": self.included,
            "samples": int(self.mag.n),
            "coverage": None if live is None else round(live.coverage, 2),
            "cells": "".join("1" if c else "0" for c in self.cells),
            "live_offsets_mG": None if live is None else [round(float(v), 1) for v in live.offsets_mG],
            "live_field_mG": None if live is None else round(live.field_mG, 1),
            "trusted": self.trusted(),
            "disturbances": self.disturbances,
            "result": self.result,
        }
