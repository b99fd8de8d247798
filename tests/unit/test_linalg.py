"""The matrix-product forms of the hot linear algebra equal the einsum forms they replace:
residual covariance, Fisher information, the posterior likelihoods and predictive noise, and
``FitProblem.predict`` without copies (contiguous channels, scattered channels, missing
samples, several experiments)."""
from __future__ import annotations

import warnings

import numpy as np
import pytest

from ema_uq import Measurement, deploy_retract, get_model, simulate_batch, statistics, synthesize
from ema_uq.bayes.posterior import LogPosterior
from ema_uq.identify import FitProblem


def test_covariance_equals_the_einsum_form():
    rng = np.random.default_rng(5)
    one = rng.standard_normal((3800, 4))
    batch = rng.standard_normal((7, 500, 3)) * [1.0, 1e-3, 1e3]
    np.testing.assert_allclose(statistics.covariance(one), np.einsum("ki,kj->ij", one, one) / 3800,
                               rtol=1e-12, atol=0)
    np.testing.assert_allclose(statistics.covariance(batch), np.einsum("ski,skj->sij", batch, batch) / 500,
                               rtol=1e-12, atol=1e-20)
    r = statistics.covariance(batch)
    np.testing.assert_array_equal(r, np.swapaxes(r, -1, -2))      # symmetric to the last bit


def test_a_diverged_trial_gives_an_infinite_objective_without_a_warning():
    residuals = np.full((200, 2), 1e200)                  # a trial simulation that blew up
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        r = statistics.covariance(residuals)
        assert statistics.log_det_r(r) == np.inf


def test_information_equals_the_three_operand_einsum():
    rng = np.random.default_rng(6)
    sens = rng.standard_normal((9, 800, 4)) * rng.uniform(0.1, 10, (9, 1, 1))
    a = rng.standard_normal((4, 4))
    r_inv = np.linalg.inv(a @ a.T + 4 * np.eye(4))
    reference = np.einsum("jkc,cd,lkd->jl", sens, r_inv, sens)
    info = statistics.information(sens, r_inv)
    assert info.shape == (9, 9)
    np.testing.assert_allclose(info, reference, rtol=1e-11, atol=1e-11 * np.abs(reference).max())


@pytest.fixture(scope="module")
def short():
    return synthesize("htls", deploy_retract().slice(0, 400), noise=0.02, seed=1)


def _reference_predict(problem: FitProblem, thetas: np.ndarray) -> np.ndarray:
    """The former copy path: simulate, then rows, then channels, concatenated."""
    parts = [simulate_batch(problem.model, thetas, b.time, b.inputs, constants=problem.constants)[:, b.rows]
             [:, :, problem.channel_index] for b in problem.blocks]
    return np.concatenate(parts, axis=1)


@pytest.mark.parametrize("channels", [None, ("Omega", "y1", "I_A"), ("y2", "Omega")])
def test_predict_equals_the_copying_form(short, channels):
    model = get_model("htls")
    values = short.values.copy()
    values[50:60, 0] = np.nan                                    # missing samples in one experiment
    holed = Measurement(short.concept, short.experiment, short.channels, values, short.attrs)
    thetas = model.parameters.nominal[None] * np.array([[1.0], [1.03]])
    for measurements in ([short], [holed], [short, holed]):
        problem = FitProblem(measurements, channels=channels)
        got = problem.predict(thetas)
        assert got.shape == (2, problem.n_samples, len(problem.channels))
        np.testing.assert_array_equal(got, _reference_predict(problem, thetas))
        np.testing.assert_array_equal(problem.residuals(thetas), problem.observed[None] - got)
    with pytest.raises(ValueError):
        problem.observed[0, 0] = 1.0                              # built once, shared: read-only


def test_posterior_likelihoods_equal_the_einsum_forms(short):
    problem = FitProblem([short], channels=("Omega", "y1", "I_A"))
    model = problem.model
    rng = np.random.default_rng(7)
    e = problem.residuals(model.parameters.nominal[None] * (1 + 0.02 * rng.standard_normal((4, 1))))
    e[2, 5, 1] = np.nan                                           # a diverged set: -inf
    n = e.shape[1]
    priors = []                                                  # the likelihood alone
    post = LogPosterior(problem, priors, model.parameters.nominal)
    ll = post.log_likelihood_of_residuals(e)
    with np.errstate(invalid="ignore"):
        sign, logdet = np.linalg.slogdet(np.einsum("ski,skj->sij", e, e) / n)
    ref = np.where((sign > 0) & np.isfinite(logdet), -0.5 * n * logdet, -np.inf)
    np.testing.assert_allclose(ll, ref, rtol=1e-12)
    assert ll[2] == -np.inf and np.all(np.isfinite(ll[[0, 1, 3]]))

    sigma = np.array([0.5, 2e-3, 0.1])
    known = LogPosterior(problem, priors, model.parameters.nominal, noise_sigma=sigma)
    ref = (-0.5 * np.sum((e / sigma) ** 2, axis=(1, 2)) - n * np.sum(np.log(sigma))
           - 0.5 * n * sigma.size * np.log(2 * np.pi))
    got = known.log_likelihood_of_residuals(e)
    np.testing.assert_allclose(got[[0, 1, 3]], ref[[0, 1, 3]], rtol=1e-12)
    assert got[2] == -np.inf
