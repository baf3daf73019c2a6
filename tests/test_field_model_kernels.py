"""The compiled covariance steps of the field-vector test's filter against the Kalman equations
written with numpy matrices (random covariances, attitudes and signals)."""
import numpy as np
import pytest

from estimators.field_model_kernels import forget_covariance, kalman_update, observe_covariance


SD = np.r_[0.05, 0.002, [5.0] * 3, [50.0] * 3, [3.0] * 3]      # the filter's prior sds (rad, rad/s, mG, mG/A)


def _spd(rng, n=11):
    """A covariance with the filter's scales and random correlations (well conditioned)."""
    a = rng.normal(size=(n, 2 * n))
    corr = a @ a.T
    d = np.sqrt(np.diag(corr))
    return corr / np.outer(d, d) * np.outer(SD, SD)


def _h(c_bt, hn, he, xt):
    """H (3 × 11): columns ε, β, h, b, f (the filter's state order)."""
    c = np.asarray(c_bt)
    a = c[:, 1] * hn - c[:, 0] * he
    return np.hstack([a[:, None], np.zeros((3, 1)), c, np.eye(3), xt * np.eye(3)])


def _rotation(rng):
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    return q * np.sign(np.linalg.det(q))


@pytest.mark.parametrize("seed", range(5))
def test_forget_is_f_p_ft_plus_q(seed):
    rng = np.random.default_rng(seed)
    P = _spd(rng)
    walk = np.r_[0.0, 0.0, rng.uniform(1e-8, 1e-3, 9)]
    dt, scale, q0, q1 = 0.02, 16.0 * 0.02, 1e-6, 1e-10
    F = np.eye(11)
    F[0, 1] = dt
    want = F @ P @ F.T + np.diag(np.r_[q0, q1, walk[2:] * scale])
    forget_covariance(P, walk, dt, scale, q0, q1)
    np.testing.assert_allclose(P, want, rtol=1e-12, atol=1e-12 * np.abs(want).max())


@pytest.mark.parametrize("seed", range(5))
def test_observe_and_update_are_the_kalman_equations(seed):
    rng = np.random.default_rng(seed)
    P = _spd(rng)
    c = _rotation(rng)
    hn, he, xt = rng.uniform(100, 400), rng.uniform(-50, 50), rng.uniform(-10, 30)
    H = _h(c, hn, he, xt)
    pht, hph, a = observe_covariance(P, tuple(tuple(r) for r in c), hn, he, xt)
    np.testing.assert_allclose(pht, P @ H.T, rtol=1e-11)
    np.testing.assert_allclose(np.reshape(hph, (3, 3)), H @ P @ H.T, rtol=1e-11)
    np.testing.assert_allclose(a, H[:, 0], rtol=1e-12)

    extra = rng.normal(size=(3, 3))
    extra = tuple((extra @ extra.T).ravel())
    r, k = 16.0, 50.0
    for nu in (rng.normal(size=3) * 2.0, rng.normal(size=3) * 500.0):      # within the clip, and clipped
        S = H @ P @ H.T + np.reshape(extra, (3, 3)) * k + r * k * np.eye(3)
        C = H @ P @ H.T + r * np.eye(3)
        d = np.sqrt(nu @ np.linalg.solve(C, nu))
        nu_used = nu * min(1.0, 3.0 / d)
        K = P @ H.T @ np.linalg.inv(S)
        want_p = P - K @ H @ P
        want_p = 0.5 * (want_p + want_p.T)
        Pk = P.copy()
        step = kalman_update(Pk, P @ H.T, tuple(np.ravel(H @ P @ H.T)), extra, k, tuple(nu), r, r * k, 3.0)
        np.testing.assert_allclose(step, K @ nu_used, rtol=1e-9, atol=1e-9 * np.abs(K @ nu_used).max())
        scale = np.outer(SD, SD)              # each element against its prior's σᵢσⱼ
        assert np.max(np.abs(Pk - want_p) / scale) < 1e-10
        assert np.array_equal(Pk, Pk.T)


def test_the_fused_step_is_forget_observe_update():
    """``FieldModelFilter.step`` (one compiled call) against ``forget``, ``observe`` and ``update``
    in turn: the same predictions, uncertainties, states and covariances over 300 steps, learning
    and not, with and without the signal's lag term."""
    from estimators.residual_trackers import FieldModelFilter
    rng = np.random.default_rng(7)
    fused, parts = FieldModelFilter([220.0, 10.0, 380.0]), FieldModelFilter([220.0, 10.0, 380.0])
    for i in range(300):
        c = tuple(tuple(r) for r in _rotation(rng).T)
        xt, dt, sigma, rate = rng.uniform(0, 20), rng.choice([0.0, 0.02, 0.1]), rng.uniform(4, 9), rng.normal(0, 0.3)
        m = tuple(float(v) for v in np.asarray(c) @ [220.0, 10.0, 380.0] + rng.normal(0, 8, 3))
        learn, lag = bool(i % 4), (list(rng.uniform(0, 5, 9)) if i % 3 == 0 else None)
        pred, hph = fused.step(dt, sigma, rate, c, xt, m, learn, 3.0, lag)
        parts.forget(dt, sigma, rate)
        obs = parts.observe(c, xt)
        if learn:
            parts.update(obs, m, dt, sigma, 3.0, lag)
        np.testing.assert_allclose(pred, obs[0], rtol=1e-13)
        np.testing.assert_allclose(hph, obs[1], rtol=1e-13)
        np.testing.assert_allclose(fused.th, parts.th, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(fused.P, parts.P, rtol=1e-12, atol=1e-15)
    assert np.max(np.abs(np.array(fused.th[5:8]))) > 1.0          # it learned an offset on the way
