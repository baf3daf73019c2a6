"""Calibration windows (estimators.cal_windows): a telemetry-rate dance inside a flight."""
from __future__ import annotations

import numpy as np
import pytest

from estimators.cal_windows import WindowSettings, field_direction_rate_deg_s, find_calibration_windows
from estimators.rotations import dcm_body_to_ned
from groundstation.sim.truth import random_rotation
from sim_arrays import H_NED, ardupilot_flight, real_logs

pytestmark = pytest.mark.filterwarnings("error")
B = np.array([150.0, -90.0, 60.0])
A = np.array([[1.03, 0.01, 0.0], [0.01, 0.98, 0.01], [0.0, 0.01, 1.01]])


def _log(seed: int = 0, dance_samples: int = 45, rate_hz: float = 1.5, flight_s: float = 400.0, soft=A):
    """Ground 60 s, a handheld dance of ``dance_samples`` telemetry samples, then a flight of level turns."""
    rng = np.random.default_rng(seed)
    t0 = np.arange(0, 60, 1 / rate_hz)
    t1 = 60 + np.arange(dance_samples) / rate_hz
    h1 = np.array([random_rotation(rng).T @ H_NED for _ in t1])
    t2 = t1[-1] + 20 + np.arange(0, flight_s, 1 / rate_hz)
    yaw = np.cumsum(np.where((t2 % 60) < 4, np.radians(30) / rate_hz, 0.0))
    h2 = np.einsum("nji,j->ni", dcm_body_to_ned(rng.normal(0, .05, len(t2)), rng.normal(0, .05, len(t2)), yaw), H_NED)
    t = np.r_[t0, t1, t2]
    h = np.r_[np.tile(H_NED, (len(t0), 1)), h1, h2]
    return t, h @ soft.T + B + rng.normal(0, 2.0, h.shape), (t1[0], t1[-1])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_45_samples_at_1_5_hz_are_a_usable_dance(seed):
    t, raw, (d0, d1) = _log(seed)
    res = find_calibration_windows(t, raw)
    assert res.status == "ok", res.message
    w = res.chosen_window
    assert w.start_s <= d0 + 1 and w.end_s >= d1 - 1 and w.source == "motion"
    assert w.n_samples <= 50 and w.coverage >= 0.45 and w.model == "ellipsoid"   # ±3 % soft iron is seen
    assert np.max(np.abs(w.fit.offsets_mG - B)) < 5.0
    assert all(not x.sufficient for i, x in enumerate(res.windows) if i != res.chosen)   # the turns are not


def test_no_soft_iron_keeps_the_sphere_model():
    t, raw, _ = _log(7, soft=np.eye(3))
    w = find_calibration_windows(t, raw).chosen_window
    assert w.model == "sphere" and np.max(np.abs(w.fit.offsets_mG - B)) < 3.0


def test_markers_add_a_window_even_without_motion_detection():
    t, raw, (d0, d1) = _log(3)
    res = find_calibration_windows(t, raw, marker_spans_s=[(d0, d1)],
                                   settings=WindowSettings(min_rate_deg_s=1e6))      # motion detection off
    assert res.status == "ok" and res.chosen_window.source == "marker"
    assert res.chosen_window.fit.offsets_mG == pytest.approx(B, abs=10.0)


def test_a_flight_of_level_turns_is_not_a_calibration():
    t, raw, (d0, d1) = _log(4)
    keep = (t < d0) | (t > d1)
    res = find_calibration_windows(t[keep], raw[keep])
    assert res.status in ("no_window", "insufficient_coverage") and res.chosen is None
    whole = find_calibration_windows(t[keep], raw[keep], marker_spans_s=[(d1 + 1, t[-1])])   # the flight as one window
    assert whole.status == "insufficient_coverage" and "cover" in whole.message
    assert whole.windows[0].n_samples > 500


def test_too_few_samples_nans_and_nothing_moving():
    t, raw, (d0, d1) = _log(5, dance_samples=10)
    res = find_calibration_windows(t, raw, marker_spans_s=[(d0, d1)], settings=WindowSettings(min_rate_deg_s=1e6))
    assert res.status == "insufficient_coverage" and "finite samples" in res.windows[0].reason
    t, raw, (d0, d1) = _log(6)
    raw[(t >= d0) & (t <= d1)][::3] = np.nan
    bad = raw.copy()
    sel = np.nonzero((t >= d0) & (t <= d1))[0][::4]
    bad[sel] = np.nan                                             # NaNs inside the window
    res = find_calibration_windows(t, bad)
    assert res.status == "ok", res.message
    assert find_calibration_windows(t, np.full_like(raw, np.nan)).status == "no_data"
    still = np.tile(raw[0], (len(t), 1))
    assert find_calibration_windows(t, still).status == "no_window"
    assert np.isnan(field_direction_rate_deg_s(t[:1], raw[:1])).all()
    assert field_direction_rate_deg_s(t[:2], raw[:2])[1] < 2.0          # at rest: noise only


def test_onboard_calibration_in_a_1_5_hz_telemetry_log_matches_mag_cal_report():
    from groundstation.jobs.calibrate.context import onboard_report
    sim, log, _ = ardupilot_flight(seed=2, dance=True, imu_rate_hz=1.5)
    for k in range(3):
        ofs, res = real_logs.window_offsets(log, k)
        assert res.status == "ok", res.message
        assert "marker" in res.chosen_window.source and res.chosen_window.n_samples < 80
        assert np.max(np.abs(ofs - np.asarray(onboard_report(log.mag_cal, k)["COMPASS_OFS"]))) < 20.0
