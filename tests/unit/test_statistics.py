"""The shared statistics against analytic answers: V and log det R at a residual of known
covariance, Ljung-Box of white noise against its χ² law, lagged correlations against numpy,
speed regimes of a sinusoid and the start grids of effect parameters."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from ema_uq import statistics
from ema_uq.params import Parameter, ParameterSet


# --------------------------------------------------------------------------------------
# the likelihood
# --------------------------------------------------------------------------------------
def test_objective_at_a_known_covariance():
    # rows ±a e1, ±b e2: R = diag(a²/2, b²/2) exactly
    a, b = 3.0, 0.5
    e = np.array([[a, 0.0], [-a, 0.0], [0.0, b], [0.0, -b]])
    r = statistics.covariance(e)
    np.testing.assert_allclose(r, np.diag([a * a / 2, b * b / 2]), rtol=1e-15)
    logdet = statistics.log_det_r(r)
    assert logdet == pytest.approx(np.log(a * a * b * b / 4), rel=1e-14)
    assert statistics.objective(4, logdet) == pytest.approx(2.0 * np.log(a * a * b * b / 4), rel=1e-14)
    # one rig pseudo-measurement (nominal 2, σ 0.5) at θ = 3: + ½ (1 / 0.5)² = 2; the free
    # parameter without a rig value adds nothing
    params = ParameterSet((Parameter("k", "-", 2.0, prior_std=0.5), Parameter("c", "-", 1.0)))
    theta = np.array([3.0, 7.0])
    assert statistics.objective(4, logdet, theta, params) == pytest.approx(2.0 * np.log(a * a * b * b / 4) + 2.0)
    # restricted to the parameters ``index`` (values in that order): only c, no rig term
    assert statistics.objective(4, logdet, theta[[1]], params, [1]) == pytest.approx(2.0 * np.log(a * a * b * b / 4))
    # a batch of residual sets, and a singular R
    assert statistics.covariance(np.stack([e, 2 * e])).shape == (2, 2, 2)
    assert statistics.log_det_r(np.zeros((2, 2))) == np.inf


def test_log_det_r_is_inf_on_every_degenerate_r():
    rng = np.random.default_rng(3)
    e = rng.standard_normal((50, 2))
    good = statistics.covariance(e)
    duplicated = statistics.covariance(np.column_stack([e[:, 0], e[:, 0]]))   # exactly singular
    cases = [np.zeros((2, 2)), duplicated, np.full((2, 2), np.nan), np.array([[1.0, 2.0], [2.0, 1.0]]),
             np.diag([np.inf, 1.0])]
    for r in cases:
        assert statistics.log_det_r(r) == np.inf
    assert statistics.log_det_r(good) == pytest.approx(np.log(np.linalg.det(good)), rel=1e-12)
    # a batch: one value per R, the degenerate ones +inf
    batch = statistics.log_det_r(np.stack([good, *cases]))
    assert batch.shape == (len(cases) + 1,)
    assert batch[0] == pytest.approx(np.log(np.linalg.det(good)), rel=1e-12) and np.all(batch[1:] == np.inf)


def test_posterior_and_sensitivity_read_the_same_log_det_r():
    from types import SimpleNamespace

    from ema_uq.bayes.posterior import LogPosterior

    rng = np.random.default_rng(4)
    e = rng.standard_normal((40, 2))
    residuals = np.stack([e, np.column_stack([e[:, 0], e[:, 0]]), np.full_like(e, np.nan)])
    ll = LogPosterior.log_likelihood_of_residuals(SimpleNamespace(noise_sigma=None), residuals)
    expected = -0.5 * 40 * statistics.log_det_r(statistics.covariance(residuals))
    np.testing.assert_allclose(ll[0], expected[0], rtol=1e-14)
    assert ll[1] == -np.inf and ll[2] == -np.inf


# --------------------------------------------------------------------------------------
# whiteness
# --------------------------------------------------------------------------------------
def test_ljung_box_of_white_noise_follows_chi2():
    rng = np.random.default_rng(11)
    lags, n, runs = 10, 2000, 400
    q = np.array([statistics.ljung_box_statistic(rng.standard_normal(n), lags) for _ in range(runs)])
    # mean L and variance 2L of χ²_L, within 4 standard errors
    assert abs(q.mean() - lags) < 4 * np.sqrt(2 * lags / runs)
    assert abs(q.var() - 2 * lags) < 4 * np.sqrt((12 * lags + 8 * lags ** 2 / 1) / runs)
    # p-values uniform (Kolmogorov-Smirnov at 1 %)
    p = stats.chi2.sf(q, lags)
    assert stats.kstest(p, "uniform").pvalue > 0.01
    # a strongly correlated AR(1) series is rejected
    x = np.zeros(n)
    noise = rng.standard_normal(n)
    for k in range(1, n):
        x[k] = 0.8 * x[k - 1] + noise[k]
    assert statistics.ljung_box(x, lags) < 1e-10


def test_lagged_correlation_matches_numpy():
    rng = np.random.default_rng(12)
    a, b = rng.standard_normal(300), rng.standard_normal(300)
    lags = np.arange(-5, 6)
    an, bn = (a - a.mean()) / a.std(), (b - b.mean()) / b.std()
    full = np.correlate(an, bn, mode="full") / a.size           # index mid + l: Σ a_{k+l} b_k
    np.testing.assert_allclose(statistics.lagged_correlation(a, b, lags), full[a.size - 1 + lags], atol=1e-14)
    assert statistics.max_cross_correlation(a, b, 5) == pytest.approx(np.max(np.abs(full[a.size - 6: a.size + 5])))
    assert statistics.lagged_correlation(a, a, np.array([0]))[0] == pytest.approx(1.0)


# --------------------------------------------------------------------------------------
# regimes and start grids
# --------------------------------------------------------------------------------------
def test_speed_regimes_of_a_sinusoid():
    dt = 1e-3
    t = np.arange(0, 2.0, dt)
    v = np.sin(2 * np.pi * t)                               # peak 1, acceleration 2π cos
    masks = statistics.speed_regimes(v, dt, low_fraction=0.1, acceleration_fraction=0.5)
    # |sin| <= 0.1 for a fraction (2/π) arcsin(0.1) of the time; |cos| > 0.5 for 2/3 of it
    assert masks["low_speed"].mean() == pytest.approx(2 / np.pi * np.arcsin(0.1), abs=2e-3)
    assert masks["accelerating"].mean() == pytest.approx(2 / 3, abs=2e-3)
    assert not np.any(masks["forward"] & masks["backward"])
    np.testing.assert_array_equal(masks["moving"], masks["forward"] | masks["backward"])
    np.testing.assert_array_equal(masks["low_speed"], ~masks["moving"])


def test_start_values_and_grids():
    np.testing.assert_allclose(statistics.start_values(2.0, 0.0, 10.0), [0.6, 2.0, 6.0, 10.0])   # 20 clipped
    np.testing.assert_allclose(statistics.start_values(2.0, 0.0, 100.0, multiples=(0.3, 1.0, 3.0)), [0.6, 2.0, 6.0])
    np.testing.assert_array_equal(statistics.start_values(0.0, -1.0, 1.0), [0.0])
    phases = statistics.start_values(0.5, -np.pi, np.pi, phase=True)
    np.testing.assert_allclose(np.sort(np.mod(phases - 0.5, 2 * np.pi)), np.arange(4) * np.pi / 2, atol=1e-12)
    assert np.all((phases >= -np.pi) & (phases <= np.pi))
    centre = np.array([1.0, 2.0, 3.0])
    full = statistics.start_grid(centre, [1, 2], [np.array([1.0, 2.0]), np.array([3.0, 4.0, 5.0])])
    assert full.shape == (6, 3) and np.all(full[:, 0] == 1.0)
    assert {tuple(r[1:]) for r in full} == {(x, y) for x in (1.0, 2.0) for y in (3.0, 4.0, 5.0)}
    # more combinations than max_grid: one parameter at a time around the centre
    one = statistics.start_grid(centre, [1, 2], [np.array([1.0, 2.0]), np.array([3.0, 4.0, 5.0])], max_grid=5)
    assert {tuple(r) for r in one} == {(1.0, 1.0, 3.0), (1.0, 2.0, 3.0), (1.0, 2.0, 4.0), (1.0, 2.0, 5.0)}
