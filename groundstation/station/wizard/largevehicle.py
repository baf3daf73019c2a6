"""Large-vehicle calibration: no dance, a known heading (MAV_CMD_FIXED_MAG_CAL_YAW).

A vehicle too big to turn over is held still at a heading the crew knows (entered), or whose
heading is the GPS course of a short straight walk or drive (``aftercheck.HeadingCheck`` "walk").
The vehicle (ArduPilot Compass::mag_cal_fixed_yaw) then sets every compass's offsets so that its
field equals the WMM field rotated into the body with its roll/pitch and that yaw; soft iron is
reset (DIA 1, ODI 0), so the method assumes a spherical field and a right sensor scale.

Ours beside it: the same offsets computed here from the same sample (OFS = expected − uncorrected).
Our check against the WMM afterwards: over ``CHECK_S`` of samples with the new parameters in
force, the reported field should match the WMM strength, inclination and the entered heading;
a field strength off by more than ``settings.wmm_mismatch_fraction`` says the assumption failed
(iron nearby or a scale error), worded as a hypothesis.
"""
from __future__ import annotations

import math

import numpy as np

from estimators.rotations import dcm_body_to_ned, wrap_angle_deg
from groundstation.io.params import unapply_ardupilot
from groundstation.station.wizard.aftercheck import circular_mean_deg, compass_heading_deg
from groundstation.station.wizard.quality import field_hypothesis

__all__ = ["FixedYawCalibration", "CHECK_S", "expected_body_field"]

CHECK_S = 2.0
CHECK_DELAY_S = 0.5


def expected_body_field(field_ned_mG: np.ndarray, roll_rad: float, pitch_rad: float, yaw_deg: float) -> np.ndarray:
    return dcm_body_to_ned(roll_rad, pitch_rad, math.radians(yaw_deg)).T @ np.asarray(field_ned_mG, float)


class FixedYawCalibration:
    """One fixed-yaw calibration: "sent" → "checking" → "done" (or "refused")."""

    def __init__(self, yaw_deg: float, source: str, field_ned_mG: np.ndarray | None, declination_deg: float | None) -> None:
        self.yaw_deg, self.source = float(yaw_deg) % 360.0, source
        self.field_ned_mG = field_ned_mG
        self.declination_deg = declination_deg
        self.state = "sent"
        self.message = f"MAV_CMD_FIXED_MAG_CAL_YAW sent with yaw {self.yaw_deg:.1f}° ({source})"
        self.ours: dict[int, list[float]] = {}
        self.vehicle: dict[int, list[float]] = {}
        self._check: list[tuple[float, np.ndarray, float, float]] = []
        self._check_from: float | None = None
        self.result: dict | None = None

    def compute_ours(self, latest: dict[int, np.ndarray], params: dict[str, float], roll_rad: float,
                     pitch_rad: float) -> None:
        """Our offsets from the mean of the last samples of each compass (the vehicle's formula
        on one sample; averaging takes the sensor noise out)."""
        if self.field_ned_mG is None:
            return
        expected = expected_body_field(self.field_ned_mG, roll_rad, pitch_rad, self.yaw_deg)
        for k, m in latest.items():
            ofs = expected - unapply_ardupilot(np.asarray(m, float), params, k)
            self.ours[k] = [round(float(v), 1) for v in ofs]

    def on_ack(self, accepted: bool, result_text: str, t_s: float) -> None:
        if accepted:
            self.state, self._check_from = "checking", t_s + CHECK_DELAY_S
            self.message = "the vehicle set its offsets; checking the field against the WMM"
        else:
            self.state = "refused"
            self.message = f"the vehicle refused MAV_CMD_FIXED_MAG_CAL_YAW ({result_text})"

    def on_params(self, params: dict[str, float]) -> None:
        for k in range(3):
            n = "" if k == 0 else str(k + 1)
            ofs = [params.get(f"COMPASS_OFS{n}_{a}") for a in "XYZ"]
            if all(v is not None for v in ofs):
                self.vehicle[k] = [round(float(v), 1) for v in ofs]

    def on_sample(self, t_s: float, mag_mG: np.ndarray, roll_rad: float, pitch_rad: float) -> None:
        if self.state != "checking" or self._check_from is None or t_s < self._check_from:
            return
        self._check.append((t_s, np.asarray(mag_mG, float), roll_rad, pitch_rad))
        if t_s - self._check[0][0] >= CHECK_S:
            self._finish_check()

    def _finish_check(self) -> None:
        m = np.array([c[1] for c in self._check])
        roll = np.array([c[2] for c in self._check])
        pitch = np.array([c[3] for c in self._check])
        out: dict = {"samples": len(m), "strength_mG": round(float(np.mean(np.linalg.norm(m, axis=1))), 1)}
        decl = self.declination_deg or 0.0
        heading = circular_mean_deg(compass_heading_deg(m, roll, pitch, decl))
        out["heading_deg"] = round(heading, 2)
        out["heading_error_deg"] = round(float(wrap_angle_deg(heading - self.yaw_deg)), 2)
        cautions = []
        if self.field_ned_mG is not None:
            f = np.asarray(self.field_ned_mG, float)
            expected = np.array([expected_body_field(f, r, p, self.yaw_deg) for r, p in zip(roll, pitch)])
            out["wmm_strength_mG"] = round(float(np.linalg.norm(f)), 1)
            out["vector_error_mG"] = round(float(np.mean(np.linalg.norm(m - expected, axis=1))), 1)
            m_ned = np.einsum("nij,nj->ni", dcm_body_to_ned(roll, pitch, np.full(len(m), math.radians(self.yaw_deg))), m)
            incl = np.degrees(np.arcsin(np.clip(m_ned[:, 2] / np.linalg.norm(m, axis=1), -1, 1)))
            wmm_incl = math.degrees(math.asin(f[2] / np.linalg.norm(f)))
            out["inclination_error_deg"] = round(float(np.mean(incl) - wmm_incl), 2)
            if abs(out["strength_mG"] - out["wmm_strength_mG"]) > 0.15 * out["wmm_strength_mG"]:
                cautions.append(field_hypothesis(out["strength_mG"], out["wmm_strength_mG"], "The corrected field"))
        out["ok"] = abs(out["heading_error_deg"]) < 3.0 and not cautions
        out["cautions"] = cautions
        self.result = out
        self.state = "done"
        self.message = (f"checked: heading {heading:.1f}° against {self.yaw_deg:.1f}° entered "
                        f"({out['heading_error_deg']:+.1f}°)" +
                        (f", field {out['strength_mG']:.0f} mG vs WMM {out.get('wmm_strength_mG', 0):.0f} mG"
                         if "wmm_strength_mG" in out else ""))

    def snapshot(self) -> dict:
        return {"state": self.state, "message": self.message, "yaw_deg": round(self.yaw_deg, 2), "source": self.source,
                "ours_ofs_mG": {str(k): v for k, v in self.ours.items()},
                "vehicle_ofs_mG": {str(k): v for k, v in self.vehicle.items()}, "check": self.result}
