"""Many related field-model fits solved in lockstep: the jackknife's delete-one-group refits and the
refits with the reference field shifted (estimators.wmm_fit), issue 29.

Each problem g is the robust Gauss–Newton of ``estimators.field_model.solve`` on its own rows
(``keep[g]``) of one set of rows, or on rows of its own (``stack_rows``: the same samples, another
reference field).  The problems are stacked on a leading axis and iterated together: one residual
and one Jacobian evaluation per iteration for all of them (``field_model.model_terms``), while each
keeps what ``solve`` keeps per problem: its Huber weights and MAD scale (the median over its own
inlier rows), its outlier flags, its step halving (up to 10 halvings against its own cost) and its
convergence test (max |step| < 1e-4), and stops when ``solve`` would stop.  A row a problem does
not keep has weight 0 and is left out of its median.  Only the parameters are returned (what the
jackknife and the field-model term use); ``solve`` stays the one-problem solver with the
covariance, and the reference this is tested against (tests/test_field_model_groups.py: the same
parameters as ``solve`` on each problem's rows, within rounding: the sums over rows add in
another order; so where ``solve``'s own test of a step, cost ≤ cost₀(1 + 1e-12), sits within
rounding of its threshold the two may take different branches).  Units: mG, rad.  Pure numpy.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from estimators.field_model import FieldRows, SolverOptions, model_jacobian, model_terms

__all__ = ["GroupSolutions", "solve_groups"]


@dataclass(frozen=True)
class GroupSolutions:
    params: np.ndarray          # (G,12)
    iterations: np.ndarray      # (G,) as Solution.iterations of ``solve``
    converged: np.ndarray       # (G,) bool


def _masked_median(s: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Median of each row of s (G,N) over its ``valid`` entries, as np.median computes it (the middle
    value, or the mean of the two middle ones); 0 where none is valid."""
    n = valid.sum(axis=1)
    srt = np.sort(np.where(valid, s, np.inf), axis=1)
    lo = np.take_along_axis(srt, np.maximum((n - 1) // 2, 0)[:, None], 1)[:, 0]
    hi = np.take_along_axis(srt, np.maximum(n // 2, 0)[:, None], 1)[:, 0]
    return np.where(n > 0, (lo + hi) / 2.0, 0.0)


def _weights(r: np.ndarray, mask: np.ndarray, huber_k: float,
             outlier_sigma: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``field_model._weights`` per problem: r (G,3,N), mask (G,N) the rows of each median."""
    s = np.sqrt(r[:, 0] ** 2 + r[:, 1] ** 2 + r[:, 2] ** 2) / np.sqrt(2.0)
    sigma = np.maximum(_masked_median(s, mask) / 0.9, 1e-9)
    a = s / sigma[:, None]
    w = np.where(a <= huber_k, 1.0, huber_k / np.maximum(a, 1e-12))
    inl = a < outlier_sigma
    return w * inl, inl, sigma


def _cost(r: np.ndarray, w: np.ndarray, p_act: np.ndarray, p0_act: np.ndarray, lam: np.ndarray,
          sigma: np.ndarray) -> np.ndarray:
    """``field_model._cost`` per problem -> (G,)."""
    return (np.sum(w[:, None, :] * r * r, axis=(1, 2)) / sigma ** 2
            + np.sum(lam * (p_act - p0_act) ** 2, axis=1))


def _steps(J: np.ndarray, r: np.ndarray, w: np.ndarray, sigma: np.ndarray, d_act: np.ndarray,
           lam: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gauss–Newton steps (G,k) from (JᵀWJ/σ² + Λ) δ = −(JᵀWr/σ² + Λ(p − p₀)), J (G,k,3,N) scaled by
    √w in place (one array of its size: the memory peak); ok (G,) False where the normal matrix is
    singular (``solve`` stops there)."""
    G, k = J.shape[:2]
    sw = np.tile(np.sqrt(w), (1, 3))[:, None, :]
    Jf = J.reshape(G, k, -1)
    Jf *= sw
    s2 = (sigma ** 2)[:, None]
    Hm = Jf @ Jf.transpose(0, 2, 1) / s2[:, :, None] + np.diag(lam)
    g = (Jf @ (r.reshape(G, 1, -1) * sw).transpose(0, 2, 1))[:, :, 0] / s2 + lam * d_act
    ok = np.ones(G, bool)
    try:
        return -np.linalg.solve(Hm, g[:, :, None])[:, :, 0], ok
    except np.linalg.LinAlgError:
        step = np.zeros((G, k))
        for i in range(G):
            try:
                step[i] = -np.linalg.solve(Hm[i], g[i])
            except np.linalg.LinAlgError:
                ok[i] = False
        return step, ok


def _at(idx: np.ndarray, G: int):
    """An index of the problems ``idx``: a slice (a view, no copy) when it is all G of them in order."""
    return slice(None) if len(idx) == G else idx


def solve_groups(rows: FieldRows, p_init: np.ndarray, p0: np.ndarray, opts: SolverOptions,
                 keep: np.ndarray | None = None, weight: np.ndarray | None = None,
                 groups: int | None = None) -> GroupSolutions:
    """The parameters ``solve`` reaches on each of G problems, iterated in lockstep (module docstring).

    rows: shared (3,N) rows, or (G,3,N) per problem (``stack_rows``); keep (G,N) bool: each problem's
    rows (None: all); weight (N,) prior per-row weights (None: 1); p_init (12,) or (G,12); p0 (12,);
    groups: G when neither keep nor the rows say it."""
    G = len(keep) if keep is not None else rows.u0_mG.shape[0] if rows.u0_mG.ndim == 3 else int(groups or 1)
    N = rows.mag_mG.shape[-1]
    keep = np.ones((G, N), bool) if keep is None else np.asarray(keep, bool)
    act = np.asarray(opts.active, bool)
    cols = np.flatnonzero(act)
    lam = np.where(np.isfinite(opts.prior_sd), 1.0 / np.square(opts.prior_sd), 0.0)[act]
    P = np.array(np.broadcast_to(np.asarray(p_init, float), (G, 12)))
    if rows.u0_mG.ndim == 2 and np.all(P == P[:1]):      # one start, shared rows: one evaluation
        r1, t1 = model_terms(P[:1], rows, opts.model)
        r, terms = np.repeat(r1, G, axis=0), [None if t is None else np.repeat(t, G, axis=0) for t in t1]
    else:
        r, terms = model_terms(P, rows, opts.model)
        terms = list(terms)                              # (A, g, q) per problem: its Jacobian's terms
    prior_w = np.ones(N) if weight is None else np.asarray(weight, float)
    w, inl, sigma = _weights(r, keep, opts.huber_k, opts.outlier_sigma)
    w = w * prior_w * keep
    running = np.ones(G, bool)
    iterations, converged = np.zeros(G, int), np.zeros(G, bool)
    for it in range(1, opts.max_iter + 1):
        idx = np.flatnonzero(running)
        if len(idx) == 0:
            break
        iterations[idx] = it
        at = _at(idx, G)
        J = model_jacobian(rows.take(at), [None if t is None else t[at] for t in terms], cols)
        step, solvable = _steps(J, r[at], w[at], sigma[at], P[at][:, act] - p0[act], lam)
        del J
        running[idx[~solvable]] = False
        idx, step = idx[solvable], step[solvable]
        at = _at(idx, G)
        cost0 = _cost(r[at], w[at], P[at][:, act], p0[act], lam, sigma[at])
        pend = np.arange(len(idx))                       # positions in idx still halving
        for _ in range(10):
            g = _at(idx[pend], G)
            trial = P[g].copy()
            trial[:, act] += step[pend]
            r_t, terms_t = model_terms(trial, rows.take(g), opts.model)
            fine = np.all(np.isfinite(r_t) | ~keep[g][:, None, :], axis=(1, 2))
            ok = fine & (_cost(np.where(fine[:, None, None], r_t, 0.0), w[g], trial[:, act], p0[act], lam,
                               sigma[g]) <= cost0[pend] * (1 + 1e-12))
            if ok.any():
                acc = idx[pend[ok]]
                P[acc], r[acc] = trial[ok], r_t[ok]
                small = np.max(np.abs(step[pend[ok]]), axis=1) < 1e-4
                converged[acc[small]] = True
                running[acc[small]] = False
                # the Jacobian's terms and the weights at the new point, for the problems that iterate again
                more = ~small & (it < opts.max_iter)
                if more.any():
                    a = _at(acc[more], G)
                    sel = np.flatnonzero(ok)[more]
                    for t, t_new in zip(terms, terms_t):
                        if t is not None:
                            t[a] = t_new[sel]
                    w_a, inl[a], sigma[a] = _weights(r[a], inl[a] & keep[a], opts.huber_k, opts.outlier_sigma)
                    w[a] = w_a * prior_w * keep[a]
            pend = pend[~ok]
            if len(pend) == 0:
                break
            step[pend] = step[pend] / 2
        running[idx[pend]] = False                       # no step lowered the cost: stop, as solve does
    return GroupSolutions(P, iterations, converged)
