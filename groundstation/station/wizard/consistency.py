"""Do the calibrated compasses agree?  ArduPilot's pre-arm consistency check, plus a closer look.

Each included compass's samples are calibrated with its own result (orientation applied) and
interpolated onto the first compass's sample times; ``estimators.compass_consistency`` compares
every pair as ArduPilot's Compass::consistent does (3-D angle 90°, XY angle 60°, XY length
200 mG) and names the odd one out.  Those limits catch only gross faults, so a pair whose median
angle exceeds ``settings.consistency_angle_deg`` is reported too: after a good calibration the
compasses of one vehicle agree within a few degrees.
"""
from __future__ import annotations

import numpy as np

from estimators.compass_consistency import compass_consistency
from groundstation.station.wizard.fit import calibrated_in_new_frame
from groundstation.station.wizard.settings import WizardSettings

__all__ = ["check_consistency"]


def check_consistency(entries: list[tuple[int, dict, np.ndarray, object]], settings: WizardSettings,
                      expected_mG: float | None) -> dict | None:
    """entries: (compass index, result, (t, mx, my, mz) table, unapply function) of included,
    successful compasses.  None with fewer than two."""
    if len(entries) < 2:
        return None
    t_ref = entries[0][2][:, 0]
    fields = []
    for _, result, mag, unapply in entries:
        cal = calibrated_in_new_frame(result, unapply(mag[:, 1:4]))
        t = mag[:, 0]
        f = np.column_stack([np.interp(t_ref, t, cal[:, i], left=np.nan, right=np.nan) for i in range(3)])
        fields.append(f)
    report = compass_consistency(fields, expected_strength_mG=expected_mG)
    names = [e[0] for e in entries]
    pairs = []
    for p in report.pairs:
        a, b = names[p.a], names[p.b]
        pairs.append({"a": a, "b": b, "angle_deg": round(p.angle_median_deg, 2),
                      "angle_p95_deg": round(p.angle_p95_deg, 2),
                      "strength_diff_mG": round(p.strength_diff_median_mG, 1),
                      "ardupilot_consistent": bool(p.ardupilot_consistent),
                      "agree": bool(p.ardupilot_consistent and p.angle_median_deg <= settings.consistency_angle_deg)})
    odd = names[report.disagreeing] if report.disagreeing is not None else None
    ok = all(p["agree"] for p in pairs)
    if ok:
        text = "The compasses agree: " + ", ".join(
            f"{p['a'] + 1}–{p['b'] + 1} {p['angle_deg']:.1f}°" for p in pairs) + f" (limit {settings.consistency_angle_deg:g}°)."
    else:
        worst = max(pairs, key=lambda p: p["angle_deg"])
        text = (f"The compasses disagree: {worst['a'] + 1}–{worst['b'] + 1} differ by {worst['angle_deg']:.1f}° "
                f"(limit {settings.consistency_angle_deg:g}°)" +
                (f"; compass {odd + 1} is the odd one out: leave it out or check its mounting." if odd is not None else "."))
        if any(not p["ardupilot_consistent"] for p in pairs):
            text += " ArduPilot's pre-arm check would refuse to arm (inconsistent compasses)."
    return {"status": "ok" if ok else "inconsistent", "text": text, "pairs": pairs, "odd_one": odd,
            "ardupilot_status": report.status}
