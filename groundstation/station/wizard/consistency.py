"""Do the calibrated compasses agree?  ArduPilot's pre-arm consistency check, plus a closer look.

Each included compass's samples are calibrated with its own result as the vehicle will apply it
(orientation applied, the symmetric matrix the exported COMPASS_DIA/ODI hold: a misalignment the
vehicle cannot correct shows as disagreement, which is what its pre-arm check will see) and
interpolated onto the first compass's sample times; ``estimators.compass_consistency`` compares
every pair as ArduPilot's Compass::consistent does (3-D angle 90°, XY angle 60°, XY length
200 mG) and names the odd one out.  Those limits catch only gross faults, so a pair whose median
angle exceeds ``settings.consistency_angle_deg`` is reported too.

Evidence beyond noise: the pairs are compared on block means (``BLOCK_S``) rather than single
samples — the angle between two single noisy samples (2–3 mG on 490 mG) is ~0.5° by noise alone,
and two compasses sampled a few ms apart during a 35°/s turn differ by the turn, neither of which
is a disagreement — and on the blocks held slower than ``SLOW_DEG_S`` when there are
``MIN_SLOW_BLOCKS`` of them (the still moments of the dance).  The block means' own noise,
sqrt(σa² + σb²)/(F √n) from the fits' residuals, is reported as ``noise_deg``; a pair disagrees
only beyond max(limit, 4 × noise).
"""
from __future__ import annotations

import numpy as np

from estimators.compass_consistency import compass_consistency
from groundstation.station.wizard.fit import calibrated_in_new_frame
from groundstation.station.wizard.settings import WizardSettings

__all__ = ["check_consistency", "BLOCK_S", "SLOW_DEG_S"]

BLOCK_S = 0.5
SLOW_DEG_S = 10.0
MIN_SLOW_BLOCKS = 12          # (compass_consistency compares pairs with at least 10 common samples)
NOISE_FACTOR = 4.0


def _block_means(t: np.ndarray, fields: list[np.ndarray], attitude: np.ndarray | None
                 ) -> tuple[list[np.ndarray], int]:
    """Per-block means of every field (blocks of ``BLOCK_S`` on the reference times), the slow
    blocks only when there are enough of them; (means, samples per block)."""
    block = np.floor((t - t[0]) / BLOCK_S).astype(int)
    _, inv, counts = np.unique(block, return_inverse=True, return_counts=True)
    k = int(inv.max()) + 1
    means = []
    for f in fields:
        ok = np.all(np.isfinite(f), axis=1)
        s = np.zeros((k, 3))
        n = np.zeros(k)
        np.add.at(s, inv[ok], f[ok])
        np.add.at(n, inv[ok], 1)
        with np.errstate(invalid="ignore", divide="ignore"):
            means.append(s / n[:, None])
    keep = np.ones(k, bool)
    if attitude is not None and len(attitude) > 2:
        from estimators.rotations import dcm_body_to_ned
        att = attitude[np.all(np.isfinite(attitude), axis=1)]
        if len(att) > 2:
            R = dcm_body_to_ned(att[:, 1], att[:, 2], att[:, 3])
            ang = np.degrees(np.arccos(np.clip((np.einsum("nij,nij->n", R[1:], R[:-1]) - 1) / 2, -1, 1)))
            rate = ang / np.maximum(np.diff(att[:, 0]), 1e-3)
            tb = np.array([t[inv == b].mean() for b in range(k)])
            slow = np.interp(tb, att[1:, 0], rate) < SLOW_DEG_S
            if slow.sum() >= MIN_SLOW_BLOCKS:
                keep = slow
    return [m[keep] for m in means], int(np.median(counts[keep])) if keep.any() else 1


def check_consistency(entries: list[tuple[int, dict, np.ndarray, object]], settings: WizardSettings,
                      expected_mG: float | None, attitude: np.ndarray | None = None) -> dict | None:
    """entries: (compass index, result, (t, mx, my, mz) table, unapply function) of included,
    successful compasses; ``attitude`` the dance's (t, roll, pitch, yaw) table (slow blocks).
    None with fewer than two."""
    if len(entries) < 2:
        return None
    t_ref = entries[0][2][:, 0]
    fields = []
    for _, result, mag, unapply in entries:
        cal = calibrated_in_new_frame(result, unapply(mag[:, 1:4]), as_vehicle=True)
        t = mag[:, 0]
        f = np.column_stack([np.interp(t_ref, t, cal[:, i], left=np.nan, right=np.nan) for i in range(3)])
        fields.append(f)
    means, per_block = _block_means(t_ref, fields, attitude)
    report = compass_consistency(means, expected_strength_mG=expected_mG)
    if not report.pairs:
        return None                       # too little in common to say anything
    names = [e[0] for e in entries]
    sigma = [float(e[1].get("residual_rms_mG") or 0.0) for e in entries]
    field = float(expected_mG or np.nanmedian(np.linalg.norm(fields[0], axis=1)))
    pairs = []
    for p in report.pairs:
        a, b = names[p.a], names[p.b]
        noise = float(np.degrees(np.hypot(sigma[p.a], sigma[p.b]) / (field * np.sqrt(max(per_block, 1)))))
        limit = max(settings.consistency_angle_deg, NOISE_FACTOR * noise)
        pairs.append({"a": a, "b": b, "angle_deg": round(p.angle_median_deg, 2),
                      "angle_p95_deg": round(p.angle_p95_deg, 2), "noise_deg": round(noise, 3),
                      "strength_diff_mG": round(p.strength_diff_median_mG, 1),
                      "ardupilot_consistent": bool(p.ardupilot_consistent),
                      "agree": bool(p.ardupilot_consistent and p.angle_median_deg <= limit)})
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
