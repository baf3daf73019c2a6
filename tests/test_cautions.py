"""No false cautions on a perfect rig, each real fault still raised (issue 25 found-item 5).

On ArduPilot SITL's perfect rig the station cautioned a 0.6–2.9° misalignment, a deviation card of
up to 2.6° after calibration (true ≤ 0.06°), "the field jumped off the fitted sphere 2 time(s)",
and compasses disagreeing by 1.2°.  Each caution now needs evidence beyond its own noise; here:
simulated perfect guided dances over many seeds raise none, and a real misalignment, a moved
magnet and a disagreeing compass still raise theirs."""
from __future__ import annotations

import copy
from dataclasses import replace

import numpy as np
import pytest

from estimators.calibration import estimate_misalignment
from estimators.rotations import dcm_body_to_ned, rotation_from_vector_rad
from groundstation.sim.vehicle_streams import guided_dance_attitude, make_hardware, pack_stream, three_compasses
from groundstation.station.wizard import CalibrationWizard
from groundstation.station.wizard.aftercheck import deviation_card

from test_wizard import dance_result

SEEDS = range(8)


def _dance(hw, seed: int = 0, edit=None) -> CalibrationWizard:
    msgs = pack_stream(guided_dance_attitude(), hw, seed=seed)
    if edit is not None:
        msgs = edit(msgs)
    return dance_result(msgs)


def _misaligned(deg_xyz, k: int = 0):
    comps = list(three_compasses())
    c = comps[k]
    comps[k] = replace(c, matrix=np.asarray(c.matrix) @ rotation_from_vector_rad(np.radians(deg_xyz)))
    return make_hardware(tuple(comps))


@pytest.mark.parametrize("seed", SEEDS)
def test_a_perfect_dance_raises_no_caution(seed):
    w = _dance(make_hardware(three_compasses()), seed)
    for k, r in w.results.items():
        assert r["status"] == "ok" and r["pass"], (k, r.get("reasons"))
        assert r["cautions"] == [], (k, r["cautions"])
        assert r["misalignment_deg"] is None, (k, r["message"])
        assert r["disturbances"] == 0
    assert w.consistency["status"] == "ok" and all(p["agree"] for p in w.consistency["pairs"])
    assert max(p["angle_deg"] for p in w.consistency["pairs"]) < 0.5        # block means, not single samples
    # The card: the uncalibrated deviation is real; after calibration what is left is the gyro
    # reference's own ~0.7° on the dance's slightly tilted Z turn (left alone, see the report),
    # far below the 2.6° the false misalignment used to put there.
    assert w.deviation is not None and w.deviation["before_significant"] and w.deviation["max_before_deg"] > 20
    assert w.deviation["max_after_deg"] < 1.0, w.deviation
    assert w.result["status"] == "ok" and "consistency_warning" not in w.result


def test_a_real_misalignment_is_found_and_shows_as_disagreement():
    """Compass 2 turned 8° in its mount: the fit finds the rotation (which COMPASS_DIA/ODI cannot
    hold), and the compasses as the vehicle will correct them disagree, compass 2 the odd one."""
    w = _dance(_misaligned((0.0, 0.0, 8.0), k=1), seed=3)
    mis = w.results[1]["misalignment_deg"]
    assert mis is not None and abs(float(np.linalg.norm(mis)) - 8.0) < 0.5, w.results[1]["message"]
    assert w.results[0]["misalignment_deg"] is None and w.results[2]["misalignment_deg"] is None
    assert w.consistency["status"] == "inconsistent" and w.consistency["odd_one"] == 1, w.consistency
    assert "compass 2 is the odd one out" in w.consistency["text"]
    assert "consistency_warning" in w.result


def test_a_small_real_misalignment_is_beyond_the_noise():
    w = _dance(_misaligned((1.0, -1.0, 0.5)), seed=4)
    mis = w.results[0]["misalignment_deg"]
    assert mis is not None and abs(float(np.linalg.norm(mis)) - 1.5) < 0.3, w.results[0]["message"]


def test_a_moved_magnet_is_a_caution():
    """80 mG on compass 1 for 2 s in the middle of the dance (a tool laid next to it)."""
    def magnet(msgs):
        t0 = msgs[0][0]
        out = []
        for unix, m in msgs:
            if m.get_type() == "RAW_IMU" and 40.0 <= unix - t0 <= 42.0:
                m = copy.copy(m)
                m.xmag += 80
            out.append((unix, m))
        return out

    w = _dance(make_hardware(three_compasses()), seed=1, edit=magnet)
    r = w.results[0]
    assert r["disturbances"] == 1 and any("left the fitted sphere 1 time(s)" in c for c in r["cautions"]), r
    assert w.results[1]["cautions"] == [] and w.results[2]["cautions"] == []


# ------------------------------------------------------------------ the deviation card on its own
def _level_turns(deviation_deg, drift_deg_s: float, seed: int):
    """Two level 400° turns at 35°/s (25 Hz): compass 'after' field with a known deviation, a gyro
    with a bias (its integrated yaw drifts), heading noise ~0.25°."""
    rng = np.random.default_rng(seed)
    rate = np.radians(35.0)
    t = np.arange(0.0, 2 * 400 / 35.0, 0.04)
    yaw = (rate * t) % (2 * np.pi)
    H = np.array([336.0, -36.0, 354.0])
    true_dev = np.radians(deviation_deg(np.degrees(yaw)))
    R = dcm_body_to_ned(np.zeros_like(t), np.zeros_like(t), yaw - true_dev)     # the compass sees ψ − δ(ψ)
    field = np.einsum("nji,j->ni", R, H) + rng.normal(0, 1.5, (len(t), 3))
    att = np.column_stack([t, np.zeros_like(t), np.zeros_like(t), yaw])
    gyro_z = np.full_like(t, rate + np.radians(drift_deg_s)) + rng.normal(0, 0.003, len(t))
    imu = np.column_stack([t, np.zeros_like(t), np.zeros_like(t), gyro_z, np.zeros((len(t), 3))])
    return t, field, att, imu


@pytest.mark.parametrize("seed", range(4))
def test_deviation_card_needs_a_deviation_beyond_noise_and_drift(seed):
    t, field, att, imu = _level_turns(lambda psi: 0.0 * psi, drift_deg_s=0.08, seed=seed)
    card = deviation_card(t, field, field, att, imu, 0.0)
    assert card is not None and not card["after_significant"] and card["max_after_deg"] < 0.3, card
    t, field, att, imu = _level_turns(lambda psi: 2.0 * np.sin(np.radians(psi)) + 1.0 * np.cos(np.radians(2 * psi)),
                                      drift_deg_s=0.08, seed=seed)
    card = deviation_card(t, field, field, att, imu, 0.0)
    assert card["after_significant"] and abs(card["max_after_deg"] - 3.0) < 0.3, card     # |2 sin ψ + cos 2ψ| ≤ 3


def test_misalignment_is_not_a_timing_lag():
    """Field samples 0.1 s late on their attitude during turns about several axes look like a
    rotation about each turn's axis; the per-block lag takes it, no misalignment is left."""
    hist = guided_dance_attitude()
    H = np.array([336.0, -36.0, 354.0])
    t = hist.t_s
    late = np.clip(t - 0.1, t[0], t[-1])
    R = dcm_body_to_ned(np.interp(late, t, hist.roll_rad), np.interp(late, t, hist.pitch_rad),
                        np.interp(late, t, np.unwrap(hist.yaw_rad)))
    m = np.einsum("nji,j->ni", R, H) + np.random.default_rng(0).normal(0, 1.5, (len(t), 3))
    fit = estimate_misalignment(m, hist.roll_rad, hist.pitch_rad, hist.yaw_rad, H, t_s=t)
    assert not fit.significant and abs(fit.lag_s + 0.1) < 0.02, (fit.angles_deg, fit.chi2, fit.lag_s)
    no_lag_model = estimate_misalignment(m, hist.roll_rad, hist.pitch_rad, hist.yaw_rad, H)
    assert no_lag_model.chi2 > fit.chi2                # without the lag the rotation would look real
