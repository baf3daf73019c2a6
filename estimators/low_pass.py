"""A first-order low-pass over irregular time steps, started from rest, compiled (numba).

    y_i = y_{i-1} + (1 − e^(−(t_i − t_{i−1})/τ)) (x_i − y_{i−1})

the exact discretisation of τ ẏ = x − y for x held over each interval.  A step whose inputs are
not all finite is skipped (the output holds); the filter (re)starts at y = 0, not at its first input,
on its first finite step and whenever time goes back.  Used for the autopilot-minus-ours tilt gap
(groundstation.jobs.tilt: an autopilot drifting open-loop drifts away from agreement, so the gap
starts from agreement).  Units are the caller's (t and τ in seconds).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["low_pass_from_rest", "low_pass_state"]


def low_pass_state(channels: int) -> np.ndarray:
    """A filter not started: [started 0/1, time of the last finite step, y_1 .. y_channels]."""
    return np.zeros(2 + channels)


@njit(cache=True)
def low_pass_from_rest(t_s: np.ndarray, x: np.ndarray, tau_s: float, state: np.ndarray) -> np.ndarray:
    """(n, k) the low-passed ``x`` (n, k) at each step, NaN before the filter's first finite step;
    ``state`` (``low_pass_state(k)``) is updated in place, so consecutive calls equal one call
    over the steps joined."""
    n, k = x.shape
    out = np.full((n, k), np.nan)
    for i in range(n):
        finite = True
        for j in range(k):
            if not math.isfinite(x[i, j]):
                finite = False
        if finite:
            if state[0] == 0.0 or t_s[i] < state[1]:
                state[0] = 1.0
                for j in range(k):
                    state[2 + j] = 0.0
            else:
                a = 1.0 - math.exp(-(t_s[i] - state[1]) / tau_s)
                for j in range(k):
                    state[2 + j] = state[2 + j] + a * (x[i, j] - state[2 + j])
            state[1] = t_s[i]
        if state[0] != 0.0:
            for j in range(k):
                out[i, j] = state[2 + j]
    return out
