"""Run control of :func:`ema_uq.bayes.sample`: walkers, ensembles, step cap, moves."""
from __future__ import annotations

import math
from dataclasses import dataclass

from .errors import BayesError

DEFAULT_ENSEMBLES = 4         # R-hat across ensembles needs several independent ones
DEFAULT_SPREAD = 9.0         # start from N(Θ_ML, 9 Σ_CRB): three Cramér-Rao sd, overdispersed
INDEPENDENCE_WALKERS = 16    # walkers per ensemble for the independence mix (any n_free)
MOVE_KINDS = ("independence", "de", "stretch")


@dataclass(frozen=True)
class SamplerSettings:
    """Run control.

    n_walkers: walkers per ensemble (None: 16 for ``"independence"``, else max(2 n_free, 16),
    rounded up to even);
    n_ensembles: independent ensembles (default 4; R-hat and ESS compare them); max_steps:
    step cap per ensemble; check_every: steps between stopping-rule checks; spread: c in
    N(Θ_ML, c Σ_CRB) for the start (default 9: overdispersed, three Cramér-Rao sd);
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
    spread: float = DEFAULT_SPREAD
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


def check_settings(settings: SamplerSettings, n_free: int) -> int:
    """Walkers per ensemble of ``settings`` for ``n_free`` free parameters; a one-line
    :class:`BayesError` for settings that cannot run."""
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
