"""The reference field's inclination refined from the flight (estimators.field_refine, jobs/calibrate/
reference.py): the profile's arithmetic, a known field error recovered from banked turns, and the
ArduPilot SITL flight against the SITL's own field."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from estimators.field_refine import inclination_direction, profile_minimum, refine_field
from estimators.rotations import dcm_body_to_ned
from estimators.wmm_fit import WmmFitSettings, fit_wmm

H_WMM = np.array([238.0, 12.0, -530.0])         # Canberra-like: I ≈ −66°
SHIFTS = np.asarray(WmmFitSettings().field_profile_shifts_mG)
SITL_ROUTE = Path(__file__).parent / "data" / "sitl_route"


def test_profile_minimum_is_the_parabolas_vertex_and_its_curvature():
    y = 3.0 * (SHIFTS - 1.3) ** 2 + 7.0
    mode, sd = profile_minimum(SHIFTS, y)
    assert mode == pytest.approx(1.3) and sd == pytest.approx(np.sqrt(1.0 / 3.0))    # −2 log L = (x − μ)²/σ²
    assert np.isnan(profile_minimum(SHIFTS, (SHIFTS - 9.0) ** 2)[0])        # lowest at an end: no minimum
    assert np.isnan(profile_minimum(SHIFTS, -SHIFTS ** 2)[0])               # no positive curvature
    assert np.isnan(profile_minimum(SHIFTS, np.full(len(SHIFTS), np.nan))[0])


def test_refine_field_is_the_kalman_update_along_the_inclination():
    e = inclination_direction(H_WMM)
    # e is the unit vector in which the field turns as its inclination grows: ⟂ to the field, in its vertical plane
    assert np.linalg.norm(e) == pytest.approx(1.0) and e @ H_WMM == pytest.approx(0.0, abs=1e-9)
    assert np.cross(e, H_WMM) @ np.array([0.0, 0.0, 1.0]) == pytest.approx(0.0, abs=1e-6 * np.linalg.norm(H_WMM))
    prior = (1.37, 0.89, 1.41)
    P0 = np.diag(np.square(prior))
    profile = (SHIFTS - 2.5) ** 2 / 0.5 ** 2                                 # the flight: +2.5 ± 0.5 mG
    r = refine_field(H_WMM, prior, SHIFTS, [profile, profile], attitude_tilt_sd_deg=0.0)
    s2 = e @ P0 @ e
    assert r.refined and r.measured_mG == pytest.approx(2.5) and r.measured_sd_mG == pytest.approx(0.5)
    assert e @ r.shift_ned_mG == pytest.approx(2.5 * s2 / (s2 + 0.25))       # the two weighted by their variances
    assert e @ r.covariance_ned_mG2 @ e == pytest.approx(s2 * 0.25 / (s2 + 0.25))
    # the tilt floor adds |B|·σ_tilt in quadrature to the flight's 1σ
    floor = refine_field(H_WMM, prior, SHIFTS, [profile], attitude_tilt_sd_deg=0.1)
    assert floor.measured_sd_mG == pytest.approx(np.hypot(0.5, np.linalg.norm(H_WMM) * np.radians(0.1)))
    # nothing usable: the prior stands
    none = refine_field(H_WMM, prior, SHIFTS, [np.full(len(SHIFTS), np.nan)], 0.1)
    assert not none.refined and not np.any(none.shift_ned_mG) and np.allclose(none.covariance_ned_mG2, P0)
    assert none.profiles == 0 and none.reason == "no compass fit gave a profile"
    beyond = refine_field(H_WMM, prior, SHIFTS, [(SHIFTS - 12.0) ** 2], 0.1)      # the best field past the shifts
    assert not beyond.refined and "beyond" in beyond.reason and not np.any(beyond.shift_ned_mG)
    flat = refine_field(H_WMM, prior, SHIFTS, [(SHIFTS - 12.0) ** 2 / 400.0], 0.1)  # ±20 mG at 1σ: no information
    assert not flat.refined and flat.reason == "the flight does not pin the inclination down"


def _turning_flight(true_field, seed=0, n=1500, noise_mG=1.5):
    """Level legs and 25° banked turns both ways over every heading; m = A h + b + ε with h the TRUE field."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) * 0.4
    yaw = np.mod(t * np.radians(6.0), 2 * np.pi)
    roll = np.radians(25.0) * np.sign(np.sin(t / 40.0)) * (np.abs(np.sin(t / 40.0)) > 0.3) + rng.normal(0, 0.01, n)
    pitch = np.radians(-4.0) + rng.normal(0, 0.01, n)
    A = np.array([[1.04, 0.02, -0.01], [0.02, 0.97, 0.015], [-0.01, 0.015, 1.03]])
    b = np.array([-42.0, 31.0, 45.0])
    h = np.einsum("nji,j->ni", dcm_body_to_ned(roll, pitch, yaw), true_field)
    raw = h @ A.T + b + rng.normal(0, noise_mG, (n, 3))
    return t, raw, roll, pitch, yaw, b


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_field_direction_error_is_measured_from_banked_turns_and_removed_from_the_offsets(seed):
    """The world's field is the WMM turned by 3 mG across it (SITL's own table lies 2.9 mG from WMM2025 at
    Canberra): fitted against the WMM the z offset is off; the flight's profile finds the 3 mG, and the fit
    against the refined field lands on the truth."""
    e = inclination_direction(H_WMM)
    t, raw, roll, pitch, yaw, b = _turning_flight(H_WMM + 3.0 * e, seed)
    s = WmmFitSettings(jackknife_blocks=0, field_model_sd_mG=(0.0, 0.0, 0.0))
    plain = fit_wmm(t, raw, roll, pitch, yaw, H_WMM, profile_direction_ned=e, settings=s)
    assert plain.status in ("ok", "weak") and plain.field_profile_nll is not None
    assert abs(plain.offsets_mG[2] - b[2]) > 2.5                           # the field's error, in b_z
    r = refine_field(H_WMM, WmmFitSettings().field_model_sd_mG, SHIFTS, [plain.field_profile_nll],
                     WmmFitSettings().attitude_tilt_sd_deg)
    assert r.refined and abs(r.measured_mG - 3.0) < 2.0 * r.measured_sd_mG
    refined = fit_wmm(t, raw, roll, pitch, yaw, H_WMM + r.shift_ned_mG, field_cov_ned_mG2=r.covariance_ned_mG2)
    assert np.max(np.abs(refined.offsets_mG - b)) < 0.5 * abs(plain.offsets_mG[2] - b[2])
    assert np.all(np.abs(refined.offsets_mG - b) < 3.0 * refined.offsets_sd_mG + 0.3)
    # the same flight in the true field: the profile says so (no shift worth the name)
    t, raw, roll, pitch, yaw, b = _turning_flight(H_WMM, seed)
    right = fit_wmm(t, raw, roll, pitch, yaw, H_WMM, profile_direction_ned=e, settings=s)
    r0 = refine_field(H_WMM, WmmFitSettings().field_model_sd_mG, SHIFTS, [right.field_profile_nll],
                      WmmFitSettings().attitude_tilt_sd_deg)
    assert abs(r0.measured_mG) < 2.0 * r0.measured_sd_mG


@pytest.mark.parametrize("kind", ["flight.BIN", "telemetry.tlog"])
def test_sitl_flight_measures_the_sitls_own_field(kind):
    """ArduPilot SITL makes its field from its declination/inclination/intensity table (pymavlink's
    ``mavextra.expected_earth_field_lat_lon`` interpolates the same table); the flight's estimate across
    the field lies within 2σ of that table's difference from the WMM, and every compass's result says it."""
    from pymavlink import mavextra

    from groundstation.io.logs import read_log
    from groundstation.jobs.calibrate import calibrate_compasses, expected_field
    log = read_log(SITL_ROUTE / kind)
    results = calibrate_compasses(log)
    ref = results[0]["reference_field"]
    assert ref is not None and ref["flight_estimate_mG"] is not None, ref
    assert all(r["reference_field"] == ref for r in results) and ref["compasses"] == [0, 1, 2]
    assert "reference field: inclination" in results[0]["message"]
    home = json.loads((SITL_ROUTE / "truth.json").read_text())["flight"]["home"]
    v = mavextra.expected_earth_field_lat_lon(home[0], home[1])
    wmm = np.asarray(expected_field(log)[0].field_ned_mG, float)
    truth = float((np.array([v.x, v.y, v.z]) - wmm) @ inclination_direction(wmm))
    assert abs(ref["flight_estimate_mG"] - truth) < 2.0 * ref["flight_sd_mG"], (ref, truth)

