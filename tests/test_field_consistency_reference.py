"""The field-vector test's numbers against a frozen reference (issue 29: the per-step loop made
faster must give today's numbers).  ``tests/data/field_consistency_reference.npz`` holds what the
code of 2026-12-05 (before the plain-float rewrite) computed on the two flights below: every status
and alarm decision, and every 25th step's numbers.  The rewrite changes the order of some sums
(numpy's BLAS against plain floats), so the floats agree to 1e-9 relative, not bit for bit; the
decisions are identical.  Regenerate only for an intended change of the test's behaviour:
``python tests/test_field_consistency_reference.py`` (writes the file with the code at hand).
Regenerated 2026-12-06 for one: a fast turn's residual of ``fast_turn_q`` σ ends its hold, and the
turn's CUSUM counts then (``turn_evidence``)."""
from __future__ import annotations

import math
import sys
from pathlib import Path

import numpy as np

from estimators.field_consistency import field_consistency
from estimators.rotations import dcm_body_to_ned

REFERENCE = Path(__file__).resolve().parent / "data" / "field_consistency_reference.npz"
EVERY = 25                      # the floats of every 25th step are kept
H_MAG = np.array([330.0, 0.0, 350.0])
B_BODY = np.array([12.0, -8.0, 5.0])
F_BODY = np.array([-1.2, 0.8, 2.0])
TILT_DEG = (2.5, 1.5, 0.0)
FIELDS = ("z", "q", "residual_mG", "motor_mG_per_unit", "motor_sd_mG_per_unit")
ENDS = ("noise_mG", "earth_field_mG", "offset_mG", "tilt_deg")


def _flight(seed: int, n_s: float = 150.0, rate_hz: float = 50.0) -> dict:
    """Level flight with 180° turns (40°/s) every 30 s and slower 10°/s turns, the current 14-30 A
    (lost for stretches), a 2.5°/1.5° tilted magnetometer, a ramp from 70 s to 88 s and a step at 115-125 s."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, n_s, 1.0 / rate_hz)
    ph = np.mod(t, 30.0)
    yaw_rate = np.where((ph >= 25.0) & (ph < 29.5), math.radians(40.0), 0.0) \
        + np.where((ph >= 8.0) & (ph < 14.0), math.radians(10.0), 0.0)
    yaw = np.cumsum(yaw_rate) / rate_hz + 0.3
    roll = np.radians(2.0) * np.sin(2 * np.pi * t / 7.0)
    pitch = np.radians(-3.0) * np.sin(2 * np.pi * t / 11.0)
    current = 20.0 + 6.0 * np.sin(2 * np.pi * t / 15.0) + np.where(np.mod(t, 20.0) < 10.0, 4.0, -4.0)
    c = dcm_body_to_ned(roll, pitch, yaw)
    mag = np.einsum("nji,j->ni", c, H_MAG) + current[:, None] * F_BODY
    mag = mag @ dcm_body_to_ned(*np.radians(TILT_DEG)) + B_BODY + rng.normal(0, 2.0, (len(t), 3))
    mag += (np.clip(t - 70.0, 0.0, 8.0) * 30.0 * (t < 88.0))[:, None] * np.array([0.7, 0.0, 0.7])
    mag += np.where((t >= 115.0) & (t < 125.0), 90.0, 0.0)[:, None] * np.array([0.0, 1.0, 0.0])
    gyro = np.zeros((len(t), 3))
    gyro[:, 2] = yaw_rate * 1.03                 # the gyro reads 3 % high: fast turns leave ψ_f off
    gyro += rng.normal(0, 0.003, gyro.shape)
    current[(t > 40.0) & (t < 47.0)] = np.nan    # the current's telemetry lost
    return dict(t=t, mag=mag, roll=roll, pitch=pitch, ok=np.ones(len(t), bool), gyro=gyro, motor=current,
                rate=np.full(len(t), rate_hz))


def _with_gaps(f: dict) -> dict:
    """The same flight with what switches the test off or restarts it: a 1 s IMU gap (settling),
    a 6 s gap (a new segment), time going back 3 s (a seek), no field for 2 s, a low IMU rate for
    2 s and a steep attitude for 2 s."""
    t = f["t"].copy()
    keep = ~(((t > 30.0) & (t < 31.0)) | ((t > 90.0) & (t < 96.0)))
    g = {k: v[keep].copy() for k, v in f.items()}
    t = g["t"]
    back = t > 130.0
    g["t"] = np.where(back, t - 3.0, t)
    g["mag"][(t > 55.0) & (t < 57.0)] = np.nan
    g["rate"][(t > 62.0) & (t < 64.0)] = 5.0
    g["ok"][(t > 100.0) & (t < 102.0)] = False
    return g


def _cases() -> list[tuple[dict, float]]:
    """(inputs, the time from which the WMM prior is known)."""
    return [(_flight(7), 3.0), (_with_gaps(_flight(8)), -math.inf)]


def _run(f: dict, prior_from_s: float):
    return field_consistency(f["t"], f["mag"], f["roll"], f["pitch"], f["ok"], f["gyro"], f["motor"], f["rate"],
                             True, earth_field_mG=tuple(H_MAG), prior_from_s=prior_from_s)


def _record(k: int, r) -> dict:
    out = {f"{k}_status": r.status.astype(np.int8), f"{k}_alarm": np.nan_to_num(r.z) >= 1.0}
    for name in FIELDS:
        out[f"{k}_{name}"] = np.asarray(getattr(r, name))[::EVERY]
    for name in ENDS:
        out[f"{k}_{name}"] = np.asarray(getattr(r, name), dtype=float)
    return out


def _close(new: np.ndarray, ref: np.ndarray, what: str) -> None:
    new, ref = np.asarray(new, dtype=float), np.asarray(ref, dtype=float)
    assert new.shape == ref.shape, what
    fin = np.isfinite(ref)
    assert np.array_equal(np.isfinite(new), fin), f"{what}: NaN/inf at other steps"
    assert np.array_equal(new[~fin], ref[~fin], equal_nan=True), what
    err = np.abs(new[fin] - ref[fin]) / np.maximum(np.abs(ref[fin]), 1.0)
    assert not len(err) or err.max() <= 1e-9, f"{what}: {err.max():.2e} relative"


def test_the_field_vector_test_gives_the_reference_numbers_and_decisions():
    ref = np.load(REFERENCE)
    for k, (f, prior_from_s) in enumerate(_cases()):
        r = _run(f, prior_from_s)
        assert np.array_equal(r.status, ref[f"{k}_status"]), f"flight {k}: statuses differ"
        assert np.array_equal(np.nan_to_num(r.z) >= 1.0, ref[f"{k}_alarm"]), f"flight {k}: alarms differ"
        for name in FIELDS + ENDS:
            _close(np.asarray(getattr(r, name))[::EVERY] if name in FIELDS else getattr(r, name),
                   ref[f"{k}_{name}"], f"flight {k} {name}")


def test_the_reference_flights_reach_every_path():
    """The frozen flights are worth comparing: they alarm, relearn, settle, restart and switch off."""
    ref = np.load(REFERENCE)
    statuses = set(ref["0_status"]) | set(ref["1_status"])
    assert statuses == {0, 1, 2, 3, 4, 5}
    starts = [np.count_nonzero(np.diff(ref[f"{k}_alarm"].astype(int)) == 1) for k in (0, 1)]
    assert starts[0] >= 2 and starts[1] >= 1              # the ramp and the step; the ramp after the gaps


if __name__ == "__main__":
    out = {}
    for k, (f, prior_from_s) in enumerate(_cases()):
        out.update(_record(k, _run(f, prior_from_s)))
    np.savez_compressed(REFERENCE, **out)
    print(f"wrote {REFERENCE} ({REFERENCE.stat().st_size} bytes)", file=sys.stderr)
