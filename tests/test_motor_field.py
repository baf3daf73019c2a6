"""Motor / current interference (estimators.motor_field): known truth, export, bad input."""
from __future__ import annotations

import numpy as np
import pytest

from estimators.motor_field import fit_motor_field, motor_compensation_params
from groundstation.io.params import rotation_enum_matrix
from sim_arrays import H_NED, ardupilot_flight, level_flight, real_logs

pytestmark = pytest.mark.filterwarnings("error")


def test_field_per_ampere_interference_and_export():
    d = level_flight(seed=5, f=(2.0, -1.5, 3.0))
    r = fit_motor_field(d["t"], d["raw"], d["roll"], d["pitch"], d["yaw"], H_NED, d["current"])
    assert r.status == "ok", r.message
    f = d["f"]
    assert np.linalg.norm(r.motor_mG_per_unit - f) / np.linalg.norm(f) < 0.05
    assert np.all(r.motor_sd_mG_per_unit < 0.1)
    imax = d["current"].max()
    assert r.signal_max == pytest.approx(imax)
    assert r.interference_pct == pytest.approx(100 * np.linalg.norm(r.motor_mG_per_unit) * imax / np.linalg.norm(H_NED))
    bins = r.norm_bins
    assert np.ptp(bins["norm_compensated_mG"]) < np.ptp(bins["norm_uncompensated_mG"])
    R = rotation_enum_matrix(2)                                       # sensor mounted yaw 90
    p = motor_compensation_params(r, instance=1, px4_slot=0, sensor_to_body=R)
    np.testing.assert_allclose([p["ardupilot"][f"COMPASS_MOT2_{a}"] for a in "XYZ"], -r.motor_mG_per_unit)
    assert p["ardupilot"]["COMPASS_MOTCT"] == 2.0 and p["px4"]["CAL_MAG_COMP_TYP"] == 2.0
    # PX4 adds power·COMP in the sensor frame, current in kA: mG/A == G/kA.
    np.testing.assert_allclose([p["px4"][f"CAL_MAG0_{a}COMP"] for a in "XYZ"], -(R.T @ r.motor_mG_per_unit))


def test_per_throttle():
    d = level_flight(seed=6)
    thr = (d["current"] - 5.0) / 40.0                                 # 0.25..0.45
    raw = d["raw"] - d["current"][:, None] * d["f"] @ d["A"].T + thr[:, None] * np.array([40.0, 0.0, -60.0]) @ d["A"].T
    r = fit_motor_field(d["t"], raw, d["roll"], d["pitch"], d["yaw"], H_NED, thr, signal="throttle")
    assert r.status == "ok", r.message
    np.testing.assert_allclose(r.motor_mG_per_unit, [40.0, 0.0, -60.0], atol=4.0)
    p = motor_compensation_params(r)
    assert p["ardupilot"]["COMPASS_MOTCT"] == 1.0 and p["px4"]["CAL_MAG_COMP_TYP"] == 1.0
    assert p["px4"]["CAL_MAG0_XCOMP"] == pytest.approx(-r.motor_mG_per_unit[0] / 1000)


def test_no_signal_and_constant_current():
    d = level_flight(seed=7, n=300)
    args = (d["t"], d["raw"], d["roll"], d["pitch"], d["yaw"], H_NED)
    assert fit_motor_field(*args, None).status == "no_motor_signal"
    assert fit_motor_field(*args, np.full(300, np.nan)).status == "no_motor_signal"
    flat = fit_motor_field(*args, np.full(300, 15.0))
    assert flat.status == "insufficient_signal_variation", flat.message
    assert motor_compensation_params(fit_motor_field(*args, None)) == {"ardupilot": {}, "px4": {}}


def test_simulated_ardupilot_flight_within_10_percent():
    sim, log, H = ardupilot_flight(seed=1)
    for k in range(3):
        _, m = real_logs.inflight_fits(log, k)
        f = np.asarray(sim.truth["compasses"][k]["motor_mG_per_A"])
        assert m.status == "ok", m.message
        assert np.linalg.norm(m.motor_mG_per_unit - f) / np.linalg.norm(f) < 0.10, (k, m.motor_mG_per_unit, f)


def _calibrated(d: dict) -> np.ndarray:
    """The flight's field calibrated with the motors off: h + f·I (offsets and matrix removed)."""
    return (d["raw"] - d["b"]) @ np.linalg.inv(d["A"]).T


def test_current_field_of_a_calibrated_field_yaw_free():
    """fit_current_field uses only the tilt (no heading): f within 5 % on five legs; the levelled
    field steadier after removing f·I; a flight without a motor field is not 'compensated'."""
    from estimators.motor_field import fit_current_field
    d = level_flight(seed=8, f=(-1.4, -1.0, 2.4))
    r = fit_current_field(_calibrated(d), d["current"], d["roll"], d["pitch"])
    assert r.status == "ok", r.message
    assert np.linalg.norm(r.motor_mG_per_A - d["f"]) / np.linalg.norm(d["f"]) < 0.05
    assert r.field_down_mG == pytest.approx(H_NED[2], abs=3.0)
    assert r.field_horizontal_mG == pytest.approx(np.hypot(H_NED[0], H_NED[1]), abs=3.0)
    clean = level_flight(seed=8, f=(0.0, 0.0, 0.0))
    r0 = fit_current_field(_calibrated(clean), clean["current"], clean["roll"], clean["pitch"])
    assert r0.status == "not_supported" and np.all(np.isnan(r0.motor_mG_per_A)), r0.message
    steady = fit_current_field(_calibrated(d), np.full(len(d["t"]), 18.0), d["roll"], d["pitch"])
    assert steady.status == "insufficient_signal_variation"
    nan = fit_current_field(np.full((10, 3), np.nan), np.ones(10), np.zeros(10), np.zeros(10))
    assert nan.status == "no_motor_signal"
