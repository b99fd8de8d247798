"""Simulation-based calibration (ema_uq.bayes.sbc): the pure pieces on hand-made input, and a
CI-sized campaign (12 replicates of a two-parameter HT/LS problem, chains capped at 60 steps)
that catches only gross miscalibration, e.g. a posterior far too narrow or off the truth
(ranks piled at 0 or L).
The full campaign is tests/statistical/test_bayes_sbc.py (``pytest -m slow``)."""
from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from ema_uq import deploy_retract, get_model
from ema_uq.bayes import BayesError, Prior, SamplerSettings
from ema_uq.bayes.sbc import (SbcResult, prior_draws, rank_counts, rank_uniformity, ranks_of, sbc_ranks,
                              thinned_draws)

N_REPLICATES = 12
N_DRAWS = 31


# --- pure pieces ------------------------------------------------------------------------
def test_ranks_count_draws_below_the_truth():
    draws = np.array([[1.0, 10.0], [2.0, 20.0], [3.0, 30.0]])
    assert ranks_of(np.array([2.5, 0.0]), draws).tolist() == [2, 0]
    assert ranks_of(np.array([9.0, 99.0]), draws).tolist() == [3, 3]


def test_uniform_ranks_pass_and_piled_ranks_fail():
    rng = np.random.default_rng(1)
    uniform = rng.integers(0, N_DRAWS + 1, 400)
    assert rank_counts(uniform, N_DRAWS, 8).sum() == 400
    assert rank_uniformity(uniform, N_DRAWS, 8)[1] > 0.01
    # a posterior far too narrow puts the truth outside every draw: ranks 0 or L
    piled = rng.choice([0, N_DRAWS], 400)
    chi2, p = rank_uniformity(piled, N_DRAWS, 8)
    assert p < 1e-10 and chi2 > 100


def test_bins_must_split_the_rank_values_evenly():
    with pytest.raises(BayesError, match="bins do not split"):
        rank_counts(np.zeros(3, dtype=int), 30, 4)


def test_prior_draws_follow_the_truncated_prior():
    priors = [Prior("normal", 1.0, 0.1, 0.0, np.inf), Prior("uniform", 2.0, 3.0, 2.0, 3.0),
              Prior("normal", 0.0, 1.0, 0.0, np.inf)]                  # the last: half-normal
    x = prior_draws(priors, np.random.default_rng(0), 4000)
    assert x.shape == (4000, 3)
    assert stats.kstest(x[:, 0], stats.norm(1.0, 0.1).cdf).pvalue > 0.01
    assert stats.kstest(x[:, 1], stats.uniform(2.0, 1.0).cdf).pvalue > 0.01
    assert stats.kstest(x[:, 2], stats.halfnorm().cdf).pvalue > 0.01
    np.testing.assert_array_equal(x, prior_draws(priors, np.random.default_rng(0), 4000))


def test_improper_prior_is_refused():
    with pytest.raises(BayesError, match="improper"):
        prior_draws([Prior("flat", lower=0.0, upper=np.inf)], np.random.default_rng(0), 1)


# --- a CI-sized campaign ----------------------------------------------------------------
def _toy_campaign():
    """(model, parameter set, priors, sampler settings) of the CI-sized campaign: two free
    parameters with 5 % normal priors, a short hybrid-integrator sampler."""
    model = get_model("htls")
    free = ("k_n", "B_TS1")
    params = model.parameters.freeing_only(free)
    priors = {n: ("normal", params[n].nominal, 0.05 * params[n].nominal) for n in free}
    settings = SamplerSettings(n_walkers=6, n_ensembles=2, max_steps=60, check_every=30, adapt_steps=0,
                               integrator="hybrid", n_predictive=0)
    return model, params, priors, settings


@pytest.fixture(scope="module")
def campaign() -> SbcResult:
    model, params, priors, settings = _toy_campaign()
    return sbc_ranks(model, deploy_retract().slice(0, 150), params, priors, n_replicates=N_REPLICATES,
                     n_draws=N_DRAWS, n_bins=4, settings=settings, seed=7)


def test_campaign_catches_gross_miscalibration(campaign):
    print(campaign.summary())
    assert campaign.ranks.shape == (N_REPLICATES, 2)
    assert campaign.ranks.min() >= 0 and campaign.ranks.max() <= N_DRAWS
    # calibrated: 2 / 32 of the ranks at 0 or L; a posterior that misses the truth: nearly all
    assert np.all(campaign.extreme_fraction() <= 0.5), campaign.summary()
    assert campaign.pooled_uniformity()[1] > 1e-4, campaign.summary()
    # the truths come from the prior: within 5 prior sd of nominal
    params = get_model("htls").parameters
    nominal = np.array([params[n].nominal for n in campaign.names])
    assert np.all(np.abs(campaign.truths - nominal) < 5 * 0.05 * nominal)


def test_result_round_trips_through_json(campaign):
    back = SbcResult.from_json(campaign.to_json())
    np.testing.assert_array_equal(back.ranks, campaign.ranks)
    assert back.names == campaign.names and back.uniformity() == campaign.uniformity()
    assert back.design["priors"]["k_n"].startswith("normal:1.2,0.06")


def test_rank_histogram_figure(campaign):
    from ema_uq.report.bayes_figures import sbc_rank_histogram

    fig = sbc_rank_histogram(campaign)
    assert len([ax for ax in fig.axes if ax.get_visible()]) == 2


# --------------------------------------------------------------------------------------
# a scattered campaign: replicates alone, then gathered
# --------------------------------------------------------------------------------------
def test_scattered_replicates_gather_to_the_serial_campaign(campaign, tmp_path):
    import json

    from ema_uq import cli
    from ema_uq.bayes.sbc import gather_replicates, ks_uniformity, replicate_rng, sbc_replicate

    model, params, priors, settings = _toy_campaign()
    picked = (4, 0, 9)                                      # any order; each replicate on its own
    records = [sbc_replicate(model, deploy_retract().slice(0, 150), params, priors, index=r, seed=7,
                             n_draws=N_DRAWS, settings=settings, backend=tmp_path / f"rep_{r}.h5") for r in picked]
    for rec in records:
        np.testing.assert_array_equal(rec["ranks"], campaign.ranks[rec["index"]])
        np.testing.assert_allclose(rec["truth"], campaign.truths[rec["index"]], rtol=0, atol=0)
    gathered = gather_replicates(records, n_bins=4)
    assert gathered.n_replicates == 3 and gathered.design["replicates"] == [0, 4, 9]
    np.testing.assert_array_equal(gathered.ranks, campaign.ranks[[0, 4, 9]])
    assert 0.0 <= ks_uniformity(gathered.ranks[:, 0], N_DRAWS) <= 1.0
    # the replicate streams are the serial campaign's children
    assert replicate_rng(7, 3).random() == np.random.default_rng(np.random.SeedSequence(7).spawn(5)[3]).random()
    # gather through the CLI: JSON with chi-square and KS p per parameter, and the figure
    paths = []
    for rec in records:
        paths.append(tmp_path / f"rep_{rec['index']}.json")
        paths[-1].write_text(json.dumps(rec))
    assert cli.main(["sbc", "--gather", *map(str, paths), "--bins", "4", "--out", str(tmp_path / "sbc.json"),
                     "--figure", str(tmp_path / "sbc.png")]) == 0
    out = json.loads((tmp_path / "sbc.json").read_text())
    assert set(out["uniformity"]) == set(out["ks_p"]) == set(priors)
    assert (tmp_path / "sbc.png").stat().st_size > 0
    # records of two campaigns are refused in one line
    other = {**records[0], "seed": 8, "index": 11}
    with pytest.raises(BayesError, match="differ"):
        gather_replicates([records[0], other])
