"""Seed 003 INS/GPS error-state filter with field-vector feedback during GPS outage."""
import numpy as np
import pytest

from estimators.ins_gps import (MODE_FIELD_FEEDBACK, MODE_GPS, MODE_OPEN_LOOP, InsGpsFilter, InsGpsSettings,
                                attitude_errors_deg, run_ins_gps)
from groundstation.sim.truth import simulate_manoeuvring_flight

B = np.radians(0.5)


def _decl(tr):
    return float(np.degrees(np.arctan2(tr.field_ned_mG[1], tr.field_ned_mG[0])))


@pytest.fixture(scope="module")
def step_flight():
    """80 s outage (40-120 s) with a 0.5 deg/s per axis gyro bias appearing at its start."""
    return simulate_manoeuvring_flight(duration_s=130.0, imu_rate_hz=50.0, outage=(40.0, 120.0),
                                       outage_gyro_bias_rad_s=(B, B, B), seed=1)


@pytest.fixture(scope="module")
def step_runs(step_flight):
    tr = step_flight
    return {name: run_ins_gps(tr.imu, tr.gps_ned, tr.mag, InsGpsSettings(declination_deg=_decl(tr), **kw))
            for name, kw in (("open", dict(field_feedback=False)), ("kalman", dict()),
                             ("kalman_fast", dict(outage_gyro_bias_sigma_rad_s=0.001, outage_field_walk_mG=0.0)),
                             ("pi", dict(feedback_law="pi")),
                             ("gravity", dict(feedback_law="pi", gravity_kp_per_s=0.2)))}


def test_gps_mode_tracks_truth_and_estimates_the_field(step_flight, step_runs):
    tr, res = step_flight, step_runs["kalman"]
    pre = (tr.t_s > 10.0) & (tr.t_s < 40.0)
    assert np.all(res.mode[pre] == MODE_GPS)
    ang, hd = attitude_errors_deg(res, tr)
    assert ang[pre].max() < 1.5 and np.abs(hd[pre]).max() < 1.5
    assert np.linalg.norm(res.pos_ned_m[pre] - tr.pos_ned_m[pre], axis=1).max() < 3.0
    assert np.linalg.norm(res.vel_ned_mps[pre] - tr.vel_ned_mps[pre], axis=1).max() < 0.5
    assert np.linalg.norm(res.field_ned_mG[pre][-1] - tr.field_ned_mG) < 8.0     # |H| ~ 480 mG


def test_outage_and_recovery_switch_modes(step_flight, step_runs):
    tr = step_flight
    inside = (tr.t_s >= 41.0) & (tr.t_s < 120.0)
    after = tr.t_s >= 121.0
    assert np.all(step_runs["kalman"].mode[inside] == MODE_FIELD_FEEDBACK)
    assert np.all(step_runs["pi"].mode[inside] == MODE_FIELD_FEEDBACK)
    assert np.all(step_runs["open"].mode[inside] == MODE_OPEN_LOOP)
    for res in step_runs.values():
        assert np.all(res.mode[after] == MODE_GPS)
        assert np.all(np.isfinite(res.roll_rad)) and np.all(np.isfinite(res.pos_ned_m))
    # the gyro-bias change learnt by the integral is handed to the Kalman filter on return
    res = step_runs["gravity"]
    i_before = np.searchsorted(tr.t_s, 39.9)
    i_after = np.searchsorted(tr.t_s, 120.5)
    err_before = np.linalg.norm(res.gyro_bias_rad_s[i_before] - B)
    err_after = np.linalg.norm(res.gyro_bias_rad_s[i_after] - B)
    assert err_after < 0.5 * err_before


def test_field_feedback_beats_open_loop_in_outage(step_flight, step_runs):
    tr = step_flight
    inside = (tr.t_s >= 40.0) & (tr.t_s < 120.0)
    rms = {k: np.sqrt(np.mean(attitude_errors_deg(r, tr)[0][inside] ** 2)) for k, r in step_runs.items()}
    heading_max = {k: np.abs(attitude_errors_deg(r, tr)[1][inside]).max() for k, r in step_runs.items()}
    # measured (seed 1): RMS open loop 30°, seed-003 PI 13°, PI + gravity 6.3°, Kalman with the
    # robust defaults 16°, Kalman tuned for a bias step (widened bias, fixed set-point) 1.7°
    assert rms["open"] > 20.0
    assert rms["pi"] < 0.6 * rms["open"]
    assert rms["gravity"] < 0.3 * rms["open"]
    assert rms["kalman"] < 0.7 * rms["open"]
    assert rms["kalman_fast"] < rms["open"] / 3.0 and rms["kalman_fast"] < 0.5 * rms["pi"]
    assert heading_max["kalman_fast"] < 0.25 * heading_max["open"]


def test_feedback_removes_an_attitude_error_perpendicular_to_the_field():
    # static vehicle; after a GPS phase the GPS stops and the attitude is knocked off by 5°
    h_ned = np.array([200.0, 15.0, 440.0])
    f = InsGpsFilter(InsGpsSettings(declination_deg=float(np.degrees(np.arctan2(15, 200))),
                                    feedback_law="pi", feedback_kp_per_s=0.5, feedback_ki_per_s2=0.02))
    acc = np.array([0.0, 0.0, -9.80665])
    for i in range(700):                                  # 5 s with GPS at 10 Hz, then 2 s without
        t = i * 0.01
        f.update_mag(t, h_ned)
        if i % 10 == 0 and i < 500:
            f.update_gps(t, np.zeros(3), np.zeros(3))
        s = f.update_imu(t, np.zeros(3), acc)
    assert s.mode == MODE_FIELD_FEEDBACK
    u = h_ned / np.linalg.norm(h_ned)
    axis = np.cross(u, [0.0, 1.0, 0.0])
    axis /= np.linalg.norm(axis)
    phi = np.radians(5.0) * axis
    k = np.array([[0, -phi[2], phi[1]], [phi[2], 0, -phi[0]], [-phi[1], phi[0], 0]])
    f.C = (np.eye(3) + k + 0.5 * k @ k) @ f.C
    errs = []
    for i in range(700, 2700):                            # 20 s more
        t = i * 0.01
        f.update_mag(t, h_ned)
        s = f.update_imu(t, np.zeros(3), acc)
        errs.append(np.degrees(np.arccos(np.clip((np.trace(f.C) - 1) / 2, -1, 1))))
    assert s.mode == MODE_FIELD_FEEDBACK
    assert errs[0] > 4.5
    assert errs[400] < 0.5 * errs[0]                      # time constant ~1/K_P = 2 s
    assert errs[-1] < 0.3


def test_bad_samples_never_break_the_filter():
    tr = simulate_manoeuvring_flight(duration_s=40.0, imu_rate_hz=50.0, outage=(20.0, 30.0), seed=4)
    imu, gps, mag = tr.imu.copy(), tr.gps_ned.copy(), tr.mag.copy()
    imu[100:120, 1:4] = np.nan
    imu[300, 0] = np.nan
    imu[400:410, 4:7] = np.inf
    imu[600, 0] -= 5.0
    gps[10:15, 1:4] = np.nan
    mag[50:80, 1:4] = np.nan
    imu = np.delete(imu, np.arange(700, 760), axis=0)     # a 1.2 s IMU gap
    res = run_ins_gps(imu, gps, mag, InsGpsSettings(declination_deg=_decl(tr)))
    for a in (res.roll_rad, res.pitch_rad, res.yaw_rad, res.vel_ned_mps, res.pos_ned_m, res.field_ned_mG):
        assert np.all(np.isfinite(a))
    assert res.mode[-1] == MODE_GPS
    res = run_ins_gps(np.full((20, 7), np.nan), np.empty((0, 7)), np.empty((0, 4)))
    assert np.all(np.isfinite(res.yaw_rad))


def test_body_fixed_field_states_recover_an_uncalibrated_offset():
    """A constant 39 mG body-fixed field (residual hard iron, motor field) on top of the Earth
    field: with ``body_field_sigma_mG`` the GPS-aided filter estimates it (the vehicle's turns
    separate it from the NED field); without, the heading carries it."""
    tr = simulate_manoeuvring_flight(duration_s=200.0, imu_rate_hz=50.0, seed=3)
    mag = tr.mag.copy()
    offset = np.array([30.0, -20.0, 15.0])
    mag[:, 1:4] += offset
    after = tr.t_s > 60.0
    f = InsGpsFilter(InsGpsSettings(declination_deg=_decl(tr), body_field_sigma_mG=30.0))
    with_states = run_ins_gps(tr.imu, tr.gps_ned, mag, filt=f)
    without = run_ins_gps(tr.imu, tr.gps_ned, mag, InsGpsSettings(declination_deg=_decl(tr)))
    # measured: body field to 0.6 mG; heading error max 0.5° with the states, 15° without
    assert np.linalg.norm(f.body_field - offset) < 3.0
    assert np.linalg.norm(f.field_ned - tr.field_ned_mG) < 3.0
    assert np.abs(attitude_errors_deg(with_states, tr)[1][after]).max() < 1.5
    assert np.abs(attitude_errors_deg(without, tr)[1][after]).max() > 5.0


def _motor_current_flight():
    """A 200 s manoeuvring flight with a motor-current field c·I (c = [-1.2, 0.8, 2.0] mG/A,
    12-28 A, the current at 10 Hz): (truth, c, current times, amps, field with c·I added)."""
    tr = simulate_manoeuvring_flight(duration_s=200.0, imu_rate_hz=50.0, seed=5)
    c = np.array([-1.2, 0.8, 2.0])
    t_cur = np.arange(0.0, 200.0, 0.1)
    amps = 20.0 + 6.0 * np.sin(0.21 * t_cur) + 2.0 * np.sin(0.9 * t_cur + 1.0)
    mag = tr.mag.copy()
    mag[:, 1:4] += np.interp(mag[:, 0], t_cur, amps)[:, None] * c
    return tr, c, t_cur, amps, mag


def test_motor_current_field_states_learn_the_field_per_amp():
    """A motor-current field c·I (c = [-1.2, 0.8, 2.0] mG/A, 12-28 A): given the battery current
    the GPS-aided filter learns c and keeps the heading; without the current it cannot.
    Measured: c to 0.04 mG/A, heading error max 0.7° after 60 s, against 16° without."""
    tr, c, t_cur, amps, mag = _motor_current_flight()
    after = tr.t_s > 60.0
    f = InsGpsFilter(InsGpsSettings(declination_deg=_decl(tr)))
    with_current = run_ins_gps(tr.imu, tr.gps_ned, mag, filt=f, current=np.c_[t_cur, amps])
    without = run_ins_gps(tr.imu, tr.gps_ned, mag, InsGpsSettings(declination_deg=_decl(tr)))
    assert np.linalg.norm(f.motor_field - c) < 0.3
    assert np.abs(attitude_errors_deg(with_current, tr)[1][after]).max() < 1.5
    assert np.abs(attitude_errors_deg(without, tr)[1][after]).max() > 3.0


def test_current_at_telemetry_rate_is_held_by_the_one_motor_timeout():
    """Battery current at 0.6 Hz (SYS_STATUS on a slow telemetry link): each sample is held for
    the one motor-signal timeout (MOTOR_TIMEOUT_S, 2.5 s), so the filter still learns c.  With a
    1 s timeout (what ins_gps had) the field is left unexplained most of the time."""
    from estimators.residual_trackers import MOTOR_TIMEOUT_S
    tr, c, t_fine, amps_fine, mag = _motor_current_flight()
    t_cur = np.arange(0.0, 200.0, 1.0 / 0.6)
    current = np.c_[t_cur, np.interp(t_cur, t_fine, amps_fine)]
    errors = {}
    for timeout in (MOTOR_TIMEOUT_S, 1.0):
        f = InsGpsFilter(InsGpsSettings(declination_deg=_decl(tr), current_timeout_s=timeout))
        run_ins_gps(tr.imu, tr.gps_ned, mag, filt=f, current=current)
        errors[timeout] = float(np.linalg.norm(f.motor_field - c))
    assert InsGpsSettings().current_timeout_s == MOTOR_TIMEOUT_S
    assert errors[MOTOR_TIMEOUT_S] < 0.5 and errors[1.0] > 1.0, errors     # measured 0.09 / 1.80 mG/A


def test_gps_outlier_fails_the_innovation_gate():
    """A 60 m GPS position jump is rejected by the 5-sigma gate (test ratio > 1, EKF2's
    innovation test); the neighbouring fixes pass with ratios well under 1."""
    tr = simulate_manoeuvring_flight(duration_s=60.0, imu_rate_hz=50.0, seed=6)
    gps = tr.gps_ned.copy()
    k = np.searchsorted(gps[:, 0], 40.0)
    gps[k, 1:4] += [60.0, 0.0, 0.0]
    f = InsGpsFilter(InsGpsSettings(declination_deg=_decl(tr)))
    res = run_ins_gps(tr.imu, gps, tr.mag, filt=f)
    i = np.searchsorted(tr.t_s, gps[k, 0])
    assert res.gps_test_ratio[i] > 1.0
    assert np.nanmax(res.gps_test_ratio[(tr.t_s > 20.0) & (tr.t_s < gps[k, 0] - 0.01)]) < 0.5
    assert np.linalg.norm(res.pos_ned_m - tr.pos_ned_m, axis=1)[tr.t_s > 20.0].max() < 3.0
    assert f.gps_status is not None and not f.gps_status.rejected


def test_outage_targets_on_a_closed_loop_mission():
    """Issue 12's GPS-outage decision on one gps-outage mission (hovers, turns, speed changes,
    gusts, motor-current field with the battery current given): gyro bias 0.5°/s per axis all
    flight, 80 s outage; heading and roll/pitch within 2° of truth throughout it.  (Three missions
    in benchmarks/heading.py; measured here 0.6° / 0.5°.)"""
    from groundstation.sim.scenarios import simulate
    sim = simulate("gps-outage", 1, duration_s=200.0)
    r, tr = sim.result, sim.truth
    o0, o1 = tr["gps_outage_s"]
    mag = np.c_[r.t_s, (r.mag_raw_mG - np.array(tr["mag"]["offsets_mG"])) @ np.array(tr["mag"]["calibration_matrix"]).T]
    gps = np.c_[r.t_s[r.gps_idx], r.gps_pos_ned_m, r.gps_vel_ned_mps][r.gps_fix_type >= 3]
    gps = gps[(gps[:, 0] < o0) | (gps[:, 0] >= o1)]
    res = run_ins_gps(np.c_[r.t_s, r.gyro_rad_s, r.accel_mps2], gps, mag,
                      InsGpsSettings(declination_deg=tr["earth_field"]["declination_deg"]),
                      current=np.c_[r.t_s, r.motor_current_A])
    inside = (r.t_s >= o0) & (r.t_s < o1)
    assert np.all(res.mode[inside][50:] == MODE_FIELD_FEEDBACK)
    hd = np.abs(np.degrees(np.angle(np.exp(1j * (res.yaw_rad - r.yaw_rad)))))[inside]
    dr = np.abs(np.degrees(np.angle(np.exp(1j * (res.roll_rad - r.roll_rad)))))[inside]
    dp = np.abs(np.degrees(res.pitch_rad - r.pitch_rad))[inside]
    assert hd.max() < 2.0 and dr.max() < 2.0 and dp.max() < 2.0
