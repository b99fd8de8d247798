"""Bayesian posterior of the free parameters by emcee, started from the ML estimate and
exported to ArviZ.

Posterior (free parameters Θ, n_free of them)::

    log p(Θ | z) = log L(Θ) + Σ_j log π_j(Θ_j) + const

with the concentrated det R likelihood or known per-channel noise
(:mod:`~ema_uq.bayes.posterior`) and priors restricted to the parameter bounds
(:mod:`~ema_uq.bayes.priors`).

Modules, in the order a run uses them:

- :mod:`~ema_uq.bayes.priors`: :class:`Prior`, :func:`build_priors`, :func:`parse_prior`;
- :mod:`~ema_uq.bayes.posterior`: :class:`LogPosterior`, batched for emcee;
- :mod:`~ema_uq.bayes.settings`: :class:`SamplerSettings` (walkers, ensembles, moves, caps);
- :mod:`~ema_uq.bayes.moves`: the Student-t independence proposal, :class:`IndependenceMove`
  (an emcee Metropolis-Hastings move) and the default move mix;
- :mod:`~ema_uq.bayes.stopping`: autocorrelation times, burn-in and thinning,
  :func:`check_stop`;
- :mod:`~ema_uq.bayes.sampler`: :func:`sample` (walker placement, HDF5 backends, pilot,
  adaptation, the run under the stopping rule);
- :mod:`~ema_uq.bayes.result`: :class:`PosteriorResult` and the ArviZ export.
"""
from __future__ import annotations

from .errors import BayesError
from .moves import DefensiveMixture, IndependenceMove, StudentTProposal, adapted_proposal, build_moves
from .posterior import LogPosterior, known_noise_sigma
from .priors import Prior, build_priors, make_prior, parse_prior
from .result import HDI_PROB, PosteriorResult
from .sampler import PLACEMENT_ROUNDS, place_walkers, sample
from .settings import DEFAULT_ENSEMBLES, DEFAULT_SPREAD, INDEPENDENCE_WALKERS, MOVE_KINDS, SamplerSettings
from .stopping import (AUTOCORR_FACTOR, AUTOCORR_WINDOW, ESS_MIN, RHAT_MAX, STOP_RULE, TAU_CHANGE_SE, TAU_RTOL,
                       StopCheck, autocorr_times, burn_in_and_thin, check_stop, pooled_draws, tau_change_tolerance,
                       tau_ess)

__all__ = [
    "AUTOCORR_FACTOR", "AUTOCORR_WINDOW", "DEFAULT_ENSEMBLES", "DEFAULT_SPREAD", "ESS_MIN", "HDI_PROB",
    "INDEPENDENCE_WALKERS", "MOVE_KINDS", "PLACEMENT_ROUNDS", "RHAT_MAX", "STOP_RULE", "TAU_CHANGE_SE", "TAU_RTOL",
    "BayesError", "DefensiveMixture", "IndependenceMove", "LogPosterior", "PosteriorResult", "Prior",
    "SamplerSettings", "StopCheck", "StudentTProposal",
    "adapted_proposal", "autocorr_times", "build_moves", "build_priors", "burn_in_and_thin", "check_stop",
    "known_noise_sigma", "make_prior", "parse_prior", "place_walkers", "pooled_draws", "sample",
    "tau_change_tolerance", "tau_ess",
]
