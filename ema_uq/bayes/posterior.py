"""The log posterior of the free parameters Θ (n_free of them), batched for emcee::

    log p(Θ | z) = log L(Θ) + Σ_j log π_j(Θ_j) + const

Likelihood, one of:

- ``"estimated"`` (default): the concentrated output-error likelihood
  log L = -(N/2) log det R(Θ), R = (1/N) Σ_k e_k e_kᵀ. It is also the exact marginal
  likelihood of Gaussian white residuals with unknown covariance under the Jeffreys prior
  p(R) ∝ |R|^{-(m+1)/2}, so the posterior over Θ is a proper marginal, not a plug-in.
- known per-channel noise σ_c [channel units]: Gaussian,
  log L = -½ Σ_k Σ_c (e_kc/σ_c)² - N Σ_c log σ_c - (N m/2) log 2π.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np

from .. import statistics
from ..identify.problem import FitProblem
from ..identify.result import FitResult
from ..statistics import covariance
from .errors import BayesError
from .priors import LOG_2PI, Prior


class LogPosterior:
    """Vectorised log posterior for emcee: ``(n_walkers, n_free) -> (n_walkers,)``.

    Free values outside the support give -inf without simulating; every call simulates all
    inside rows in one batched simulator call. ``noise_sigma`` None = concentrated det R
    likelihood, else (n_channels,) known noise σ in the fitted channels' units.
    """

    def __init__(self, problem: FitProblem, priors: Sequence[Prior], base: np.ndarray,
                 noise_sigma: np.ndarray | None = None):
        self.problem = problem
        self.priors = list(priors)
        self.base = np.asarray(base, dtype=float)
        self.lower = np.array([p.lower for p in self.priors])
        self.upper = np.array([p.upper for p in self.priors])
        self.noise_sigma = None if noise_sigma is None else np.asarray(noise_sigma, dtype=float)
        if self.noise_sigma is not None:
            if self.noise_sigma.shape != (len(problem.channels),) or not np.all(self.noise_sigma > 0):
                raise BayesError(f"known noise σ must be {len(problem.channels)} positive numbers "
                                 f"(channels {', '.join(problem.channels)}), got {self.noise_sigma}")
        self.n_simulations = 0

    @property
    def n_free(self) -> int:
        return len(self.priors)

    def log_prior(self, free: np.ndarray) -> np.ndarray:
        """(n,) sum of prior log densities of (n, n_free) values."""
        free = np.atleast_2d(free)
        return np.sum([p.logpdf(free[:, j]) for j, p in enumerate(self.priors)], axis=0)

    def log_likelihood_of_residuals(self, residuals: np.ndarray) -> np.ndarray:
        """(n,) log L of residuals (n, N, n_channels); -inf for a singular R or NaN residuals."""
        n_obs = residuals.shape[1]
        if self.noise_sigma is None:
            ll = -0.5 * n_obs * statistics.log_det_r(covariance(residuals))  # singular R: +inf log det, -inf here
        else:
            s = self.noise_sigma
            # Σ_k Σ_c (e_kc/σ_c)² as (Σ_k e_kc²) · σ⁻²: no scaled copy of the residuals
            sq = np.einsum("skc,skc->sc", residuals, residuals)
            ll = (-0.5 * (sq @ s ** -2.0)
                  - n_obs * np.sum(np.log(s)) - 0.5 * n_obs * s.size * LOG_2PI)
        return np.where(np.isfinite(ll), ll, -np.inf)

    def log_likelihood(self, free: np.ndarray) -> np.ndarray:
        """(n,) log L at (n, n_free) free values (one batched simulation)."""
        free = np.atleast_2d(free)
        residuals = self.problem.residuals(self.problem.full_vectors(free, self.base))
        self.n_simulations += free.shape[0]
        return self.log_likelihood_of_residuals(residuals)

    def __call__(self, free: np.ndarray) -> np.ndarray:
        free = np.atleast_2d(np.asarray(free, dtype=float))
        lp = self.log_prior(free)
        ok = np.isfinite(lp)
        if np.any(ok):
            lp[ok] += self.log_likelihood(free[ok])
        lp[~np.isfinite(lp)] = -np.inf
        return lp


class OneAtATime:
    """The same posterior evaluated one walker per simulator call (the unbatched peer)."""

    def __init__(self, posterior: LogPosterior):
        self.posterior = posterior

    def __call__(self, free: np.ndarray) -> float:
        return float(self.posterior(np.asarray(free)[None, :])[0])


def known_noise_sigma(problem: FitProblem, fit: FitResult) -> np.ndarray:
    """(n_channels,) per-channel σ taken as known: the RMS residual at the ML estimate."""
    e = problem.residuals(fit.estimate[None])[0]
    return np.sqrt(np.mean(e ** 2, axis=0))
