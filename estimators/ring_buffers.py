"""Fixed-capacity double-ended queues (ring buffers) for compiled per-step code: the recent-sample
windows of the field-vector test (estimators.field_consistency_kernel, estimators.residual_trackers)
as rows of a preallocated array, since numba code cannot grow a ``collections.deque``.

A ring is its rows ``buf[CAPACITY, ...]`` and two integers ``p`` (an int64 array): ``p[0]`` the
row of its oldest entry, ``p[1]`` how many entries it holds.  ``push`` onto a full ring drops the
oldest entry first, deterministically.  The windows hold samples over at most 2 s
(``tilt_lag_s``; ``signal_lag_s`` 1.5 s), so CAPACITY = 16384 rows is exact up to ~8 kHz IMU
steps (the fastest logs: ~1 kHz; checked equal to the deque code it replaced at 1 and 2.5 kHz).
Faster, the window's oldest samples are lost: the signal's spread then spans CAPACITY steps only and
the tilt, which needs a sample ``tilt_lag_s`` old, stops learning (with 4096 rows that happened at
2.5 kHz).  The arrays are np.zeros (untouched pages cost no memory): ~1.5 MB per field-vector test
at most.  The functions are inlined into their callers (numba ``inline="always"``: one compile).
"""
from __future__ import annotations

import numpy as np
from numba import njit

__all__ = ["CAPACITY", "size", "first", "last", "at", "push", "pop_front", "pop_back"]

CAPACITY = 16384    # rows per ring: rate [Hz] × window [s] must stay below this (see module docstring)


@njit(cache=True, inline="always")
def size(p: np.ndarray) -> int:
    """How many entries the ring holds."""
    return p[1]


@njit(cache=True, inline="always")
def at(p: np.ndarray, i: int, capacity: int) -> int:
    """The buffer row of the ring's i-th entry (0: the oldest)."""
    return (p[0] + i) % capacity


@njit(cache=True, inline="always")
def first(p: np.ndarray, capacity: int) -> int:
    """The buffer row of the oldest entry."""
    return p[0]


@njit(cache=True, inline="always")
def last(p: np.ndarray, capacity: int) -> int:
    """The buffer row of the newest entry."""
    return (p[0] + p[1] - 1) % capacity


@njit(cache=True, inline="always")
def push(p: np.ndarray, capacity: int) -> int:
    """Append an entry (dropping the oldest when full); returns the buffer row to fill."""
    head, n = p[0], p[1]
    if n == capacity:
        head = (head + 1) % capacity
        n -= 1
    p[0] = head
    p[1] = n + 1
    return (head + n) % capacity


@njit(cache=True, inline="always")
def pop_front(p: np.ndarray, capacity: int) -> None:
    """Drop the oldest entry (the ring is not empty)."""
    p[0] = (p[0] + 1) % capacity
    p[1] -= 1


@njit(cache=True, inline="always")
def pop_back(p: np.ndarray) -> None:
    """Drop the newest entry (the ring is not empty)."""
    p[1] -= 1
