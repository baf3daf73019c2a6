"""Orientation check (estimators.orientation_check) as ArduPilot's COMPASS_AUTO_ROT."""
from __future__ import annotations

import numpy as np
import pytest

from estimators.orientation_check import OrientationSettings, check_orientation
from estimators.rotations import dcm_body_to_ned, euler_from_dcm
from groundstation.io.params import rotation_enum_matrix
from groundstation.sim.truth import random_rotation
from sim_arrays import H_NED

pytestmark = pytest.mark.filterwarnings("error")
CANDIDATES = [(i, rotation_enum_matrix(i)) for i in range(38)]


def _dance(n=300, seed=0):
    rng = np.random.default_rng(seed)
    R = np.array([random_rotation(rng) for _ in range(n)])
    r, p, y = euler_from_dcm(R)
    body = np.einsum("nji,j->ni", R, H_NED) + rng.normal(0, 2.0, (n, 3))
    return body, r, p, y


def test_correct_orientation_is_confirmed():
    body, r, p, y = _dance()
    c = check_orientation(body, r, p, y, CANDIDATES, current_id=0)
    assert c.status == "confirmed" and c.best_id == 0 and c.confidence > 10


def test_wrongly_configured_external_compass_is_found():
    body, r, p, y = _dance(seed=1)
    mount = rotation_enum_matrix(2)                    # physically yaw 90
    sensor = body @ mount                               # v_sensor = mountᵀ v_body
    shown = sensor                                      # COMPASS_ORIENT = 0: the autopilot uses it as body
    c = check_orientation(shown, r, p, y, CANDIDATES, current_id=0)
    assert c.status == "rotation_found" and c.best_id == 2, c.message
    shown12 = sensor @ rotation_enum_matrix(12).T      # configured as pitch 180 instead
    c = check_orientation(shown12, r, p, y, CANDIDATES, current_id=12)
    assert c.status == "rotation_found" and c.best_id == 2


def test_level_yaw_turns_cannot_tell_yaw_rotations_apart_unless_the_yaw_is_independent():
    rng = np.random.default_rng(2)
    n = 300
    yaw = rng.uniform(-np.pi, np.pi, n)
    roll, pitch = np.zeros(n), np.zeros(n)          # exactly level: every rotation about Z fits as well
    body = np.einsum("nji,j->ni", dcm_body_to_ned(roll, pitch, yaw), H_NED) + rng.normal(0, 2.0, (n, 3))
    sensor = body @ rotation_enum_matrix(2)
    c = check_orientation(sensor, roll, pitch, yaw, CANDIDATES, current_id=0)
    assert c.status == "ambiguous", c.message
    c = check_orientation(sensor, roll, pitch, yaw, CANDIDATES, current_id=0, field_ned_mG=H_NED,
                          settings=OrientationSettings(reference="expected"))
    assert c.status == "rotation_found" and c.best_id == 2
    tilt = rng.normal(0, 0.05, (2, n))              # a few degrees of tilt, as in real flight, separate them
    body = np.einsum("nji,j->ni", dcm_body_to_ned(tilt[0], tilt[1], yaw), H_NED) + rng.normal(0, 2.0, (n, 3))
    c = check_orientation(body @ rotation_enum_matrix(2), tilt[0], tilt[1], yaw, CANDIDATES, current_id=0)
    assert c.status == "rotation_found" and c.best_id == 2


def test_bad_input():
    body, r, p, y = _dance(n=15)
    assert check_orientation(body, r, p, y, CANDIDATES, 0).status == "insufficient_data"
    body, r, p, y = _dance(n=50)
    assert check_orientation(body, None, None, None, CANDIDATES, 0).status == "no_attitude"
    assert check_orientation(body, r, p, y, CANDIDATES[1:], 0).status == "insufficient_data"
    assert check_orientation(body, r, p, y, CANDIDATES, 0,
                             settings=OrientationSettings(reference="expected")).status == "insufficient_data"
