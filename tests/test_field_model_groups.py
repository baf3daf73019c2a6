"""Issue 29 (review speed): the field model's fits solved in lockstep (estimators.field_model_groups)
give what the straightforward solve gives on each problem's own rows, and the residual's per-row
terms (estimators.field_model.model_terms) are the model's: the yaw-free residual is the smallest
over the heading, its Jacobian the projected derivative."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from estimators import field_model as fm
from estimators.field_model_groups import solve_groups
from estimators.wmm_fit import WmmFitSettings, _options, _with_flight_wide_errors, _with_jackknife

pytestmark = pytest.mark.filterwarnings("error")

RTOL = 1e-9          # the sums over rows add in another order: equal to rounding, not bit for bit


def _flight(n: int = 700, seed: int = 3, weighted: bool = False, per_row_field: bool = False) -> fm.FieldData:
    """A simulated flight: tilts, every heading, soft iron, offsets, a motor field, 3 mG noise and a
    few outliers (so that the Huber weights and the outlier flags matter)."""
    rng = np.random.default_rng(seed)
    t = np.arange(n) / 5.0
    roll, pitch = 0.25 * np.sin(t / 3.0), 0.2 * np.cos(t / 4.3)
    yaw = np.mod(0.2 * t + 0.3 * np.sin(t / 2.0), 2 * np.pi)
    H = np.array([230.0, 25.0, 440.0])
    if per_row_field:
        H = H + np.column_stack([np.linspace(0, 4, n), np.linspace(0, -2, n), np.linspace(0, 3, n)])
    truth = fm.nominal_params(offsets_mG=[35.0, -50.0, 15.0])
    truth[3:9] = [1.04, 0.97, 1.02, 0.02, -0.015, 0.01]
    truth[9:12] = [1.2, -0.7, 1.8]
    x = np.abs(np.sin(t / 6.0)) * 12.0
    clean = fm.FieldData(np.zeros((n, 3)), roll, pitch, yaw, x, H)
    m = -fm.residuals(truth, clean, "vector") + rng.normal(0.0, 3.0, (n, 3))
    m[rng.choice(n, n // 40, replace=False)] += rng.normal(0.0, 60.0, (n // 40, 3))
    w = rng.uniform(0.5, 1.5, n) if weighted else None
    return fm.FieldData(m, roll, pitch, yaw, x, H, None if w is None else w / w.mean())


def _opts(model: str, k: int) -> fm.SolverOptions:
    active = np.zeros(12, bool)
    active[:k] = True
    return replace(_options(model, active, WmmFitSettings()), max_iter=8)


def _start(data: fm.FieldData, model: str, k: int) -> np.ndarray:
    """A point near the solution, as the jackknife starts from the full fit's."""
    p0 = fm.nominal_params()
    return fm.solve(data, p0, p0, replace(_opts(model, k), max_iter=25)).params


@pytest.mark.parametrize("model,k,weighted", [("yaw_free", 6, False), ("yaw_free", 12, True),
                                              ("vector", 12, False), ("vector", 9, True)])
def test_lockstep_solves_equal_the_straightforward_solve_of_each_group(model, k, weighted):
    data = _flight(weighted=weighted)
    n = len(data.roll_rad)
    p0 = fm.nominal_params()
    opts = _opts(model, k)
    start = _start(data, model, k)
    blocks = np.minimum((np.arange(n) * 8) // n, 7)
    sector = (np.mod(data.yaw_rad, 2 * np.pi) / (2 * np.pi) * 12).astype(int) % 12
    for block in (blocks, sector):
        keep = np.asarray([block != g for g in np.unique(block)])
        got = solve_groups(data.rows(), start, p0, opts, keep, data.weight)
        for g, kp in enumerate(keep):
            ref = fm.solve(data.subset(kp), start, p0, opts)
            np.testing.assert_allclose(got.params[g], ref.params, rtol=RTOL, atol=1e-12)
            assert got.iterations[g] == ref.iterations and got.converged[g] == ref.converged
        assert np.ptp(got.params[:, :3], axis=0).max() > 0.01          # the groups did differ
    # a start of its own per problem, from far off (step halving, several iterations each)
    starts = start + np.random.default_rng(1).normal(0.0, 1.0, (5, 12)) * np.r_[[20.0] * 3, [0.02] * 6, [0.5] * 3]
    starts[:, k:] = start[k:]
    keep = np.random.default_rng(2).random((5, n)) > 0.2
    got = solve_groups(data.rows(), starts, p0, opts, keep, data.weight)
    for g in range(5):
        ref = fm.solve(data.subset(keep[g]), starts[g], p0, opts)
        np.testing.assert_allclose(got.params[g], ref.params, rtol=RTOL, atol=1e-12)
        assert got.iterations[g] == ref.iterations


@pytest.mark.parametrize("per_row_field", [False, True])
def test_lockstep_solves_of_stacked_fields_equal_one_solve_per_field(per_row_field):
    data = _flight(per_row_field=per_row_field)
    H = np.asarray(data.field_ned_mG, float)
    datas = [data] + [replace(data, field_ned_mG=H + d) for d in ([3.0, 0, 0], [0, -2.0, 0], [0, 0, 4.0])]
    p0 = fm.nominal_params()
    opts = _opts("yaw_free", 12)
    start = _start(data, "yaw_free", 12)
    got = solve_groups(fm.stack_rows(datas), start, p0, opts)
    for g, d in enumerate(datas):
        np.testing.assert_allclose(got.params[g], fm.solve(d, start, p0, opts).params, rtol=RTOL, atol=1e-12)


def test_the_jackknife_and_field_model_terms_equal_their_per_group_definitions():
    """wmm_fit's covariance terms against the straightforward loops they replace: one solve per
    deleted group (on the subset) and one per shifted field component."""
    s = WmmFitSettings()
    data = _flight()
    n = len(data.roll_rad)
    p0 = fm.nominal_params()
    active = np.r_[np.ones(9, bool), np.zeros(3, bool)]
    sol = fm.solve(data, p0, p0, _options("yaw_free", active, s))
    opts = replace(_options("yaw_free", active, s), max_iter=8)
    var = np.zeros(12)
    sector = (np.mod(data.yaw_rad, 2 * np.pi) / (2 * np.pi) * 12).astype(int) % 12
    for block in (np.minimum((np.arange(n) * 8) // n, 7), sector):
        groups = [g for g in np.unique(block) if (block == g).sum() >= max(10, n // 50)]
        P = np.asarray([fm.solve(data.subset(block != g), sol.params, p0, opts).params for g in groups])
        var = np.maximum(var, (len(P) - 1) / len(P) * np.sum((P - P.mean(axis=0)) ** 2, axis=0))
    sd = np.sqrt(np.diag(sol.covariance))
    scale = np.where(sd > 0, np.sqrt(np.maximum(1.0, var / np.where(sd > 0, sd ** 2, 1.0))), 1.0)
    jk = _with_jackknife(sol.covariance, data, sol, active, p0, "yaw_free", s)
    np.testing.assert_allclose(jk, sol.covariance * np.outer(scale, scale), rtol=RTOL, atol=0.0)
    assert np.any(scale > 1.0)                                            # the jackknife raised some
    base = fm.solve(data, sol.params, p0, opts).params
    S = np.zeros((12, 5))                      # the field's three 1σ shifts, then roll and pitch tilted
    for j, sd_j in enumerate(s.field_model_sd_mG):
        shifted = replace(data, field_ned_mG=np.asarray(data.field_ned_mG) + sd_j * np.eye(3)[j])
        S[:, j] = fm.solve(shifted, sol.params, p0, opts).params - base
    tilt = np.radians(s.attitude_tilt_sd_deg)
    S[:, 3] = fm.solve(replace(data, roll_rad=data.roll_rad + tilt), sol.params, p0, opts).params - base
    S[:, 4] = fm.solve(replace(data, pitch_rad=data.pitch_rad + tilt), sol.params, p0, opts).params - base
    got = _with_flight_wide_errors(sol.covariance, data, sol, active, p0, "yaw_free", s)
    np.testing.assert_allclose(got - sol.covariance, S @ S.T, rtol=1e-6, atol=1e-9 * np.abs(S @ S.T).max())


def test_the_yaw_free_residual_is_the_least_over_the_heading_and_its_jacobian_the_projected_derivative():
    """Independent of the closed form: |r| of the yaw-free model against the vector model's over a
    fine grid of headings (then refined), and the Jacobian against central differences."""
    data = _flight(n=200)
    p = _start(data, "yaw_free", 12) + np.r_[[5.0, -3.0, 2.0], [0.01] * 6, [0.2] * 3]
    r = fm.residuals(p, data, "yaw_free")
    n = len(r)

    def norm_at(yaw):
        return np.linalg.norm(fm.residuals(p, replace(data, yaw_rad=yaw), "vector"), axis=1)

    grid = np.linspace(-np.pi, np.pi, 3601)
    coarse = np.array([norm_at(np.full(n, y)) for y in grid])
    around = grid[np.argmin(coarse, axis=0)]
    best = np.min([norm_at(around + d) for d in np.linspace(-2e-3, 2e-3, 2001)], axis=0)
    e = np.linalg.norm(r, axis=1)
    assert np.all(e <= best + 1e-9)                             # never above any heading tried
    np.testing.assert_allclose(e, best, rtol=1e-7)             # and the fine grid comes that close
    r0, J = fm.residuals(p, data, "yaw_free", True)
    q_fd = np.zeros_like(J)
    for j in range(12):
        h = 1e-4 if j < 3 or j >= 9 else 1e-6
        dp = np.eye(12)[j] * h
        q_fd[:, :, j] = (fm.residuals(p + dp, data, "yaw_free") - fm.residuals(p - dp, data, "yaw_free")) / (2 * h)
    # the full derivative moves along q (the heading) too; projected off q it is Kaufman's Jacobian
    _, (_, _, q) = fm.model_terms(p[None, :], data.rows(), "yaw_free")
    qn = q[0].T
    proj = q_fd - qn[:, :, None] * np.einsum("nr,nrp->np", qn, q_fd)[:, None, :]
    np.testing.assert_allclose(proj, J, atol=1e-5 * np.abs(J).max())


def test_step_halving_and_giving_up_are_each_groups_own(monkeypatch):
    """A residual that is not finite outside a box of offsets (a trust region made up for the test)
    makes steps that leave it halve, and a point at its edge give up after 10 halvings: each group on
    its own, as the straightforward solve does."""
    import estimators.field_model_groups as fmg

    data = _flight()
    n = len(data.roll_rad)
    p0 = fm.nominal_params()
    opts = _opts("yaw_free", 12)
    start = _start(data, "yaw_free", 12)
    centre, half = start[:3] + np.array([15.0, 0.0, -15.0]), 10.0       # the solutions lie outside the box
    model_terms = fm.model_terms

    def boxed(P, rows, model):
        r, terms = model_terms(P, rows, model)
        out = np.max(np.abs(P[:, :3] - centre), axis=1) > half
        return np.where(out[:, None, None], np.nan, r), terms

    monkeypatch.setattr(fm, "model_terms", boxed)
    monkeypatch.setattr(fmg, "model_terms", boxed)
    starts = np.tile(start, (6, 1))
    starts[:, :3] = centre + np.random.default_rng(4).uniform(-8.0, 8.0, (6, 3))
    keep = (np.arange(n)[None, :] % 6) != np.arange(6)[:, None]
    got = solve_groups(data.rows(), starts, p0, opts, keep)
    gave_up = 0
    for g in range(6):
        ref = fm.solve(data.subset(keep[g]), starts[g], p0, opts)
        np.testing.assert_allclose(got.params[g], ref.params, rtol=RTOL, atol=1e-12)
        assert got.iterations[g] == ref.iterations and got.converged[g] == ref.converged
        gave_up += not ref.converged and ref.iterations < opts.max_iter
    assert np.all(np.max(np.abs(got.params[:, :3] - centre), axis=1) <= half)
    assert gave_up > 0                                                  # the giving-up path was taken
