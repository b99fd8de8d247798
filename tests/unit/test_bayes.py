"""Bayesian sampling: seeded reproducibility, HDF5 resume, InferenceData layout and NetCDF
round trip, the log posterior by hand, bad input and the ``sample`` verb.

A small HT/LS problem keeps every run to about a second: the first 3 s of deploy-retract
(the motor starts at 1 s), channels Omega, y1, I_A, three free parameters, 2 ensembles of 8
walkers for a few dozen steps.
"""
from __future__ import annotations

import subprocess
import sys

import emcee
import numpy as np
import pytest

from ema_uq import bayes, deploy_retract, get_model, io, synthesize
from ema_uq.bayes import BayesError, LogPosterior, PosteriorResult, SamplerSettings
from ema_uq.identify import FitProblem, covariance, estimate
from ema_uq.report import bayes_figures

CHANNELS = ("Omega", "y1", "I_A")
FREE = ["J", "B_TS1", "C_TS1"]
FAST = SamplerSettings(n_walkers=8, n_ensembles=2, max_steps=40, check_every=20, n_predictive=10)


@pytest.fixture(scope="module")
def model():
    return get_model("htls")


@pytest.fixture(scope="module")
def data():
    return synthesize("htls", deploy_retract().slice(0, 300), noise=0.02, seed=5)


@pytest.fixture(scope="module")
def problem(model, data):
    return FitProblem([data], parameters=model.parameters.freeing_only(FREE), channels=CHANNELS)


@pytest.fixture(scope="module")
def fit(problem, model):
    return estimate(problem, start=model.parameters.nominal)


@pytest.fixture(scope="module")
def result(problem, fit):
    return bayes.sample(problem, fit, settings=FAST, seed=11)


def backend_chain(path, k=0):
    return emcee.backends.HDFBackend(str(path), name=f"ensemble_{k}", read_only=True).get_chain()


# --------------------------------------------------------------------------------------
# reproducibility and resume
# --------------------------------------------------------------------------------------
def test_same_seed_gives_the_same_chain_and_another_seed_does_not(problem, fit, result):
    again = bayes.sample(problem, fit, settings=FAST, seed=11)
    np.testing.assert_array_equal(result.draws(), again.draws())
    np.testing.assert_array_equal(result.idata.sample_stats["lp"].values, again.idata.sample_stats["lp"].values)
    np.testing.assert_array_equal(result.idata.posterior_predictive["Omega"].values,
                                  again.idata.posterior_predictive["Omega"].values)
    other = bayes.sample(problem, fit, settings=FAST, seed=12)
    assert not np.array_equal(result.draws(), other.draws())
    assert result.seed == 11 and result.attrs["ema_uq_version"]


def test_a_stopped_run_resumes_to_the_uninterrupted_chain(problem, fit, tmp_path):
    full = bayes.sample(problem, fit, settings=FAST, seed=4, backend=tmp_path / "full.h5")
    path = tmp_path / "resume.h5"
    stopped = SamplerSettings(**{**FAST.__dict__, "max_steps": 13})
    bayes.sample(problem, fit, settings=stopped, seed=4, backend=path, predictive=False)
    first = [backend_chain(path, k) for k in range(2)]
    assert all(c.shape == (13, 8, 3) for c in first)
    resumed = bayes.sample(problem, fit, settings=FAST, seed=4, backend=path)
    for k in range(2):
        chain = backend_chain(path, k)
        assert chain.shape == (40, 8, 3)
        np.testing.assert_array_equal(chain[:13], first[k])            # the stored part is kept
        np.testing.assert_array_equal(chain, backend_chain(tmp_path / "full.h5", k))
    np.testing.assert_array_equal(resumed.draws(), full.draws())


def test_a_killed_run_resumes_where_it_stopped(problem, fit, tmp_path, monkeypatch):
    """Interrupted inside a step of the first ensemble's second chunk: ensembles end at
    different lengths; the rerun completes both to the uninterrupted chains."""
    full = bayes.sample(problem, fit, settings=FAST, seed=8, backend=tmp_path / "full.h5", predictive=False)
    original = LogPosterior.log_likelihood
    calls = {"n": 0}

    def dying(self, free):
        calls["n"] += 1
        if calls["n"] > 90:
            raise KeyboardInterrupt("killed")
        return original(self, free)

    path = tmp_path / "killed.h5"
    monkeypatch.setattr(LogPosterior, "log_likelihood", dying)
    with pytest.raises(KeyboardInterrupt):
        bayes.sample(problem, fit, settings=FAST, seed=8, backend=path)
    monkeypatch.setattr(LogPosterior, "log_likelihood", original)
    lengths = [backend_chain(path, k).shape[0] for k in range(2)]
    assert 0 < min(lengths) < 40 and lengths[0] != lengths[1]
    partial = [backend_chain(path, k) for k in range(2)]
    resumed = bayes.sample(problem, fit, settings=FAST, seed=8, backend=path, predictive=False)
    for k in range(2):
        chain = backend_chain(path, k)
        np.testing.assert_array_equal(chain[: lengths[k]], partial[k])
        np.testing.assert_array_equal(chain, backend_chain(tmp_path / "full.h5", k))
    np.testing.assert_array_equal(resumed.draws(), full.draws())


def test_a_backend_of_another_run_is_refused(problem, fit, tmp_path):
    path = tmp_path / "run.h5"
    bayes.sample(problem, fit, settings=SamplerSettings(**{**FAST.__dict__, "max_steps": 5}), seed=1,
                 backend=path, predictive=False)
    with pytest.raises(BayesError, match="different data or settings"):
        bayes.sample(problem, fit, settings=FAST, seed=2, backend=path)
    (tmp_path / "junk.h5").write_text("not hdf5")
    with pytest.raises(BayesError, match="not an HDF5 file"):
        bayes.sample(problem, fit, settings=FAST, seed=2, backend=tmp_path / "junk.h5")


def test_a_stale_backend_is_moved_aside_on_request_and_the_run_starts_afresh(problem, fit, tmp_path):
    import h5py

    path = tmp_path / "run.h5"
    short = SamplerSettings(**{**FAST.__dict__, "max_steps": 5})
    bayes.sample(problem, fit, settings=short, seed=1, backend=path, predictive=False)
    old = backend_chain(path)
    lines = []
    res = bayes.sample(problem, fit, settings=FAST, seed=2, backend=path, predictive=False,
                       replace_stale_backend=True, progress=lines.append)
    aside = tmp_path / "run.stale.h5"
    assert "moved it to" in lines[0] and str(aside) in lines[0]
    np.testing.assert_array_equal(backend_chain(aside), old)          # the old chains are kept, not lost
    assert res.attrs["stale_backend_moved_to"] == str(aside)
    with h5py.File(path, "r") as f:
        assert f.attrs["ema_uq_signature"] == res.attrs["signature"]
    fresh = bayes.sample(problem, fit, settings=FAST, seed=2, predictive=False)
    np.testing.assert_array_equal(res.draws(), fresh.draws())          # nothing carried over
    # the same run again is resumed, not moved aside
    again = bayes.sample(problem, fit, settings=FAST, seed=2, backend=path, predictive=False,
                         replace_stale_backend=True)
    np.testing.assert_array_equal(again.draws(), res.draws())
    np.testing.assert_array_equal(backend_chain(aside), old)


def test_the_likelihood_integrator_can_be_chosen(problem, fit):
    rk4 = bayes.LogPosterior(problem, bayes.build_priors(problem), fit.estimate)
    res = bayes.sample(problem, fit, settings=SamplerSettings(**{**FAST.__dict__, "integrator": "dopri5"}), seed=11,
                       predictive=False)
    assert res.attrs["integrator"] == "dopri5" and problem.model.integrator == "rk4"
    # both integrators are converged far below the noise: the log posterior at the stored
    # draws agrees to well under the 0.1 nats that would matter to an acceptance decision
    draws = res.draws().reshape(-1, len(res.names))[::37]
    lp = res.idata.sample_stats["lp"].values.reshape(-1)[::37]
    np.testing.assert_allclose(rk4(draws), lp, atol=1e-2)
    assert not np.array_equal(rk4(draws), lp)                          # it did use the other integrator
    with pytest.raises(BayesError, match="unknown integrator 'euler'; choose rk4, dopri5 or hybrid"):
        bayes.sample(problem, fit, settings=SamplerSettings(**{**FAST.__dict__, "integrator": "euler"}))
    import dataclasses

    own = dataclasses.replace(problem, model=dataclasses.replace(problem.model, batch_simulator=lambda *a: None))
    with pytest.raises(BayesError, match="has its own simulator: its integrator cannot be chosen"):
        bayes.sample(own, fit, settings=SamplerSettings(**{**FAST.__dict__, "integrator": "dopri5"}))


# --------------------------------------------------------------------------------------
# the InferenceData
# --------------------------------------------------------------------------------------
def test_inference_data_groups_and_netcdf_round_trip(result, problem, tmp_path):
    idata = result.idata
    for group in ("posterior", "sample_stats", "log_likelihood", "observed_data", "posterior_predictive"):
        assert group in idata.groups()
    assert idata.posterior["J"].shape[0] == FAST.n_ensembles           # one chain per ensemble
    assert set(idata.posterior.data_vars) == set(FREE)
    assert {"lp", "accepted", "acceptance_rate", "log_prior"} <= set(idata.sample_stats.data_vars)
    assert 0.05 < float(idata.sample_stats["acceptance_rate"].mean()) < 0.95
    np.testing.assert_array_equal(idata.observed_data["y1"].values, problem.observed[:, 1])
    assert idata.posterior_predictive["I_A"].shape == (1, 10, problem.n_samples)
    np.testing.assert_allclose(idata.log_likelihood["z"] + idata.sample_stats["log_prior"],
                               idata.sample_stats["lp"], rtol=0, atol=1e-9)
    # every draw comes after burn-in, thinned: ceil((n_steps - burn) / thin) per walker, the
    # 8 walkers of an ensemble one after the other
    n_kept = -(-(result.n_steps - result.burn_in) // result.thin)
    assert idata.posterior.sizes["draw"] == 8 * n_kept
    np.testing.assert_array_equal(idata.posterior["walker"], np.repeat(np.arange(8), n_kept))
    np.testing.assert_array_equal(idata.posterior["step"][:n_kept],
                                  result.burn_in + result.thin * np.arange(n_kept))
    assert idata.sample_stats["acceptance_rate"].shape == (FAST.n_ensembles, 8)

    path = result.to_netcdf(tmp_path / "post.nc")
    back = PosteriorResult.from_netcdf(path)
    assert set(back.idata.groups()) == set(idata.groups())
    np.testing.assert_array_equal(back.draws(), result.draws())
    assert back.names == tuple(FREE) and back.seed == 11 and back.n_steps == result.n_steps
    np.testing.assert_array_equal(back.tau, result.tau)

    table = back.summary()
    for col in ("mean", "sd", "hdi_5%", "hdi_95%", "r_hat", "ess_bulk", "ess_tail", "mcse_mean", "ml", "crb_sd"):
        assert col in table.columns
    assert list(table.index) == FREE
    assert "Posterior: htls" in back.report()


def test_figures(result):
    import matplotlib.pyplot as plt

    for fig in (bayes_figures.trace(result), bayes_figures.pair(result, max_params=3),
                bayes_figures.predictive_bands(result)):
        assert fig.axes
        plt.close(fig)
    with pytest.raises(ValueError, match="no posterior for k_n"):
        bayes_figures.pair(result, names=["J", "k_n"])
    # the corner plot's choice: the parameters of the strongest correlations, the rest named
    shown, left_out = bayes_figures.corner_parameters(result, max_params=2)
    assert len(shown) == 2 and sorted(shown + left_out) == sorted(result.names)
    draws = np.column_stack([result.idata.posterior[n].values.ravel() for n in result.names])
    rho = np.abs(np.corrcoef(draws, rowvar=False) - np.eye(len(result.names)))
    i, j = np.unravel_index(np.argmax(rho), rho.shape)
    assert set(shown) == {result.names[i], result.names[j]}


# --------------------------------------------------------------------------------------
# the log posterior by hand
# --------------------------------------------------------------------------------------
def test_log_posterior_matches_a_hand_computation(model, data):
    params = model.parameters.freeing_only(["J", "k_n", "p_ACE"])
    problem = FitProblem([data], parameters=params, channels=CHANNELS)
    priors = bayes.build_priors(problem, {"J": ("lognormal", np.log(0.05), 0.3)})
    base = params.nominal
    post = LogPosterior(problem, priors, base)
    free = np.array([[0.055, 1.21, 2050.0], [0.045, 1.19, 1980.0]])

    def hand(x, sigma=None):
        theta = base.copy()
        theta[problem.free_index] = x
        e = problem.residuals(theta[None])[0]
        n = e.shape[0]
        if sigma is None:
            r = sum(np.outer(ek, ek) for ek in e) / n
            ll = -0.5 * n * np.log(np.linalg.det(r))
        else:
            ll = sum(-0.5 * (ek[c] / sigma[c]) ** 2 - np.log(sigma[c]) - 0.5 * np.log(2 * np.pi)
                     for ek in e for c in range(len(sigma)))
        lj = np.log(x[0])
        prior = (-0.5 * ((lj - np.log(0.05)) / 0.3) ** 2 - lj - np.log(0.3 * np.sqrt(2 * np.pi))
                 - 0.5 * ((x[2] - 2000.0) / 40.0) ** 2 - np.log(40.0 * np.sqrt(2 * np.pi)))  # rig σ = 2 %
        return ll + prior, ll

    got = post(free)
    for i in range(2):
        want, ll = hand(free[i])
        assert got[i] == pytest.approx(want, rel=1e-10)
        # the det R likelihood is the ML objective's likelihood part
        e = problem.residuals(problem.full_vectors(free[i], base))[0]
        assert ll == pytest.approx(-0.5 * problem.n_samples * np.linalg.slogdet(covariance(e))[1], rel=1e-12)

    sigma = np.array([0.3, 1e-4, 0.2])
    known = LogPosterior(problem, priors, base, noise_sigma=sigma)
    assert known(free[:1])[0] == pytest.approx(hand(free[0], sigma)[0], rel=1e-10)

    # outside the support: -inf without a simulation
    before = post.n_simulations
    out = post(np.array([[-0.01, 1.2, 2000.0], [0.05, 1.2, 0.5]]))   # J < 0, p_ACE below its bound 2
    assert np.all(out == -np.inf) and post.n_simulations == before


def test_known_sigma_run_records_its_sigma(problem, fit):
    res = bayes.sample(problem, fit, noise_sigma="known", settings=FAST, seed=3, predictive=False)
    sigma = np.array(res._json_attr("noise_sigma"))
    e = problem.residuals(fit.estimate[None])[0]
    np.testing.assert_allclose(sigma, np.sqrt(np.mean(e ** 2, axis=0)))
    assert res.attrs["likelihood"].startswith("Gaussian")


# --------------------------------------------------------------------------------------
# moves and the stopping rule
# --------------------------------------------------------------------------------------
def test_student_t_proposal_matches_scipy():
    from scipy import stats

    rng = np.random.default_rng(2)
    a = rng.standard_normal((4, 4))
    scale = a @ a.T + 4 * np.eye(4)
    center = rng.standard_normal(4)
    q = bayes.StudentTProposal(center, np.linalg.cholesky(scale), 10.0)
    x = center + 3 * rng.standard_normal((6, 4))
    np.testing.assert_allclose(q.logpdf(x), stats.multivariate_t(center, scale, df=10.0).logpdf(x), rtol=1e-12)
    draws = q.draw(np.random.RandomState(0), 200_000)
    np.testing.assert_allclose(np.cov(draws.T), scale * 10 / 8, rtol=0, atol=0.03 * np.max(np.diag(scale)))
    # squared Mahalanobis distance / d of a t_ν draw is F(d, ν) distributed
    z = np.linalg.solve(np.linalg.cholesky(scale), (draws[:20_000] - center).T)
    assert stats.kstest(np.sum(z * z, axis=0) / 4, stats.f(4, 10).cdf).pvalue > 1e-3


def test_defensive_mixture_density_and_draws():
    from scipy import stats

    rng = np.random.default_rng(3)
    a = rng.standard_normal((3, 3))
    scale = a @ a.T + 3 * np.eye(3)
    center = rng.standard_normal(3)
    chol = np.linalg.cholesky(scale)
    q = bayes.DefensiveMixture(bayes.StudentTProposal(center, chol, 20.0),
                               bayes.StudentTProposal(center, 2.0 * chol, 20.0), 0.2)
    x = center + 4 * rng.standard_normal((5, 3))
    want = np.log(0.8 * stats.multivariate_t(center, scale, df=20.0).pdf(x)
                  + 0.2 * stats.multivariate_t(center, 4.0 * scale, df=20.0).pdf(x))
    np.testing.assert_allclose(q.logpdf(x), want, rtol=1e-12)
    draws = q.draw(np.random.RandomState(1), 200_000)
    # covariance of the mixture: (0.8 + 0.2 * 4) * ν/(ν-2) * S
    np.testing.assert_allclose(np.cov(draws.T), 1.6 * scale * 20 / 18, rtol=0, atol=0.04 * np.max(np.diag(scale)))


def test_independence_move_leaves_the_target_exactly_invariant():
    """A proposal off-centre by 0.8 sd and twice too wide still samples N(m, C) exactly: the
    proposal density ratio enters the acceptance. The same move without that ratio samples
    ∝ π·q instead, visibly shifted towards the proposal's centre (the test can fail)."""
    m = np.array([1.0, -2.0, 0.5])
    sd = np.array([1.0, 0.1, 3.0])
    corr = np.array([[1.0, 0.6, -0.3], [0.6, 1.0, 0.2], [-0.3, 0.2, 1.0]])
    cov = corr * np.outer(sd, sd)
    icov = np.linalg.inv(cov)

    def log_prob(x):
        d = x - m
        return -0.5 * np.einsum("ni,ij,nj->n", d, icov, d)

    proposal = bayes.StudentTProposal(m + 0.8 * sd, np.linalg.cholesky(2.0 * cov), 10.0)
    exact = bayes.IndependenceMove(proposal)
    naive = emcee.moves.MHMove(lambda coords, random: (proposal.draw(random, coords.shape[0]),
                                                       np.zeros(coords.shape[0])))

    def draws(move):
        sampler = emcee.EnsembleSampler(64, 3, log_prob, vectorize=True, moves=move)
        sampler.random_state = np.random.RandomState(7).get_state()
        start = m + np.random.default_rng(1).standard_normal((64, 3)) * sd
        sampler.run_mcmc(start, 650)
        return sampler.get_chain(discard=50, flat=True)

    defensive = bayes.IndependenceMove(bayes.DefensiveMixture(
        proposal, bayes.StudentTProposal(proposal.center, 2.0 * proposal.chol, 10.0), 0.2))
    for good in (draws(exact), draws(defensive)):
        z_mean = (good.mean(axis=0) - m) / sd
        assert np.all(np.abs(z_mean) < 0.05), z_mean               # MC error of the mean ~0.01 sd
        np.testing.assert_allclose(np.cov(good.T) / np.outer(sd, sd), corr, atol=0.05)
    biased = (draws(naive).mean(axis=0) - m) / sd
    assert np.max(np.abs(biased)) > 0.15, biased                 # π·q is shifted by ~0.27 sd


def test_adapted_proposal_moves_the_centre_and_widens_only_where_the_pilot_spreads_further():
    rng = np.random.default_rng(4)
    sd = np.array([2.0, 0.1, 5.0, 1.0])
    a = rng.standard_normal((4, 4))
    c = a @ a.T + np.eye(4)
    corr = c / np.sqrt(np.outer(np.diag(c), np.diag(c)))
    cov = corr * np.outer(sd, sd)
    lam, vec = np.linalg.eigh(corr)
    d = sd[:, None] * vec                                        # principal directions, weakest first
    # the truth: twice the bound's variance along the weakest direction, 0.5 along the next,
    # and a mean 0.7 sd off the ML estimate along the weakest
    ml = np.array([1.0, 2.0, 3.0, 4.0])
    mean = ml + 0.7 * np.sqrt(lam[0]) * d[:, 0]
    truth = d @ np.diag(lam * np.array([2.0, 0.5, 1.0, 1.0])) @ d.T
    pilot = rng.multivariate_normal(mean, truth, size=40_000)
    center, widened, ratios = bayes.adapted_proposal(ml, cov, pilot)
    np.testing.assert_allclose(ratios, [2.0, 0.5, 1.0, 1.0], rtol=0.03)
    np.testing.assert_allclose(center, pilot.mean(axis=0), rtol=1e-12)
    np.testing.assert_allclose((center - ml) / sd, (mean - ml) / sd, atol=0.02)
    want = d @ np.diag(lam * np.maximum(1.0, ratios)) @ d.T      # never narrower than the bound
    np.testing.assert_allclose(widened, want, rtol=1e-10, atol=1e-14)
    np.testing.assert_allclose(widened, d @ np.diag(lam * [2.0, 1.0, 1.0, 1.0]) @ d.T, rtol=0.05, atol=1e-3)
    assert np.all(np.linalg.eigvalsh(widened - cov) > -1e-10)


def test_a_run_resumed_across_the_pilot_gives_the_uninterrupted_chain(problem, fit, tmp_path):
    settings = SamplerSettings(n_walkers=8, n_ensembles=2, max_steps=30, check_every=10, adapt_steps=10,
                               n_predictive=0)
    full = bayes.sample(problem, fit, settings=settings, seed=6, backend=tmp_path / "full.h5", predictive=False)
    assert full.attrs["adapt_steps"] == 10 and full.burn_in > 10
    ratios = np.array(full._json_attr("proposal_widening"))
    assert ratios.shape == (3,) and np.all(ratios > 0)
    cov = np.array(full._json_attr("proposal_covariance"))
    assert np.all(np.linalg.eigvalsh(cov - np.asarray(fit.covariance)) > -1e-12 * np.abs(cov).max())
    path = tmp_path / "resume.h5"
    for cap in (7, 15):                                        # stopped inside, then after the pilot
        bayes.sample(problem, fit, settings=SamplerSettings(**{**settings.__dict__, "max_steps": cap}), seed=6,
                     backend=path, predictive=False)
    resumed = bayes.sample(problem, fit, settings=settings, seed=6, backend=path, predictive=False)
    for k in range(2):
        np.testing.assert_array_equal(backend_chain(path, k), backend_chain(tmp_path / "full.h5", k))
    np.testing.assert_array_equal(resumed.draws(), full.draws())
    np.testing.assert_array_equal(np.array(resumed._json_attr("proposal_covariance")), cov)
    assert np.array(resumed._json_attr("proposal_mean")).shape == (3,)


def ar1_chains(rng, phi, n, walkers, n_free, n_ensembles):
    """AR(1) chains with unit marginal variance, τ = (1 + φ)/(1 - φ)."""
    out = []
    for _ in range(n_ensembles):
        x = np.empty((n, walkers, n_free))
        x[0] = rng.standard_normal((walkers, n_free))
        for t in range(1, n):
            x[t] = phi * x[t - 1] + np.sqrt(1 - phi ** 2) * rng.standard_normal((walkers, n_free))
        out.append(x)
    return out


def test_r_hat_and_ess_take_one_chain_per_ensemble_of_its_walkers_concatenated():
    steps, walkers = np.arange(10)[:, None, None], np.arange(3)[None, :, None]
    chains = [100 * k + 10 * walkers + steps + np.zeros((10, 3, 2)) for k in range(2)]
    pooled = bayes.pooled_draws(chains, 4, 2)                    # steps 4, 6, 8 of walkers 0, 1, 2
    assert pooled.shape == (2, 9, 2)
    np.testing.assert_array_equal(pooled[1, :, 0], [104, 106, 108, 114, 116, 118, 124, 126, 128])
    assert bayes.pooled_draws([c[..., 0] for c in chains], 4, 2).shape == (2, 9)
    # walkers that agree with each other but not with the other ensemble: R-hat across the
    # ensembles sees it, R-hat across all walkers as chains would barely
    rng = np.random.default_rng(3)
    offsets = [rng.standard_normal(3) * 0.15 for _ in range(4)]
    common = [o + rng.standard_normal((400, 16, 3)) for o in offsets]
    check = bayes.check_stop(common, 400, 50)
    assert "R-hat < 1.01" in check.missing and check.max_rhat > 1.01


def test_stopping_rule_on_synthetic_chains():
    rng = np.random.default_rng(0)
    # independent draws (τ = 1): stop. The bare 1 % rule would not: its τ estimate moves by
    # more than 1 % between checks from noise alone.
    iid = [rng.standard_normal((300, 16, 3)) for _ in range(2)]
    check = bayes.check_stop(iid, 300, 50)
    assert check.converged, check.missing
    assert check.max_rhat < 1.01 and min(check.min_ess_bulk, check.min_ess_tail) > 5000
    assert (check.burn_in, check.thin) == (int(np.ceil(2 * check.tau.max())), 1)
    # emcee's ESS beside ArviZ's: 2 x 16 walkers x (300 - burn-in) steps / τ
    np.testing.assert_allclose(check.ess_tau, 32 * (300 - check.burn_in) / check.tau.mean(axis=0), rtol=1e-12)
    prev = np.array([bayes.autocorr_times(c[:250]) for c in iid])
    assert np.max(np.abs(check.tau - prev) / check.tau) > 0.01

    # τ = 19 (φ = 0.9): 300 steps are fewer than 50 τ
    slow = bayes.check_stop(ar1_chains(rng, 0.9, 300, 16, 3, 2), 300, 50)
    assert not slow.converged and slow.missing[0].startswith("50 tau")
    assert 12 < slow.tau.max() < 30
    # one ensemble off by half a standard deviation: R-hat says no (and ESS, which ArviZ
    # computes from the variance across the ensembles)
    shifted = bayes.check_stop([iid[0], iid[1] + np.array([0.0, 0.5, 0.0])], 300, 50)
    assert "R-hat < 1.01" in shifted.missing and shifted.max_rhat > 1.02, shifted.missing
    # too few draws: 2 walkers x 2 ensembles x 90 steps
    few = bayes.check_stop([c[:90, :2] for c in iid], 90, 30)
    assert "ESS >= 400" in few.missing

    # the τ tolerance: Sokal's standard error of the change, never below 1 %
    tol = bayes.tau_change_tolerance(np.array([2.0]), 200, 50, 16)
    np.testing.assert_allclose(tol, [3 * np.sqrt(2 * (2 * 5 * 2.0 + 1) / (200 * 16) * 50 / 150)], rtol=1e-12)
    assert bayes.tau_change_tolerance(np.array([50.0]), 10 ** 8, 100, 32)[0] == 0.01


@pytest.mark.parametrize("moves", ["independence", "de", "stretch"])
def test_every_move_kind_evaluates_walkers_in_batches_and_is_recorded(problem, fit, moves, monkeypatch):
    calls, placed = [], {}
    call, place = LogPosterior.__call__, bayes.place_walkers

    def counting(self, free):
        calls.append(np.atleast_2d(free).shape[0])
        return call(self, free)

    def placing(*args, **kwargs):
        out = place(*args, **kwargs)
        placed["at"] = len(calls)
        return out

    monkeypatch.setattr(LogPosterior, "__call__", counting)
    monkeypatch.setattr(bayes.sampler, "place_walkers", placing)
    settings = SamplerSettings(n_walkers=8, n_ensembles=1, max_steps=24, check_every=24, moves=moves, n_predictive=0)
    res = bayes.sample(problem, fit, settings=settings, seed=1, predictive=False)
    sampling = calls[placed["at"]:]
    # every step evaluates every walker once: all 8 in one call (independence), two halves
    # of 4 (DE, stretch) or four quarters (DE snooker); never one walker per call
    assert sum(sampling) == (1 + 24) * 8 and set(sampling) <= {2, 4, 8}   # start + 24 steps
    assert (8 in sampling[1:]) == (moves == "independence")
    assert res.attrs["moves"] == moves
    assert ("Student-t df 20" in res.attrs["move_mix"]) == (moves == "independence")
    assert 0.05 < float(res.idata.sample_stats["acceptance_rate"].mean()) < 0.95


@pytest.mark.parametrize("changes, message", [
    ({"moves": "gibbs"}, "unknown moves 'gibbs'; choose independence, de, stretch"),
    ({"proposal_df": 2.0}, "degrees of freedom must be above 2"),
    ({"independence_weight": 0.0}, "weight must be in"),
    ({"proposal_scale": -1.0}, "proposal scale must be a positive number"),
    ({"adapt_steps": 1}, "pilot of 1 steps: give 0"),
])
def test_bad_move_settings_are_refused(problem, fit, changes, message):
    with pytest.raises(BayesError, match=message):
        bayes.sample(problem, fit, settings=SamplerSettings(**{**FAST.__dict__, **changes}))


def test_a_singular_cramer_rao_covariance_is_refused(problem, fit):
    import dataclasses

    cov = np.array(fit.covariance, dtype=float)
    cov[2] = cov[1]
    cov[:, 2] = cov[:, 1]                                     # C_TS1 a copy of B_TS1: rank 2
    with pytest.raises(BayesError, match="covariance is not positive definite; fix the non-identifiable"):
        bayes.sample(problem, dataclasses.replace(fit, covariance=cov), settings=FAST)


# --------------------------------------------------------------------------------------
# bad input
# --------------------------------------------------------------------------------------
def test_init_of_another_concept_is_refused(problem, fit):
    import dataclasses

    other = dataclasses.replace(fit, concept="lths")
    with pytest.raises(BayesError, match="concept lths"):
        bayes.sample(problem, other, settings=FAST)
    wrong_free = dataclasses.replace(fit, free=get_model("htls").parameters.freeing_only(["J", "k_n", "B_U1"]).free_mask)
    with pytest.raises(BayesError, match="free the same parameters"):
        bayes.sample(problem, wrong_free, settings=FAST)


@pytest.mark.parametrize("spec, message", [
    (("uniform", 0.1, 0.01), "lower bound not below upper bound"),
    (("uniform", -2.0, -1.0), "no support inside the bounds"),
    (("lognormal", -3.0, 0.0), "positive spread"),
    (("gamma", 1.0, 1.0), "unknown kind"),
])
def test_impossible_priors_are_refused(problem, fit, spec, message):
    with pytest.raises(BayesError, match=message):
        bayes.sample(problem, fit, priors={"J": spec}, settings=FAST)


def test_prior_parsing():
    assert bayes.parse_prior("J=lognormal:-3,0.5") == ("J", "lognormal", -3.0, 0.5)
    for bad in ("J", "J=uniform:1", "J=uniform:a,b", "=uniform:1,2"):
        with pytest.raises(BayesError, match="cannot read --prior"):
            bayes.parse_prior(bad)


def test_walkers_that_cannot_be_placed_are_refused(problem, fit):
    ml = fit.value("J")
    with pytest.raises(BayesError, match="ML estimate of J .* outside its prior support"):
        bayes.sample(problem, fit, priors={"J": ("uniform", 2 * ml, 3 * ml)}, settings=FAST)
    tiny = 1e-9 * fit.std[0]
    with pytest.raises(BayesError, match="cannot place 16 walkers"):
        bayes.sample(problem, fit, priors={"J": ("uniform", ml - tiny, ml + tiny)}, settings=FAST)
    with pytest.raises(BayesError, match="even number of at least 6"):
        bayes.sample(problem, fit, settings=SamplerSettings(n_walkers=4))
    with pytest.raises(BayesError, match="de move needs at least 2 x 3 = 6"):
        bayes.sample(problem, fit, settings=SamplerSettings(n_walkers=4, moves="de"))


# --------------------------------------------------------------------------------------
# the sample verb
# --------------------------------------------------------------------------------------
def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "ema_uq", *args], capture_output=True, text=True, timeout=300)


def test_study_sample_section_agrees_with_the_settings_and_the_cli():
    from pathlib import Path

    from ema_uq.cli import build_parser
    from ema_uq.study import load_study

    section = load_study(Path(__file__).parents[2] / "studies" / "htls.yaml")["sample"]
    keys = ("walkers", "ensembles", "max_steps", "check_every", "moves")
    d = SamplerSettings()
    assert tuple(section[k] for k in keys) == (d.n_walkers, d.n_ensembles, d.max_steps, d.check_every, d.moves)
    base = ["sample", "d.nc", "--concept", "htls", "--init", "f.json", "--out", "p.nc"]
    defaults = build_parser().parse_args(base)
    assert (defaults.walkers, defaults.chains, defaults.max_steps, defaults.check_every, defaults.moves) == \
        tuple(section[k] for k in keys)
    given = build_parser().parse_args(base + ["--walkers", "8", "--ensembles", "3", "--max-steps", "100",
                                              "--check-every", "25", "--moves", "de"])
    assert (given.walkers, given.chains, given.max_steps, given.check_every, given.moves) == (8, 3, 100, 25, "de")


def test_sample_verb_end_to_end_and_errors(data, fit, tmp_path):
    data_path = io.write_measurement(tmp_path / "short.nc", data)
    fit_path = io.write_json(tmp_path / "fit.json", fit.to_json())
    out = tmp_path / "post.nc"
    common = [str(data_path), "--concept", "htls", "--init", str(fit_path), "--walkers", "8", "--chains", "2",
              "--max-steps", "30", "--check-every", "15", "--predictive", "5", "--seed", "2"]
    proc = run_cli("sample", *common, "--out", str(out), "--prior", "J=lognormal:-3,1")
    assert proc.returncode == 0, proc.stderr
    assert "wrote" in proc.stdout and "NOT converged" in proc.stdout
    assert "step 30/30" in proc.stderr                       # progress lines
    assert (tmp_path / "post.h5").is_file()                  # default backend next to --out
    res = PosteriorResult.from_netcdf(out)
    assert res.names == tuple(FREE) and "lognormal" in res._json_attr("priors")["J"]

    # rerun with the same settings resumes the finished backend and reproduces the file's draws
    again = run_cli("sample", *common, "--out", str(tmp_path / "again.nc"), "--backend", str(tmp_path / "post.h5"),
                    "--prior", "J=lognormal:-3,1", "--quiet")
    assert again.returncode == 0, again.stderr
    assert again.stderr == ""
    np.testing.assert_array_equal(PosteriorResult.from_netcdf(tmp_path / "again.nc").draws(), res.draws())

    lths_fit = dict(io.read_json(fit_path), concept="lths")
    io.write_json(tmp_path / "lths.json", lths_fit)
    for extra, message in [
        (["--init", str(tmp_path / "lths.json")], "fit of concept lths"),
        (["--prior", "J=uniform:5,1"], "lower bound not below upper bound"),
        (["--prior", "J=uniform:1,2"], "cannot place walkers"),
        (["--prior", "k_n=uniform:1,2"], "k_n is fixed"),
        (["--walkers", "4"], "even number of at least 6"),
        (["--spread", "-1"], "--spread must be a positive number"),
    ]:
        args = list(common)
        if extra[0] == "--init":
            i = args.index("--init")
            args[i + 1] = extra[1]
            extra = []
        proc = run_cli("sample", *args, *extra, "--out", str(tmp_path / "bad.nc"), "--backend",
                       str(tmp_path / "bad.h5"))
        assert proc.returncode == 2, (extra, proc.stderr)
        assert proc.stderr.count("\n") == 1 and message in proc.stderr, proc.stderr
        assert not (tmp_path / "bad.nc").exists()
    # an output the posterior cannot be, or one that is the chains' own file, stops before sampling
    for out, backend, message in [("other.txt", "chains.h5", "give a .nc file"),
                                  ("same.nc", "same.nc", "the chains and the posterior need two files")]:
        proc = run_cli("sample", *common, "--out", str(tmp_path / out), "--backend", str(tmp_path / backend))
        assert proc.returncode == 2 and proc.stderr.count("\n") == 1 and message in proc.stderr, proc.stderr
        assert not (tmp_path / out).exists() and not (tmp_path / "chains.h5").exists()
