"""Magnetometer calibration: seed 000 RLS ellipsoid, general robust ellipsoid, seed 004 misalignment.

Model (issue 3):  m_raw = A · m_body + b + noise.   Calibration:  m_cal = C · (m_raw − b) ≈ m_body.

Contents
--------
* ``RlsEllipsoidCalibrator`` — seed 000 §1.2: recursive least squares on the linear form
  y = a·c (eq. 3–5), c0 = [0 1 0 1 0 −H0²], P0 = 1000·I, per-sample update (step 3), parameters
  recovered by eq. (6).  Internally the field is divided by H0 so the prior P0 = 1000·I means
  exactly what it means in the seed (H0 = 1) whatever unit the caller uses.
  ``seed000_solve_batch`` is the vectorised, mathematically identical information form
  (RLS with prior (c0, P0) after N samples == (P0⁻¹ + AᵀA)⁻¹ (P0⁻¹c0 + Aᵀy)), over many runs at once.
  ``refine_seed000_batch`` adds Gauss–Newton steps on the geometric residual (removes the
  algebraic form's errors-in-variables scale bias).
* ``RlsGeneralEllipsoid`` — seed 004 step 1 (claim 3, step 12): RLS on the 9-parameter general
  quadric  v·[x², y², z², 2xy, 2xz, 2yz, 2x, 2y, 2z] = 1  (offsets + full symmetric matrix:
  sensitivity, non-orthogonality and soft iron together).
* ``fit_ellipsoid_robust`` (in estimators.ellipsoid_fit, re-exported here) — batch refinement.  Choice and why: an algebraic least-squares quadric
  fit (closed form, no start value needed, in centred/normalised coordinates for conditioning)
  gives the start; it is biased (the algebraic distance weights points unevenly), so it is refined
  by Levenberg–Marquardt on the geometric residual r = |L(m − b)| − 1 (the physical quantity the
  issue asks to minimise, |m_cal| − F), with Huber IRLS weights (scale from the MAD) so spikes do not
  pull the fit, and hard rejection of points beyond ``outlier_sigma`` robust sigmas.  9 parameters,
  ~5–10 iterations, a few ms for 10,000 samples.
* ``fit_sphere_robust`` (estimators.ellipsoid_fit) — offsets + radius only, for sparse windows (a telemetry-rate dance).
  Both robust fits return the offsets covariance (σ²(JᵀWJ)⁻¹ of the last step), the quality
  measure of estimators.cal_windows.
* ``estimate_misalignment`` — seed 004 step 2 (claim 4): sensor-to-body rotation from attitude
  (roll, pitch, yaw) and the expected Earth field in NED.  Small-angle linear LS (the seed's
  C = I + [φ×]) and the general rotation (Wahba's problem solved by SVD / Kabsch).
* ``combine_calibration`` — seed 004 step 3 (claims 5–7): C_total = R_mis · C, M_b = b,
  M_cal = C_total · (M_0 − M_b).
* ``fit_ellipse_2d`` — the horizontal-plane 2-D ellipse baseline of seed 000 table 1 (benchmark only).
* Quality: ``sphere_coverage``, ``rotation_progress_deg``, ``planarity_ratio``.

Units: field in mG (any consistent unit works), angles rad unless the name says deg.
Frames: NED navigation, FRD body.  Pure numpy, no I/O.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from estimators.ellipsoid_fit import (EllipsoidFit, _calibration_from_shape, _finite_rows, _quadric_design,
                                     _quadric_to_center_shape, _sym_sqrt, fit_ellipsoid_robust, fit_sphere_robust)
from estimators.rotations import dcm_body_to_ned, rotation_to_vector_deg

__all__ = [
    "RlsEllipsoidCalibrator", "seed000_solve_batch", "seed000_params_from_c", "refine_seed000_batch",
    "RlsGeneralEllipsoid", "EllipsoidFit", "fit_ellipsoid_robust", "fit_sphere_robust",
    "MisalignmentFit", "estimate_misalignment", "combine_calibration",
    "apply_calibration", "polar_decomposition",
    "fit_ellipse_2d", "sphere_coverage", "coverage_cells", "rotation_progress_deg",
    "planarity_ratio",
]


# ---------------------------------------------------------------------------------------------
# Seed 000: RLS on y = a·c (6 parameters)
# ---------------------------------------------------------------------------------------------

def _seed000_regressors(h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Seed 000 eq. (4)-(5) for normalised field h (..., 3): y = −hx², a = [−2hx, hy², −2hy, hz², −2hz, 1]."""
    hx, hy, hz = h[..., 0], h[..., 1], h[..., 2]
    a = np.stack([-2 * hx, hy * hy, -2 * hy, hz * hz, -2 * hz, np.ones_like(hx)], axis=-1)
    return a, -hx * hx


def seed000_params_from_c(c: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Seed 000 eq. (6) inverted, for c (..., 6) in units of H0 (H0 = 1).

    c = [δx, (sx/sy)², δy(sx/sy)², (sx/sz)², δz(sx/sz)², δx² + δy²(sx/sy)² + δz²(sx/sz)² − H0²sx²].
    Returns (offsets (..., 3) in H0 units, scales (..., 3), valid (...) bool).
    """
    c = np.asarray(c, dtype=float)
    ry, rz = c[..., 1], c[..., 3]
    with np.errstate(divide="ignore", invalid="ignore"):
        dx, dy, dz = c[..., 0], c[..., 2] / ry, c[..., 4] / rz
        sx2 = dx * dx + ry * dy * dy + rz * dz * dz - c[..., 5]
        sx = np.sqrt(sx2)
        sy, sz = sx / np.sqrt(ry), sx / np.sqrt(rz)
    off = np.stack([dx, dy, dz], axis=-1)
    sc = np.stack([sx, sy, sz], axis=-1)
    valid = (ry > 0) & (rz > 0) & (sx2 > 0) & np.all(np.isfinite(off), -1) & np.all(np.isfinite(sc), -1)
    return off, sc, valid


def seed000_solve_batch(mag_raw: np.ndarray, field_strength: float, p0: float = 1000.0,
                        c0: np.ndarray | None = None, p0_inv: np.ndarray | None = None
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Seed 000 RLS result after all samples, in closed information form, for one or many runs.

    mag_raw: (N, 3) or (R, N, 3), same unit as ``field_strength`` (H0).  Exactly equal (up to
    round-off) to running step 3 sample by sample from c0 = [0 1 0 1 0 −1], P0 = p0·I:
        P_N = (P0⁻¹ + Σ aᵀa)⁻¹,  c_N = P_N (P0⁻¹ c0 + Σ aᵀ y).
    Returns (offsets (…,3) in the input unit, scales (…,3), c (…,6) normalised, P (…,6,6)).
    Rows with non-finite values are given zero weight.
    """
    m = np.asarray(mag_raw, dtype=float)
    single = m.ndim == 2
    if single:
        m = m[None]
    h = m / float(field_strength)
    good = np.all(np.isfinite(h), axis=-1)
    h = np.where(good[..., None], h, 0.0)
    a, y = _seed000_regressors(h)
    a = a * good[..., None]
    y = y * good
    if c0 is None:
        c0 = np.array([0.0, 1.0, 0.0, 1.0, 0.0, -1.0])
    if p0_inv is None:
        p0_inv = np.eye(6) / p0
    info = p0_inv + np.matmul(a.transpose(0, 2, 1), a)
    rhs = (p0_inv @ c0) + np.einsum("rni,rn->ri", a, y)
    c = np.linalg.solve(info, rhs[..., None])[..., 0]
    P = np.linalg.inv(info)
    off, sc, _ = seed000_params_from_c(c)
    off = off * field_strength
    if single:
        return off[0], sc[0], c[0], P[0]
    return off, sc, c, P


def refine_seed000_batch(mag_raw: np.ndarray, offsets: np.ndarray, scales: np.ndarray, field_strength: float,
                         iterations: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """Gauss–Newton refinement of the seed 000 model on the geometric residual |(m − δ) ⊘ s| − H0.

    The algebraic form y = a·c has noisy regressors (hy², hz²), so its scale estimates carry an
    errors-in-variables bias of a few σ²/H0² (≈ 7e-4 for σ = 0.01, see benchmarks/calibration.py);
    the geometric residual removes it; the small lengthening of |w| by tangential noise (≈ σ²)
    is corrected with the residual variance.  Start from the RLS result.
    mag_raw (N, 3) or (R, N, 3); offsets/scales (3,) or (R, 3).  Non-finite rows get zero weight.
    """
    m = np.asarray(mag_raw, dtype=float)
    single = m.ndim == 2
    if single:
        m, offsets, scales = m[None], np.asarray(offsets)[None], np.asarray(scales)[None]
    h = m / field_strength
    good = np.all(np.isfinite(h), axis=-1)
    h = np.where(good[..., None], h, 0.0)
    d = np.array(offsets, dtype=float) / field_strength
    s = np.array(scales, dtype=float)
    for _ in range(iterations):
        w = (h - d[:, None]) / s[:, None]
        n = np.linalg.norm(w, axis=-1)
        u = w / np.maximum(n, 1e-12)[..., None]
        J = np.concatenate([-u / s[:, None], -u * w / s[:, None]], axis=-1) * good[..., None]
        # Noise in the two tangential directions lengthens |w| by ≈ σ_r² (σ_r: radial residual sd):
        # aim at 1 + σ_r² so the scales come out unbiased.
        cnt = np.maximum(good.sum(-1), 1)
        dev = (n - 1.0) * good
        var = np.sum(dev * dev, -1) / cnt - (np.sum(dev, -1) / cnt) ** 2
        r = (n - 1.0 - var[:, None]) * good
        H = np.matmul(J.transpose(0, 2, 1), J) + 1e-12 * np.eye(6)
        step = np.linalg.solve(H, -np.einsum("rni,rn->ri", J, r)[..., None])[..., 0]
        d, s = d + step[:, :3], s + step[:, 3:]
    d = d * field_strength
    return (d[0], s[0]) if single else (d, s)


class RlsEllipsoidCalibrator:
    """Seed 000 §1.2 recursive least-squares ellipsoid calibration (offsets + per-axis scale).

    ``update(mag_raw_mG)`` is step 3:  K = P a / (1 + aᵀ P a),  P ← (I − K aᵀ) P,  c ← c + K (y − a·c).
    ``offsets_mG`` and ``scales`` come from eq. (6); the calibrated field is (m − δ)/s, of
    magnitude H0.  Until the solution is valid (enough rotation) they stay at the prior
    (zero offsets, unit scales) and ``valid`` is False.  Non-finite samples are ignored.
    """

    def __init__(self, field_strength_mG: float = 500.0, p0: float = 1000.0) -> None:
        """field_strength_mG: H0 of eq. (2), the local field (WMM when known; ~500 mG typical)."""
        self.field_strength_mG = float(field_strength_mG)
        self.c = np.array([0.0, 1.0, 0.0, 1.0, 0.0, -1.0])      # normalised: H0 = 1
        self.P = np.eye(6) * float(p0)
        self.n_samples = 0

    def update(self, mag_raw_mG) -> None:
        hx, hy, hz = (float(v) / self.field_strength_mG for v in mag_raw_mG)
        if not (np.isfinite(hx) and np.isfinite(hy) and np.isfinite(hz)):
            return
        a = np.array([-2 * hx, hy * hy, -2 * hy, hz * hz, -2 * hz, 1.0])
        Pa = self.P @ a
        k = Pa / (1.0 + a @ Pa)
        self.c += k * (-hx * hx - a @ self.c)
        self.P -= np.outer(k, Pa)
        self.n_samples += 1

    def update_batch(self, mag_raw_mG: np.ndarray) -> None:
        """Absorb many samples at once (information form; identical to repeated ``update``)."""
        m = _finite_rows(mag_raw_mG)
        if len(m) == 0:
            return
        p_inv = np.linalg.inv(self.P)
        _, _, c, P = seed000_solve_batch(m, self.field_strength_mG, c0=self.c, p0_inv=p_inv)
        self.c, self.P = c, P
        self.n_samples += len(m)

    def _params(self):
        off, sc, ok = seed000_params_from_c(self.c)
        return off * self.field_strength_mG, sc, bool(ok)

    @property
    def valid(self) -> bool:
        return self._params()[2]

    @property
    def offsets_mG(self) -> np.ndarray:
        off, _, ok = self._params()
        return off if ok else np.zeros(3)

    @property
    def scales(self) -> np.ndarray:
        _, sc, ok = self._params()
        return sc if ok else np.ones(3)

    @property
    def matrix(self) -> np.ndarray:
        """C = diag(1/s): m_cal = C (m − δ)."""
        return np.diag(1.0 / self.scales)


# ---------------------------------------------------------------------------------------------
# General ellipsoid (offsets + full symmetric matrix)
# ---------------------------------------------------------------------------------------------

class RlsGeneralEllipsoid:
    """Seed 004 step 1: recursive LS on the general quadric (9 parameters), per-sample update.

    Samples are divided by ``field_scale_mG`` (a rough field magnitude) for conditioning; the
    form with right-hand side 1 needs the raw origin off the ellipsoid surface (true unless the
    hard-iron offset equals the field strength).  ``solution()`` gives (offsets_mG, C) with
    C symmetric, det C = 1 (or |m_cal| = field_strength_mG when given), or None while the quadric
    is not yet an ellipsoid.
    """

    def __init__(self, field_scale_mG: float = 500.0, p0: float = 1000.0) -> None:
        self.scale = float(field_scale_mG)
        self.v = np.array([1.0, 1.0, 1.0, 0, 0, 0, 0, 0, 0])   # prior: unit sphere at the origin
        self.P = np.eye(9) * float(p0)
        self.n_samples = 0

    def update(self, mag_raw_mG) -> None:
        z = np.asarray(mag_raw_mG, dtype=float).reshape(1, 3) / self.scale
        if not np.all(np.isfinite(z)):
            return
        a = _quadric_design(z)[0]
        Pa = self.P @ a
        k = Pa / (1.0 + a @ Pa)
        self.v += k * (1.0 - a @ self.v)
        self.P -= np.outer(k, Pa)
        self.n_samples += 1

    def solution(self, field_strength_mG: float | None = None) -> tuple[np.ndarray, np.ndarray] | None:
        cs = _quadric_to_center_shape(self.v)
        if cs is None:
            return None
        c, Q = cs
        b, C, _ = _calibration_from_shape(c * self.scale, _sym_sqrt(Q) / self.scale, field_strength_mG)
        return b, C


def apply_calibration(mag_raw_mG: np.ndarray, offsets_mG: np.ndarray, matrix: np.ndarray) -> np.ndarray:
    """m_cal = C (m_raw − b), row-wise for (N, 3) or a single (3,) vector (seed 004 claim 7)."""
    m = np.asarray(mag_raw_mG, dtype=float)
    return (m - np.asarray(offsets_mG, float)) @ np.asarray(matrix, float).T


# ---------------------------------------------------------------------------------------------
# Seed 004 step 2 and 3: misalignment, combination
# ---------------------------------------------------------------------------------------------

def polar_decomposition(C: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """C = R · S with R a proper rotation and S symmetric (S = Rᵀ C; positive definite when det C > 0).

    The order matches PX4 (corrected = R · S · (raw − off)) and keeps S equal to the symmetric
    (attitude-free) ellipsoid solution, so S → DIA/ODI or CAL_MAGn_*SCALE/ODIAG, R → misalignment.
    """
    U, sv, Vt = np.linalg.svd(np.asarray(C, float))
    d = np.sign(np.linalg.det(U @ Vt)) or 1.0
    D = np.diag([1.0, 1.0, d])
    R = U @ D @ Vt
    S = Vt.T @ D @ np.diag(sv) @ Vt
    return R, (S + S.T) / 2


@dataclass(frozen=True)
class MisalignmentFit:
    """Sensor-to-body rotation R (body = R · sensor) and its angles; seed 004 step 2."""
    ok: bool
    reason: str
    rotation: np.ndarray          # general (Wahba/SVD) solution
    angles_deg: np.ndarray        # rotation vector of ``rotation`` (≈ φx, φy, φz)
    small_angle_deg: np.ndarray   # linear small-angle LS solution (seed 004 claim 4)
    residual_deg: float           # RMS angle between R·m and the expected direction
    observability: float          # sqrt(λmid/λmax) of Σ h hᵀ of expected directions (0: one direction)
    angles_sd_deg: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))  # block-robust standard error
    chi2: float = float("nan")    # Wald statistic φᵀ V⁻¹ φ of the small-angle rotation (3 degrees of freedom)
    lag_s: float = float("nan")   # median timing offset of the attitude estimated with it (t_s given)
    significant: bool = False     # chi2 beyond MISALIGNMENT_CHI2 and the angle beyond MISALIGNMENT_MIN_DEG


MISALIGNMENT_CHI2 = 16.27         # χ²(3) at p = 0.001: the rotation is beyond the fit's own noise
MISALIGNMENT_MIN_DEG = 0.25       # and large enough to matter (heading targets are 0.5°)
MISALIGNMENT_BLOCKS = 30          # time blocks of the block-robust covariance (at least 2 s each)


def _misalignment_test(m: np.ndarray, h: np.ndarray, t_s: np.ndarray | None
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Small-angle LS h_i − m_i = −[m_i×] φ − δ_b ḣ_i over K contiguous time blocks b (at least 2 s,
    ``MISALIGNMENT_BLOCKS`` of the span): φ the misalignment, δ_b each block's timing offset of the
    attitude (when t_s is given; ḣ the expected direction's rate) — a link's timing drifts, a
    mounting rotation does not, and a turn about one axis cannot tell the two apart, so only a
    rotation common to turns about different axes counts.  Block-robust ("cluster sandwich")
    covariance V = (AᵀA)⁺ (Σ_b g_b g_bᵀ) (AᵀA)⁺ · K/(K−1), g_b = Σ_{i∈b} A_iᵀ e_i, so residuals
    correlated in time (timing jitter, a slow disturbance) count as the noise they are.
    Returns (φ rad, its 3×3 covariance, δ per sample s (zeros without t_s))."""
    n = len(m)
    mx = np.zeros((n, 3, 3))
    mx[:, 0, 1], mx[:, 0, 2], mx[:, 1, 2] = -m[:, 2], m[:, 1], -m[:, 0]
    mx[:, 1, 0], mx[:, 2, 0], mx[:, 2, 1] = m[:, 2], -m[:, 1], m[:, 0]
    if t_s is not None and t_s[-1] > t_s[0]:
        width = max(2.0, (t_s[-1] - t_s[0]) / MISALIGNMENT_BLOCKS)
        block = np.floor((t_s - t_s[0]) / width).astype(int)
    else:
        block = np.arange(n) * MISALIGNMENT_BLOCKS // max(n, 1)
    _, inv = np.unique(block, return_inverse=True)
    k = int(inv.max()) + 1
    p = 3 + (k if t_s is not None else 0)
    A = np.zeros((n, 3, p))
    A[:, :, :3] = -mx
    if t_s is not None:
        hdot = np.gradient(h, axis=0) / np.maximum(np.gradient(t_s), 1e-3)[:, None]
        A[np.arange(n), :, 3 + inv] = -hdot
    y = h - m
    A2 = A.reshape(-1, p)
    bread = np.linalg.pinv(A2.T @ A2)
    x = bread @ (A2.T @ y.ravel())
    e = y - np.einsum("nij,j->ni", A, x)
    gb = np.zeros((k, p))
    np.add.at(gb, inv, np.einsum("nij,ni->nj", A, e))        # g_b = Σ A_iᵀ e_i
    V = bread @ (gb.T @ gb) @ bread * (k / max(k - 1, 1))
    lag = x[3 + inv] if t_s is not None else np.zeros(n)
    return x[:3], V[:3, :3], lag


def estimate_misalignment(mag_cal_mG: np.ndarray, roll_rad: np.ndarray, pitch_rad: np.ndarray,
                          yaw_rad: np.ndarray, field_ned_mG: np.ndarray,
                          min_observability: float = 0.05, t_s: np.ndarray | None = None) -> MisalignmentFit:
    """Seed 004 step 2: find R with R·m_cal,i ≈ C_n^b(att_i)·H_n (directions only, so the field
    strength scale of C does not matter).

    General solution: Wahba's problem, B = Σ h_i m_iᵀ, B = U Σ Vᵀ, R = U diag(1, 1, det UVᵀ) Vᵀ.
    Small-angle solution: R ≈ I + [φ×], h_i − m_i = −[m_i×] φ, linear LS (what the seed's RLS
    converges to).  Needs rotation about at least two axes; otherwise ``ok`` is False.
    Note: if the attitude yaw was itself derived from this magnetometer, the rotation about the
    vertical is only as good as that yaw.

    Significance (``_misalignment_test``): with ``t_s`` (s, increasing) a timing offset of the
    attitude per time block is fitted beside φ (a field sample lagging its attitude by δ during a
    turn at ω looks like a rotation ω δ about the turn's axis: on ArduPilot SITL's exact attitude a
    session .tlog's compass lags its ATTITUDE by ~0.1 s, arrival-timed RAW_IMU by a varying amount,
    a false 1–3° "misalignment"), and the Wahba solution is taken on the lag-corrected directions.
    ``significant`` only when the Wald χ² of φ against its block-robust covariance exceeds
    ``MISALIGNMENT_CHI2`` and |φ| exceeds ``MISALIGNMENT_MIN_DEG``.
    """
    m = np.asarray(mag_cal_mG, float).reshape(-1, 3)
    att = np.stack([np.asarray(roll_rad, float).ravel(), np.asarray(pitch_rad, float).ravel(),
                    np.asarray(yaw_rad, float).ravel()], 1)
    good = np.all(np.isfinite(m), 1) & np.all(np.isfinite(att), 1) & (np.linalg.norm(m, axis=1) > 0)
    nan3 = np.full(3, np.nan)
    if good.sum() < 10 or not np.all(np.isfinite(field_ned_mG)):
        return MisalignmentFit(False, "too few samples with attitude", np.eye(3), nan3, nan3, float("nan"), 0.0)
    m = m[good] / np.linalg.norm(m[good], axis=1, keepdims=True)
    Hn = np.asarray(field_ned_mG, float)
    Hn = Hn / np.linalg.norm(Hn)
    Cbn = dcm_body_to_ned(att[good, 0], att[good, 1], att[good, 2])
    h = np.einsum("nji,j->ni", Cbn, Hn)          # C_n^b H_n = (C_b^n)ᵀ H_n
    ev = np.linalg.eigvalsh(h.T @ h / len(h))   # uncentred: Wahba needs non-parallel directions
    obs = float(np.sqrt(max(ev[1], 0) / max(ev[-1], 1e-15)))  # 2 non-parallel directions suffice
    ts = None
    if t_s is not None:
        ts = np.asarray(t_s, float).ravel()[good]
        if len(ts) != len(m) or not np.all(np.isfinite(ts)) or np.any(np.diff(ts) < 0):
            ts = None
    phi_t, V, lags = _misalignment_test(m, h, ts)
    lag = float(np.median(lags)) if ts is not None else float("nan")
    if ts is not None:
        dt = np.maximum(np.gradient(ts), 1e-3)
        h = h + lags[:, None] * np.gradient(h, axis=0) / dt[:, None]     # the directions at the field's own times
        h /= np.linalg.norm(h, axis=1, keepdims=True)
    with np.errstate(invalid="ignore"):
        sd = np.degrees(np.sqrt(np.clip(np.diag(V), 0, None)))
        try:
            chi2 = float(phi_t @ np.linalg.solve(V, phi_t))
        except np.linalg.LinAlgError:
            chi2 = float("nan")
    B = h.T @ m
    U, _, Vt = np.linalg.svd(B)
    R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt)) or 1.0]) @ Vt
    mx = np.zeros((len(m), 3, 3))
    mx[:, 0, 1], mx[:, 0, 2], mx[:, 1, 2] = -m[:, 2], m[:, 1], -m[:, 0]
    mx[:, 1, 0], mx[:, 2, 0], mx[:, 2, 1] = m[:, 2], -m[:, 1], m[:, 0]
    phi, *_ = np.linalg.lstsq(-mx.reshape(-1, 3), (h - m).ravel(), rcond=None)
    err = np.degrees(np.arccos(np.clip(np.sum((m @ R.T) * h, 1), -1, 1)))
    resid = float(np.sqrt(np.mean(err ** 2)))
    ok = obs >= min_observability
    angles = rotation_to_vector_deg(R)
    significant = bool(ok and np.isfinite(chi2) and chi2 > MISALIGNMENT_CHI2
                       and float(np.linalg.norm(angles)) > MISALIGNMENT_MIN_DEG)
    return MisalignmentFit(ok, "" if ok else "attitude varied about one axis only (rotation unobservable)",
                           R, angles, np.degrees(phi), resid, obs, sd, chi2, lag, significant)


def combine_calibration(offsets_mG: np.ndarray, matrix: np.ndarray, misalignment_rotation: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Seed 004 step 3 (claims 5–7): C_total = R_mis · C,  M_b = b;  M_cal = C_total (M_0 − M_b)."""
    return np.asarray(misalignment_rotation, float) @ np.asarray(matrix, float), np.asarray(offsets_mG, float).copy()


# ---------------------------------------------------------------------------------------------
# 2-D ellipse baseline (seed 000 table 1)
# ---------------------------------------------------------------------------------------------

def fit_ellipse_2d(mag_raw_mG: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Horizontal-plane ellipse calibration (the seed's comparison method, 4 of 6 parameters).

    Fits (x − δx)²/sx² + (y − δy)²/sy² = const to the X/Y components of samples taken while
    turning level, by linear LS on −x² = [−2x, y², −2y, 1]·c (seed 000 eq. 3–6 in 2-D).
    Returns (offsets (3,) with z offset 0, C = diag(1, sx/sy, 1)) for ``apply_calibration``;
    Z is left uncalibrated.
    """
    m = _finite_rows(mag_raw_mG)
    x, y = m[:, 0], m[:, 1]
    s = float(np.sqrt(np.mean(x * x + y * y))) or 1.0
    x, y = x / s, y / s
    A = np.stack([-2 * x, y * y, -2 * y, np.ones_like(x)], 1)
    c, *_ = np.linalg.lstsq(A, -x * x, rcond=None)
    r = c[1]
    off = np.array([c[0] * s, c[2] / r * s, 0.0])
    return off, np.diag([1.0, np.sqrt(r), 1.0])


# ---------------------------------------------------------------------------------------------
# Quality
# ---------------------------------------------------------------------------------------------

def coverage_cells(vectors: np.ndarray, n_bands: int = 10, n_sectors: int = 10) -> np.ndarray:
    """Visited mask of n_bands·n_sectors equal-area cells on the unit sphere (bands equal in z,
    sectors equal in longitude: equal area by Archimedes).  Returns bool (n_bands*n_sectors,)."""
    v = _finite_rows(vectors)
    nrm = np.linalg.norm(v, axis=1)
    v = v[nrm > 0] / nrm[nrm > 0, None]
    visited = np.zeros(n_bands * n_sectors, bool)
    if len(v) == 0:
        return visited
    band = np.clip(((v[:, 2] + 1) / 2 * n_bands).astype(int), 0, n_bands - 1)
    lon = np.arctan2(v[:, 1], v[:, 0]) + np.pi
    sector = np.clip((lon / (2 * np.pi) * n_sectors).astype(int), 0, n_sectors - 1)
    visited[band * n_sectors + sector] = True
    return visited


def sphere_coverage(vectors: np.ndarray, n_bands: int = 10, n_sectors: int = 10) -> float:
    """Fraction (0..1) of ~100 equal-area direction cells visited by the vectors (e.g. calibrated field)."""
    return float(coverage_cells(vectors, n_bands, n_sectors).mean())


def rotation_progress_deg(gyro_rad_s: np.ndarray, t_s: np.ndarray) -> np.ndarray:
    """Degrees turned about body X, Y, Z: ∫|ω_k| dt per axis (trapezoid; NaN rows and gaps > 1 s skipped)."""
    g = np.asarray(gyro_rad_s, float).reshape(-1, 3)
    t = np.asarray(t_s, float).ravel()
    if len(t) < 2:
        return np.zeros(3)
    dt = np.diff(t)
    seg = np.abs(g[1:]) + np.abs(g[:-1])
    ok = np.isfinite(dt) & (dt > 0) & (dt < 1.0) & np.all(np.isfinite(seg), 1)
    return np.degrees(np.sum(0.5 * seg[ok] * dt[ok, None], axis=0))


def planarity_ratio(mag_raw_mG: np.ndarray) -> float:
    """sqrt(λmin/λmax) of the sample covariance: ~0 for a single rotation plane, ~1 for a full sphere."""
    m = _finite_rows(mag_raw_mG)
    if len(m) < 4:
        return 0.0
    ev = np.linalg.eigvalsh(np.cov(m.T))
    return float(np.sqrt(max(ev[0], 0.0) / ev[-1])) if ev[-1] > 0 else 0.0
