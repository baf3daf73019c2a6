"""ArduPilot / PX4 compass parameter conventions: export, apply with the autopilot's formula, round trip."""
from __future__ import annotations


import numpy as np
import pytest

from estimators.calibration import apply_calibration, polar_decomposition
from estimators.rotations import rotation_from_vector_rad
from groundstation.io.params import (apply_ardupilot, apply_px4, ardupilot_params_from_calibration,
                                            detect_autopilot, export_params, format_param_file, px4_params_from_calibration,
                                            px4_rotation, px4_slot, rotation_enum_matrix, unapply_ardupilot,
                                            unapply_onboard_calibration, unapply_px4)

from conftest import SHARED_DATA, shared_data
PX4_LOGS = SHARED_DATA / "px4-pyulog"


def _sym(rng):
    C = np.diag(rng.uniform(0.8, 1.2, 3))
    o = rng.uniform(-0.1, 0.1, 3)
    C[0, 1] = C[1, 0] = o[0]
    C[0, 2] = C[2, 0] = o[1]
    C[1, 2] = C[2, 1] = o[2]
    return C


def test_rotation_enums():
    np.testing.assert_allclose(rotation_enum_matrix(2) @ [1, 0, 0], [0, 1, 0], atol=1e-12)    # YAW_90
    np.testing.assert_allclose(rotation_enum_matrix(8) @ [0, 1, 1], [0, -1, -1], atol=1e-12)  # ROLL_180
    # ROLL_90_PITCH_90 (28): (x, y, z) -> (y, -z, -x) as ArduPilot's Vector3::rotate does it.
    np.testing.assert_allclose(rotation_enum_matrix(28) @ [1, 2, 3], [2, -3, -1], atol=1e-12)
    with pytest.raises(ValueError):
        rotation_enum_matrix(77)
    # the table's matrices are made once and shared: a caller cannot change them for the next one
    R = rotation_enum_matrix(2)
    with pytest.raises(ValueError):
        R[0, 0] = 5.0
    np.testing.assert_allclose(rotation_enum_matrix(2) @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    np.testing.assert_allclose(rotation_enum_matrix(100, (0.0, 0.0, 90.0)), rotation_enum_matrix(2), atol=1e-12)


def test_ardupilot_round_trip_symmetric():
    rng = np.random.default_rng(0)
    b, C = rng.uniform(-400, 400, 3), _sym(rng)
    raw = rng.normal(0, 500, (200, 3))
    p = ardupilot_params_from_calibration(b, C)
    assert p["COMPASS_OFS_X"] == pytest.approx(-b[0])          # ArduPilot *adds* OFS
    assert p["COMPASS_SCALE"] == 1.0
    np.testing.assert_allclose(apply_ardupilot(raw, p), apply_calibration(raw, b, C), atol=1e-9)
    # Second compass uses COMPASS_OFS2_*, COMPASS_DIA2_* ...
    p2 = ardupilot_params_from_calibration(b, C, instance=1)
    assert "COMPASS_OFS2_X" in p2 and "COMPASS_DIA2_Y" in p2 and "COMPASS_ODI2_Z" in p2
    np.testing.assert_allclose(apply_ardupilot(raw, p2, instance=1), apply_calibration(raw, b, C), atol=1e-9)


def test_ardupilot_unapply_inverts_onboard_correction():
    rng = np.random.default_rng(1)
    params = {"COMPASS_OFS_X": -96.0, "COMPASS_OFS_Y": 3.6, "COMPASS_OFS_Z": 60.2, "COMPASS_DIA_X": 1.02,
              "COMPASS_DIA_Y": 0.97, "COMPASS_DIA_Z": 1.01, "COMPASS_ODI_X": 0.01, "COMPASS_ODI_Y": -0.02,
              "COMPASS_ODI_Z": 0.005, "COMPASS_SCALE": 1.05, "COMPASS_ORIENT": 0}
    raw = rng.normal(0, 500, (100, 3))
    corrected = apply_ardupilot(raw, params)
    np.testing.assert_allclose(unapply_ardupilot(corrected, params), raw, atol=1e-9)
    back, note = unapply_onboard_calibration(corrected, params)
    np.testing.assert_allclose(back, raw, atol=1e-9)
    assert "ArduPilot" in note
    # DIA all zero is treated as identity (as ArduPilot does); SCALE 0 means unset.
    p0 = {"COMPASS_OFS_X": 10.0, "COMPASS_SCALE": 0.0}
    np.testing.assert_allclose(apply_ardupilot([[0, 0, 0]], p0), [[10, 0, 0]])


def test_non_symmetric_matrix_rotation_is_not_folded_into_dia():
    rng = np.random.default_rng(2)
    S = _sym(rng)
    R = rotation_from_vector_rad(np.radians([2, -3, 4]))
    b = rng.uniform(-100, 100, 3)
    R2, S2 = polar_decomposition(R @ S)
    np.testing.assert_allclose(R2, R, atol=1e-12)
    np.testing.assert_allclose(S2, S, atol=1e-12)
    p = ardupilot_params_from_calibration(b, R @ S)
    raw = rng.normal(0, 500, (50, 3))
    # ArduPilot output = the symmetric part; our body-frame output = R · that.
    np.testing.assert_allclose(apply_ardupilot(raw, p) @ R.T, apply_calibration(raw, b, R @ S), atol=1e-9)


@pytest.mark.parametrize("rot_params", [
    {"CAL_MAG0_ROT": 0},
    {"CAL_MAG0_ROT": 2},
    {"CAL_MAG0_ROT": 100, "CAL_MAG0_ROLL": 5.0, "CAL_MAG0_PITCH": -10.0, "CAL_MAG0_YAW": 30.0},
    {"CAL_MAG0_ROT": -1, "SENS_BOARD_ROT": 4, "SENS_BOARD_X_OFF": 1.0},
])
def test_px4_round_trip(rot_params):
    rng = np.random.default_rng(3)
    b, C = rng.uniform(-400, 400, 3), _sym(rng)
    params = {"CAL_MAG0_ID": 1, **rot_params}
    R = px4_rotation(params, 0)
    raw_sensor = rng.normal(0, 500, (100, 3))
    exported = px4_params_from_calibration(b, C, 0, R)
    assert exported["CAL_MAG0_XOFF"] == pytest.approx((R.T @ b)[0] / 1000)          # gauss, subtracted
    full = {**params, **exported}
    # PX4's own formula on sensor-frame raw == our calibration on body-aligned raw (R · raw).
    ours = apply_calibration(raw_sensor @ R.T, b, C)
    np.testing.assert_allclose(apply_px4(raw_sensor, full), ours, atol=1e-9)
    # Un-applying PX4's correction gives our body-aligned raw back.
    np.testing.assert_allclose(unapply_px4(apply_px4(raw_sensor, full), full), raw_sensor @ R.T, atol=1e-9)


def test_export_params_and_param_file():
    b, C = np.array([1.0, 2.0, 3.0]), np.eye(3)
    ap, px4 = export_params(b, C, {"CAL_MAG_PRIME": 7, "CAL_MAG1_ID": 7, "CAL_MAG1_ROT": 0})
    assert "CAL_MAG1_XOFF" in px4 and px4["CAL_MAG1_ZOFF"] == pytest.approx(0.003)
    assert set(ap) == {f"COMPASS_{k}" for k in
                       ("OFS_X", "OFS_Y", "OFS_Z", "DIA_X", "DIA_Y", "DIA_Z", "ODI_X", "ODI_Y", "ODI_Z", "SCALE")}
    text = format_param_file({"COMPASS_OFS_X": -1.0, "A": 2.5})
    assert text == "A,2.5\nCOMPASS_OFS_X,-1\n"
    assert format_param_file({"A": 2.5}, style="space") == "A 2.5\n"


def test_real_px4_log_params():
    pyulog = pytest.importorskip("pyulog")
    small = shared_data("px4-pyulog/sample_log_small.ulg")
    events = shared_data("px4-pyulog/sample_px4_events.ulg")
    # sample_log_small: prime magnetometer is calibration slot 1 (CAL_MAG_PRIME == CAL_MAG1_ID).
    ps = pyulog.ULog(str(small), ["vehicle_magnetometer"]).initial_parameters
    assert detect_autopilot(ps) == "px4" and px4_slot(ps) == 1
    u = pyulog.ULog(str(events), ["vehicle_magnetometer", "sensor_mag"])
    pe = u.initial_parameters
    vm = u.get_dataset("vehicle_magnetometer").data
    corrected = np.stack([vm[f"magnetometer_ga[{i}]"] for i in range(3)], 1) * 1000.0
    raw, note = unapply_onboard_calibration(corrected, pe, "px4")
    # Identity calibration on that vehicle: raw == corrected (board X offset 1e-6 deg only).
    np.testing.assert_allclose(raw, corrected, atol=1e-3)
    sm = u.get_dataset("sensor_mag").data
    sensor = np.stack([sm["x"], sm["y"], sm["z"]], 1) * 1000.0
    # Real sensor_mag and un-applied vehicle_magnetometer agree in magnitude (same device, same air).
    assert abs(np.median(np.linalg.norm(sensor, axis=1)) - np.median(np.linalg.norm(raw, axis=1))) < 15.0
    # With sample_log_small's real (non-trivial) slot-1 calibration, apply/unapply round-trips real data.
    slot = px4_slot(ps)
    body_raw = unapply_px4(corrected, ps, slot)
    assert np.max(np.abs(body_raw - corrected)) > 100          # offsets of hundreds of mG really removed
    R = px4_rotation(ps, slot)
    np.testing.assert_allclose(apply_px4(body_raw @ R, ps, slot), corrected, atol=1e-9)


def test_raw_px4_samples_are_only_rotated():
    params = {"CAL_MAG0_ID": 5, "CAL_MAG0_ROT": 2, "CAL_MAG0_XOFF": 0.2, "CAL_MAG0_XSCALE": 1.1}
    raw = np.array([[100.0, 0.0, 50.0]])
    body, note = unapply_onboard_calibration(raw, params, "px4", applied=False)
    np.testing.assert_allclose(body, [[0.0, 100.0, 50.0]], atol=1e-9)          # YAW_90, no offsets
    corrected, _ = unapply_onboard_calibration(raw, params, "px4", applied=True)
    assert not np.allclose(corrected, body)
    same, note = unapply_onboard_calibration(raw, {}, None, applied=None)
    np.testing.assert_allclose(same, raw)
