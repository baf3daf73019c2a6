"""Tilt-compensated heading (seed 000 eqs. 11-13), velocity split, and the heading chain."""
import numpy as np
import pytest

from estimators.heading import HeadingChain, run_heading_chain, split_velocity, tilt_compensated_heading_rad
from estimators.rotations import dcm_body_to_ned, wrap_angle_deg, wrap_angle_rad

H_NED = np.array([210.0, 25.0, 430.0])       # mG, inclination ~64 deg


@pytest.mark.parametrize("heading_deg", [0.0, 30.0, 90.0, 135.0, 180.0, 225.0, 270.0, 300.0, 359.5, 0.5, -179.5])
@pytest.mark.parametrize("roll_deg,pitch_deg", [(0, 0), (-20, 0), (25, -15), (-40, 35)])
def test_heading_all_quadrants_with_tilt(heading_deg, roll_deg, pitch_deg):
    h_mag = np.array([np.hypot(H_NED[0], H_NED[1]), 0.0, H_NED[2]])   # magnetic-north frame
    r, p, y = np.radians([roll_deg, pitch_deg, heading_deg])
    m_body = dcm_body_to_ned(r, p, y).T @ h_mag
    got = np.degrees(tilt_compensated_heading_rad(m_body, r, p))
    assert 0.0 <= got < 360.0
    assert abs(wrap_angle_deg(got - heading_deg)) < 1e-9


def test_heading_is_vectorised_and_matches_seed_eq13_cases():
    # eq. (13) written out case by case for H_X, H_Y on the axes and in each quadrant
    hx = np.array([1.0, 0.0, -1.0, 0.0, 1.0, -1.0, -1.0, 1.0])
    hy = np.array([0.0, -1.0, 0.0, 1.0, -1.0, -1.0, 1.0, 1.0])
    expected = np.array([0.0, 90.0, 180.0, 270.0, 45.0, 135.0, 225.0, 315.0])
    m = np.c_[hx, hy, np.zeros(8)]
    got = np.degrees(tilt_compensated_heading_rad(m, np.zeros(8), np.zeros(8)))
    np.testing.assert_allclose(got, expected, atol=1e-12)


def test_wrap_angles():
    np.testing.assert_allclose(wrap_angle_deg([181.0, -181.0, 360.0, 540.0, -180.0, 180.0]),
                               [-179.0, 179.0, 0.0, 180.0, 180.0, 180.0])
    assert wrap_angle_rad(3 * np.pi) == pytest.approx(np.pi)
    assert wrap_angle_rad(-np.pi) == pytest.approx(np.pi)


def test_split_velocity():
    fwd, lat = split_velocity(np.array([0.0, 5.0, 3.0]), np.array([5.0, 0.0, 4.0]), np.radians([90.0, 90.0, 0.0]))
    np.testing.assert_allclose(fwd, [5.0, 0.0, 3.0], atol=1e-12)
    np.testing.assert_allclose(lat, [0.0, -5.0, 4.0], atol=1e-12)    # lateral positive to the right


def _sim(n=3000, rate=100.0, seed=0, mag_every=4):
    """Vehicle turning and rolling, IMU at rate, magnetometer slower; truth Euler angles."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / rate
    roll = 0.3 * np.sin(0.4 * t)
    pitch = 0.2 * np.sin(0.25 * t + 1.0)
    yaw = 0.6 * t                                        # ~34 deg/s turn, several full turns
    dr, dp, dy = 0.12 * np.cos(0.4 * t), 0.05 * np.cos(0.25 * t + 1.0), np.full(n, 0.6)
    rates = np.c_[dr - dy * np.sin(pitch), dp * np.cos(roll) + dy * np.cos(pitch) * np.sin(roll),
                  -dp * np.sin(roll) + dy * np.cos(pitch) * np.cos(roll)]
    C = dcm_body_to_ned(roll, pitch, yaw)
    acc = np.einsum("nji,j->ni", C, [0.0, 0.0, -9.81]) + rng.normal(0, 0.02, (n, 3))
    imu = np.c_[t, rates + rng.normal(0, 0.002, (n, 3)), acc]
    mi = np.arange(0, n, mag_every)
    mag = np.c_[t[mi] + 0.001, np.einsum("nji,j->ni", C[mi], H_NED) + rng.normal(0, 1.0, (len(mi), 3))]
    return imu, mag, roll, pitch, yaw


def test_chain_tracks_a_turning_rolling_vehicle():
    imu, mag, roll, pitch, yaw = _sim()
    decl = np.degrees(np.arctan2(H_NED[1], H_NED[0]))
    r = run_heading_chain(imu, mag, decl)
    s = slice(500, None)                                  # after the filters settled
    assert np.all(r.valid[5:])
    assert np.abs(np.degrees(r.roll_rad - roll)[s]).max() < 0.5
    assert np.abs(np.degrees(r.pitch_rad - pitch)[s]).max() < 0.5
    err = wrap_angle_deg(np.degrees(r.heading_true_rad - yaw))[s]
    # turning at 34 deg/s with the magnetometer held ~0.024 s on average: ~0.8 deg of lag
    assert np.abs(err).max() < 1.3
    assert abs(np.mean(err)) < 1.0
    # the raw tilt-compensated heading (latest mag sample) is noisier and lags by the mag hold
    err_raw = wrap_angle_deg(np.degrees(r.mag_heading_rad + np.radians(decl) - yaw))[s]
    assert np.abs(err_raw).max() < 3.0


def _per_sample(imu, mag, decl):
    hc = HeadingChain(decl)
    out, j = [], 0
    for i in range(len(imu)):
        while j < len(mag) and mag[j, 0] <= imu[i, 0]:
            hc.update_mag(mag[j, 0], mag[j, 1:4])
            j += 1
        s = hc.update_imu(imu[i, 0], imu[i, 1:4], imu[i, 4:7])
        out.append([s.roll_rad, s.pitch_rad, s.yaw_rad, s.mag_heading_rad, s.heading_true_rad, s.valid])
    return np.array(out)


def test_batch_equals_per_sample_with_bad_samples_and_gaps():
    imu, mag, *_ = _sim(n=2500, seed=1)
    imu[100:110, 2] = np.nan          # gyro dropouts
    imu[500, 0] = np.nan              # bad time stamp
    imu[800:805, 4] = np.nan          # accelerometer dropouts
    imu[900, 0] -= 1.0                # a backwards time stamp
    imu[1200:, 0] += 2.0              # a 2 s gap (re-initialisation)
    mag[1200 // 4:, 0] += 2.0
    mag[50, 2] = np.nan
    mag = np.delete(mag, np.arange(300, 400), axis=0)     # magnetometer missing for 4 s
    r = run_heading_chain(imu, mag, 3.0)
    b = np.c_[r.roll_rad, r.pitch_rad, r.yaw_rad, r.mag_heading_rad, r.heading_true_rad]
    assert np.all(np.isfinite(b))
    p = _per_sample(imu, mag, 3.0)
    d = np.abs(np.angle(np.exp(1j * (p[:, :5] - b))))
    assert d.max() < 1e-9
    np.testing.assert_array_equal(p[:, 5].astype(bool), r.valid)


def test_all_nan_and_empty_inputs_stay_finite():
    imu = np.full((50, 7), np.nan)
    r = run_heading_chain(imu, np.empty((0, 4)), 0.0)
    assert np.all(np.isfinite(r.yaw_rad)) and not r.valid.any()
    r = run_heading_chain(np.empty((0, 7)), np.empty((0, 4)), 0.0)
    assert len(r.t_s) == 0
    imu, mag, *_ = _sim(n=200)
    r = run_heading_chain(imu, np.empty((0, 4)), 0.0)      # no magnetometer at all
    assert np.all(np.isfinite(r.heading_true_rad)) and not r.valid.any()
    assert np.all(np.isfinite(r.roll_rad))


def test_declination_array_and_true_heading():
    imu, mag, *_ = _sim(n=600)
    a = run_heading_chain(imu, mag, 0.0)
    b = run_heading_chain(imu, mag, np.full(600, 10.0))
    assert b.valid[1:].all() and not b.valid[0]            # first magnetometer sample at t = 0.001 s
    np.testing.assert_allclose(wrap_angle_deg(np.degrees(b.heading_true_rad - a.yaw_rad))[b.valid], 10.0, atol=1e-9)
    assert b.heading_true_rad[0] == 0.0 and b.roll_rad[0] == 0.0     # not valid yet: zeros
