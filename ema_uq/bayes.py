"""Bayesian posterior of the free parameters by emcee, started from the ML estimate and
exported to ArviZ.

Posterior (free parameters Θ, n_free of them)::

    log p(Θ | z) = log L(Θ) + Σ_j log π_j(Θ_j) + const

Likelihood, one of:

- ``"estimated"`` (default): the concentrated output-error likelihood
  log L = -(N/2) log det R(Θ), R = (1/N) Σ_k e_k e_kᵀ. It is also the exact marginal
  likelihood of Gaussian white residuals with unknown covariance under the Jeffreys prior
  p(R) ∝ |R|^{-(m+1)/2}, so the posterior over Θ is a proper marginal, not a plug-in.
- known per-channel noise σ_c [channel units]: Gaussian,
  log L = -½ Σ_k Σ_c (e_kc/σ_c)² - N Σ_c log σ_c - (N m/2) log 2π.

Priors π_j per free parameter: flat on the parameter's bounds (improper when a bound is
infinite), the rig pseudo-measurement N(rig, σ_rig) for parameters with ``prior_std``
(p_ACE, p_PCE), or a user choice ``lognormal:mu,sigma`` (of ln Θ) / ``uniform:lo,hi`` /
``normal:mean,sd``; every prior is restricted to the parameter's bounds.

Sampling: ``n_ensembles`` independent emcee ensembles (default 2) of ``n_walkers`` walkers
(default 16), started from N(Θ_ML, c Σ_CRB) restricted to the support, every
log-probability call a batch (``vectorize=True``) through one simulator call. Default moves:
70 % independence Metropolis-Hastings steps with a Student-t proposal (20 degrees of freedom,
covariance 1.25 Σ_CRB, centred at Θ_ML; exact through the proposal density ratio), 30 %
differential-evolution steps. With data this informative the HT/LS posterior is close to
N(Θ_ML, Σ_CRB): about 75 % of the independent proposals are accepted and τ is ~3 steps
instead of ~70 with DE alone (see ``benchmarks/sample.py``). The LT/HS posterior departs
from the Gaussian along L_A, p_PCE and p_ACE (1.7 times the Cramér-Rao variance along one
direction, skewed, heavy-tailed): every walker moves in only 25-34 % of the steps and τ is
10-20 steps, so its chains need 1000-2000 steps after the pilot.

Stopping rule (:func:`check_stop`), evaluated every ``check_every`` steps: every chain is
longer than 50 τ, τ changed by < 1 % since the previous check (or by less than three
standard errors of its estimate, which a τ of a few steps needs), and the kept draws give
rank-normalised R-hat < 1.01 and bulk and tail ESS >= 400 for every parameter. R-hat of
chains with τ > 1 exceeds 1 by about (τ - 1)/L for L kept draws per chain, so with short τ it
is R-hat, not 50 τ, that sets the length.

Each ensemble is one group of an emcee HDF5 backend that also stores its random state after
every step, so a killed run resumes exactly where it stopped and gives the chain an
uninterrupted run would have given. The stopping rule uses only the stored chains, so it is
resume-invariant as well.

Layout of the ArviZ export: ArviZ ``chain`` = one walker (``ensemble``/``walker``
coordinates say which), so R-hat compares walkers within and across the independent
ensembles; ``draw`` = kept step after burn-in and thinning.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from .identify.problem import FitProblem
from .identify.result import FitResult

HDI_PROB = 0.9
AUTOCORR_FACTOR = 50.0       # every chain must be longer than 50 τ
TAU_RTOL = 0.01              # and τ must have changed by < 1 % since the previous check ...
TAU_CHANGE_SE = 3.0          # ... or by less than 3 standard errors of that change
AUTOCORR_WINDOW = 5.0        # emcee's window constant c: τ is summed over lags M >= c τ
RHAT_MAX = 1.01              # and the kept draws must give rank-normalised split R-hat < 1.01
ESS_MIN = 400.0              # and bulk and tail ESS >= 400 for every parameter
DEFAULT_ENSEMBLES = 2
INDEPENDENCE_WALKERS = 16    # walkers per ensemble for the independence mix (any n_free)
PLACEMENT_ROUNDS = 50        # rejection rounds when drawing start positions
_LOG_2PI = math.log(2.0 * math.pi)


class BayesError(ValueError):
    """Bad sampling input: init of another concept, impossible prior, walkers that cannot be
    placed, a backend of another run."""


# --------------------------------------------------------------------------------------
# priors
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Prior:
    """Prior of one free parameter, restricted to ``[lower, upper]``.

    ``kind``: ``"flat"`` (constant density on the bounds; a, b unused), ``"uniform"``
    (on [a, b]), ``"normal"`` (mean a, sd b), ``"lognormal"`` (ln Θ ~ N(a, b)). Values in
    the parameter's units. ``lower``/``upper`` are the effective support (bounds ∩ prior).
    """

    kind: str
    a: float = 0.0
    b: float = 0.0
    lower: float = -np.inf
    upper: float = np.inf

    def logpdf(self, x: np.ndarray) -> np.ndarray:
        """Log density (n,) of values (n,); -inf outside the support. Normalised except for
        the truncation to the bounds (a constant)."""
        x = np.asarray(x, dtype=float)
        inside = (x >= self.lower) & (x <= self.upper)
        if self.kind == "flat":
            width = self.upper - self.lower
            val = np.full_like(x, -math.log(width) if np.isfinite(width) else 0.0)
        elif self.kind == "uniform":
            val = np.full_like(x, -math.log(self.b - self.a))
        elif self.kind == "normal":
            val = -0.5 * ((x - self.a) / self.b) ** 2 - math.log(self.b) - 0.5 * _LOG_2PI
        elif self.kind == "lognormal":
            with np.errstate(divide="ignore", invalid="ignore"):
                lx = np.log(x)
                val = -0.5 * ((lx - self.a) / self.b) ** 2 - lx - math.log(self.b) - 0.5 * _LOG_2PI
            inside &= x > 0
        else:  # pragma: no cover - constructor guards
            raise BayesError(f"unknown prior kind {self.kind!r}")
        return np.where(inside, val, -np.inf)

    def describe(self) -> str:
        support = f"on [{self.lower:g}, {self.upper:g}]"
        if self.kind == "flat":
            return f"flat {support}"
        return f"{self.kind}:{self.a:g},{self.b:g} {support}"


def make_prior(name: str, kind: str, a: float, b: float, lower: float, upper: float) -> Prior:
    """A :class:`Prior` for parameter ``name`` with bounds [lower, upper]; one-line errors."""
    if kind not in ("flat", "uniform", "normal", "lognormal"):
        raise BayesError(f"prior of {name}: unknown kind {kind!r}; use lognormal:mu,sigma, uniform:lo,hi or normal:mean,sd")
    if kind != "flat" and not (math.isfinite(a) and math.isfinite(b)):
        raise BayesError(f"prior of {name}: {kind}:{a:g},{b:g} needs two finite numbers")
    if kind == "uniform":
        if not a < b:
            raise BayesError(f"prior of {name}: uniform:{a:g},{b:g} has lower bound not below upper bound; give lo < hi")
        lo, hi = max(lower, a), min(upper, b)
    elif kind in ("normal", "lognormal"):
        if not b > 0:
            raise BayesError(f"prior of {name}: {kind}:{a:g},{b:g} needs a positive spread (second number)")
        lo, hi = (max(lower, 0.0), upper) if kind == "lognormal" else (lower, upper)
    else:
        lo, hi = lower, upper
    if not lo < hi:
        raise BayesError(f"prior of {name}: {kind}:{a:g},{b:g} has no support inside the bounds "
                         f"[{lower:g}, {upper:g}] of {name}; choose a prior that overlaps them")
    return Prior(kind, float(a), float(b), float(lo), float(hi))


def parse_prior(text: str) -> tuple[str, str, float, float]:
    """``NAME=kind:a,b`` (command-line ``--prior``) -> (name, kind, a, b)."""
    name, sep, rest = text.partition("=")
    kind, sep2, values = rest.partition(":")
    parts = [v.strip() for v in values.split(",")]
    try:
        if not (sep and sep2 and name.strip()) or len(parts) != 2:
            raise ValueError
        a, b = float(parts[0]), float(parts[1])
    except ValueError:
        raise BayesError(f"cannot read --prior {text!r}: write NAME=lognormal:mu,sigma, NAME=uniform:lo,hi "
                         "or NAME=normal:mean,sd, e.g. J=uniform:0.01,0.1") from None
    return name.strip(), kind.strip().lower(), a, b


def build_priors(problem: FitProblem, overrides: Mapping[str, tuple[str, float, float]] | None = None) -> list[Prior]:
    """Priors of the free parameters in free-vector order.

    Default: flat on the bounds; N(rig, σ_rig) for parameters with ``prior_std``.
    ``overrides`` maps a free parameter name to (kind, a, b).
    """
    params = problem.parameters
    overrides = dict(overrides or {})
    for name in overrides:
        params.index(name)
        if name not in params.free_names:
            raise BayesError(f"--prior {name}: {name} is fixed in the init fit; give priors for free parameters "
                             f"only ({', '.join(params.free_names)})")
    priors = []
    for i in problem.free_index:
        p = params.parameters[i]
        if p.name in overrides:
            priors.append(make_prior(p.name, *overrides[p.name], p.lower, p.upper))
        elif p.prior_std is not None:
            priors.append(make_prior(p.name, "normal", p.nominal, p.prior_std, p.lower, p.upper))
        else:
            priors.append(make_prior(p.name, "flat", 0.0, 0.0, p.lower, p.upper))
    return priors


# --------------------------------------------------------------------------------------
# the log posterior
# --------------------------------------------------------------------------------------
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
            r = np.einsum("ski,skj->sij", residuals, residuals) / n_obs
            with np.errstate(invalid="ignore"):          # a diverged simulation: NaN -> -inf below
                sign, logdet = np.linalg.slogdet(r)
            ll = -0.5 * n_obs * logdet
            ll = np.where(sign > 0, ll, -np.inf)
        else:
            s = self.noise_sigma
            ll = (-0.5 * np.sum((residuals / s) ** 2, axis=(1, 2))
                  - n_obs * np.sum(np.log(s)) - 0.5 * n_obs * s.size * _LOG_2PI)
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


class _OneAtATime:
    """The same posterior evaluated one walker per simulator call (the unbatched peer)."""

    def __init__(self, posterior: LogPosterior):
        self.posterior = posterior

    def __call__(self, free: np.ndarray) -> float:
        return float(self.posterior(np.asarray(free)[None, :])[0])


# --------------------------------------------------------------------------------------
# settings, start positions, backend bookkeeping
# --------------------------------------------------------------------------------------
MOVE_KINDS = ("independence", "de", "stretch")


@dataclass(frozen=True)
class SamplerSettings:
    """Run control.

    n_walkers: walkers per ensemble (None: 16 for ``"independence"``, else max(2 n_free, 16),
    rounded up to even);
    n_ensembles: independent ensembles; max_steps: step cap per ensemble; check_every:
    steps between stopping-rule checks; spread: c in N(Θ_ML, c Σ_CRB) for the start;
    n_predictive: posterior draws simulated for the predictive group; vectorize: one
    batched call per log-probability evaluation (False = one call per walker, for benchmarks);
    integrator: of the likelihood's simulations, "rk4", "dopri5" or "hybrid" (None: the
    model's; see :func:`ema_uq.simulate.simulate_batch`). The adaptive ones are faster (dopri5
    1.6-2.7 times, hybrid 5-10 times on the deploy-retract run); their step selection jitters
    log L by ~1e-4 (3.5e-4 on LT/HS), which stalls a Gauss-Newton line search but is far below
    what changes an MCMC acceptance decision.

    moves, one of :data:`MOVE_KINDS`:

    - ``"independence"`` (default): with probability ``independence_weight`` a step is an
      independence Metropolis-Hastings move (every walker proposes a draw of a multivariate
      Student-t with ``proposal_df`` degrees of freedom centred at Θ_ML whose covariance is
      ``proposal_scale`` · Σ_CRB), otherwise a differential-evolution step as ``"de"``. The
      data make the posterior nearly Gaussian around Θ_ML, so most independent proposals are
      accepted and every walker decorrelates in a few steps; the polynomial tails of the
      proposal keep π/q bounded for a Gaussian-tailed posterior, and the DE steps move walkers
      locally where the posterior departs from the Gaussian (the red-blue split of a DE step
      then needs no 2·n_free walkers: the independence steps already move every walker
      through all directions). Lighter tails than the usual 5-10 degrees of freedom measured
      better on both concepts: acceptance of the independent proposals on HT/LS 0.75 with
      df 20 against 0.69 with df 10 and 0.62 with df 7 (covariance 1.25 Σ_CRB each).
      After a pilot of ``adapt_steps`` steps (0: none) the proposal is adapted once, and
      then frozen: centred at the mean of the pilot's second half and widened along the
      principal directions of the Cramér-Rao correlation matrix in which the pilot spread
      further than the bound (:func:`adapted_proposal`); the stopping rule and the exported
      draws use only the steps after it. On LT/HS one direction (L_A with p_PCE and p_ACE)
      has 1.7 times the Cramér-Rao variance, skewness -0.6 and a long tail; neither a
      covariance from the pilot nor t factors along the directions in which a quadratic fit
      of the pilot's log posterior falls off slowest raised the acceptance (measured on two
      seeds; see the study file).
    - ``"de"``: differential evolution 80 % + snooker 20 %.
    - ``"stretch"``: emcee's affine-invariant stretch move.
    """

    n_walkers: int | None = None
    n_ensembles: int = DEFAULT_ENSEMBLES
    max_steps: int = 20000
    check_every: int = 50
    spread: float = 1.0
    moves: str = "independence"
    n_predictive: int = 100
    vectorize: bool = True
    independence_weight: float = 0.7
    proposal_df: float = 20.0
    proposal_scale: float = 1.25
    adapt_steps: int = 100
    defensive_weight: float = 0.0
    defensive_width: float = 2.0
    integrator: str | None = None

    def walkers_for(self, n_free: int) -> int:
        if self.n_walkers is not None:
            return int(self.n_walkers)
        if self.moves == "independence":
            return INDEPENDENCE_WALKERS
        n = max(2 * n_free, 16)
        return n + n % 2

    def move_description(self) -> str:
        """One line naming the moves and their weights (stored with the result)."""
        de = "DE 80 % + DE snooker 20 %"
        if self.moves == "independence":
            wide = (f"; {self.defensive_weight:.0%} of draws from a {self.defensive_width:g}x wider component"
                    if self.defensive_weight > 0 else "")
            return (f"independence MH {self.independence_weight:.0%} (Student-t df {self.proposal_df:g}, "
                    f"covariance {self.proposal_scale:g} x Cramér-Rao covariance, centred at the ML estimate{wide}) "
                    f"+ ({de}) {1 - self.independence_weight:.0%}")
        return de if self.moves == "de" else "stretch (a = 2)"


def _check_settings(settings: SamplerSettings, n_free: int) -> int:
    n_walkers = settings.walkers_for(n_free)
    if settings.moves == "independence":
        if n_walkers < 6 or n_walkers % 2:
            raise BayesError(f"{n_walkers} walkers: the DE steps of the independence mix need an even number "
                             "of at least 6; raise --walkers")
    elif n_walkers < 2 * n_free:
        raise BayesError(f"{n_walkers} walkers for {n_free} free parameters: emcee's {settings.moves} move needs "
                         f"at least 2 x {n_free} = {2 * n_free}; raise --walkers")
    if settings.n_ensembles < 1:
        raise BayesError(f"need at least one ensemble (--chains), got {settings.n_ensembles}")
    if settings.max_steps < 1 or settings.check_every < 1:
        raise BayesError("max_steps and check_every must be positive")
    if not (math.isfinite(settings.spread) and settings.spread > 0):
        raise BayesError(f"--spread must be a positive number, got {settings.spread}")
    if settings.moves not in MOVE_KINDS:
        raise BayesError(f"unknown moves {settings.moves!r}; choose {', '.join(MOVE_KINDS)}")
    if not 0.0 < settings.independence_weight <= 1.0:
        raise BayesError(f"independence move weight must be in (0, 1], got {settings.independence_weight}")
    if not (math.isfinite(settings.proposal_df) and settings.proposal_df > 2):
        raise BayesError(f"Student-t proposal degrees of freedom must be above 2 (finite covariance), "
                         f"got {settings.proposal_df}")
    if not (math.isfinite(settings.proposal_scale) and settings.proposal_scale > 0):
        raise BayesError(f"proposal scale must be a positive number, got {settings.proposal_scale}")
    if not 0.0 <= settings.defensive_weight < 1.0:
        raise BayesError(f"defensive mixture weight must be in [0, 1), got {settings.defensive_weight}")
    if not (math.isfinite(settings.defensive_width) and settings.defensive_width >= 1.0):
        raise BayesError(f"defensive component width must be a number >= 1, got {settings.defensive_width}")
    if settings.integrator not in (None, "rk4", "dopri5", "hybrid"):
        raise BayesError(f"unknown integrator {settings.integrator!r}; choose rk4, dopri5 or hybrid")
    if settings.adapt_steps < 0 or settings.adapt_steps == 1:
        raise BayesError(f"pilot of {settings.adapt_steps} steps: give 0 (no adaptation) or at least 2 steps")
    return n_walkers


def _cholesky(cov: np.ndarray, n: int, what: str) -> np.ndarray:
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


def _independence_move(proposal: StudentTProposal | DefensiveMixture):
    """emcee move: every walker proposes an independent draw x' ~ q and accepts it with
    probability min(1, π(x') q(x) / (π(x) q(x'))). The factor log q(x) - log q(x') goes to
    emcee as the proposal's log ratio, so the move leaves π exactly invariant however far q
    is from π; q only sets the acceptance rate."""
    import emcee

    class IndependenceMove(emcee.moves.MHMove):
        def __init__(self):
            super().__init__(self._propose, ndim=proposal.center.size)

        @staticmethod
        def _propose(coords: np.ndarray, random) -> tuple[np.ndarray, np.ndarray]:
            new = proposal.draw(random, coords.shape[0])
            return new, proposal.logpdf(coords) - proposal.logpdf(new)

    return IndependenceMove()


def _moves(settings: SamplerSettings, center: np.ndarray | None = None, cov: np.ndarray | None = None):
    """emcee moves for ``settings.moves``; the independence move needs the ML ``center``
    (n_free,) and the Cramér-Rao ``cov`` (n_free, n_free)."""
    import emcee

    if settings.moves == "de":
        return [(emcee.moves.DEMove(), 0.8), (emcee.moves.DESnookerMove(), 0.2)]
    if settings.moves == "stretch":
        return emcee.moves.StretchMove()
    # t_ν scale matrix S has covariance ν/(ν-2)·S
    df = settings.proposal_df
    chol = _cholesky(settings.proposal_scale * (df - 2.0) / df * np.asarray(cov, dtype=float), len(center),
                     "build the independence proposal")
    proposal = StudentTProposal(center, chol, df)
    if settings.defensive_weight > 0.0:
        proposal = DefensiveMixture(proposal, StudentTProposal(center, settings.defensive_width * chol, df),
                                    settings.defensive_weight)
    move = _independence_move(proposal)
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


def place_walkers(rng: np.random.Generator, posterior: LogPosterior, center: np.ndarray, cov: np.ndarray,
                  spread: float, n_walkers: int, n_ensembles: int) -> np.ndarray:
    """Start positions (n_ensembles, n_walkers, n_free) from N(center, spread·cov) restricted to
    the support and to finite log posterior (rejection: out-of-support draws are redrawn).

    Raises :class:`BayesError` when the centre is outside the support or when too few draws
    land inside it.
    """
    names = posterior.problem.parameters.free_names
    outside = [n for n, c, lo, hi in zip(names, center, posterior.lower, posterior.upper) if not lo <= c <= hi]
    if outside:
        j = names.index(outside[0])
        raise BayesError(f"cannot place walkers: the ML estimate of {outside[0]} = {center[j]:g} lies outside its prior "
                         f"support [{posterior.lower[j]:g}, {posterior.upper[j]:g}]; widen the prior or refit")
    chol = _cholesky(spread * np.asarray(cov, dtype=float), center.size, "place walkers")
    need = n_walkers * n_ensembles
    kept = np.empty((0, center.size))
    drawn = 0
    for _ in range(PLACEMENT_ROUNDS):
        draws = center + rng.standard_normal((2 * need, center.size)) @ chol.T
        drawn += draws.shape[0]
        draws = draws[np.all((draws > posterior.lower) & (draws < posterior.upper), axis=1)]
        if draws.shape[0]:
            draws = draws[: need - kept.shape[0]]
            draws = draws[np.isfinite(posterior(draws))]
            kept = np.concatenate([kept, draws])
        if kept.shape[0] >= need:
            return kept[:need].reshape(n_ensembles, n_walkers, center.size)
    raise BayesError(f"cannot place {need} walkers inside the support: only {kept.shape[0]} of {drawn} draws from "
                     f"N(Θ_ML, {spread:g}·Σ_CRB) have a finite posterior; reduce --spread or widen the priors")


def _ensemble_seeds(seed: int, n: int) -> tuple[np.random.Generator, list[np.random.RandomState]]:
    """A Generator for start positions / predictive draws and one RandomState per ensemble,
    all derived from ``seed`` (independent streams through SeedSequence.spawn)."""
    ss = np.random.SeedSequence(seed)
    children = ss.spawn(n + 1)
    return np.random.default_rng(children[0]), [np.random.RandomState(np.random.MT19937(c)) for c in children[1:]]


def _signature(problem: FitProblem, priors, base, center, noise_sigma, settings, n_walkers, seed) -> str:
    """Hash of everything that determines the chains; a backend of another run is refused."""
    h = hashlib.sha256()
    for arr in (problem.observed, base, center, np.zeros(0) if noise_sigma is None else noise_sigma):
        h.update(np.ascontiguousarray(arr, dtype=float).tobytes())
    h.update(json.dumps({
        "concept": problem.model.name, "channels": list(problem.channels),
        "free": list(problem.parameters.free_names), "priors": [p.describe() for p in priors],
        "walkers": n_walkers, "ensembles": settings.n_ensembles, "spread": settings.spread,
        "moves": settings.move_description(), "seed": seed, "check_every": settings.check_every,
        "adapt_steps": settings.adapt_steps if settings.moves == "independence" else 0,
        "integrator": problem.model.integrator,
    }, sort_keys=True).encode())
    return h.hexdigest()[:32]


def _open_backends(path: str | os.PathLike, signature: str, n_ensembles: int, replace_stale: bool = False
                   ) -> tuple[list, Path | None]:
    """One emcee HDFBackend group per ensemble in ``path``, and where a stale file went.

    A file of another run is refused, or with ``replace_stale`` moved aside to
    ``<stem>.stale.h5`` (replacing an older one) and the run starts afresh: a workflow reruns
    the stage after its data or settings changed."""
    import emcee
    import h5py

    path = Path(path)
    aside = None
    if path.exists():
        try:
            with h5py.File(path, "r") as f:
                stored = f.attrs.get("ema_uq_signature")
        except OSError:
            raise BayesError(f"backend {path} is not an HDF5 file; delete it or choose another --backend") from None
        stale = stored is None or (stored.decode() if isinstance(stored, bytes) else str(stored)) != signature
        if stale and replace_stale:
            aside = path.with_name(path.stem + ".stale.h5")
            path.replace(aside)
        elif stale:
            raise BayesError(f"backend {path} holds a run with different data or settings; delete it to start "
                             "afresh, choose another --backend or give --replace-stale-backend")
    if not path.exists():
        path.parent.mkdir(parents=True, exist_ok=True)
        with h5py.File(path, "w") as f:
            f.attrs["ema_uq_signature"] = signature
    return [emcee.backends.HDFBackend(str(path), name=f"ensemble_{k}") for k in range(n_ensembles)], aside


# --------------------------------------------------------------------------------------
# the stopping rule
# --------------------------------------------------------------------------------------
def autocorr_times(chain: np.ndarray) -> np.ndarray:
    """Integrated autocorrelation time [steps] per parameter of one ensemble's chain
    (n_steps, n_walkers, n_free), emcee's estimator without the length check."""
    import emcee

    with np.errstate(invalid="ignore", divide="ignore"):
        tau = emcee.autocorr.integrated_time(chain, tol=0)
    # a walker that never moved in a very short chain has no autocorrelation estimate:
    # take the whole length, the most pessimistic value
    return np.where(np.isfinite(tau), tau, float(chain.shape[0]))


def burn_in_and_thin(taus: np.ndarray, n: int) -> tuple[int, int]:
    """Burn-in 2 max τ and thinning ½ min τ [steps] for chains of ``n`` steps, leaving at
    least 4 kept draws per walker."""
    burn = int(min(max(1, math.ceil(2.0 * np.max(taus))), n - 1))
    thin = int(max(1, math.floor(0.5 * np.min(taus))))
    return burn, min(thin, max(1, (n - burn) // 4))


def tau_change_tolerance(taus: np.ndarray, n: int, check_every: int, n_walkers: int) -> np.ndarray:
    """Relative change of τ [-] accepted between the estimates at ``n - check_every`` and
    ``n`` steps: 1 %, or 3 standard errors of the change when the estimator cannot resolve 1 %.

    Sokal's variance of the windowed estimator from n·W draws of W walkers, window
    M = c τ: var(τ̂)/τ² = 2(2M + 1)/(n W). The two estimates share their first n - Δ steps,
    so their difference has variance var(τ̂)·Δ/(n - Δ). For short τ (independence moves,
    τ of a few steps) the 1 % test alone would be decided by estimator noise for thousands
    of steps after the chains have converged; for long τ it is unchanged.
    """
    window = AUTOCORR_WINDOW * np.asarray(taus, dtype=float)
    rel_var = 2.0 * (2.0 * window + 1.0) / (n * n_walkers)
    rel_se_change = np.sqrt(rel_var * check_every / max(n - check_every, 1))
    return np.maximum(TAU_RTOL, TAU_CHANGE_SE * rel_se_change)


@dataclass(frozen=True)
class StopCheck:
    """The stopping rule at step ``n``, from the first n stored steps only (so a resumed run
    decides exactly as an uninterrupted one).

    ``tau`` (n_ensembles, n_free) [steps]; ``burn_in``/``thin`` [steps] of the export;
    ``max_rhat``/``min_ess_bulk``/``min_ess_tail`` over the kept draws (ArviZ, walkers as
    chains); ``missing``: the conditions not yet met (empty when converged).
    """

    n: int
    tau: np.ndarray
    burn_in: int
    thin: int
    max_rhat: float
    min_ess_bulk: float
    min_ess_tail: float
    missing: tuple[str, ...]

    @property
    def converged(self) -> bool:
        return not self.missing


STOP_RULE = (f"every chain longer than {AUTOCORR_FACTOR:g} tau, tau changed < {TAU_RTOL:.0%} (or < "
             f"{TAU_CHANGE_SE:g} standard errors of its estimate), R-hat < {RHAT_MAX:g} and bulk and tail "
             f"ESS >= {ESS_MIN:g}")


def check_stop(chains: Sequence[np.ndarray], n: int, check_every: int) -> StopCheck:
    """Evaluate the stopping rule on the first ``n`` steps of each ensemble's chain
    (n_steps, n_walkers, n_free)."""
    import arviz as az

    chains = [c[:n] for c in chains]
    taus = np.array([autocorr_times(c) for c in chains])
    burn, thin = burn_in_and_thin(taus, n)
    # (steps, walkers, p) -> (chain = ensemble*walker, draw, p), as in the export
    kept = np.concatenate([c[burn::thin].transpose(1, 0, 2) for c in chains])
    with np.errstate(invalid="ignore", divide="ignore"):
        rhat = np.array([az.rhat(kept[:, :, j]) for j in range(kept.shape[2])], dtype=float)
        ess = np.array([[az.ess(kept[:, :, j], method=m) for m in ("bulk", "tail")] for j in range(kept.shape[2])],
                       dtype=float)
    max_rhat = float(np.max(np.where(np.isfinite(rhat), rhat, np.inf)))
    min_ess = np.min(np.where(np.isfinite(ess), ess, 0.0), axis=0)
    missing = []
    if not np.all(n > AUTOCORR_FACTOR * taus):
        missing.append(f"{AUTOCORR_FACTOR:g} tau = {AUTOCORR_FACTOR * np.max(taus):.0f} steps")
    if n <= check_every:
        missing.append("a previous tau estimate")
    else:
        prev = np.array([autocorr_times(c[: n - check_every]) for c in chains])
        tolerance = tau_change_tolerance(taus, n, check_every, chains[0].shape[1])
        if not np.all(np.abs(taus - prev) / taus < tolerance):
            missing.append("stable tau")
    if not max_rhat < RHAT_MAX:
        missing.append(f"R-hat < {RHAT_MAX:g}")
    if not np.all(min_ess >= ESS_MIN):
        missing.append(f"ESS >= {ESS_MIN:g}")
    return StopCheck(n, taus, burn, thin, max_rhat, float(min_ess[0]), float(min_ess[1]), tuple(missing))


# --------------------------------------------------------------------------------------
# the result
# --------------------------------------------------------------------------------------
@dataclass
class PosteriorResult:
    """Outcome of :func:`sample`: the ArviZ InferenceData plus run facts.

    ``idata`` groups: ``posterior`` (one variable per free parameter, dims chain, draw),
    ``sample_stats`` (``lp`` log posterior, ``log_prior``, ``accepted`` 0/1 at each kept
    step, ``acceptance_rate`` per walker), ``log_likelihood`` (``z``: total log L of all
    data per draw; pointwise values would be N x draws), ``observed_data`` (fitted channels,
    dim ``obs`` with ``time``/``experiment`` coordinates) and ``posterior_predictive``
    (``<channel>``: replicate with noise, ``<channel>_model``: noise-free output, for a
    random subsample of draws). Run facts live in ``idata.posterior.attrs`` and are
    mirrored by the properties below.
    """

    idata: Any

    # --- run facts ---------------------------------------------------------------
    @property
    def attrs(self) -> dict[str, Any]:
        return dict(self.idata.posterior.attrs)

    def _json_attr(self, key: str):
        return json.loads(self.idata.posterior.attrs[key])

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self._json_attr("free_parameters"))

    @property
    def converged(self) -> bool:
        return bool(int(self.idata.posterior.attrs["converged"]))

    @property
    def n_steps(self) -> int:
        return int(self.idata.posterior.attrs["n_steps"])

    @property
    def burn_in(self) -> int:
        return int(self.idata.posterior.attrs["burn_in"])

    @property
    def thin(self) -> int:
        return int(self.idata.posterior.attrs["thin"])

    @property
    def tau(self) -> np.ndarray:
        """(n_ensembles, n_free) integrated autocorrelation times [steps] at the end."""
        return np.array(self._json_attr("tau"))

    @property
    def seed(self) -> int:
        return int(self.idata.posterior.attrs["seed"])

    @property
    def wall_time_s(self) -> float:
        return float(self.idata.posterior.attrs["wall_time_s"])

    @property
    def n_simulations(self) -> int:
        return int(self.idata.posterior.attrs["n_simulations"])

    @property
    def ml_estimate(self) -> np.ndarray:
        return np.array(self._json_attr("ml_estimate"))

    @property
    def crb_std(self) -> np.ndarray:
        return np.array(self._json_attr("crb_std"))

    # --- numbers -----------------------------------------------------------------
    def draws(self) -> np.ndarray:
        """(n_chains, n_draws, n_free) kept samples in free-vector order."""
        return np.stack([self.idata.posterior[n].values for n in self.names], axis=-1)

    def summary(self, hdi_prob: float = HDI_PROB):
        """pandas DataFrame per free parameter: mean, sd, hdi bounds, mcse_mean, mcse_sd,
        ess_bulk, ess_tail, r_hat (ArviZ), plus the ML estimate and its Cramér-Rao σ."""
        import arviz as az

        table = az.summary(self.idata, var_names=list(self.names), hdi_prob=hdi_prob, round_to="none")
        table["ml"] = self.ml_estimate
        table["crb_sd"] = self.crb_std
        return table

    def interval(self, prob: float = HDI_PROB) -> np.ndarray:
        """(n_free, 2) highest-density intervals."""
        import arviz as az

        hdi = az.hdi(self.idata.posterior[list(self.names)], hdi_prob=prob)
        return np.array([hdi[n].values for n in self.names])

    def report(self) -> str:
        a = self.attrs
        head = (f"[[Posterior: {a['concept']} by emcee]] {'converged' if self.converged else 'NOT converged'} "
                f"({a['stop_reason']}); {a['n_ensembles']} ensembles x {a['n_walkers']} walkers x {self.n_steps} steps, "
                f"burn-in {self.burn_in}, thin {self.thin}, max tau {float(np.max(self.tau)):.1f}, "
                f"{self.n_simulations} simulations, {self.wall_time_s:.1f} s, seed {self.seed}")
        return head + "\n" + self.summary().to_string(float_format=lambda v: f"{v:.6g}")

    # --- files -------------------------------------------------------------------
    def to_netcdf(self, path: str | os.PathLike) -> Path:
        """Write the InferenceData (all groups) to ``path`` atomically; returns the path."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
        try:
            self.idata.to_netcdf(str(tmp), engine="h5netcdf")
            os.replace(tmp, path)
        finally:
            if tmp.exists():
                tmp.unlink()
        return path

    @classmethod
    def from_netcdf(cls, path: str | os.PathLike) -> "PosteriorResult":
        import arviz as az

        if not Path(path).is_file():
            raise BayesError(f"file {path}: no such file; run 'ema-uq sample' first")
        idata = az.from_netcdf(str(path), engine="h5netcdf")
        if "posterior" not in idata.groups() or "free_parameters" not in idata.posterior.attrs:
            raise BayesError(f"file {path} is not a posterior written by 'ema-uq sample'")
        return cls(idata.load() if hasattr(idata, "load") else idata)


# --------------------------------------------------------------------------------------
# driver
# --------------------------------------------------------------------------------------
def known_noise_sigma(problem: FitProblem, fit: FitResult) -> np.ndarray:
    """(n_channels,) per-channel σ taken as known: the RMS residual at the ML estimate."""
    e = problem.residuals(fit.estimate[None])[0]
    return np.sqrt(np.mean(e ** 2, axis=0))


def _check_fit(problem: FitProblem, fit: FitResult) -> None:
    if fit.concept != problem.model.name:
        raise BayesError(f"the init fit is of concept {fit.concept}, the data of {problem.model.name}; "
                         "use a fit of the same concept")
    if tuple(fit.names) != problem.parameters.names:
        raise BayesError(f"the init fit's parameters {', '.join(fit.names)} do not match concept {problem.model.name}")
    if tuple(fit.free_names) != problem.parameters.free_names:
        raise BayesError(f"the init fit estimated {', '.join(fit.free_names)} but the problem frees "
                         f"{', '.join(problem.parameters.free_names)}; free the same parameters")
    if np.shape(fit.covariance) != (len(fit.free_names),) * 2:
        raise BayesError("the init fit has no Cramér-Rao covariance of its free parameters; write it with 'ema-uq identify'")


def sample(
    problem: FitProblem,
    fit: FitResult,
    *,
    priors: Mapping[str, tuple[str, float, float]] | None = None,
    noise_sigma: str | np.ndarray | None = "estimated",
    settings: SamplerSettings = SamplerSettings(),
    seed: int = 0,
    backend: str | os.PathLike | None = None,
    progress: Callable[[str], None] | None = None,
    predictive: bool = True,
    replace_stale_backend: bool = False,
) -> PosteriorResult:
    """Sample the posterior of ``problem``'s free parameters starting from ``fit``.

    Parameters
    ----------
    problem : data and layout; its free parameters must be the fit's free parameters.
    fit : ML result: ``estimate`` (full vector, also the value of fixed parameters) and
        ``covariance`` (n_free, n_free) Cramér-Rao bound for the start distribution.
    priors : overrides {name: (kind, a, b)}, see :func:`build_priors`.
    noise_sigma : ``"estimated"``/None (det R likelihood), ``"known"`` (σ = RMS residual at
        the ML estimate per channel) or an (n_channels,) array of σ.
    settings : :class:`SamplerSettings`.
    seed : seeds start positions, every ensemble's emcee RandomState and the predictive draws.
    backend : HDF5 file; an existing file of the same run is resumed. None: in memory.
    progress : called with one line of text at every check.
    predictive : simulate the posterior predictive subsample.
    replace_stale_backend : a ``backend`` file of another run (other data or settings) is
        moved aside to ``<stem>.stale.h5`` instead of refused.
    """
    import emcee

    t0 = time.perf_counter()
    _check_fit(problem, fit)
    prior_list = build_priors(problem, priors)
    n_free = len(prior_list)
    n_walkers = _check_settings(settings, n_free)
    if isinstance(noise_sigma, str) and noise_sigma not in ("estimated", "known"):
        raise BayesError(f"noise sigma {noise_sigma!r}: choose known or estimated")
    if isinstance(noise_sigma, str):
        sigma = known_noise_sigma(problem, fit) if noise_sigma == "known" else None
    else:
        sigma = None if noise_sigma is None else np.asarray(noise_sigma, dtype=float)
    if settings.integrator not in (None, problem.model.integrator):
        if problem.model.batch_simulator is not None:
            raise BayesError(f"concept {problem.model.name} has its own simulator: its integrator cannot be chosen; "
                             "drop --integrator")
        problem = dataclasses.replace(problem, model=dataclasses.replace(problem.model, integrator=settings.integrator))
    base = np.asarray(fit.estimate, dtype=float)
    center = base[problem.free_index]
    posterior = LogPosterior(problem, prior_list, base, sigma)

    rng, states = _ensemble_seeds(seed, settings.n_ensembles)
    start = place_walkers(rng, posterior, center, fit.covariance, settings.spread, n_walkers, settings.n_ensembles)
    signature = _signature(problem, prior_list, base, center, sigma, settings, n_walkers, seed)
    stale_moved_to = None
    if backend is None:
        backends = [emcee.backends.Backend() for _ in range(settings.n_ensembles)]
    else:
        backends, stale_moved_to = _open_backends(backend, signature, settings.n_ensembles, replace_stale_backend)
        if stale_moved_to is not None and progress is not None:
            progress(f"backend {backend} held a run with other data or settings: moved it to {stale_moved_to}, "
                     "starting afresh")
    log_prob = posterior if settings.vectorize else _OneAtATime(posterior)

    def make_samplers(mean: np.ndarray, cov: np.ndarray) -> list:
        return [emcee.EnsembleSampler(n_walkers, n_free, log_prob, vectorize=settings.vectorize,
                                      moves=_moves(settings, mean, cov), backend=b) for b in backends]

    samplers = make_samplers(center, fit.covariance)
    for k, s in enumerate(samplers):
        if s.iteration == 0:
            s.random_state = states[k].get_state()

    def advance(k: int, target: int) -> None:
        s = samplers[k]
        todo = target - s.iteration
        if todo <= 0:
            return
        if s.iteration == 0:
            state = emcee.State(start[k], random_state=states[k].get_state())
        else:
            state = s.backend.get_last_sample()          # with the stored random state
        # emcee's check wants more walkers than parameters, which only the red-blue moves need
        for _ in s.sample(state, iterations=todo, skip_initial_state_check=settings.moves == "independence"):
            pass

    # the pilot: the proposal is adapted once at step `adapt` and frozen; the stopping rule
    # and the export see only the steps after it (all before it are burn-in)
    adapt = settings.adapt_steps if settings.moves == "independence" and settings.adapt_steps < settings.max_steps \
        else 0
    proposal_mean, proposal_cov, ratios = center, np.asarray(fit.covariance, dtype=float), None
    n, first, stop_reason = 0, 0, ""
    while True:
        n = min(n + settings.check_every, settings.max_steps, adapt if n < adapt else settings.max_steps)
        for k in range(settings.n_ensembles):
            advance(k, n)
        if n == adapt:
            pilot = np.concatenate([s.backend.get_chain()[adapt // 2: adapt].reshape(-1, n_free) for s in samplers])
            proposal_mean, proposal_cov, ratios = adapted_proposal(center, fit.covariance, pilot)
            samplers = make_samplers(proposal_mean, proposal_cov)
            first = adapt
            if progress is not None:
                j = int(np.argmax(ratios))
                shift = np.sqrt((proposal_mean - center) @ np.linalg.solve(fit.covariance, proposal_mean - center))
                progress(f"step {n}/{settings.max_steps}: end of the pilot; proposal centre moved by {shift:.2f} "
                         f"Cramér-Rao sd, widened along {int(np.sum(ratios > 1))} of {n_free} directions, at most "
                         f"x{ratios[j]:.2f} in variance (direction {j + 1}, weakest first), "
                         f"{posterior.n_simulations} simulations, {time.perf_counter() - t0:.0f} s")
            continue
        check = check_stop([s.backend.get_chain()[first:] for s in samplers], n - first, settings.check_every)
        if progress is not None:
            acc = np.mean([np.mean(s.backend.accepted) / max(s.iteration, 1) for s in samplers])
            progress(f"step {n}/{settings.max_steps}: max tau {np.max(check.tau):.1f} "
                     f"(50 tau = {AUTOCORR_FACTOR * np.max(check.tau):.0f}), R-hat {check.max_rhat:.3f}, "
                     f"bulk/tail ESS {check.min_ess_bulk:.0f}/{check.min_ess_tail:.0f}, acceptance {acc:.2f}, "
                     f"{posterior.n_simulations} simulations, {time.perf_counter() - t0:.0f} s"
                     + ("" if check.converged else f"; waiting for {', '.join(check.missing)}"))
        if n < adapt:
            continue                                     # no stopping inside the pilot
        if check.converged:
            stop_reason = STOP_RULE
            break
        if n >= settings.max_steps:
            stop_reason = (f"step cap {settings.max_steps} reached before the stopping rule "
                           f"(missing: {', '.join(check.missing)})")
            break

    converged, taus, burn, thin = check.converged, check.tau, first + check.burn_in, check.thin
    chains = [s.backend.get_chain()[:n] for s in samplers]
    log_probs = [s.backend.get_log_prob()[:n] for s in samplers]
    accepted_total = [np.asarray(s.backend.accepted) for s in samplers]
    idata = _inference_data(
        problem, posterior, fit, chains, log_probs, accepted_total, burn, thin,
        rng if predictive else None, settings.n_predictive,
        attrs={
            "concept": problem.model.name, "seed": int(seed), "converged": int(converged),
            "stop_reason": stop_reason, "n_steps": int(n), "burn_in": burn, "thin": thin,
            "n_ensembles": settings.n_ensembles, "n_walkers": n_walkers, "spread": settings.spread,
            "moves": settings.moves, "move_mix": settings.move_description(),
            "max_steps": settings.max_steps, "check_every": settings.check_every, "adapt_steps": int(first),
            "proposal_widening": json.dumps(None if ratios is None else ratios.tolist()),
            "proposal_mean": json.dumps(proposal_mean.tolist() if settings.moves == "independence" else None),
            "proposal_covariance": json.dumps(proposal_cov.tolist() if settings.moves == "independence" else None),
            "integrator": problem.model.integrator,
            "likelihood": "concentrated det R" if sigma is None else "Gaussian, known sigma",
            "noise_sigma": json.dumps(None if sigma is None else sigma.tolist()),
            "priors": json.dumps({n_: p.describe() for n_, p in zip(problem.parameters.free_names, prior_list)}),
            "tau": json.dumps(taus.tolist()),
            "free_parameters": json.dumps(list(problem.parameters.free_names)),
            "fixed_values": json.dumps({n_: float(v) for n_, v, f in zip(problem.parameters.names, base,
                                                                         problem.parameters.free_mask) if not f}),
            "ml_estimate": json.dumps(center.tolist()),
            "crb_std": json.dumps(np.sqrt(np.diag(fit.covariance)).tolist()),
            "channels": json.dumps(list(problem.channels)),
            "signature": signature,
            "stale_backend_moved_to": "" if stale_moved_to is None else str(stale_moved_to),
            "n_simulations": int(posterior.n_simulations),
            "wall_time_s": float(time.perf_counter() - t0),
        })
    return PosteriorResult(idata)


def _inference_data(problem, posterior, fit, chains, log_probs, accepted_total, burn, thin, rng, n_predictive, attrs):
    """Assemble the ArviZ InferenceData (see :class:`PosteriorResult`)."""
    import arviz as az
    import emcee
    import xarray as xr

    from . import __version__

    names = list(problem.parameters.free_names)
    n_ens, n_walkers = len(chains), chains[0].shape[1]
    n_chain = n_ens * n_walkers
    # (steps, walkers, p) -> (chain = ensemble*walker, draw, p)
    kept = np.concatenate([c[burn::thin].transpose(1, 0, 2) for c in chains])
    lp = np.concatenate([l[burn::thin].T for l in log_probs])
    moved = np.concatenate([np.any(c[1:] != c[:-1], axis=2)[burn - 1::thin].T for c in chains]).astype(float)
    n_draw = kept.shape[1]
    log_prior = posterior.log_prior(kept.reshape(-1, len(names))).reshape(n_chain, n_draw)
    rate = np.concatenate([a / chains[0].shape[0] for a in accepted_total])
    coords = {"chain": np.arange(n_chain), "draw": np.arange(n_draw)}
    chain_coords = {"ensemble": ("chain", np.repeat(np.arange(n_ens), n_walkers)),
                    "walker": ("chain", np.tile(np.arange(n_walkers), n_ens))}
    meta = {"ema_uq_version": __version__, "emcee_version": emcee.__version__,
            "arviz_version": az.__version__, "created_by": "ema_uq.bayes.sample"}
    post = xr.Dataset({n: (("chain", "draw"), kept[:, :, j], {"units": problem.parameters[n].unit})
                       for j, n in enumerate(names)}, coords={**coords, **chain_coords},
                      attrs={**meta, **attrs})
    stats = xr.Dataset({"lp": (("chain", "draw"), lp), "log_prior": (("chain", "draw"), log_prior),
                        "accepted": (("chain", "draw"), moved),
                        "acceptance_rate": (("chain",), rate)}, coords=coords, attrs=meta)
    loglik = xr.Dataset({"z": (("chain", "draw"), lp - log_prior)}, coords=coords,
                        attrs={**meta, "note": "total log likelihood of all data per draw"})
    times = np.concatenate([b.time[b.rows] for b in problem.blocks])
    exps = np.concatenate([[m.experiment.name] * b.rows.size for m, b in zip(problem.measurements, problem.blocks)])
    obs_coords = {"obs": np.arange(times.size), "time": ("obs", times), "experiment": ("obs", exps.astype(str))}
    observed = xr.Dataset({ch: ("obs", problem.observed[:, c], {"units": problem.model.unit_of(ch)})
                           for c, ch in enumerate(problem.channels)}, coords=obs_coords, attrs=meta)
    groups = {"posterior": post, "sample_stats": stats, "log_likelihood": loglik, "observed_data": observed}
    if rng is not None and n_predictive > 0:
        flat = kept.reshape(-1, len(names))
        pick = np.sort(rng.choice(flat.shape[0], size=min(n_predictive, flat.shape[0]), replace=False))
        thetas = problem.full_vectors(flat[pick], posterior.base)
        model_out = problem.predict(thetas)                       # (n_pp, N, m)
        if posterior.noise_sigma is None:
            e = problem.observed[None] - model_out
            r = np.einsum("ski,skj->sij", e, e) / e.shape[1]
            chol = np.linalg.cholesky(r)
            noise = np.einsum("sij,skj->ski", chol, rng.standard_normal(model_out.shape))
        else:
            noise = rng.standard_normal(model_out.shape) * posterior.noise_sigma
        replicate = model_out + noise
        pp_vars = {}
        for c, ch in enumerate(problem.channels):
            pp_vars[ch] = (("chain", "draw", "obs"), replicate[None, :, :, c].astype(np.float32))
            pp_vars[f"{ch}_model"] = (("chain", "draw", "obs"), model_out[None, :, :, c].astype(np.float32))
        groups["posterior_predictive"] = xr.Dataset(
            pp_vars, coords={"chain": [0], "draw": pick, **obs_coords},
            attrs={**meta, "note": "draw = index into the flattened (chain, draw) posterior; "
                                   "<channel>: with noise N(0, R(theta)) or known sigma, <channel>_model: noise-free"})
    return az.InferenceData(**groups)
