"""Step progress: the net angle turned about one body axis, from the attitude.

Between two attitude samples the body turns by ΔR = R_prevᵀ · R_now (R = C_b^n, body to NED); its
rotation vector φ (log map, ``estimators.rotations.rotation_to_vector_deg``) is in the body
frame, so φ_k is the angle turned about body axis k.  The step's progress is |Σ φ_k| over the
step: a full turn about X gives 360°; wobbling back and forth cancels; a turn about another axis
adds nothing, and an increment whose rotation axis is more than 45° off the step's axis
(|φ_k| < 0.7 |φ|) is not counted, so a tumble or a turn about a tilted axis does not creep the
step's counter up and down; held still the attitude does not change, so nothing creeps (the sum of the
increments telescopes to the change of attitude).  Near pitch ±90° the Euler angles of ATTITUDE
stop defining roll and yaw separately, so there the gyro's turn between the two attitude samples is
used; without ATTITUDE messages the gyro is integrated throughout (signed, so noise averages out).

The recent rotation rate (|φ| per second over ``still_window_s``) gives the "no motion" hint.
"""
from __future__ import annotations

import math
from collections import deque

import numpy as np

from estimators.rotations import dcm_body_to_ned, rotation_to_vector_deg

__all__ = ["AxisProgress"]

ATTITUDE_STALE_S = 1.0      # no ATTITUDE for this long: integrate the gyro instead
FLUSH_EVERY = 10            # attitude samples counted per vectorised pass
GIMBAL_PITCH_RAD = math.radians(80.0)
AXIS_SHARE = 0.7            # an increment counts when its rotation axis is within 45° of the step's


def _small_rotations_deg(rel: np.ndarray) -> np.ndarray:
    """Rotation vectors (deg) of rotation matrices (N, 3, 3): asin of the antisymmetric part's vee
    (sin θ · axis), the exact log map (``estimators.rotations.rotation_to_vector_deg``) beyond 20°."""
    w = np.stack([rel[:, 2, 1] - rel[:, 1, 2], rel[:, 0, 2] - rel[:, 2, 0], rel[:, 1, 0] - rel[:, 0, 1]], 1) / 2.0
    s = np.linalg.norm(w, axis=1)
    scale = np.where(s > 1e-12, np.arcsin(np.clip(s, 0.0, 1.0)) / np.maximum(s, 1e-12), 1.0)
    out = np.degrees(w * scale[:, None])
    for i in np.flatnonzero(s > 0.34):
        out[i] = rotation_to_vector_deg(rel[i])
    return out


class AxisProgress:
    """Net rotation about the current step's body axis (0 = X, 1 = Y, 2 = Z, None = no axis)."""

    def __init__(self, still_window_s: float = 2.0) -> None:
        self.still_window_s = still_window_s
        self.net_deg = np.zeros(3)
        self.axis: int | None = None
        self._prev: tuple[float, np.ndarray] | None = None
        self._last_att_t = -math.inf
        self._last_gyro_t: float | None = None
        self._gyro_since_att = np.zeros(3)
        self._pending: list[tuple] = []
        self._recent: deque = deque()          # (t_s, |rotation| deg) of recent increments
        self.last_t = -math.inf

    def reset(self) -> None:
        self.__init__(self.still_window_s)

    def set_axis(self, axis: int | None) -> None:
        self.axis = axis

    def restart_axis(self, axis: int) -> None:
        """The step starts over (after a long link drop)."""
        self.flush()
        self.net_deg[axis] = 0.0

    def gap(self) -> None:
        """Samples were lost: the rotation across the gap is not counted."""
        self.flush()
        self._prev = None
        self._last_gyro_t = None
        self._gyro_since_att = np.zeros(3)
        self._recent.clear()

    def on_attitude(self, t_s: float, roll_rad: float, pitch_rad: float, yaw_rad: float) -> None:
        """Queue one attitude sample (with the gyro's turn since the previous one); ``flush``
        counts the queue in one vectorised pass."""
        self._pending.append((t_s, roll_rad, pitch_rad, yaw_rad, *self._gyro_since_att))
        self._last_att_t = t_s
        self._gyro_since_att = np.zeros(3)
        if len(self._pending) >= FLUSH_EVERY:
            self.flush()

    def flush(self) -> None:
        """Count the queued attitude samples."""
        if not self._pending:
            return
        rows = np.asarray(self._pending, float)
        self._pending.clear()
        R = dcm_body_to_ned(rows[:, 1], rows[:, 2], rows[:, 3])
        gimbal = np.abs(rows[:, 2]) > GIMBAL_PITCH_RAD
        prev = self._prev
        self._prev = (rows[-1, 0], R[-1], bool(gimbal[-1]))
        if prev is not None:
            rows, R = np.vstack([[prev[0], 0, 0, 0, 0, 0, 0], rows]), np.concatenate([prev[1][None], R])
            gimbal = np.concatenate([[prev[2]], gimbal])
        if len(rows) < 2:
            return
        phi = _small_rotations_deg(np.einsum("nji,njk->nik", R[:-1], R[1:]))
        # near pitch ±90° roll and yaw of ATTITUDE are ill-defined (their split is arbitrary):
        # the gyro turned through that interval instead
        near = gimbal[:-1] | gimbal[1:]
        phi[near] = rows[1:, 4:7][near]
        dt = np.diff(rows[:, 0])
        for t, ok, p in zip(rows[1:, 0], (dt > 0) & (dt < 1.0), phi):
            if ok:
                self._count(float(t), p)

    def on_gyro(self, t_s: float, gyro_rad_s) -> None:
        last = self._last_gyro_t
        self._last_gyro_t = t_s
        if last is None or not 0 < t_s - last < 1.0:
            return
        step = np.degrees(np.asarray(gyro_rad_s, float)) * (t_s - last)
        if t_s - self._last_att_t < ATTITUDE_STALE_S:
            self._gyro_since_att += step
        else:
            self.flush()
            self._count(t_s, step)

    def _count(self, t_s: float, phi_deg: np.ndarray) -> None:
        x, y, z = float(phi_deg[0]), float(phi_deg[1]), float(phi_deg[2])
        if not (math.isfinite(x) and math.isfinite(y) and math.isfinite(z)):
            return
        if self.axis is not None:
            along = (x, y, z)[self.axis]
            if abs(along) >= AXIS_SHARE * math.sqrt(x * x + y * y + z * z):
                self.net_deg[self.axis] += along
        self._recent.append((t_s, math.sqrt(x * x + y * y + z * z)))
        while self._recent and self._recent[0][0] < t_s - self.still_window_s:
            self._recent.popleft()
        self.last_t = t_s

    @property
    def progress_deg(self) -> np.ndarray:
        """|net turn| per axis of what was counted so far (call ``flush`` first for the latest)."""
        return np.abs(self.net_deg)

    def rate_deg_s(self) -> float | None:
        """Mean rotation rate over the last ``still_window_s`` (None until the window is full)."""
        r = self._recent
        if len(r) < 2 or r[-1][0] - r[0][0] < 0.8 * self.still_window_s:
            return None
        return sum(a for _, a in r) / max(r[-1][0] - r[0][0], 1e-6)
