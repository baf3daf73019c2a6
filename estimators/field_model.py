"""Predicted-field model and robust Gauss–Newton solver for in-flight compass fits.

Sensor model (the simulator's and ArduPilot's, in the rotated-raw body frame):

    m = A (h + f·x) + b + ε,    h = C_nᵇ H_ned  (the Earth field seen by the body)

A symmetric distortion (soft iron and scale; the correction matrix is M = A⁻¹), b offsets [mG]
(ArduPilot COMPASS_OFS = −b), f motor field per unit of x [mG/A or mG per full throttle]
(ArduPilot COMPASS_MOT = −f), ε sensor noise.  Parameters (12): b, diag(A), off-diagonals of A
(A01, A02, A12), f; any subset is fitted, the rest held at nominal.

The residual is taken in *measurement* space, r = m − A(h + f·x) − b, where the regressors (attitude,
WMM, current) carry no sensor noise: fitting the correction form M(m − b) ≈ h instead regresses a
noise-free target on the noisy field and shrinks the fitted scale (errors in variables; 2–5 % on
the vertical axis and 10–25 mG of z offset at 3–6 mG noise in level flight, measured while writing
this module).  Two ways to get h:
* ``vector``:   h = C(φ, θ, ψ)ᵀ H with the attitude's yaw ψ;
* ``yaw_free``: h = C(φ, θ, ψ*)ᵀ H with ψ* the heading of the sample's own corrected field
  c = A⁻¹(m − b) − f·x (tilt compensated, declination of H).  The attitude's heading never enters,
  so an attitude whose yaw was computed from this very compass cannot pull the offsets toward the
  ones it was using; ψ* is a per-sample nuisance at its optimum (to first order for A ≈ I), so the
  tangential residual is absorbed and the horizontal offsets are observed through the change of the
  horizontal magnitude with heading (the idea of pymavlink's magfit_WMM.py, which also takes the yaw
  from the corrected field being fitted).

Solver: Gauss–Newton on Σ wᵢ|rᵢ|²/σ² + (p − p₀)ᵀΛ(p − p₀) with Gaussian priors Λ (bounded
terms), Huber IRLS weights on the per-sample residual (scale from the MAD) and hard rejection beyond
``outlier_sigma``; step halving when the cost rises.  Covariance σ²(JᵀWJ + σ²Λ)⁻¹ inflated by
τ, the residual's integrated autocorrelation time (``autocorrelation_time``: attitude errors are
slow, so the samples are not independent).

The residual is written for G parameter rows at once (``model_terms``, ``model_jacobian``, arrays
(G, 3, N)) on the per-row terms that do not depend on the parameters (``FieldRows``, computed once
per FieldData): ``solve`` uses it with G = 1, estimators.field_model_groups solves many related
problems in lockstep with it (issue 29).  Units: mG, rad.  Pure numpy.
"""
from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cached_property

import numpy as np

from estimators.rotations import dcm_body_to_ned

__all__ = ["PARAM_NAMES", "FieldData", "SolverOptions", "Solution", "matrix_from_params", "corrected_field",
           "residuals", "solve", "nominal_params", "distortion_from_params", "FieldRows", "field_rows", "stack_rows",
           "distortion_stack", "model_terms", "model_jacobian"]

PARAM_NAMES = ("b_x", "b_y", "b_z", "a_x", "a_y", "a_z", "a_xy", "a_xz", "a_yz", "f_x", "f_y", "f_z")
_OFFDIAG = ((0, 1), (0, 2), (1, 2))


@dataclass(frozen=True)
class FieldData:
    """Per-sample inputs (N rows, all finite): raw body field, attitude, motor signal, WMM field."""
    mag_raw_mG: np.ndarray      # (N,3)
    roll_rad: np.ndarray
    pitch_rad: np.ndarray
    yaw_rad: np.ndarray
    motor_signal: np.ndarray    # (N,) A or throttle 0..1 (zeros when unused)
    field_ned_mG: np.ndarray    # (3,) one field for every sample, or (N,3) the WMM at each sample (along the flight)
    weight: np.ndarray | None = None    # (N,) prior per-sample weights (mean 1; e.g. sphere cells), None = 1

    def tilt(self) -> np.ndarray:
        """Ry(θ)Rx(φ) per sample (N,3,3); computed once (the solver asks for it every iteration)."""
        return self._tilt

    @cached_property
    def _tilt(self) -> np.ndarray:
        return dcm_body_to_ned(self.roll_rad, self.pitch_rad, np.zeros_like(self.roll_rad))

    def field_rows(self) -> np.ndarray:
        """The NED field at each sample (N,3), whether one field or one per sample was given."""
        return np.broadcast_to(np.asarray(self.field_ned_mG, float), (len(self.roll_rad), 3))

    def subset(self, keep: np.ndarray) -> "FieldData":
        """The rows ``keep``; the per-row tilt and expected field already computed are kept (rows of them)."""
        H = np.asarray(self.field_ned_mG, float)
        out = FieldData(self.mag_raw_mG[keep], self.roll_rad[keep], self.pitch_rad[keep], self.yaw_rad[keep],
                        self.motor_signal[keep], H if H.ndim == 1 else H[keep],
                        None if self.weight is None else self.weight[keep])
        for name in ("_tilt", "_expected_body"):
            if name in self.__dict__:
                out.__dict__[name] = self.__dict__[name][keep]
        return out

    def with_field(self, field_ned_mG: np.ndarray) -> "FieldData":
        """The same samples under another reference field; the tilt already computed is kept."""
        out = replace(self, field_ned_mG=field_ned_mG)
        if "_tilt" in self.__dict__:
            out.__dict__["_tilt"] = self.__dict__["_tilt"]
        return out

    def expected_body_mG(self) -> np.ndarray:
        return self._expected_body

    def rows(self) -> "FieldRows":
        """The residual's parameter-free terms per row (``FieldRows``), computed once."""
        return self._rows

    @cached_property
    def _rows(self) -> "FieldRows":
        return field_rows(self)

    @cached_property
    def _expected_body(self) -> np.ndarray:
        C = dcm_body_to_ned(self.roll_rad, self.pitch_rad, self.yaw_rad)
        return np.einsum("nji,nj->ni", C, self.field_rows())


@dataclass(frozen=True)
class SolverOptions:
    model: str                  # "vector" | "yaw_free"
    active: np.ndarray          # (12,) bool: fitted parameters
    prior_sd: np.ndarray        # (12,) prior standard deviation around p0 (inf = none)
    huber_k: float = 1.345
    outlier_sigma: float = 5.0
    max_iter: int = 25


@dataclass(frozen=True)
class Solution:
    params: np.ndarray          # (12,)
    covariance: np.ndarray      # (12,12), zero rows/cols for fixed parameters
    sigma_mG: float             # residual scale (per component, inliers)
    inliers: np.ndarray         # (N,) bool
    residual_rms_mG: float
    iterations: int
    converged: bool
    autocorr: float             # the residual's integrated autocorrelation time τ [samples] (covariance × τ)
    lag1: float = 0.0           # its lag-1 autocorrelation ρ₁

    @property
    def support_covariance(self) -> np.ndarray:
        """The covariance with the lag-1 factor (1 + ρ₁)/(1 − ρ₁) in place of τ: what the in-flight
        fit judges a term's support by (estimators.wmm_fit._fit_terms; the rule was measured with
        it: judged with τ, the dronekit log's compass 0 drops terms and lands 43 mG off)."""
        return self.covariance / max(self.autocorr, 1.0) * (1.0 + self.lag1) / (1.0 - self.lag1)


def nominal_params(matrix: np.ndarray | None = None, offsets_mG=None) -> np.ndarray:
    """p₀ from a correction matrix M (A = M⁻¹; default I) and offsets (default 0); f = 0."""
    A = np.eye(3) if matrix is None else np.linalg.inv(np.asarray(matrix, float))
    A = (A + A.T) / 2
    p = np.zeros(12)
    if offsets_mG is not None:
        p[:3] = offsets_mG
    p[3:6] = np.diag(A)
    p[6:9] = [A[i, j] for i, j in _OFFDIAG]
    return p


def distortion_from_params(p: np.ndarray) -> np.ndarray:
    """A (symmetric) from the parameter vector."""
    A = np.diag(p[3:6]).astype(float)
    for k, (i, j) in enumerate(_OFFDIAG):
        A[i, j] = A[j, i] = p[6 + k]
    return A


def matrix_from_params(p: np.ndarray) -> np.ndarray:
    """The correction matrix M = A⁻¹ (m_cal = M (m − b) − f·x)."""
    return np.linalg.inv(distortion_from_params(p))


def corrected_field(p: np.ndarray, data: FieldData) -> np.ndarray:
    """c = A⁻¹ (m − b) − f·x  (N,3)."""
    return (data.mag_raw_mG - p[:3]) @ matrix_from_params(p).T - data.motor_signal[:, None] * p[9:12]


@dataclass(frozen=True)
class FieldRows:
    """The residual's parameter-free terms per row, component-major (3, N) so that the solver's sums
    over the three components are adds of rows; a leading group axis (G, 3, N) stacks problems on
    the same samples under different reference fields (``stack_rows``).

    With T = Ry(θ)Rx(φ) and α = ψ − declination the yaw-free body field is
    h(α) = Tᵀ[H_h cos α, −H_h sin α, H_d] = cos α·u₀ + sin α·v₀ + d₀,  u₀ = H_h Tᵀe_x,
    v₀ = −H_h Tᵀe_y, d₀ = H_d Tᵀe_z: A and b enter only through A u₀, A v₀, A d₀."""
    mag_mG: np.ndarray          # (3,N) m
    motor: np.ndarray           # (N,) x
    body_mG: np.ndarray         # (3,N) h = C(φ, θ, ψ)ᵀ H with the attitude's yaw ("vector")
    u0_mG: np.ndarray           # (3,N) H_h Tᵀe_x
    v0_mG: np.ndarray           # (3,N) −H_h Tᵀe_y
    d0_mG: np.ndarray           # (3,N) H_d Tᵀe_z

    def take(self, groups: np.ndarray) -> "FieldRows":
        """The rows of the problems ``groups`` (all of them when the rows are shared)."""
        return self if self.u0_mG.ndim == 2 else FieldRows(*(a[groups] for a in (
            self.mag_mG, self.motor, self.body_mG, self.u0_mG, self.v0_mG, self.d0_mG)))


def field_rows(data: FieldData) -> FieldRows:
    """``FieldRows`` of ``data`` (computed once per FieldData: ``FieldData.rows``)."""
    H = data.field_rows()
    T = data.tilt()
    hh = np.hypot(H[:, 0], H[:, 1])
    return FieldRows(np.ascontiguousarray(data.mag_raw_mG.T), np.asarray(data.motor_signal, float),
                     np.ascontiguousarray(data.expected_body_mG().T), (T[:, 0, :] * hh[:, None]).T.copy(),
                     (T[:, 1, :] * -hh[:, None]).T.copy(), (T[:, 2, :] * H[:, 2:3]).T.copy())


def stack_rows(datas: list[FieldData]) -> FieldRows:
    """The ``FieldRows`` of several FieldData of the same rows, stacked on a leading group axis."""
    rows = [d.rows() for d in datas]
    return FieldRows(*(np.stack([getattr(r, k) for r in rows]) for k in
                       ("mag_mG", "motor", "body_mG", "u0_mG", "v0_mG", "d0_mG")))


def _dot3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Σ_c a[:, c] b[:, c] over the component axis of (G, 3, N) arrays -> (G, N)."""
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def distortion_stack(P: np.ndarray) -> np.ndarray:
    """A (G,3,3), symmetric, of each parameter row of P (G,12)."""
    A = np.zeros((len(P), 3, 3))
    for j in range(3):
        A[:, j, j] = P[:, 3 + j]
    for k, (i, j) in enumerate(_OFFDIAG):
        A[:, i, j] = A[:, j, i] = P[:, 6 + k]
    return A


def _cos_sin(d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(cos d, sin d); for |d| ≤ 0.1 (the Newton steps of ``_nuisance_cos_sin``) by their Taylor
    series to d⁸ and d⁹ (the terms left out are below 3e-17), else by np.cos/np.sin: the
    polynomials are a few times cheaper than numpy's cosine and sine of doubles."""
    if not np.max(np.abs(d), initial=0.0) <= 0.1:
        return np.cos(d), np.sin(d)
    d2 = d * d
    c = 1.0 + d2 * (-1 / 2 + d2 * (1 / 24 + d2 * (-1 / 720 + d2 * (1 / 40320))))
    s = d * (1.0 + d2 * (-1 / 6 + d2 * (1 / 120 + d2 * (-1 / 5040 + d2 * (1 / 362880)))))
    return c, s


def _nuisance_cos_sin(zu, zv, uu, vv, uv) -> tuple[np.ndarray, np.ndarray]:
    """(cos α, sin α) per row, α minimising |e(α)|², e = z − u cos α − v sin α (variable projection),
    from the five dot products of z, u = A u₀ and v = A v₀.  Start α = atan2(z·v, z·u) (exact for
    orthogonal A), then three Newton steps δ on ½ d|e|²/dα = e·d, d = u sin α − v cos α, each applied
    as a rotation of (cos α, sin α) by δ.  With c = cos α, s = sin α, c₂ = c² − s², s₂ = 2cs,
    D = u·u − v·v:  e·d = s z·u − c z·v − ½ s₂ D + c₂ u·v  and its derivative
    d·d + e·(u c + v s) = c z·u + s z·v − c₂ D − 2 s₂ u·v."""
    rho = np.sqrt(zu * zu + zv * zv)
    none = rho == 0.0                                       # atan2(0, 0) = 0
    rho = np.where(none, 1.0, rho)
    c, s = np.where(none, 1.0, zu / rho), zv / rho
    D = uu - vv
    for _ in range(3):
        c2, s2 = c * c - s * s, 2.0 * c * s
        g = s * zu - c * zv - 0.5 * s2 * D + c2 * uv
        hess = c * zu + s * zv - c2 * D - 2.0 * s2 * uv
        ok = hess > 1e-9
        cd, sd = _cos_sin(-np.where(ok, g / np.where(ok, hess, 1.0), 0.0))
        c, s = c * cd - s * sd, s * cd + c * sd
    return c, s


def model_terms(P: np.ndarray, rows: FieldRows, model: str):
    """Residuals r = m − A(h + f·x) − b (G,3,N) of the parameter rows P (G,12) and the terms their
    Jacobian is built from (``model_jacobian``).  yaw_free: h = h(α*) with α* per row and problem
    (``_nuisance_cos_sin``); then r = z − u cos α* − v sin α*, z = m − b − A f x − A d₀, and
    q = ∂r/∂α / |∂r/∂α| is the direction α* absorbs."""
    A = distortion_stack(P)
    x = rows.motor[..., None, :]
    f = P[:, 9:12, None]
    if model == "vector":
        g = rows.body_mG + f * x
        return rows.mag_mG - A @ g - P[:, :3, None], (A, g, None)
    u, v = A @ rows.u0_mG, A @ rows.v0_mG
    z = rows.mag_mG - P[:, :3, None] - (A @ f) * x - A @ rows.d0_mG
    c, s = _nuisance_cos_sin(_dot3(z, u), _dot3(z, v), _dot3(u, u), _dot3(v, v), _dot3(u, v))
    c, s = c[:, None, :], s[:, None, :]
    r = z - u * c - v * s
    d1 = u * s - v * c
    q = d1 / np.maximum(np.sqrt(_dot3(d1, d1)), 1e-12)[:, None, :]
    g = rows.u0_mG * c + rows.v0_mG * s + rows.d0_mG + f * x
    return r, (A, g, q)


def model_jacobian(rows: FieldRows, terms, columns=None) -> np.ndarray:
    """∂r/∂p (G, k, 3, N) over the parameter ``columns`` (all 12 when None) from ``model_terms``'
    terms: −e_j for b_j, −g_j e_j for A_jj, −(g_j e_i + g_i e_j) for A_ij, −x A e_j for f_j, with
    g = h + f x.  yaw_free: each column j projected off q (Kaufman's variable-projection form),
    j − q (q·j), q·j written out per kind of column."""
    A, g, q = terms
    cols = range(12) if columns is None else columns
    x = rows.motor[..., None, :]
    J = np.zeros((g.shape[0], len(cols), 3, g.shape[2]))
    Atq = None if q is None or not any(c >= 9 for c in cols) else A.transpose(0, 2, 1) @ q     # Aᵀq
    for k, c in enumerate(cols):
        col = J[:, k]
        if c < 3:                       # b
            col[:, c] = -1.0
            qj = None if q is None else -q[:, c]
        elif c < 6:                     # diag(A)
            col[:, c - 3] = -g[:, c - 3]
            qj = None if q is None else -(q[:, c - 3] * g[:, c - 3])
        elif c < 9:                     # A's off-diagonal pair (i, j)
            i, j = _OFFDIAG[c - 6]
            col[:, i], col[:, j] = -g[:, j], -g[:, i]
            qj = None if q is None else -(q[:, i] * g[:, j] + q[:, j] * g[:, i])
        else:                           # f
            col[...] = -A[:, :, c - 9, None] * x
            qj = None if q is None else -(Atq[:, c - 9] * x[..., 0, :])
        if q is not None:
            col -= q * qj[:, None, :]
    return J


def residuals(p: np.ndarray, data: FieldData, model: str, with_jacobian: bool = False):
    """r = m − A(h + f·x) − b  (N,3) and optionally ∂r/∂p (N,3,12).  yaw_free: h = h(ψ*) and the
    Jacobian is projected off the direction ψ* absorbs (Kaufman's variable-projection form)."""
    r, terms = _residuals_terms(p, data, model)
    return (r, _jacobian(p, data, terms)) if with_jacobian else r


def _residuals_terms(p: np.ndarray, data: FieldData, model: str):
    """(r (N,3), terms): the residual and what its Jacobian is built from (``_jacobian``), so a
    solver that accepts a trial point does not solve for ψ* there again."""
    r, terms = model_terms(np.asarray(p, float)[None, :], data.rows(), model)
    return r[0].T, terms


def _jacobian(p: np.ndarray, data: FieldData, terms) -> np.ndarray:
    """∂r/∂p (N,3,12) from ``_residuals_terms``' terms at p."""
    return model_jacobian(data.rows(), terms)[0].transpose(2, 1, 0)


def _weights(r: np.ndarray, mask: np.ndarray, huber_k: float, outlier_sigma: float) -> tuple[np.ndarray, np.ndarray, float]:
    s = np.linalg.norm(r, axis=1) / np.sqrt(2.0)
    med = np.median(s[mask]) if np.any(mask) else 0.0
    # |r|/√2 of 2–3 noisy components has its median at ≈ 0.83–1.0 σ: 1/0.9 as a middle factor
    sigma = max(med / 0.9, 1e-9)
    a = s / sigma
    w = np.where(a <= huber_k, 1.0, huber_k / np.maximum(a, 1e-12))
    inl = a < outlier_sigma
    return w * inl, inl, sigma


def _cost(r: np.ndarray, w: np.ndarray, p: np.ndarray, p0: np.ndarray, lam: np.ndarray, sigma: float) -> float:
    return float(np.sum(w[:, None] * r * r) / sigma ** 2 + np.sum(lam * (p - p0) ** 2))


AUTOCORR_WINDOW_C = 5.0        # Sokal's automatic window: the smallest W ≥ c·τ(W)
AUTOCORR_MIN_LENGTH = 50.0     # τ is estimated reliably only from n ≳ 50 τ samples: at most n/50 is used


def autocorrelation_time(x: np.ndarray, c: float = AUTOCORR_WINDOW_C) -> tuple[float, float]:
    """Integrated autocorrelation time τ = 1 + 2 Σ_{k=1..W} ρ_k of a series, with Sokal's automatic
    window (the smallest W ≥ c·τ(W); Sokal 1997, "Monte Carlo methods in statistical mechanics",
    sec. 3; as emcee's autocorr).  The variance of a mean of n correlated samples is τ σ²/n.  τ ≥ 1,
    at most n/``AUTOCORR_MIN_LENGTH`` (a longer τ is not resolved by the series: a residual that is a
    function of the leg flown, on an A–B mission, gave τ ≈ n/5 and a 1σ of 213 mG on a 16 mG error;
    the time-block jackknife of estimators.wmm_fit carries errors that slow).  The AR(1) factor (1 + ρ₁)/(1 − ρ₁) it replaces saw only the first lag: on the
    ArduPilot SITL route flights the residual's τ is 9–30 samples where (1 + ρ₁)/(1 − ρ₁) is 3–4 (slow
    attitude errors over tens of seconds beside fast noise), so the stated 1σ was 1.5–2.5× too small.
    Returns (τ, ρ₁), ρ₁ the lag-1 autocorrelation (clipped to 0..0.95)."""
    x = np.asarray(x, float)
    n = len(x)
    if n < 10:
        return 1.0, 0.0
    x = x - x.mean()
    den = float(np.dot(x, x))
    if not den > 0:
        return 1.0, 0.0
    f = np.fft.rfft(x, 2 * n)
    rho = np.fft.irfft(f * np.conj(f))[:n] / den
    tau = 1.0 + 2.0 * np.cumsum(rho[1:])
    w = np.arange(1, n)
    ok = w >= c * tau
    t = float(tau[np.argmax(ok)]) if ok.any() else float(tau[-1])
    return float(np.clip(t, 1.0, max(1.0, n / AUTOCORR_MIN_LENGTH))), float(np.clip(rho[1], 0.0, 0.95))


def solve(data: FieldData, p_init: np.ndarray, p0: np.ndarray, opts: SolverOptions) -> Solution:
    """Robust Gauss–Newton with priors (see module docstring).  Never raises on finite input."""
    act = np.asarray(opts.active, bool)
    lam_all = np.where(np.isfinite(opts.prior_sd), 1.0 / np.square(opts.prior_sd), 0.0)
    lam = lam_all[act]
    p = np.array(p_init, float)
    r, J = residuals(p, data, opts.model, True)
    prior_w = np.ones(len(r)) if data.weight is None else np.asarray(data.weight, float)
    w, inl, sigma = _weights(r, np.ones(len(r), bool), opts.huber_k, opts.outlier_sigma)
    w = w * prior_w
    converged, it = False, 0
    for it in range(1, opts.max_iter + 1):
        A = J[:, :, act].reshape(-1, int(act.sum()))
        wr = np.repeat(w, r.shape[1])
        Hm = (A * wr[:, None]).T @ A / sigma ** 2 + np.diag(lam)
        g = (A * wr[:, None]).T @ r.ravel() / sigma ** 2 + lam * (p[act] - p0[act])
        try:
            step = -np.linalg.solve(Hm, g)
        except np.linalg.LinAlgError:
            break
        cost0 = _cost(r, w, p[act], p0[act], lam, sigma)
        for _ in range(10):
            trial = p.copy()
            trial[act] += step
            r_t, terms = _residuals_terms(trial, data, opts.model)
            if np.all(np.isfinite(r_t)) and _cost(r_t, w, trial[act], p0[act], lam, sigma) <= cost0 * (1 + 1e-12):
                break
            step = step / 2
        else:
            break
        p = trial
        r, J = r_t, _jacobian(p, data, terms)
        w, inl, sigma = _weights(r, inl, opts.huber_k, opts.outlier_sigma)
        w = w * prior_w
        if np.max(np.abs(step)) < 1e-4:
            converged = True
            break
    A = J[:, :, act].reshape(-1, int(act.sum()))
    rows = 3 if opts.model == "vector" else 2          # ψ* absorbs one direction per sample
    sig_c = float(np.sqrt(np.sum(w[:, None] * r * r) / max(np.sum(w) * rows - act.sum(), 1.0)))
    info = (A * np.repeat(w, r.shape[1])[:, None]).T @ A / max(sig_c, 1e-9) ** 2 + np.diag(lam)
    tau, rho1 = autocorrelation_time(np.mean(r[inl], axis=1)) if np.any(inl) else (1.0, 0.0)
    cov = np.zeros((12, 12))
    try:
        cov_a = np.linalg.inv(info)
        if data.weight is not None:     # weights that are not inverse variances: the sandwich H⁻¹ (JᵀW²J + Λ) H⁻¹
            w2 = np.repeat(w * prior_w, r.shape[1])
            cov_a = cov_a @ ((A * w2[:, None]).T @ A / max(sig_c, 1e-9) ** 2 + np.diag(lam)) @ cov_a
        cov_a = cov_a * tau
        cov[np.ix_(act, act)] = cov_a
    except np.linalg.LinAlgError:
        cov[np.ix_(act, act)] = np.inf
    rms = float(np.sqrt(np.mean(r[inl] ** 2))) if np.any(inl) else float("nan")
    return Solution(p, cov, sig_c, inl, rms, it, converged, tau, rho1)
