"""The stopping rule: autocorrelation times, burn-in and thinning, R-hat and ESS.

Evaluated every ``check_every`` steps (:func:`check_stop`): every ensemble's chain is longer
than 50 τ, τ changed by < 1 % since the previous check (or by less than three standard errors
of its estimate, which a τ of a few steps needs), and the kept draws give rank-normalised
split R-hat < 1.01 and bulk and tail ESS >= 400 for every parameter. The rule uses only the
stored chains, so it is resume-invariant.

R-hat and ESS compare the independent ensembles, not the walkers of one ensemble: the
walkers of an ensemble move together (a differential-evolution step moves a walker along the
difference of two others), so they are not independent chains, and R-hat across them cannot
see an ensemble that as a whole has not forgotten its start. Estimator
(:func:`pooled_draws`): one ArviZ chain per ensemble, the kept draws of its walkers
concatenated walker after walker; split R-hat then also compares the first half of an
ensemble's walkers with the second. The emcee figure ESS_τ = (steps after burn-in) x (walkers
of all ensembles) / τ, τ the mean over ensembles, is reported beside ArviZ's bulk and tail ESS.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Sequence

import numpy as np

AUTOCORR_FACTOR = 50.0       # every chain must be longer than 50 τ
TAU_RTOL = 0.01              # and τ must have changed by < 1 % since the previous check ...
TAU_CHANGE_SE = 3.0          # ... or by less than 3 standard errors of that change
AUTOCORR_WINDOW = 5.0        # emcee's window constant c: τ is summed over lags M >= c τ
RHAT_MAX = 1.01              # and the kept draws must give rank-normalised split R-hat < 1.01
ESS_MIN = 400.0              # and bulk and tail ESS >= 400 for every parameter


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


def pooled_draws(chains: Sequence[np.ndarray], burn: int, thin: int) -> np.ndarray:
    """One chain per ensemble: (n_ensembles, n_walkers * n_kept, ...) from per-ensemble
    stored arrays (n_steps, n_walkers, ...) (chains with a trailing n_free axis, or log
    probabilities without it), keeping steps ``burn::thin`` and concatenating the walkers' kept
    steps walker after walker (draw w * n_kept + i is walker w's i-th kept step)."""
    kept = [np.swapaxes(c[burn::thin], 0, 1) for c in chains]        # (walkers, n_kept, ...)
    return np.stack([k.reshape((-1,) + k.shape[2:]) for k in kept])


def tau_ess(taus: np.ndarray, n_after_burn: int, n_walkers_total: int) -> np.ndarray:
    """emcee's effective sample size per parameter (n_free,): steps after burn-in times the
    walkers of all ensembles over τ (``taus`` (n_ensembles, n_free) [steps], averaged over
    the ensembles)."""
    return n_after_burn * n_walkers_total / np.mean(np.atleast_2d(taus), axis=0)


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
    ``max_rhat``/``min_ess_bulk``/``min_ess_tail`` over the kept draws (ArviZ, one chain per
    ensemble: :func:`pooled_draws`); ``ess_tau`` (n_free,) emcee's ESS (:func:`tau_ess`);
    ``missing``: the conditions not yet met (empty when converged).
    """

    n: int
    tau: np.ndarray
    burn_in: int
    thin: int
    max_rhat: float
    min_ess_bulk: float
    min_ess_tail: float
    ess_tau: np.ndarray
    missing: tuple[str, ...]

    @property
    def converged(self) -> bool:
        return not self.missing

    @property
    def min_ess_tau(self) -> float:
        return float(np.min(self.ess_tau))


STOP_RULE = (f"every chain longer than {AUTOCORR_FACTOR:g} tau, tau changed < {TAU_RTOL:.0%} (or < "
             f"{TAU_CHANGE_SE:g} standard errors of its estimate), R-hat < {RHAT_MAX:g} and bulk and tail "
             f"ESS >= {ESS_MIN:g} across the ensembles")


def check_stop(chains: Sequence[np.ndarray], n: int, check_every: int) -> StopCheck:
    """Evaluate the stopping rule on the first ``n`` steps of each ensemble's chain
    (n_steps, n_walkers, n_free); R-hat and ESS with one chain per ensemble."""
    import arviz as az

    chains = [c[:n] for c in chains]
    taus = np.array([autocorr_times(c) for c in chains])
    burn, thin = burn_in_and_thin(taus, n)
    kept = pooled_draws(chains, burn, thin)                            # as in the export
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
        with np.errstate(divide="ignore", invalid="ignore"):   # tau 0 (a chain too short to move): not stable
            stable = np.all(np.abs(taus - prev) / taus < tolerance)
        if not stable:
            missing.append("stable tau")
    if not max_rhat < RHAT_MAX:
        missing.append(f"R-hat < {RHAT_MAX:g}")
    if not np.all(min_ess >= ESS_MIN):
        missing.append(f"ESS >= {ESS_MIN:g}")
    ess_tau = tau_ess(taus, n - burn, sum(c.shape[1] for c in chains))
    return StopCheck(n, taus, burn, thin, max_rhat, float(min_ess[0]), float(min_ess[1]), ess_tau, tuple(missing))
