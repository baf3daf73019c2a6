"""Vector complementary filters (seed 000 eq. 9/10) against closed-form cases."""
import numpy as np
import pytest

from estimators.attitude import (FieldVectorFilter, GravityVectorFilter, VectorFilterSettings,
                                 roll_pitch_from_specific_force)
from estimators.rotations import dcm_body_to_ned, euler_from_dcm


def test_constant_rotation_without_measurement_is_exact():
    # after initialisation the gain has no effect without measurements: dH/dt = -w x H,
    # closed form H(t) = |H| [cos wt, -sin wt, 0]   (seed 000 eq. 7)
    f = FieldVectorFilter(VectorFilterSettings(gain_per_s=0.5, hold_timeout_s=0.0))
    f.update(0.0, [0, 0, 0], [300.0, 0.0, 0.0])          # initialises from the measurement
    w = 0.7
    for i in range(1, 2001):
        h = f.update(i * 0.01, [0.0, 0.0, w])
    t = 20.0
    np.testing.assert_allclose(h, [300 * np.cos(w * t), -300 * np.sin(w * t), 0.0], atol=1e-6)


def test_step_in_field_is_first_order_with_time_constant_one_over_k():
    k = 0.8
    f = FieldVectorFilter(VectorFilterSettings(gain_per_s=k))
    h1, h2 = np.array([200.0, 50.0, 400.0]), np.array([150.0, -80.0, 420.0])
    f.update(0.0, [0, 0, 0], h1)
    dt = 0.02
    for i in range(1, 251):
        t = i * dt
        h = f.update(t, [0, 0, 0], h2)
        np.testing.assert_allclose(h, h2 + (h1 - h2) * np.exp(-k * t), atol=1e-9)
    # and the Euler step of eq. (10) is the same to first order in k*dt
    assert np.exp(-k * dt) == pytest.approx(1 - k * dt, abs=(k * dt) ** 2)


def test_rotation_with_consistent_measurement_tracks_exactly_and_slow_mag_is_held():
    # body rotates about a tilted axis; magnetometer at 1/5 of the gyro rate is held in between
    axis = np.array([0.3, -0.2, 0.9]); axis /= np.linalg.norm(axis)
    w = 0.5 * axis
    h0 = np.array([220.0, 10.0, 430.0])
    def truth(t):  # H(t) = exp(-[w x] t) h0
        a = np.linalg.norm(w) * t
        return h0 * np.cos(a) - np.sin(a) * np.cross(axis, h0) + (1 - np.cos(a)) * axis.dot(h0) * axis
    f = FieldVectorFilter(VectorFilterSettings(gain_per_s=0.3))
    err = []
    for i in range(0, 3000):
        t = i * 0.01
        if i % 5 == 0:
            f.set_measurement(t, truth(t))
        err.append(np.linalg.norm(f.update(t, w) - truth(t)))
    # held (stale) measurement pulls by at most k*|dH| ~ 0.3 * 0.5*0.04*480: tiny vs the field
    assert max(err[1:]) < 1.5
    assert np.isfinite(err).all()


def test_static_tilt_roll_pitch():
    roll, pitch = np.radians(20.0), np.radians(-10.0)
    c = dcm_body_to_ned(roll, pitch, 1.0)
    f_body = c.T @ np.array([0.0, 0.0, -9.81])
    g = GravityVectorFilter()
    g.update(0.0, [0, 0, 0], f_body + 0.5)              # a disturbed first sample ...
    for i in range(1, 4001):                              # ... decays as exp(-k t), k = 0.2/s
        g.update(i * 0.01, [0, 0, 0], f_body)
    r, p = g.roll_pitch_rad
    assert r == pytest.approx(roll, abs=1e-3) and p == pytest.approx(pitch, abs=1e-3)
    # closed form of roll/pitch from specific force, vectorised, all signs
    rr, pp = np.meshgrid(np.radians([-170, -60, 0, 45, 179]), np.radians([-80, -20, 0, 30, 85]))
    cc = dcm_body_to_ned(rr, pp, 0.3 * np.ones_like(rr))
    fb = np.einsum("...ji,j->...i", cc, [0.0, 0.0, -9.81])
    r2, p2 = roll_pitch_from_specific_force(fb)
    np.testing.assert_allclose(r2, rr, atol=1e-9)
    np.testing.assert_allclose(p2, pp, atol=1e-9)
    np.testing.assert_allclose(euler_from_dcm(cc)[0], rr, atol=1e-9)


def test_bad_input_stays_finite_and_gap_reinitialises():
    f = FieldVectorFilter()
    f.update(0.0, [0, 0, 0], [100.0, 0.0, 0.0])
    for t, w, m in [(0.01, [np.nan, 0, 0], None), (np.nan, [0, 0, 1], [np.nan, 1, 1]),
                    (0.005, [0, 0, 1], None), (0.02, [np.inf, 1, 1], [1, np.nan, 1]), (0.03, [0, 0, 0], None)]:
        h = f.update(t, w, m)
        assert np.all(np.isfinite(h))
    np.testing.assert_allclose(f.estimate, [100.0, 0.0, 0.0], atol=1e-9)
    f.update(5.0, [0, 0, 3.0], [0.0, 100.0, 0.0])    # 5 s gap: re-initialised to the new measurement
    np.testing.assert_allclose(f.estimate, [0.0, 100.0, 0.0], atol=1e-9)


# ----------------------------------------------------------------------------- offline smoother

def _turning_log(n=12000, rest_end_s=20.0, bias_deg_s=(0.3, -0.3, 0.3), seed=3):
    """A body turning and rocking from the first sample (no rest at the start, so the causal AHRS
    starts with an unknown gyro bias), with lateral accelerations, then ``rest_end_s`` still."""
    from estimators.rotations import rotation_from_vector_rad
    rng = np.random.default_rng(seed)
    dt = 0.01
    t = np.arange(n) * dt
    moving = t < t[-1] - rest_end_s
    rates = np.c_[0.3 * np.sin(0.7 * t), 0.25 * np.cos(0.45 * t), 0.2 + 0.1 * np.sin(0.2 * t)] * moving[:, None]
    C = np.empty((n, 3, 3))
    C[0] = np.eye(3)
    for i in range(1, n):
        C[i] = C[i - 1] @ rotation_from_vector_rad(rates[i] * dt)
    acc = np.c_[1.5 * np.sin(1.3 * t), 1.0 * np.cos(0.9 * t), np.zeros(n)] * moving[:, None]
    h = np.array([210.0, 25.0, 430.0])
    f = np.einsum("nji,nj->ni", C, acc - [0.0, 0.0, 9.80665]) + rng.normal(0, 0.03, (n, 3))
    m = np.einsum("nji,j->ni", C, h) + rng.normal(0, 1.0, (n, 3))
    gyro = rates + np.radians(bias_deg_s) + rng.normal(0, 0.002, (n, 3))
    return np.c_[t, gyro, f], np.c_[t, m], C, moving


def _tilt_heading_errors_deg(r, C):
    roll = np.arctan2(C[:, 2, 1], C[:, 2, 2])
    pitch = -np.arcsin(np.clip(C[:, 2, 0], -1, 1))
    yaw = np.arctan2(C[:, 1, 0], C[:, 0, 0])
    tilt = np.hypot(np.degrees(np.angle(np.exp(1j * (r.roll_rad - roll)))), np.degrees(r.pitch_rad - pitch))
    decl = np.arctan2(25.0, 210.0)
    return tilt, np.degrees(np.angle(np.exp(1j * (r.yaw_rad + decl - yaw))))


def test_time_reversal_is_its_own_inverse():
    from estimators.attitude_smoother import _reverse
    imu, mag, _, _ = _turning_log(n=500)
    imu[::7, 0] += 0.001                                   # uneven steps
    imu_r, mag_r, pivot = _reverse(imu, mag)
    assert np.all(np.diff(imu_r[:, 0]) >= 0) and np.all(np.diff(mag_r[:, 0]) >= 0)
    # the step into reversed sample j uses the rate of the forward step it undoes
    np.testing.assert_array_equal(imu_r[1:, 1:4], -imu[:0:-1, 1:4])
    imu_2, mag_2, _ = _reverse(imu_r, mag_r)
    np.testing.assert_allclose(imu_2[:, 0], imu[:, 0], atol=1e-12)
    np.testing.assert_array_equal(imu_2[1:, 1:], imu[1:, 1:])       # row 0's rate is never used
    np.testing.assert_allclose(mag_2, mag, atol=1e-12)


def test_offline_smoother_beats_the_causal_ahrs_against_truth():
    """A log that starts moving with an unknown 0.3°/s bias and ends at rest: the offline estimate
    knows the bias from the end (bias hand-over) and averages the forward and backward low-pass
    errors, so its tilt and heading errors are well below the causal filter's, above all early."""
    from estimators.ahrs_batch import run_ahrs
    from estimators.attitude_smoother import smooth_ahrs, smooth_heading_chain
    imu, mag, C, moving = _turning_log()
    causal, offline = run_ahrs(imu, mag), smooth_ahrs(imu, mag)
    assert offline.valid[1:].all()
    tc, hc = _tilt_heading_errors_deg(causal, C)
    to, ho = _tilt_heading_errors_deg(offline, C)
    rms = lambda a, sel: float(np.sqrt(np.mean(a[sel] ** 2)))  # noqa: E731
    early = moving & (imu[:, 0] < 30.0)
    assert rms(to, moving) < 0.7 * rms(tc, moving) and rms(ho, moving) < 0.7 * rms(hc, moving)
    assert rms(to, early) < 0.5 * rms(tc, early) and rms(ho, early) < 0.5 * rms(hc, early)
    chain = smooth_heading_chain(imu, mag, 5.0)
    assert chain.estimator == "offline"
    np.testing.assert_allclose(np.angle(np.exp(1j * (chain.heading_true_rad - offline.yaw_rad))), np.radians(5.0),
                               atol=1e-12)


def test_offline_smoother_on_bad_input_stays_finite():
    from estimators.attitude_smoother import smooth_ahrs
    imu, mag, _, _ = _turning_log(n=3000)
    imu[100:105, 1] = np.nan                               # gyro dropouts
    imu[200, 0] = np.nan                                   # a bad and a backwards time stamp
    imu[300, 0] -= 1.0
    imu[400:403, 4] = np.inf
    mag[50, 0] = np.nan
    mag[60, 2] = np.nan
    r = smooth_ahrs(imu, mag)
    assert all(np.all(np.isfinite(a)) for a in (r.roll_rad, r.pitch_rad, r.yaw_rad, r.gravity_body, r.field_body_mG))
    assert r.valid[10:].all()
    no_mag = smooth_ahrs(imu, np.zeros((0, 4)))            # no magnetometer: tilt only, never valid
    assert not no_mag.valid.any() and np.all(np.isfinite(no_mag.roll_rad))
    assert len(smooth_ahrs(imu[:1], mag).t_s) == 1 and len(smooth_ahrs(np.zeros((0, 7)), mag).t_s) == 0
