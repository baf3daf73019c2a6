"""Robust batch ellipsoid and sphere fits of magnetometer samples (the batch half of
estimators.calibration, which re-exports them).

Model:  m_raw = A · m_body + b + noise;  calibration  m_cal = C · (m_raw − b),  |m_cal| ≈ F.

* ``fit_ellipsoid_robust`` — offsets + full symmetric C.  An algebraic least-squares quadric fit
  (closed form, no start value, in centred/normalised coordinates for conditioning) gives the
  start; it is biased (the algebraic distance weights points unevenly), so it is refined by
  Levenberg–Marquardt on the geometric residual r = |L(m − b)| − 1 (|m_cal| − F, the physical
  quantity), with Huber IRLS weights (scale from the MAD) and hard rejection beyond
  ``outlier_sigma`` robust sigmas.  9 parameters, ~5–10 iterations, a few ms for 10,000 samples.
* ``fit_sphere_robust`` — offsets + radius (4 parameters), for sparse windows (a telemetry-rate
  dance), as ArduPilot's calibrator runs a sphere fit before its ellipsoid fit.
Both return the offsets covariance σ²(JᵀWJ)⁻¹ of the last step (the quality measure of
estimators.cal_windows).  Units: mG (any consistent unit works).  Pure numpy.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["EllipsoidFit", "fit_ellipsoid_robust", "fit_sphere_robust"]


def _finite_rows(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, dtype=float).reshape(-1, 3)
    return x[np.all(np.isfinite(x), axis=1)]


def _quadric_design(z: np.ndarray) -> np.ndarray:
    x, y, w = z[:, 0], z[:, 1], z[:, 2]
    return np.stack([x * x, y * y, w * w, 2 * x * y, 2 * x * w, 2 * y * w, 2 * x, 2 * y, 2 * w], axis=1)


def _quadric_to_center_shape(v: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """v·[x², y², z², 2xy, 2xz, 2yz, 2x, 2y, 2z] = 1  ->  (centre c, Q) with (x−c)ᵀQ(x−c) = 1, Q ≻ 0."""
    A = np.array([[v[0], v[3], v[4]], [v[3], v[1], v[5]], [v[4], v[5], v[2]]])
    g = v[6:9]
    try:
        c = -np.linalg.solve(A, g)
    except np.linalg.LinAlgError:
        return None
    k = 1.0 + c @ A @ c
    if not np.isfinite(k) or abs(k) < 1e-12:
        return None
    Q = A / k
    w = np.linalg.eigvalsh(Q)
    if not np.all(np.isfinite(w)) or w[0] <= 0:
        return None
    return c, Q


def _sym_sqrt(Q: np.ndarray) -> np.ndarray:
    w, V = np.linalg.eigh(Q)
    return (V * np.sqrt(np.maximum(w, 0))) @ V.T


def _calibration_from_shape(center: np.ndarray, L: np.ndarray, field_strength_mG: float | None
                            ) -> tuple[np.ndarray, np.ndarray, float]:
    """|L(m − center)| = 1  ->  (b, C, F): C = F·L with det C = 1 unless F is given."""
    det = float(np.linalg.det(L))
    F = float(field_strength_mG) if field_strength_mG else det ** (-1.0 / 3.0)
    return center, F * L, F


@dataclass(frozen=True)
class EllipsoidFit:
    """Result of ``fit_ellipsoid_robust``.  ``ok`` False -> ``reason`` says why; arrays then NaN."""
    ok: bool
    reason: str
    offsets_mG: np.ndarray
    matrix: np.ndarray               # symmetric C, m_cal = C (m − b)
    field_strength_mG: float         # |m_cal| of the fit
    residual_rms_mG: float           # RMS of |m_cal| − F over inliers
    inliers: np.ndarray              # bool mask over the *finite* input rows
    n_used: int
    condition_number: float          # of the normalised algebraic design matrix
    iterations: int
    # Covariance [mG²] of offsets_mG: σ²(JᵀWJ)⁻¹ of the final LM step (σ: inlier residual scale);
    # None for a failed fit.
    offsets_cov_mG2: np.ndarray | None = None


def _failed_fit(reason: str, n: int, cond: float = float("inf")) -> EllipsoidFit:
    nan3 = np.full(3, np.nan)
    return EllipsoidFit(False, reason, nan3, np.full((3, 3), np.nan), float("nan"), float("nan"),
                        np.zeros(n, bool), 0, cond, 0)


def _sym_from6(p: np.ndarray) -> np.ndarray:
    return np.array([[p[0], p[3], p[4]], [p[3], p[1], p[5]], [p[4], p[5], p[2]]])


def _screened_normalised(m: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, float] | None:
    """Gross-outlier screen around the median centre (radius beyond 8 robust sigmas), then
    centring and scaling for conditioning: (keep mask, z = (m − μ)/s, μ, s); None without spread."""
    med = np.median(m, axis=0)
    r = np.linalg.norm(m - med, axis=1)
    r_med = np.median(r)
    r_mad = 1.4826 * np.median(np.abs(r - r_med)) + 1e-9 * (r_med + 1.0)
    keep = np.abs(r - r_med) < 8.0 * r_mad + 0.5 * r_med
    mu = m[keep].mean(axis=0)
    s = float(np.sqrt(np.mean(np.sum((m[keep] - mu) ** 2, axis=1))))
    if not np.isfinite(s) or s <= 0:
        return None
    return keep, (m - mu) / s, mu, s


def _algebraic_start(z: np.ndarray) -> tuple[np.ndarray | None, float, str]:
    """(p = [centre, L11, L22, L33, L12, L13, L23], condition number, failure reason)."""
    D = _quadric_design(z)
    DtD = D.T @ D
    ev = np.linalg.eigvalsh(DtD)
    cond = float(np.sqrt(ev[-1] / ev[0])) if ev[0] > 0 else float("inf")
    try:
        v = np.linalg.solve(DtD, D.sum(axis=0))
    except np.linalg.LinAlgError:
        return None, cond, "algebraic fit is singular (data too planar or sparse)"
    cs = _quadric_to_center_shape(v)
    if cs is None:
        return None, cond, "algebraic fit is not an ellipsoid (data too planar or sparse)"
    c, Q = cs
    L = _sym_sqrt(Q)
    return np.concatenate([c, [L[0, 0], L[1, 1], L[2, 2], L[0, 1], L[0, 2], L[1, 2]]]), cond, ""


def _geometric_residual(z: np.ndarray, p: np.ndarray) -> tuple[np.ndarray, tuple]:
    """r = |L(z − c)| − 1 and what the Jacobian reuses."""
    w = z - p[:3]
    Lm = _sym_from6(p[3:])
    vv = w @ Lm  # = L w (L symmetric)
    nv = np.sqrt(np.einsum("ij,ij->i", vv, vv))
    return nv - 1.0, (w, Lm, vv, nv)


def _geometric_jacobian(aux: tuple) -> np.ndarray:
    w, Lm, vv, nv = aux
    u = vv / np.maximum(nv, 1e-12)[:, None]
    J = np.empty((len(w), 9))
    J[:, :3] = -(u @ Lm)
    J[:, 3:6] = u * w
    J[:, 6] = u[:, 0] * w[:, 1] + u[:, 1] * w[:, 0]
    J[:, 7] = u[:, 0] * w[:, 2] + u[:, 2] * w[:, 0]
    J[:, 8] = u[:, 1] * w[:, 2] + u[:, 2] * w[:, 1]
    return J


def _huber(res: np.ndarray, mask: np.ndarray, huber_k: float, outlier_sigma: float) -> tuple[np.ndarray, np.ndarray]:
    """Huber IRLS weights (scale from the MAD over ``mask``) and the inlier mask."""
    sig = 1.4826 * np.median(np.abs(res[mask])) + 1e-12
    a = np.abs(res) / sig
    wt = np.where(a <= huber_k, 1.0, huber_k / np.maximum(a, 1e-12))
    inl = a < outlier_sigma
    return wt * inl, inl


def _levenberg_marquardt(z: np.ndarray, p: np.ndarray, keep: np.ndarray, max_iter: int, huber_k: float,
                         outlier_sigma: float) -> tuple[np.ndarray, np.ndarray, tuple, np.ndarray, np.ndarray, int]:
    """Robust LM on the geometric residual: (p, residual, aux, weights, inliers, iterations)."""
    res, aux = _geometric_residual(z, p)
    wt, inl = _huber(res, keep, huber_k, outlier_sigma)
    wt, inl = wt * keep, inl & keep
    lam = 1e-4
    it = 0
    for it in range(1, max_iter + 1):
        J = _geometric_jacobian(aux)
        cost = np.sum(wt * res * res)
        JW = J * wt[:, None]
        H = JW.T @ J
        g = JW.T @ res
        improved = False
        step = np.zeros(9)
        for _ in range(8):
            try:
                step = np.linalg.solve(H + lam * np.diag(np.diag(H) + 1e-12), -g)
            except np.linalg.LinAlgError:
                break
            res_new, aux_new = _geometric_residual(z, p + step)
            if np.all(np.isfinite(res_new)) and np.sum(wt * res_new * res_new) <= cost:
                p, res, aux = p + step, res_new, aux_new
                lam = max(lam / 10, 1e-9)
                improved = True
                break
            lam *= 10
        wt, inl = _huber(res, inl, huber_k, outlier_sigma)
        if not improved or np.max(np.abs(step)) < 1e-7:
            break
    return p, res, aux, wt, inl, it


def fit_ellipsoid_robust(mag_raw_mG: np.ndarray, field_strength_mG: float | None = None,
                         max_iter: int = 30, huber_k: float = 1.345, outlier_sigma: float = 5.0,
                         ) -> EllipsoidFit:
    """Robust batch ellipsoid fit (offsets + full symmetric C); see module docstring for the method.

    Non-finite rows are dropped first (``inliers`` indexes the finite rows only; use
    ``np.all(np.isfinite(m), 1)`` to map back).  Gross outliers are removed before the algebraic
    start (radius from the median centre beyond 8 robust sigmas), the LM loop uses Huber
    weights with hard rejection beyond ``outlier_sigma`` robust sigmas.
    """
    m = _finite_rows(mag_raw_mG)
    n = len(m)
    if n < 12:
        return _failed_fit(f"too few finite samples ({n})", n)
    screened = _screened_normalised(m)
    if screened is None:
        return _failed_fit("samples do not vary", n)
    keep, z, mu, s = screened
    p, cond, why = _algebraic_start(z[keep])
    if p is None:
        return _failed_fit(why, n, cond)
    p, res, aux, wt, inl, it = _levenberg_marquardt(z, p, keep, max_iter, huber_k, outlier_sigma)
    L = _sym_from6(p[3:])
    if np.linalg.eigvalsh(L)[0] <= 0:
        return _failed_fit("refined fit is not an ellipsoid", n, cond)
    b, C, F = _calibration_from_shape(mu + s * p[:3], L / s, field_strength_mG)
    rms = float(F * np.sqrt(np.mean(res[inl] ** 2))) if np.any(inl) else float("nan")
    cov = _offsets_covariance(_geometric_jacobian(aux), res, wt, s, 9)
    return EllipsoidFit(True, "", b, C, F, rms, inl, int(inl.sum()), cond, it, cov)


def _offsets_covariance(J: np.ndarray, res: np.ndarray, wt: np.ndarray, scale: float, n_params: int) -> np.ndarray:
    """σ²(JᵀWJ)⁻¹ restricted to the centre (first 3 parameters, normalised units) times scale²."""
    dof = max(float(np.sum(wt > 0)) - n_params, 1.0)
    sigma2 = float(np.sum(wt * res * res) / dof)
    try:
        cov = np.linalg.inv((J * wt[:, None]).T @ J)[:3, :3] * sigma2 * scale * scale
    except np.linalg.LinAlgError:
        cov = np.full((3, 3), np.inf)
    return cov if np.all(np.isfinite(cov)) else np.full((3, 3), np.inf)


def fit_sphere_robust(mag_raw_mG: np.ndarray, max_iter: int = 30, huber_k: float = 1.345,
                      outlier_sigma: float = 5.0) -> EllipsoidFit:
    """Robust sphere fit (offsets + radius, 4 parameters): the model for sparse windows (a 1–4 Hz
    telemetry dance of 20–60 samples), as ArduPilot's calibrator runs a sphere fit before its
    ellipsoid fit (CompassCalibrator::run_sphere_fit).  Start: linear LS |m|² = 2m·c + k; then
    Gauss–Newton on |m − c| − R with Huber weights and rejection beyond ``outlier_sigma``.
    Returns an EllipsoidFit with matrix = I and field_strength_mG = R."""
    m = _finite_rows(mag_raw_mG)
    n = len(m)
    if n < 8:
        return _failed_fit(f"too few finite samples ({n})", n)
    mu = m.mean(axis=0)
    sc = float(np.sqrt(np.mean(np.sum((m - mu) ** 2, axis=1))))
    if not np.isfinite(sc) or sc <= 0:
        return _failed_fit("samples do not vary", n)
    z = (m - mu) / sc
    A = np.column_stack([2 * z, np.ones(n)])
    ev = np.linalg.eigvalsh(A.T @ A)
    cond = float(np.sqrt(ev[-1] / ev[0])) if ev[0] > 0 else float("inf")
    sol, *_ = np.linalg.lstsq(A, np.sum(z * z, axis=1), rcond=None)
    c = sol[:3]
    R = float(np.sqrt(max(sol[3] + c @ c, 1e-12)))
    wt = np.ones(n)
    inl = np.ones(n, bool)
    it = 0
    for it in range(1, max_iter + 1):
        d = z - c
        nd = np.maximum(np.linalg.norm(d, axis=1), 1e-12)
        res = nd - R
        sig = 1.4826 * np.median(np.abs(res[inl])) + 1e-12
        a = np.abs(res) / sig
        inl = a < outlier_sigma
        wt = np.where(a <= huber_k, 1.0, huber_k / np.maximum(a, 1e-12)) * inl
        J = np.column_stack([-d / nd[:, None], -np.ones(n)])
        try:
            step = np.linalg.solve((J * wt[:, None]).T @ J, -(J * wt[:, None]).T @ res)
        except np.linalg.LinAlgError:
            return _failed_fit("sphere fit is singular", n, cond)
        c, R = c + step[:3], R + step[3]
        if np.max(np.abs(step)) < 1e-9:
            break
    d = z - c
    nd = np.maximum(np.linalg.norm(d, axis=1), 1e-12)
    res = nd - R
    J = np.column_stack([-d / nd[:, None], -np.ones(n)])
    if not (np.isfinite(R) and R > 0):
        return _failed_fit("sphere fit diverged", n, cond)
    rms = float(sc * np.sqrt(np.mean(res[inl] ** 2))) if np.any(inl) else float("nan")
    cov = _offsets_covariance(J, res, wt, sc, 4)
    return EllipsoidFit(True, "", mu + sc * c, np.eye(3), sc * R, rms, inl, int(inl.sum()), cond, it, cov)
