"""Vector complementary filters for the Earth field and gravity in the body frame (seed 000, sec. 2.1).

Seed 000 eq. (9):   dĤ/dt = k (H_m − Ĥ) − ω × Ĥ
    the magnetometer H_m supplies the low frequencies (k/(s+k)), the gyro ω the high ones
    (s/(s+k)); one gain k [1/s] is the crossover frequency.  Eq. (7) (dH^b/dt = −ω × H^b) is the
    gyro part.  The same filter with the accelerometer's specific force in place of H_m gives the
    gravity vector in the body frame and from it roll and pitch (seed 000 sec. 2.2).

Discretisation.  Seed 000 eq. (10) is the Euler step Ĥ(n+1) = Ĥ(n) + [k(H_m − Ĥ) − ω × Ĥ] T_s.
We use the same first-order filter with each part integrated exactly over the step dt:

    Ĥ(n+1) = (1 − g) R(−ω dt) Ĥ(n) + g H_m,     g = 1 − exp(−k dt)

which equals eq. (10) to first order in dt, keeps |Ĥ| under pure rotation (so a constant rotation
is reproduced exactly) and stays stable for any dt (time gaps).  The step is affine in Ĥ, which the
batch path (``run_vector_filter``) exploits: it evaluates the recursion as a chunked affine scan,
vectorised over chunks, and gives the same numbers as the per-sample classes.

Slower measurements: between measurement samples the last measurement is held (zero-order hold)
until it is ``hold_timeout_s`` old; after that the filter runs on the gyro alone.  (Seed 000 holds
the innovation H_m − Ĥ; holding the measurement is the same at equal rates, keeps the step affine
and is the exact zero-order-hold discretisation of eq. (9).)

Bad input never breaks the state: a non-finite gyro sample counts as zero rate for that step, a
non-finite measurement is ignored (the previous one stays held), a non-finite or backwards time
step is treated as dt = 0, and a gap longer than ``max_gap_s`` re-initialises the estimate from
the next measurement.  Units: rates rad/s, field mG, specific force m/s^2, body frame FRD.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = [
    "VectorFilterSettings", "FieldVectorFilter", "GravityVectorFilter",
    "step_coefficients", "run_vector_filter", "roll_pitch_from_specific_force",
]


@dataclass(frozen=True)
class VectorFilterSettings:
    """Settings of one vector complementary filter (seed 000 eq. 9).

    gain_per_s:     k, crossover frequency [rad/s]; time constant of the measurement path is 1/k.
    hold_timeout_s: a held measurement older than this is no longer used (gyro only).
    max_gap_s:      a time step longer than this is a gap: no gyro propagation over it and the
                    estimate is re-initialised from the next measurement.
    """
    gain_per_s: float = 0.5
    hold_timeout_s: float = 1.0
    max_gap_s: float = 0.5


def step_coefficients(dt_s: np.ndarray, gyro_rad_s: np.ndarray, gain_per_s: float,
                      have_meas: np.ndarray, reinit: np.ndarray):
    """Per-step coefficients of the affine step x' = (1 − g) R x + g m (vectorised over steps).

    Returns (theta (N,3), cos_t (N,), sinc_t (N,), vers_t (N,), g (N,)) where
    R v = cos_t v − sinc_t (theta × v) + vers_t (theta·v) theta   (rotation by −theta, Rodrigues),
    theta = gyro dt.  ``have_meas``: a measurement is held at this step; ``reinit``: the state is
    (re)initialised to the measurement at this step (g = 1).
    """
    dt = np.asarray(dt_s, dtype=float)
    w = np.asarray(gyro_rad_s, dtype=float)
    theta = w * dt[..., None]
    ang2 = np.einsum("...i,...i->...", theta, theta)
    ang = np.sqrt(ang2)
    small = ang < 1e-4
    safe = np.where(small, 1.0, ang)
    cos_t = np.cos(ang)
    sinc_t = np.where(small, 1.0 - ang2 / 6.0, np.sin(ang) / safe)
    vers_t = np.where(small, 0.5 - ang2 / 24.0, (1.0 - cos_t) / (safe * safe))
    g = np.where(have_meas, -np.expm1(-gain_per_s * dt), 0.0)
    g = np.where(reinit, 1.0, g)
    return theta, cos_t, sinc_t, vers_t, g


def _rotate(v, theta, cos_t, sinc_t, vers_t):
    """Rodrigues rotation by −theta of v; v (..., 3, K), theta (..., 3, 1) style broadcasting."""
    tx, ty, tz = theta[..., 0, :], theta[..., 1, :], theta[..., 2, :]
    vx, vy, vz = v[..., 0, :], v[..., 1, :], v[..., 2, :]
    dot = tx * vx + ty * vy + tz * vz
    cx = ty * vz - tz * vy
    cy = tz * vx - tx * vz
    cz = tx * vy - ty * vx
    return np.stack([cos_t * vx - sinc_t * cx + vers_t * dot * tx,
                     cos_t * vy - sinc_t * cy + vers_t * dot * ty,
                     cos_t * vz - sinc_t * cz + vers_t * dot * tz], axis=-2)


def run_vector_filter(dt_s: np.ndarray, gyro_rad_s: np.ndarray, meas: np.ndarray,
                      have_meas: np.ndarray, reinit: np.ndarray, gain_per_s: float,
                      x0: np.ndarray | None = None, chunk: int | None = None) -> np.ndarray:
    """Batch form of the filter: x_n = (1 − g_n) R_n x_{n−1} + g_n m_n for n = 0..N−1.

    Inputs are per-step arrays already cleaned (finite; see ``HeadingChain`` / ``run_heading_chain``
    for how raw logs are turned into them).  The affine recursion is evaluated as a two-pass chunked
    scan: pass 1 runs every chunk from zero state and from identity (transition product) in
    parallel, a short sequential loop links the chunk start states, pass 2 re-runs every chunk from
    its true start state.  Cost O(N) numpy work in O(sqrt N) Python iterations.
    Returns x (N, 3).
    """
    n = len(dt_s)
    out = np.zeros((n, 3))
    if n == 0:
        return out
    theta, cos_t, sinc_t, vers_t, g = step_coefficients(dt_s, gyro_rad_s, gain_per_s, have_meas, reinit)
    b = g[:, None] * np.where(have_meas[:, None] | reinit[:, None], meas, 0.0)
    a = 1.0 - g
    L = chunk or max(16, int(np.sqrt(n)))
    c = -(-n // L)
    pad = c * L - n

    def shape(arr, fill):
        if pad:
            arr = np.concatenate([arr, np.full((pad,) + arr.shape[1:], fill, dtype=float)])
        return arr.reshape((c, L) + arr.shape[1:])

    th = shape(theta, 0.0)
    co, si, ve = shape(cos_t, 1.0), shape(sinc_t, 1.0), shape(vers_t, 0.5)
    aa, bb = shape(a, 1.0), shape(b, 0.0)
    # pass 1: columns 0 = local state from zero, 1..3 = transition product applied to e1, e2, e3
    state = np.zeros((c, 3, 4))
    state[:, :, 1:] = np.eye(3)
    for p in range(L):
        t_ = th[:, p, :, None]
        state = _rotate(state, t_, co[:, p, None], si[:, p, None], ve[:, p, None]) * aa[:, p, None, None]
        state[:, :, 0] += bb[:, p]
    starts = np.empty((c, 3))
    x = np.zeros(3) if x0 is None else np.asarray(x0, dtype=float)
    for j in range(c):
        starts[j] = x
        x = state[j, :, 1:] @ x + state[j, :, 0]
    # pass 2: exact run of each chunk from its start state
    xs = starts[:, :, None]
    res = np.empty((c, L, 3))
    for p in range(L):
        xs = _rotate(xs, th[:, p, :, None], co[:, p, None], si[:, p, None], ve[:, p, None]) * aa[:, p, None, None]
        xs[:, :, 0] += bb[:, p]
        res[:, p] = xs[:, :, 0]
    return res.reshape(c * L, 3)[:n]


def roll_pitch_from_specific_force(f_body_mps2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Roll and pitch [rad] from the body-frame specific force at rest (FRD: level reads [0,0,−g]).

    f = C_n^b (−g_n) = g [sin θ, −cos θ sin φ, −cos θ cos φ]  ⇒  φ = atan2(−f_y, −f_z),
    θ = atan2(f_x, sqrt(f_y² + f_z²)).  Vectorised over leading axes.
    """
    f = np.asarray(f_body_mps2, dtype=float)
    fx, fy, fz = f[..., 0], f[..., 1], f[..., 2]
    roll = np.arctan2(-fy, -fz)
    pitch = np.arctan2(fx, np.hypot(fy, fz))
    return roll, pitch


class _VectorComplementaryFilter:
    """Per-sample filter (seed 000 eq. 9/10) on a body-frame vector; base of the two filters."""

    def __init__(self, settings: VectorFilterSettings | None = None):
        self.settings = settings or type(self).default_settings()
        self.estimate = np.zeros(3)
        self.initialised = False
        self._t: float | None = None
        self._meas = np.zeros(3)
        self._meas_t = -np.inf
        self._reinit = True

    @staticmethod
    def default_settings() -> VectorFilterSettings:
        return VectorFilterSettings()

    def set_measurement(self, t_s: float, vector) -> None:
        """Hold a new measurement (zero-order hold until the next one or the timeout).
        Non-finite samples and samples older than the held one are ignored."""
        v = np.asarray(vector, dtype=float)
        if v.shape == (3,) and np.all(np.isfinite(v)) and np.isfinite(t_s) and t_s >= self._meas_t:
            self._meas = v.copy()
            self._meas_t = float(t_s)

    def update(self, t_s: float, gyro_rad_s, measurement=None) -> np.ndarray:
        """Propagate to t_s with the gyro rate of this sample, using the held measurement.

        ``measurement`` (optional) is a new measurement at t_s, held from now on.
        Returns the estimate (copy).
        """
        if measurement is not None:
            self.set_measurement(t_s, measurement)
        s = self.settings
        t = float(t_s)
        if not np.isfinite(t) or (self._t is not None and t < self._t):
            dt, t = 0.0, (self._t if self._t is not None else 0.0)   # bad/backwards time: no step
        elif self._t is None:
            dt = 0.0
        else:
            dt = t - self._t
        self._t = t
        if dt > s.max_gap_s:
            dt, self._reinit = 0.0, True
        try:
            wx, wy, wz = (float(v) for v in gyro_rad_s)
        except (TypeError, ValueError):
            wx = wy = wz = 0.0
        if not (math.isfinite(wx) and math.isfinite(wy) and math.isfinite(wz)):
            wx = wy = wz = 0.0
        have = (t - self._meas_t) <= s.hold_timeout_s and self._meas_t <= t
        reinit = bool(have and self._reinit)
        # same step as step_coefficients/_rotate, in plain floats (the live path runs per sample)
        tx, ty, tz = wx * dt, wy * dt, wz * dt
        ang2 = tx * tx + ty * ty + tz * tz
        ang = math.sqrt(ang2)
        cos_t = math.cos(ang)
        if ang < 1e-4:
            sinc_t, vers_t = 1.0 - ang2 / 6.0, 0.5 - ang2 / 24.0
        else:
            sinc_t, vers_t = math.sin(ang) / ang, (1.0 - cos_t) / ang2
        g = 1.0 if reinit else (-math.expm1(-s.gain_per_s * dt) if have else 0.0)
        vx, vy, vz = (float(v) for v in self.estimate)
        dot = tx * vx + ty * vy + tz * vz
        cx, cy, cz = ty * vz - tz * vy, tz * vx - tx * vz, tx * vy - ty * vx
        a = 1.0 - g
        rx = cos_t * vx - sinc_t * cx + vers_t * dot * tx
        ry = cos_t * vy - sinc_t * cy + vers_t * dot * ty
        rz = cos_t * vz - sinc_t * cz + vers_t * dot * tz
        if have or reinit:
            mx, my, mz = self._meas
            self.estimate = np.array([a * rx + g * mx, a * ry + g * my, a * rz + g * mz])
        else:
            self.estimate = np.array([a * rx, a * ry, a * rz])
        if reinit:
            self._reinit = False
            self.initialised = True
        return self.estimate.copy()


class FieldVectorFilter(_VectorComplementaryFilter):
    """Earth field in the body frame from calibrated magnetometer [mG] + gyro (seed 000 eq. 9/10)."""

    @property
    def field_body_mG(self) -> np.ndarray:
        return self.estimate.copy()


class GravityVectorFilter(_VectorComplementaryFilter):
    """Specific force of gravity in the body frame from accelerometer + gyro → roll, pitch.

    Same filter as eq. (9) with the accelerometer as measurement (seed 000 sec. 2.2): the gyro keeps
    the fast attitude changes, the accelerometer (low-passed at k) the long-term vertical.
    """

    @staticmethod
    def default_settings() -> VectorFilterSettings:
        return VectorFilterSettings(gain_per_s=0.2)

    @property
    def roll_pitch_rad(self) -> tuple[float, float]:
        r, p = roll_pitch_from_specific_force(self.estimate)
        return float(r), float(p)
