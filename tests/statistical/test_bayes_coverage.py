"""Statistical acceptance of the Bayesian posterior (issue: Bayesian posterior with emcee).

Synthetic HT/LS data with known truth; rig values of p_ACE/p_PCE drawn around the truth with
their rig σ, so the normal rig prior is calibrated. Per data set: ML fit, then emcee from it
with the default moves (independence Metropolis-Hastings mixed with differential evolution)
under the default stopping rule.

Checks (``check``):
- pooled over (data set, parameter): the 90 % HDI contains the truth in a fraction consistent
  with 90 % (two-sided binomial test at 1 %), and for no parameter in fewer than 60 % of the
  data sets;
- posterior sd within a factor 1.5 of the Cramér-Rao σ for well-identified parameters
  (CRB below 10 % of the value: the near-linear regime where both must agree);
- posterior means within 3 sd of the truth: no more pairs beyond 3 sd than the 0.27 % a
  calibrated posterior gives (binomial upper tail at 1 %; with 320 pairs about one such pair
  is expected, so "every pair" would be a wrong test);
- the standardised errors (mean - truth)/sd as a whole: Σ z² against χ²(n) at 0.1 %, which
  fails when the posterior widths are systematically too narrow or too wide (e.g. a
  likelihood scaled by the wrong N) even with few data sets.

CI runs a reduced problem (3 s of data, 3 channels, 4 free parameters, 6 data sets, ~30 s);
``pytest -m slow`` runs 20 data sets of the default HT/LS study problem (deploy-retract, every
channel, all 16 parameters free, 2 ensembles x 8 walkers under the default stopping rule;
7000-8000 simulations per data set).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import pytest
from scipy import stats

from ema_uq import bayes, deploy_retract, get_model, synthesize
from ema_uq.identify import FitProblem, estimate

Z_OUTSIDE = 3.0
P_OUTSIDE = 2 * stats.norm.sf(Z_OUTSIDE)       # 0.27 %


@dataclass(frozen=True)
class Campaign:
    n_samples: int
    channels: tuple[str, ...] | None
    free: tuple[str, ...] | None                 # None: every parameter
    settings: bayes.SamplerSettings


FAST = Campaign(300, ("Omega", "y1", "I_A"), ("J", "B_TS1", "C_TS1", "p_PCE"),
                bayes.SamplerSettings(n_walkers=8, n_ensembles=2, max_steps=1000, adapt_steps=0, n_predictive=0))
FULL = Campaign(3800, None, None, bayes.SamplerSettings(n_walkers=8, n_ensembles=2, max_steps=3000, n_predictive=0))


def run(campaign: Campaign, seeds) -> dict:
    model = get_model("htls")
    truth_full = model.parameters.nominal
    experiment = deploy_retract().slice(0, campaign.n_samples)
    free = campaign.free or model.parameters.names
    out = {k: [] for k in ("inside", "mean", "sd", "crb", "ml", "rhat", "ess", "truth", "converged", "steps")}
    for seed in seeds:
        data = synthesize("htls", experiment, noise=0.02, seed=seed)
        rng = np.random.default_rng([seed, 77])
        rig = {p.name: rng.normal(p.nominal, p.prior_std) for p in model.parameters if p.prior_std}
        params = model.parameters.with_nominal(rig).freeing_only(free)
        problem = FitProblem([data], parameters=params, channels=campaign.channels)
        fit = estimate(problem, start=truth_full)
        assert fit.converged, fit.message
        res = bayes.sample(problem, fit, settings=campaign.settings, seed=seed, predictive=False)
        table = res.summary()
        truth = truth_full[problem.free_index]
        hdi = res.interval(0.9)
        out["inside"].append((hdi[:, 0] <= truth) & (truth <= hdi[:, 1]))
        out["mean"].append(table["mean"].values - truth)
        out["sd"].append(table["sd"].values)
        out["crb"].append(table["crb_sd"].values)
        out["ml"].append(table["ml"].values)
        out["rhat"].append(table["r_hat"].values)
        out["ess"].append(table["ess_bulk"].values)
        out["truth"].append(truth)
        out["converged"].append(res.converged)
        out["steps"].append(res.n_steps)
    result = {k: np.array(v) for k, v in out.items()}
    result["names"] = tuple(problem.parameters.free_names)
    return result


def figures(result, binomial_alpha=0.01) -> dict:
    """The campaign's figures: pooled coverage and its binomial p, per-parameter coverage,
    sd/CRB ratios of the well-identified parameters, standardised errors."""
    inside = result["inside"]
    n, hits = inside.size, int(inside.sum())
    per_param = inside.mean(axis=0)
    well = result["crb"] / np.abs(result["truth"]) < 0.1
    ratio = result["sd"] / result["crb"]
    z = result["mean"] / result["sd"]
    n_far = int(np.sum(np.abs(z) > Z_OUTSIDE))
    chi2 = float(np.sum(z ** 2))
    return {
        "pairs": n, "hits": hits, "coverage": hits / n, "binomial_p": float(stats.binomtest(hits, n, 0.9).pvalue),
        "per_param": dict(zip(result["names"], per_param)), "worst": result["names"][int(np.argmin(per_param))],
        "worst_coverage": float(per_param.min()), "well": well, "ratio": ratio,
        "ratio_range": (float(ratio[well].min()), float(ratio[well].max())) if well.any() else (np.nan, np.nan),
        "z": z, "n_far": n_far, "far_p": float(stats.binom.sf(n_far - 1, z.size, P_OUTSIDE)),
        "chi2": chi2, "chi2_cdf": float(stats.chi2.cdf(chi2, z.size)),
        "max_rhat": float(result["rhat"].max()), "min_ess": float(result["ess"].min()),
    }


def describe(f: dict) -> str:
    return (f"90 % HDI coverage {f['hits']}/{f['pairs']} = {f['coverage']:.3f} (binomial p = {f['binomial_p']:.3g}); "
            f"worst parameter {f['worst']} {f['worst_coverage']:.0%}; sd/CRB of well-identified parameters in "
            f"[{f['ratio_range'][0]:.3f}, {f['ratio_range'][1]:.3f}]; {f['n_far']} means beyond 3 sd "
            f"(p = {f['far_p']:.3g}); sum z^2 = {f['chi2']:.1f} for chi2({f['z'].size}) (cdf {f['chi2_cdf']:.3f}); "
            f"max R-hat {f['max_rhat']:.4f}, min bulk ESS {f['min_ess']:.0f}")


def check(result, binomial_alpha=0.01):
    f = figures(result, binomial_alpha)
    names = result["names"]
    assert f["binomial_p"] > binomial_alpha, describe(f)
    assert f["worst_coverage"] >= 0.6, describe(f)
    well, ratio = f["well"], f["ratio"]
    bad = well & ((ratio > 1.5) | (ratio < 1 / 1.5))
    assert not bad.any(), f"posterior sd / CRB sigma out of [1/1.5, 1.5]: {ratio[bad]} " \
                          f"for {[names[j] for j in np.nonzero(bad)[1]]}"
    assert f["far_p"] > binomial_alpha, f"{f['n_far']} of {f['z'].size} posterior means beyond 3 sd of the truth " \
                                        f"(max |z| = {np.abs(f['z']).max():.2f})"
    assert 5e-4 < f["chi2_cdf"] < 1 - 5e-4, describe(f)
    return f


def test_fast_subset():
    result = run(FAST, range(6))
    f = check(result)
    print(describe(f), "; steps", result["steps"])
    assert not (np.abs(f["z"]) > Z_OUTSIDE).any()               # 24 pairs: none expected beyond 3 sd
    # the default stopping rule was met: walkers of both ensembles agree
    assert result["converged"].all(), result["steps"]
    assert f["max_rhat"] < 1.01 and f["min_ess"] >= 400, describe(f)


@pytest.mark.slow
def test_full_campaign():
    result = run(FULL, range(20))
    f = check(result)
    print(describe(f), "; steps", result["steps"])
    assert result["converged"].all(), result["steps"]
    assert f["max_rhat"] < 1.01, describe(f)
