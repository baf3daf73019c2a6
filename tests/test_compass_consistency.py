"""Compass consistency (estimators.compass_consistency) as ArduPilot's pre-arm check."""
from __future__ import annotations

import numpy as np
import pytest

from estimators.compass_consistency import compass_consistency
from estimators.rotations import dcm_body_to_ned, rotation_from_vector_rad
from sim_arrays import H_NED

pytestmark = pytest.mark.filterwarnings("error")


def _fields(n=400, seed=0):
    rng = np.random.default_rng(seed)
    yaw = rng.uniform(-np.pi, np.pi, n)
    body = np.einsum("nji,j->ni", dcm_body_to_ned(rng.normal(0, .1, n), rng.normal(0, .1, n), yaw), H_NED)
    return [body + rng.normal(0, 3, body.shape) for _ in range(3)]


def test_three_consistent_compasses():
    rep = compass_consistency(_fields())
    assert rep.status == "ok" and rep.disagreeing is None and len(rep.pairs) == 3
    assert all(p.angle_median_deg < 1.0 and p.ardupilot_consistent for p in rep.pairs)


def test_a_compass_rotated_20_degrees_is_named_though_it_passes_ardupilot():
    f = _fields(seed=1)
    f[1] = f[1] @ rotation_from_vector_rad(np.radians([0, 0, 20])).T
    rep = compass_consistency(f)
    assert rep.status == "ok" and rep.disagreeing == 1          # 20° < ArduPilot's 60° XY limit
    f[2] = f[2] @ rotation_from_vector_rad(np.radians([180, 0, 0])).T      # flipped: gross
    rep = compass_consistency(f)
    assert rep.status == "inconsistent"
    assert not [p for p in rep.pairs if (p.a, p.b) == (0, 2)][0].ardupilot_consistent


def test_two_compasses_and_the_expected_strength():
    f = _fields(seed=2)
    weak = f[1] * 0.85                                            # 15 % scale error: ~85 mG
    rep = compass_consistency([f[0], weak], expected_strength_mG=float(np.linalg.norm(H_NED)))
    assert rep.disagreeing == 1
    assert compass_consistency([f[0], weak]).disagreeing is None     # no reference: cannot tell


def test_dropout_and_missing_compasses():
    f = _fields(seed=3)
    f[2][200:] = np.nan                                           # drops out mid-log
    rep = compass_consistency(f)
    assert rep.status == "ok" and [p.n for p in rep.pairs] == [400, 200, 200]
    assert compass_consistency([f[0], None, None]).status == "insufficient_data"
    assert compass_consistency([f[0], np.full((400, 3), np.nan)]).status == "insufficient_data"
    assert compass_consistency([f[0][:5], f[1][:5]]).status == "insufficient_data"
