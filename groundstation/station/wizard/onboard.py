"""The vehicle's own calibrator (ArduPilot onboard calibration) as the station follows it.

MAV_CMD_DO_START_MAG_CAL starts it; MAG_CAL_PROGRESS brings, per compass, the status, attempt,
completion percentage and the 80-section completion mask (``groundstation.io.magcal``);
MAG_CAL_REPORT the outcome: status, fitness (RMS residual, mG), offsets (ArduPilot convention:
*added* to the field, = −b of ours), diagonal and off-diagonal soft iron, orientation.  Accept
(MAV_CMD_DO_ACCEPT_MAG_CAL) makes the vehicle save them; cancel (MAV_CMD_DO_CANCEL_MAG_CAL)
drops them.  ``compare`` puts the vehicle's numbers beside our fit of the same dance.
"""
from __future__ import annotations

import math

from groundstation.io.magcal import CAL_STATUS, N_SECTIONS, sections_from_mask

__all__ = ["OnboardCalibration"]


def _r(v, d=2):
    return None if v is None or not math.isfinite(float(v)) else round(float(v), d)


class OnboardCalibration:
    """State of the vehicle's calibrator: "starting" → "running" → "reported" → "accepted"/"cancelled"."""

    def __init__(self) -> None:
        self.state = "starting"
        self.message = "asking the vehicle to start its calibrator"
        self.compasses: dict[int, dict] = {}

    def on_ack(self, accepted: bool, result_text: str) -> None:
        if self.state == "starting":
            self.state = "running" if accepted else "refused"
            self.message = ("the vehicle's calibrator is running: turn the vehicle as the steps say" if accepted else
                            f"the vehicle refused to start its calibrator ({result_text})")

    def on_progress(self, msg) -> None:
        c = self.compasses.setdefault(int(msg.compass_id), {})
        c.update(status=int(msg.cal_status), status_text=CAL_STATUS.get(int(msg.cal_status), str(msg.cal_status)),
                 attempt=int(msg.attempt), completion_pct=int(msg.completion_pct),
                 sections=sections_from_mask(list(msg.completion_mask)))
        if self.state in ("starting", "running"):
            self.state = "running"

    def on_report(self, msg) -> None:
        c = self.compasses.setdefault(int(msg.compass_id), {})
        if c.get("report") is None:
            c["sections"] = c.get("sections") or []
        c.update(status=int(msg.cal_status), status_text=CAL_STATUS.get(int(msg.cal_status), str(msg.cal_status)),
                 completion_pct=100 if msg.cal_status == 4 else c.get("completion_pct", 0))
        c["report"] = {
            "success": int(msg.cal_status) == 4, "fitness_mG": _r(msg.fitness), "autosaved": bool(msg.autosaved),
            "ofs_mG": [_r(msg.ofs_x, 1), _r(msg.ofs_y, 1), _r(msg.ofs_z, 1)],
            "diag": [_r(msg.diag_x, 4), _r(msg.diag_y, 4), _r(msg.diag_z, 4)],
            "offdiag": [_r(msg.offdiag_x, 4), _r(msg.offdiag_y, 4), _r(msg.offdiag_z, 4)],
            "orientation_confidence": _r(msg.orientation_confidence), "old_orientation": int(msg.old_orientation),
            "new_orientation": int(msg.new_orientation), "scale_factor": _r(msg.scale_factor, 4)}
        if self.state in ("starting", "running") and self.all_reported():
            self.state = "reported"
            ok = all(x["report"]["success"] for x in self.compasses.values())
            self.message = ("the vehicle's calibrator finished: compare, then accept or cancel" if ok else
                            "the vehicle's calibrator failed for at least one compass: cancel and redo, or accept ours")

    def all_reported(self) -> bool:
        return bool(self.compasses) and all(c.get("report") is not None for c in self.compasses.values())

    def snapshot(self) -> dict:
        return {"state": self.state, "message": self.message, "sections_total": N_SECTIONS,
                "compasses": [{"index": k, **{key: v for key, v in c.items()}} for k, c in sorted(self.compasses.items())]}


def compare(report: dict | None, ours: dict | None) -> dict | None:
    """The vehicle's report beside our fit of compass k, in ArduPilot's parameter convention."""
    if not report or not ours or ours.get("status") != "ok":
        return None
    n = "" if ours.get("compass", 0) == 0 else str(ours["compass"] + 1)
    p = ours.get("ardupilot_params") or {}
    our_ofs = [p.get(f"COMPASS_OFS{n}_{a}") for a in "XYZ"]
    diffs = [abs(a - b) for a, b in zip(report["ofs_mG"], our_ofs) if a is not None and b is not None]
    return {"vehicle_ofs_mG": report["ofs_mG"], "our_ofs_mG": [_r(v, 1) for v in our_ofs],
            "vehicle_fitness_mG": report["fitness_mG"], "our_fitness_mG": _r(ours.get("fitness_mG")),
            "vehicle_diag": report["diag"], "our_diag": [_r(p.get(f"COMPASS_DIA{n}_{a}"), 4) for a in "XYZ"],
            "max_offset_difference_mG": _r(max(diffs), 1) if diffs else None}
