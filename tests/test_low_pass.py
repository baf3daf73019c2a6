"""estimators.low_pass against the step response of τ ẏ = x − y, on irregular steps."""
from __future__ import annotations

import numpy as np

from estimators.low_pass import low_pass_from_rest, low_pass_state


def test_step_response_holds_and_restarts():
    rng = np.random.default_rng(3)
    t = np.cumsum(rng.exponential(0.05, 400))
    x = np.c_[np.full(400, 2.0), np.full(400, -0.5)]
    x[:5] = np.nan                                   # nothing finite yet: no output
    x[100:130, 1] = np.inf                           # a step with a bad channel holds both
    y = low_pass_from_rest(t, x, 3.0, low_pass_state(2))
    assert np.isnan(y[:5]).all()
    expect = np.outer(1.0 - np.exp(-(t - t[5]) / 3.0), [2.0, -0.5])     # started at rest on step 5
    good = np.r_[5:100, 130:400]
    assert np.allclose(y[good[:95]], expect[good[:95]], rtol=0, atol=1e-12)
    assert (y[100:130] == y[99]).all()              # held over the skipped steps
    # after the hold it goes on from the held value over the whole interval since the last update
    held = y[99] + (1 - np.exp(-(t[130] - t[99]) / 3.0)) * (np.array([2.0, -0.5]) - y[99])
    assert np.allclose(y[130], held, rtol=0, atol=1e-12)
    back = t.copy()
    back[200:] -= 100.0                              # time goes back: the filter starts again from rest
    z = low_pass_from_rest(back, x, 3.0, low_pass_state(2))
    assert (z[200] == 0.0).all() and z[:200].tobytes() == y[:200].tobytes()


def test_calls_in_pieces_equal_one_call():
    rng = np.random.default_rng(4)
    t = np.cumsum(rng.exponential(0.02, 1000))
    x = rng.normal(size=(1000, 2))
    x[rng.random((1000, 2)) < 0.1] = np.nan
    whole = low_pass_from_rest(t, x, 10.0, low_pass_state(2))
    state = low_pass_state(2)
    parts = [low_pass_from_rest(t[a:b], x[a:b], 10.0, state) for a, b in ((0, 1), (1, 1), (1, 377), (377, 1000))]
    assert np.concatenate(parts).tobytes() == whole.tobytes()
    assert low_pass_from_rest(t[:0], x[:0], 10.0, low_pass_state(2)).shape == (0, 2)
