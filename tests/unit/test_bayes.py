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


# --------------------------------------------------------------------------------------
# the InferenceData
# --------------------------------------------------------------------------------------
def test_inference_data_groups_and_netcdf_round_trip(result, problem, tmp_path):
    idata = result.idata
    for group in ("posterior", "sample_stats", "log_likelihood", "observed_data", "posterior_predictive"):
        assert group in idata.groups()
    n_chain = FAST.n_ensembles * 8
    assert idata.posterior["J"].shape[0] == n_chain
    assert set(idata.posterior.data_vars) == set(FREE)
    assert {"lp", "accepted", "acceptance_rate", "log_prior"} <= set(idata.sample_stats.data_vars)
    assert 0.05 < float(idata.sample_stats["acceptance_rate"].mean()) < 0.95
    np.testing.assert_array_equal(idata.observed_data["y1"].values, problem.observed[:, 1])
    assert idata.posterior_predictive["I_A"].shape == (1, 10, problem.n_samples)
    np.testing.assert_allclose(idata.log_likelihood["z"] + idata.sample_stats["log_prior"],
                               idata.sample_stats["lp"], rtol=0, atol=1e-9)
    # every draw comes after burn-in, thinned: n_draw = ceil((n_steps - burn) / thin)
    assert idata.posterior.sizes["draw"] == -(-(result.n_steps - result.burn_in) // result.thin)

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
    with pytest.raises(BayesError, match="at least 2 x 3 = 6"):
        bayes.sample(problem, fit, settings=SamplerSettings(n_walkers=4))


# --------------------------------------------------------------------------------------
# the sample verb
# --------------------------------------------------------------------------------------
def run_cli(*args):
    return subprocess.run([sys.executable, "-m", "ema_uq", *args], capture_output=True, text=True, timeout=300)


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
        (["--walkers", "4"], "at least 2 x 3 = 6"),
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
