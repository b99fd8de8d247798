"""Proposals and emcee moves.

Default mix (``moves="independence"``): 70 % independence Metropolis-Hastings steps with a
Student-t proposal (20 degrees of freedom, covariance 1.25 Σ_CRB, centred at Θ_ML; exact
through the proposal density ratio), 30 % differential-evolution steps. With data this
informative the HT/LS posterior is close to N(Θ_ML, Σ_CRB): about 75 % of the independent
proposals are accepted and τ is ~3 steps instead of ~70 with DE alone (see
``benchmarks/sample.py``). The LT/HS posterior departs from the Gaussian along L_A, p_PCE and
p_ACE (1.7 times the Cramér-Rao variance along one direction, skewed, heavy-tailed): every
walker moves in only 25-34 % of the steps and τ is 10-20 steps, so its chains need
1000-2000 steps after the pilot.
"""
from __future__ import annotations

import math

import emcee
import numpy as np

from .errors import BayesError
from .settings import SamplerSettings


def cholesky_factor(cov: np.ndarray, n: int, what: str) -> np.ndarray:
    """Lower Cholesky factor of a symmetric (n, n) covariance; one-line error if it has none."""
    cov = np.asarray(cov, dtype=float)
    if cov.shape != (n, n) or not np.all(np.isfinite(cov)):
        raise BayesError(f"cannot {what}: the init fit has no finite Cramér-Rao covariance for every free "
                         "parameter; fix the non-identifiable parameters and refit")
    try:
        return np.linalg.cholesky(0.5 * (cov + cov.T))
    except np.linalg.LinAlgError:
        raise BayesError(f"cannot {what}: the init fit's Cramér-Rao covariance is not positive definite; "
                         "fix the non-identifiable parameters and refit") from None


class StudentTProposal:
    """Multivariate Student-t t_ν(center, S) with S = L Lᵀ: draws and log densities.

    ``center`` (d,) [parameter units], ``chol`` (d, d) lower Cholesky factor of the scale
    matrix S (the covariance is ν/(ν-2)·S for ν > 2), ``df`` ν > 0.
    """

    def __init__(self, center: np.ndarray, chol: np.ndarray, df: float):
        self.center = np.asarray(center, dtype=float)
        self.chol = np.asarray(chol, dtype=float)
        self.df = float(df)
        d = self.center.size
        self._whiten = np.linalg.inv(self.chol).T         # (x - center) @ _whiten: standardised
        self._norm = (math.lgamma(0.5 * (self.df + d)) - math.lgamma(0.5 * self.df)
                      - 0.5 * d * math.log(self.df * math.pi) - float(np.sum(np.log(np.diag(self.chol)))))

    def logpdf(self, x: np.ndarray) -> np.ndarray:
        """(n,) normalised log density at (n, d) points."""
        z = (np.atleast_2d(x) - self.center) @ self._whiten
        mahalanobis2 = np.sum(z * z, axis=1)
        d = self.center.size
        return self._norm - 0.5 * (self.df + d) * np.log1p(mahalanobis2 / self.df)

    def draw(self, random, n: int) -> np.ndarray:
        """(n, d) draws using ``random`` (a numpy RandomState or Generator-like with
        ``standard_normal`` and ``chisquare``)."""
        d = self.center.size
        z = random.standard_normal((n, d)) @ self.chol.T
        w = random.chisquare(self.df, n)
        return self.center + z * np.sqrt(self.df / w)[:, None]


class DefensiveMixture:
    """(1 - α) q + α q_wide: a proposal with a wider component of weight α, so that the weight
    π/q stays bounded where the posterior reaches further than q (a walker that lands there
    otherwise keeps rejecting for many steps). Same interface as :class:`StudentTProposal`."""

    def __init__(self, core: StudentTProposal, wide: StudentTProposal, weight: float):
        self.core, self.wide, self.weight = core, wide, float(weight)
        self.center = core.center

    def logpdf(self, x: np.ndarray) -> np.ndarray:
        return np.logaddexp(math.log1p(-self.weight) + self.core.logpdf(x), math.log(self.weight) + self.wide.logpdf(x))

    def draw(self, random, n: int) -> np.ndarray:
        core, wide = self.core.draw(random, n), self.wide.draw(random, n)
        return np.where((random.uniform(size=n) < self.weight)[:, None], wide, core)


class IndependenceMove(emcee.moves.MHMove):
    """emcee move: every walker proposes an independent draw x' ~ q and accepts it with
    probability min(1, π(x') q(x) / (π(x) q(x'))). The factor log q(x) - log q(x') goes to
    emcee as the proposal's log ratio, so the move leaves π exactly invariant however far q
    is from π; q only sets the acceptance rate.

    ``proposal``: a :class:`StudentTProposal` or :class:`DefensiveMixture` over the free
    parameters (n_free,).
    """

    def __init__(self, proposal: StudentTProposal | DefensiveMixture):
        self.proposal = proposal
        super().__init__(self._propose, ndim=proposal.center.size)

    def _propose(self, coords: np.ndarray, random) -> tuple[np.ndarray, np.ndarray]:
        new = self.proposal.draw(random, coords.shape[0])
        return new, self.proposal.logpdf(coords) - self.proposal.logpdf(new)


def build_moves(settings: SamplerSettings, center: np.ndarray | None = None, cov: np.ndarray | None = None):
    """emcee moves for ``settings.moves``; the independence move needs the ML ``center``
    (n_free,) and the Cramér-Rao ``cov`` (n_free, n_free)."""
    if settings.moves == "de":
        return [(emcee.moves.DEMove(), 0.8), (emcee.moves.DESnookerMove(), 0.2)]
    if settings.moves == "stretch":
        return emcee.moves.StretchMove()
    # t_ν scale matrix S has covariance ν/(ν-2)·S
    df = settings.proposal_df
    chol = cholesky_factor(settings.proposal_scale * (df - 2.0) / df * np.asarray(cov, dtype=float), len(center),
                     "build the independence proposal")
    proposal = StudentTProposal(center, chol, df)
    if settings.defensive_weight > 0.0:
        proposal = DefensiveMixture(proposal, StudentTProposal(center, settings.defensive_width * chol, df),
                                    settings.defensive_weight)
    move = IndependenceMove(proposal)
    w = settings.independence_weight
    if w >= 1.0:
        return move
    de = [(emcee.moves.DEMove(live_dangerously=True), 0.8), (emcee.moves.DESnookerMove(live_dangerously=True), 0.2)]
    return [(move, w)] + [(m, (1.0 - w) * p) for m, p in de]


def adapted_proposal(center: np.ndarray, cov: np.ndarray, pilot: np.ndarray
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centre and covariance of the independence proposal after the pilot: (center (n,),
    covariance (n, n), variance ratios (n,)).

    In the principal directions of the Cramér-Rao correlation matrix, scaled back to
    parameter units (Σ = D diag(λ) Dᵀ; the coordinates u = D⁻¹(θ - Θ_ML) are uncorrelated with
    variances λ under the bound), the centre moves to the pilot mean and the variance becomes
    λ max(1, ratio), ratio = pilot variance / λ. Widened only: a proposal narrower than the
    posterior traps walkers, one slightly too wide costs a little acceptance. In this fixed
    basis each ratio is a one-dimensional variance estimate, so pilot noise does not pile up
    in one direction as it does in the largest eigenvalue of a full sample covariance.
    ``pilot`` (n_draws, n) [parameter units]; ``center`` Θ_ML.
    """
    cov = 0.5 * (np.asarray(cov, dtype=float) + np.asarray(cov, dtype=float).T)
    sd = np.sqrt(np.diag(cov))
    lam, vec = np.linalg.eigh(cov / np.outer(sd, sd))
    directions = sd[:, None] * vec
    u = np.linalg.solve(directions, (np.asarray(pilot, dtype=float) - center).T)
    ratios = np.var(u, axis=1) / lam
    widened = directions @ np.diag(lam * np.maximum(1.0, ratios)) @ directions.T
    return center + directions @ np.mean(u, axis=1), 0.5 * (widened + widened.T), ratios
