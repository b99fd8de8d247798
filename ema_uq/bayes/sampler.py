"""The sampler: emcee ensembles started from the ML estimate, run under the stopping rule.

``n_ensembles`` independent emcee ensembles (default 4) of ``n_walkers`` walkers (default
16), started overdispersed from N(Θ_ML, c Σ_CRB) restricted to the support (c = 9: three
Cramér-Rao standard deviations, so that R-hat across the ensembles can see a run that has not
forgotten its start), every log-probability call a batch (``vectorize=True``) through one
simulator call. The independence proposal is adapted
once after a pilot and then frozen (:func:`~ema_uq.bayes.moves.adapted_proposal`).

Each ensemble is one group of an emcee HDF5 backend that also stores its random state after
every step, so a killed run resumes exactly where it stopped and gives the chain an
uninterrupted run would have given.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Mapping

import emcee
import numpy as np

from ..identify.problem import FitProblem, PredictionMemo
from ..identify.result import FitResult
from .errors import BayesError
from .moves import adapted_proposal, build_moves, cholesky_factor
from .posterior import LogPosterior, OneAtATime, known_noise_sigma
from .priors import Prior, build_priors
from .result import PosteriorResult, inference_data
from .settings import SamplerSettings, check_settings
from .stopping import AUTOCORR_FACTOR, STOP_RULE, StopCheck, check_stop

PLACEMENT_ROUNDS = 50        # rejection rounds when drawing start positions


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
    steps: Callable[[int], None] | None = None,
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
    steps : called with the number of steps every ensemble has reached, after each advance
        (a progress bar's counter; the checks come every ``settings.check_every`` steps).
    predictive : simulate the posterior predictive subsample.
    replace_stale_backend : a ``backend`` file of another run (other data or settings) is
        moved aside to ``<stem>.stale.h5`` instead of refused.
    """
    t0 = time.perf_counter()
    run = _prepare(problem, fit, priors, noise_sigma, settings, seed)
    ensembles = _Ensembles.open(run, backend, replace_stale_backend, progress)
    outcome = _run_until_stop(run, ensembles, t0, progress, steps)
    return _result(run, ensembles, outcome, predictive, t0)


# --------------------------------------------------------------------------------------
# setup: checks, the log posterior, seeds and start positions
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class _Run:
    """Everything about a run that is fixed before its first step."""

    problem: FitProblem             # with the settings' integrator
    fit: FitResult
    priors: list[Prior]             # in free-vector order
    posterior: LogPosterior
    sigma: np.ndarray | None        # known noise σ (n_channels,); None: det R likelihood
    settings: SamplerSettings
    seed: int
    n_walkers: int                  # per ensemble
    base: np.ndarray                # full vector: the ML estimate, also the fixed values
    center: np.ndarray              # (n_free,) Θ_ML
    rng: np.random.Generator        # start positions, then the predictive draws
    states: list                    # one numpy RandomState per ensemble
    start: np.ndarray               # (n_ensembles, n_walkers, n_free) start positions
    signature: str                  # hash of everything that determines the chains

    @property
    def n_free(self) -> int:
        return self.center.size


def _prepare(problem, fit, priors, noise_sigma, settings, seed) -> _Run:
    """Check the input, build the log posterior and place the walkers (see :func:`sample`)."""
    _check_fit(problem, fit)
    prior_list = build_priors(problem, priors)
    n_walkers = check_settings(settings, len(prior_list))
    sigma = _noise_sigma(problem, fit, noise_sigma)
    problem = _with_integrator(problem, settings.integrator)
    # a walker's proposals never repeat: keeping each prediction for reuse would only copy it
    # (3 % of an HT/LS run's time), so this problem keeps none
    problem = dataclasses.replace(problem, predictions=PredictionMemo(problem, capacity_bytes=0))
    base = np.asarray(fit.estimate, dtype=float)
    center = base[problem.free_index]
    posterior = LogPosterior(problem, prior_list, base, sigma)
    rng, states = _ensemble_seeds(seed, settings.n_ensembles)
    start = place_walkers(rng, posterior, center, fit.covariance, settings.spread, n_walkers, settings.n_ensembles)
    signature = _signature(problem, prior_list, base, center, sigma, settings, n_walkers, seed)
    return _Run(problem, fit, prior_list, posterior, sigma, settings, seed, n_walkers, base, center, rng, states,
                start, signature)


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


def _noise_sigma(problem: FitProblem, fit: FitResult, noise_sigma: str | np.ndarray | None) -> np.ndarray | None:
    """Known per-channel σ (n_channels,) of ``sample``'s ``noise_sigma``; None: det R likelihood."""
    if isinstance(noise_sigma, str) and noise_sigma not in ("estimated", "known"):
        raise BayesError(f"noise sigma {noise_sigma!r}: choose known or estimated")
    if isinstance(noise_sigma, str):
        return known_noise_sigma(problem, fit) if noise_sigma == "known" else None
    return None if noise_sigma is None else np.asarray(noise_sigma, dtype=float)


def _with_integrator(problem: FitProblem, integrator: str | None) -> FitProblem:
    """``problem`` whose model simulates with ``integrator`` (None: the model's own)."""
    if integrator in (None, problem.model.integrator):
        return problem
    if problem.model.batch_simulator is not None:
        raise BayesError(f"concept {problem.model.name} has its own simulator: its integrator cannot be chosen; "
                         "drop --integrator")
    return dataclasses.replace(problem, model=dataclasses.replace(problem.model, integrator=integrator))


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
    chol = cholesky_factor(spread * np.asarray(cov, dtype=float), center.size, "place walkers")
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
# the ensembles and the run under the stopping rule
# --------------------------------------------------------------------------------------
class _Ensembles:
    """The run's emcee samplers, one per ensemble, each on its own backend (an HDF5 group or
    memory). ``stale_moved_to``: where a backend file of another run was moved, or None."""

    def __init__(self, run: _Run, backends: list, stale_moved_to: Path | None = None):
        self.run, self.backends, self.stale_moved_to = run, backends, stale_moved_to
        self.log_prob = run.posterior if run.settings.vectorize else OneAtATime(run.posterior)
        self.use_proposal(run.center, run.fit.covariance)
        for k, s in enumerate(self.samplers):
            if s.iteration == 0:
                s.random_state = run.states[k].get_state()

    @classmethod
    def open(cls, run: _Run, backend: str | os.PathLike | None, replace_stale: bool,
             progress: Callable[[str], None] | None) -> "_Ensembles":
        """In-memory backends (``backend`` None) or the groups of an HDF5 file, resumed when it
        holds the same run."""
        if backend is None:
            return cls(run, [emcee.backends.Backend() for _ in range(run.settings.n_ensembles)])
        backends, moved = _open_backends(backend, run.signature, run.settings.n_ensembles, replace_stale)
        if moved is not None and progress is not None:
            progress(f"backend {backend} held a run with other data or settings: moved it to {moved}, "
                     "starting afresh")
        return cls(run, backends, moved)

    def use_proposal(self, mean: np.ndarray, cov: np.ndarray) -> None:
        """(Re)build the samplers with moves whose independence proposal is centred at ``mean``
        (n_free,) with covariance scaled from ``cov`` (n_free, n_free)."""
        s = self.run.settings
        self.samplers = [emcee.EnsembleSampler(self.run.n_walkers, self.run.n_free, self.log_prob,
                                               vectorize=s.vectorize, moves=build_moves(s, mean, cov), backend=b)
                         for b in self.backends]

    def advance(self, target: int) -> None:
        """Run every ensemble, one after the other, to ``target`` stored steps."""
        settings = self.run.settings
        for k, s in enumerate(self.samplers):
            todo = target - s.iteration
            if todo <= 0:
                continue
            if s.iteration == 0:
                state = emcee.State(self.run.start[k], random_state=self.run.states[k].get_state())
            else:
                state = s.backend.get_last_sample()          # with the stored random state
            # emcee's check wants more walkers than parameters, which only the red-blue moves need
            for _ in s.sample(state, iterations=todo, skip_initial_state_check=settings.moves == "independence"):
                pass

    def chains(self, first: int = 0, stop: int | None = None) -> list[np.ndarray]:
        """Stored steps ``first:stop`` of every ensemble, each (n_steps, n_walkers, n_free)."""
        return [s.backend.get_chain()[first:stop] for s in self.samplers]

    def acceptance(self) -> float:
        """Mean fraction of accepted moves over walkers and ensembles."""
        return float(np.mean([np.mean(s.backend.accepted) / max(s.iteration, 1) for s in self.samplers]))


@dataclass(frozen=True)
class _Outcome:
    """How a run ended."""

    n: int                          # steps run per ensemble
    first: int                      # first step after the pilot (0: no pilot)
    check: StopCheck                # the last evaluation of the stopping rule
    stop_reason: str
    proposal_mean: np.ndarray       # (n_free,) of the independence proposal at the end
    proposal_cov: np.ndarray        # (n_free, n_free)
    widening: np.ndarray | None     # (n_free,) variance ratios of the adaptation; None: none


def _pilot_length(settings: SamplerSettings) -> int:
    """Steps after which the independence proposal is adapted (0: never)."""
    if settings.moves == "independence" and settings.adapt_steps < settings.max_steps:
        return settings.adapt_steps
    return 0


def _run_until_stop(run: _Run, ensembles: _Ensembles, t0: float, progress: Callable[[str], None] | None,
                    steps: Callable[[int], None] | None = None) -> _Outcome:
    """Advance the ensembles check by check until the stopping rule holds or the step cap is
    reached. The proposal is adapted once at the end of the pilot and then frozen; the
    stopping rule and the export see only the steps after it (all before it are burn-in)."""
    settings = run.settings
    adapt = _pilot_length(settings)
    mean, cov, widening = run.center, np.asarray(run.fit.covariance, dtype=float), None
    n, first = 0, 0
    while True:
        n = min(n + settings.check_every, settings.max_steps, adapt if n < adapt else settings.max_steps)
        ensembles.advance(n)
        if steps is not None:
            steps(n)
        if n == adapt:
            mean, cov, widening = _end_pilot(run, ensembles, adapt, t0, progress)
            first = adapt
            continue
        check = check_stop(ensembles.chains(first), n - first, settings.check_every)
        if progress is not None:
            progress(_check_line(run, ensembles, check, n, t0))
        if n < adapt:
            continue                                     # no stopping inside the pilot
        if check.converged:
            return _Outcome(n, first, check, STOP_RULE, mean, cov, widening)
        if n >= settings.max_steps:
            reason = (f"step cap {settings.max_steps} reached before the stopping rule "
                      f"(missing: {', '.join(check.missing)})")
            return _Outcome(n, first, check, reason, mean, cov, widening)


def _end_pilot(run: _Run, ensembles: _Ensembles, adapt: int, t0: float, progress: Callable[[str], None] | None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Adapt the independence proposal to the pilot's second half and rebuild the samplers
    with it; returns (mean, covariance, variance ratios) of :func:`adapted_proposal`."""
    pilot = np.concatenate([c.reshape(-1, run.n_free) for c in ensembles.chains(adapt // 2, adapt)])
    mean, cov, ratios = adapted_proposal(run.center, run.fit.covariance, pilot)
    ensembles.use_proposal(mean, cov)
    if progress is not None:
        j = int(np.argmax(ratios))
        shift = np.sqrt((mean - run.center) @ np.linalg.solve(run.fit.covariance, mean - run.center))
        progress(f"step {adapt}/{run.settings.max_steps}: end of the pilot; proposal centre moved by {shift:.2f} "
                 f"Cramér-Rao sd, widened along {int(np.sum(ratios > 1))} of {run.n_free} directions, at most "
                 f"x{ratios[j]:.2f} in variance (direction {j + 1}, weakest first), "
                 f"{run.posterior.n_simulations} simulations, {time.perf_counter() - t0:.0f} s")
    return mean, cov, ratios


def _check_line(run: _Run, ensembles: _Ensembles, check: StopCheck, n: int, t0: float) -> str:
    """The progress line of one evaluation of the stopping rule at step ``n``."""
    return (f"step {n}/{run.settings.max_steps}: max tau {np.max(check.tau):.1f} "
            f"(50 tau = {AUTOCORR_FACTOR * np.max(check.tau):.0f}), across {len(ensembles.samplers)} ensembles "
            f"R-hat {check.max_rhat:.3f}, bulk/tail ESS {check.min_ess_bulk:.0f}/{check.min_ess_tail:.0f} "
            f"(tau ESS {check.min_ess_tau:.0f}), "
            f"acceptance {ensembles.acceptance():.2f}, "
            f"{run.posterior.n_simulations} simulations, {time.perf_counter() - t0:.0f} s"
            + ("" if check.converged else f"; waiting for {', '.join(check.missing)}"))


# --------------------------------------------------------------------------------------
# the result
# --------------------------------------------------------------------------------------
def _result(run: _Run, ensembles: _Ensembles, outcome: _Outcome, predictive: bool, t0: float) -> PosteriorResult:
    """The :class:`PosteriorResult` of a finished run: kept draws after burn-in (pilot plus
    2 max τ) and thinning, the run facts and, with ``predictive``, the predictive group."""
    n = outcome.n
    burn, thin = outcome.first + outcome.check.burn_in, outcome.check.thin
    chains = ensembles.chains(0, n)
    log_probs = [s.backend.get_log_prob()[:n] for s in ensembles.samplers]
    accepted_total = [np.asarray(s.backend.accepted) for s in ensembles.samplers]
    attrs = _run_facts(run, ensembles, outcome, burn, thin, t0)
    idata = inference_data(run.problem, run.posterior, chains, log_probs, accepted_total, burn, thin,
                           run.rng if predictive else None, run.settings.n_predictive, attrs)
    return PosteriorResult(idata)


def _run_facts(run: _Run, ensembles: _Ensembles, outcome: _Outcome, burn: int, thin: int, t0: float
               ) -> dict:
    """The attributes of the posterior group (see :class:`PosteriorResult`)."""
    settings, problem, params = run.settings, run.problem, run.problem.parameters
    independence = settings.moves == "independence"
    return {
        "concept": problem.model.name, "seed": int(run.seed), "converged": int(outcome.check.converged),
        "stop_reason": outcome.stop_reason, "n_steps": int(outcome.n), "burn_in": burn, "thin": thin,
        "n_ensembles": settings.n_ensembles, "n_walkers": run.n_walkers, "spread": settings.spread,
        "moves": settings.moves, "move_mix": settings.move_description(),
        "max_steps": settings.max_steps, "check_every": settings.check_every, "adapt_steps": int(outcome.first),
        "proposal_widening": json.dumps(None if outcome.widening is None else outcome.widening.tolist()),
        "proposal_mean": json.dumps(outcome.proposal_mean.tolist() if independence else None),
        "proposal_covariance": json.dumps(outcome.proposal_cov.tolist() if independence else None),
        "integrator": problem.model.integrator,
        "likelihood": "concentrated det R" if run.sigma is None else "Gaussian, known sigma",
        "noise_sigma": json.dumps(None if run.sigma is None else run.sigma.tolist()),
        "priors": json.dumps({n: p.describe() for n, p in zip(params.free_names, run.priors)}),
        "tau": json.dumps(outcome.check.tau.tolist()),
        "ess_tau": json.dumps(outcome.check.ess_tau.tolist()),
        "diagnostics": "R-hat and ESS across ensembles: one chain per ensemble, its walkers' kept draws concatenated",
        "free_parameters": json.dumps(list(params.free_names)),
        "fixed_values": json.dumps({n: float(v) for n, v, f in zip(params.names, run.base, params.free_mask)
                                    if not f}),
        "ml_estimate": json.dumps(run.center.tolist()),
        "crb_std": json.dumps(np.sqrt(np.diag(run.fit.covariance)).tolist()),
        "channels": json.dumps(list(problem.channels)),
        "signature": run.signature,
        "stale_backend_moved_to": "" if ensembles.stale_moved_to is None else str(ensembles.stale_moved_to),
        "n_simulations": int(run.posterior.n_simulations),
        "wall_time_s": float(time.perf_counter() - t0),
    }

