"""Corrections in force over time (estimators.compass_corrections) and log alignment helpers."""
from __future__ import annotations

import numpy as np
import pytest

from estimators.compass_corrections import (CorrectionsInForce, apply_ardupilot_corrections, changes_summary,
                                            corrections_from_param_changes, motor_offset_mG,
                                            unapply_ardupilot_corrections, values_in_force)
from estimators.log_alignment import attitude_at, interp_series, nearest_series

pytestmark = pytest.mark.filterwarnings("error")


def test_values_in_force_step_hold():
    t = np.array([0.0, 1.0, 2.0, 3.0, 4.0])
    vals, known = values_in_force(t, [1.0, 3.0], np.array([[10.0], [20.0]]))
    np.testing.assert_array_equal(known, [False, True, True, True, True])     # a change at t applies at t
    np.testing.assert_array_equal(vals[1:, 0], [10, 10, 20, 20])
    assert np.isnan(vals[0, 0])
    vals, known = values_in_force(t, [3.0, 1.0], np.array([[20.0], [10.0]]), initial=[5.0])   # unsorted input
    np.testing.assert_array_equal(vals[:, 0], [5, 10, 10, 20, 20])
    assert known.all()


def test_parameter_history_per_instance_and_defaults():
    t = np.arange(0.0, 10.0)
    ch = [(0.0, "COMPASS_OFS2_X", 5.0), (0.0, "COMPASS_OFS2_Y", 6.0), (0.0, "COMPASS_OFS2_Z", 7.0),
          (4.0, "COMPASS_OFS2_X", -5.0), (4.0, "COMPASS_DIA2_X", 1.1), (0.0, "COMPASS_OFS_X", 99.0),
          (2.0, "COMPASS_MOTCT", 2.0), (2.0, "COMPASS_MOT2_Z", 0.5)]
    c = corrections_from_param_changes(t, ch, instance=1)
    np.testing.assert_array_equal(c.offsets_mG[:, 0], [5, 5, 5, 5, -5, -5, -5, -5, -5, -5])
    np.testing.assert_array_equal(c.diag[:4], 0.0)                # DIA never set: 0 = identity
    np.testing.assert_array_equal(c.diag[4:, 0], 1.1)
    np.testing.assert_array_equal(c.motor_type, [0, 0, 2, 2, 2, 2, 2, 2, 2, 2])
    assert c.known.all()
    c0 = corrections_from_param_changes(t, ch, instance=0)       # only OFS_X known: Y, Z missing
    assert not c0.known.any()
    assert [x for x, _ in changes_summary(c, t)] == [0.0, 4.0]


def _random_corrections(rng, n, t):
    first = t < t[n // 2]
    ofs = np.where(first[:, None], [30.0, -20.0, 10.0], [-80.0, 45.0, 12.0])
    diag = np.where(first[:, None], 0.0, [1.05, 0.97, 1.01])      # identity, then a soft-iron fit
    odi = np.where(first[:, None], 0.0, [0.02, -0.01, 0.015])
    scale = np.where(first, 0.0, 1.03)
    mot = np.tile([0.8, -0.5, 1.6], (n, 1))
    return CorrectionsInForce(ofs, diag, odi, scale, mot, np.full(n, 2), np.ones(n, bool))


@pytest.mark.parametrize("after", [True, False])
def test_apply_unapply_round_trip_with_a_change_mid_log(after):
    rng = np.random.default_rng(0)
    n = 400
    t = np.arange(n) * 0.5
    raw = rng.normal(0, 300, (n, 3))
    cur = rng.uniform(5, 30, n)
    corr = _random_corrections(rng, n, t)
    cal = apply_ardupilot_corrections(raw, corr, current_A=cur, motor_after_matrix=after)
    back = unapply_ardupilot_corrections(cal, corr, current_A=cur, motor_after_matrix=after)
    assert back.status == "ok"
    np.testing.assert_allclose(back.raw_mG, raw, atol=1e-9)
    # Using the last values for the whole log (the bug issue 11 reports) is wrong before the change.
    last = CorrectionsInForce.constant(n, corr.offsets_mG[-1], corr.diag[-1], corr.offdiag[-1], 1.03,
                                       corr.motor_per_unit[-1], 2)
    wrong = unapply_ardupilot_corrections(cal, last, current_A=cur, motor_after_matrix=after).raw_mG
    assert np.max(np.abs(wrong[: n // 2] - raw[: n // 2])) > 50.0
    np.testing.assert_allclose(wrong[n // 2:], raw[n // 2:], atol=1e-9)


def test_order_matters_only_with_a_matrix_and_motor_terms():
    n = 5
    raw = np.tile([100.0, 50.0, -300.0], (n, 1))
    cur = np.full(n, 20.0)
    ident = CorrectionsInForce.constant(n, (10, 20, 30), motor_per_unit=(1, 2, 3), motor_type=2)
    np.testing.assert_allclose(apply_ardupilot_corrections(raw, ident, cur, motor_after_matrix=True),
                               apply_ardupilot_corrections(raw, ident, cur, motor_after_matrix=False))
    soft = CorrectionsInForce.constant(n, (10, 20, 30), diag=(1.2, 1.0, 1.0), motor_per_unit=(1, 0, 0), motor_type=2)
    new = apply_ardupilot_corrections(raw, soft, cur, motor_after_matrix=True)
    old = apply_ardupilot_corrections(raw, soft, cur, motor_after_matrix=False)
    assert new[0, 0] == pytest.approx(1.2 * 110 + 20) and old[0, 0] == pytest.approx(1.2 * 130)


def test_motor_offset_per_throttle_current_and_missing_signal():
    n = 4
    c_thr = CorrectionsInForce.constant(n, motor_per_unit=(10, 0, 0), motor_type=1)
    np.testing.assert_allclose(motor_offset_mG(c_thr, throttle=[0.0, 0.5, np.nan, 1.0])[:, 0], [0, 5, 0, 10])
    c_cur = CorrectionsInForce.constant(n, motor_per_unit=(1, 0, 0), motor_type=2)
    assert np.all(motor_offset_mG(c_cur, current_A=None) == 0)      # ArduPilot adds nothing without current
    np.testing.assert_allclose(motor_offset_mG(c_cur, current_A=[1, 2, 3, 4])[:, 0], [1, 2, 3, 4])
    assert np.all(motor_offset_mG(CorrectionsInForce.constant(n, motor_per_unit=(1, 1, 1)), current_A=[9] * 4) == 0)


def test_logged_motor_offsets_override_and_bad_input_statuses():
    n = 6
    raw = np.tile([100.0, 0.0, 0.0], (n, 1))
    corr = CorrectionsInForce.constant(n, (5, 0, 0), motor_per_unit=(2, 0, 0), motor_type=2)
    cal = apply_ardupilot_corrections(raw, corr, current_A=np.full(n, 10.0))
    logged = motor_offset_mG(corr, current_A=np.full(n, 10.0))
    back = unapply_ardupilot_corrections(cal, corr, logged_motor_offset_mG=logged)
    np.testing.assert_allclose(back.raw_mG, raw)
    cal[2] = np.nan
    part = unapply_ardupilot_corrections(cal, corr, current_A=np.full(n, 10.0))
    assert part.status == "partial" and "1 of 6" in part.message and np.isnan(part.raw_mG[2]).all()
    unknown = CorrectionsInForce(np.full((n, 3), np.nan), corr.diag, corr.offdiag, corr.scale, corr.motor_per_unit,
                                 corr.motor_type, np.zeros(n, bool))
    assert unapply_ardupilot_corrections(cal, unknown).status == "no_data"
    singular = CorrectionsInForce.constant(n, diag=(1, 1, 1), offdiag=(1, 1, 1))
    assert unapply_ardupilot_corrections(raw, singular).status == "no_data"
    assert unapply_ardupilot_corrections(np.empty((0, 3)), corr).status == "no_data"


def test_interp_and_nearest_respect_gaps():
    tt = np.array([0.0, 1.0, 2.0, 10.0, 11.0])
    v = np.array([0.0, 1.0, 2.0, 10.0, 11.0])
    out, ok = interp_series([0.5, 5.0, 10.5, 12.0, np.nan], tt, v, max_gap_s=2.0)
    np.testing.assert_array_equal(ok, [True, False, True, False, False])
    np.testing.assert_allclose(out[ok, 0], [0.5, 10.5])
    near, ok = nearest_series([0.9, 5.0, 10.2], tt, v, max_dt_s=0.3)
    np.testing.assert_array_equal(ok, [True, False, True])
    np.testing.assert_allclose(near[ok, 0], [1.0, 10.0])
    assert not interp_series([1.0], [], [])[1].any()


def test_attitude_at_unwraps_yaw_and_measures_rate():
    t_att = np.arange(0.0, 20.0, 0.25)
    yaw = np.angle(np.exp(1j * np.radians(30.0 * t_att)))               # 30 deg/s, wrapping through ±180
    a = attitude_at([3.1, 6.05, 12.0, 30.0], t_att, np.zeros_like(t_att), np.zeros_like(t_att), yaw)
    np.testing.assert_allclose(a.rate_deg_s[:3], 30.0, rtol=1e-6)
    np.testing.assert_allclose(np.degrees(np.angle(np.exp(1j * (a.yaw_rad[:3] - np.radians(30 * np.array([3.1, 6.05, 12.0])))))),
                               0.0, atol=1e-6)
    assert not a.valid[3] and np.isnan(a.yaw_rad[3])


def test_per_sample_tracker_equals_the_batch_rebuild_on_a_log_whose_offsets_change():
    """CorrectionsTracker (live) fed the parameter history and the samples in time order gives the
    batch numbers after the first offsets arrived, across the onboard calibration's change."""
    import tempfile
    from pathlib import Path

    from estimators.compass_corrections import CorrectionsTracker
    from groundstation.io.logs import read_log
    from groundstation.jobs.compass_raw import compass_fields, motor_signals
    from groundstation.sim.ardupilot import ArduSimConfig, simulate_ardupilot

    sim = simulate_ardupilot(ArduSimConfig(seed=3, imu_rate_hz=1.5))
    with tempfile.TemporaryDirectory() as d:
        log = read_log(sim.write_tlog(Path(d) / "s.tlog"))
    for cf in compass_fields(log):
        live = CorrectionsTracker(cf.compass)
        hist = iter(log.param_history)
        pending = next(hist, None)
        cur, _ = motor_signals(log, cf.t_s)          # the current the batch form uses (NaN past the table)
        out = np.full_like(cf.raw_mG, np.nan)
        for i, t in enumerate(cf.t_s):
            while pending is not None and pending[0] <= t:
                live.update(pending[1], pending[2])
                pending = next(hist, None)
            out[i] = live.unapply(cf.logged_mG[i], current_A=cur[i])
        known = np.all(np.isfinite(out), axis=1)
        assert known.mean() > 0.95                      # unknown only before the first COMPASS_OFS arrived
        np.testing.assert_allclose(out[known], cf.raw_mG[known], atol=1e-9)
        assert sim.cal_applied_s < cf.t_s[known][-1]


def test_attitude_at_rotation_rate_chunked_is_the_same_and_right():
    """``attitude_at`` takes the rotation between attitudes a chunk at a time: any chunk, the same
    numbers; and the rate is the known one (a steady 30°/s yaw at a 10° roll)."""
    tt = np.arange(0.0, 20.0, 0.02)
    roll, pitch, yaw = np.full(len(tt), np.radians(10.0)), np.zeros(len(tt)), np.radians(30.0) * tt
    t = np.arange(0.01, 19.9, 0.013)
    whole = attitude_at(t, tt, roll, pitch, yaw)
    np.testing.assert_allclose(whole.rate_deg_s[whole.valid], 30.0, rtol=1e-6)
    for chunk in (1, 7, 500):
        part = attitude_at(t, tt, roll, pitch, yaw, chunk=chunk)
        for name in ("roll_rad", "pitch_rad", "yaw_rad", "rate_deg_s", "valid"):
            np.testing.assert_array_equal(getattr(part, name), getattr(whole, name), err_msg=f"{name} chunk {chunk}")
