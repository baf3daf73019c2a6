"""The compass at each IMU step: the reading held there, turned by the body's rotation since it
was read (``field_at_steps``), from the time the reading first arrived (``reading_times``; live:
``groundstation.jobs.live.HeldReading``).  ``step_inputs`` and the field-vector test take it (``detection_inputs``, and
``groundstation.jobs.live`` per sample).  Units: mG, rad/s, s.

Why: ArduCopter reads its compass at 10 Hz (its 10 Hz battery-and-compass task) and RAW_IMU
re-sends the last reading at the stream's rate (50 Hz: five packets with the same field), so
the field held at a step was read 0-100 ms before it, against the attitude at the step.  A body
turning at ω makes that a residual of |ω × m| · age: at 30°/s of roll or pitch and 480 mG, about
12 mG for the 50 ms of mean age, 3σ at the 4 mG noise floor (SITL population flight pop0_1 at
117 s, a 30° roll: the field-vector score 0.88 on the .BIN, whose MAG records are stamped at the
reading, 1.60 on the .tlog, where each reading arrives ~10 ms after it and is re-sent; turned to
the step, 0.00 and 0.54).

The autopilot's tilt is brought to the step too, by our AHRS's change since its sample
(``groundstation.jobs.tilt.brought_forward``).  Two ways for one idea, because the spans differ:
a compass reading is at most FIELD_FORWARD_S old, over which the step's gyro is the rate, while
ATTITUDE is held up to 0.5 s (2 Hz streams), over which the rate changes and only the attitude's
history (carried in ``StepState``) gives the change.
"""
from __future__ import annotations

import numpy as np

__all__ = ["FIELD_FORWARD_S", "reading_times", "field_at_steps"]

FIELD_FORWARD_S = 0.25   # a reading up to this old is turned by the step's gyro (a 4 Hz compass);
                         # an older one is used as held (the rate over that long is not the step's)
TURN_ROWS = 1 << 16      # rows turned at a time (the temporaries of a 2-hour log's steps stay a few MB)


def reading_times(t_s, mag) -> np.ndarray:
    """(n,) per row of a compass table the time of its reading: the row's own time, or the
    first of the rows before it that carry the very same field (a re-sent reading, as
    ArduPilot's RAW_IMU repeats the 10 Hz compass at 50 Hz).  ``mag`` (n, 3) as sent (a new
    reading equal on all three axes to the last one is turned from the earlier time, which is
    right as well: the body field did not change)."""
    t = np.asarray(t_s, dtype=float)
    m = np.asarray(mag, dtype=float).reshape(len(t), 3)
    if not len(t):
        return t.copy()
    new = np.r_[True, np.any(m[1:] != m[:-1], axis=1)]
    return t[np.maximum.accumulate(np.where(new, np.arange(len(t)), 0))]


def field_at_steps(mag_mG, age_s, gyro_rad_s) -> np.ndarray:
    """(n, 3) each held field ``mag_mG`` turned to its step: a field fixed in the navigation
    frame moves in the body as ṁ = −ω × m, so m(t) = exp(−[ω a]×) m(t − a) (Rodrigues) with ω
    the step's bias-corrected gyro and a = ``age_s`` (t less the reading's time).  A reading older
    than FIELD_FORWARD_S, or without an age or a gyro, is left as held.  The body-fixed part of m
    (offset, motor field: tens of mG at most) is turned as well, under 1 mG at a few degrees."""
    m = np.asarray(mag_mG, dtype=float).reshape(-1, 3)
    a = np.asarray(age_s, dtype=float).reshape(len(m))
    w = np.asarray(gyro_rad_s, dtype=float).reshape(len(m), 3)
    out = np.empty_like(m)
    for lo in range(0, len(m), TURN_ROWS):        # row by row math: its temporaries a block at a time
        rows = slice(lo, lo + TURN_ROWS)
        out[rows] = _turned(m[rows], a[rows], w[rows])
    return out


def _turned(m: np.ndarray, a: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``field_at_steps`` on a block of rows."""
    with np.errstate(invalid="ignore"):
        use = np.isfinite(a) & (a >= 0.0) & (a <= FIELD_FORWARD_S) & np.all(np.isfinite(w), axis=1)
    phi = -w * np.where(use, a, 0.0)[:, None]
    phi[~use] = 0.0
    th = np.linalg.norm(phi, axis=1)
    k = phi / np.where(th > 0.0, th, 1.0)[:, None]
    c, s = np.cos(th)[:, None], np.sin(th)[:, None]
    return m * c + np.cross(k, m) * s + k * np.sum(k * m, axis=1, keepdims=True) * (1.0 - c)
