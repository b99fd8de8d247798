"""Maximum-likelihood output-error estimation: Gauss-Newton with step halving (eqs. 50-53)
and Levenberg-Marquardt as the paper describes it (eq. 54 and its listed steps).

Both work in scaled coordinates s = Θ / d (d = magnitude of the start), so that values
from 4e-4 (J) to 3.5e4 (p_ACE) share one well-conditioned information matrix, and both
hold R at its current estimate while computing a step ("relaxation strategy").
"""
from __future__ import annotations

import time
from typing import Callable
from dataclasses import dataclass

import numpy as np

from .problem import FitProblem, IdentificationError, covariance
from .result import FitResult

FD_RELATIVE_STEP = 1e-5
SINGULAR_RCOND = 1e-12
#: Gauss-Newton, Levenberg-Marquardt
METHODS = ("gn", "lm")


@dataclass(frozen=True)
class Settings:
    """Stopping and step control. ``tolerance`` is the paper's |(J_i - J_{i-1})/J_i| (eq. 53)."""

    tolerance: float = 1e-5
    max_iterations: int = 50
    max_halvings: int = 10
    lm_lambda0: float = 1e-3     # relative to the mean diagonal of the scaled information matrix
    lm_nu: float = 10.0
    lm_max_increases: int = 12
    #: Cramér-Rao bounds at the estimate (central differences, 2 x free simulations); off for
    #: inner fits whose bounds nobody reads (profile likelihoods), where they cost ~40 %
    cramer_rao: bool = True
    #: also stop when the decrease of 2V still to come, extrapolated from the last two accepted
    #: iterations as a geometric series (Gauss-Newton converges linearly on a residual that is
    #: not small), is below this, in units of 2 ln L (those of BIC and of evidence margins); for
    #: callers that use V only through differences far larger than it. None: ``tolerance`` alone
    decrease_tolerance: float | None = None
    #: how the decrease still to come is judged against ``decrease_tolerance``: "extrapolated"
    #: (the last two decreases as a geometric series, after each step) or "predicted" (before each
    #: step, the decrease of 2V that the full Gauss-Newton step promises at the current iterate, the
    #: quadratic model's own estimate: the history of decreases is no bound, since a plateau of small
    #: steps through a curved valley can come before a large decrease)
    decrease_estimate: str = "extrapolated"
    #: with ``unidentifiable="fix"``: report the identifiable combination of each held group
    #: (:func:`ema_uq.identify.reduction.identifiable_combinations`: 2 x free simulations around
    #: the estimate, which the fit has simulated already); off for callers that read only the fit
    combinations: bool = True

    def __post_init__(self) -> None:
        value = self.decrease_tolerance
        if value is not None and not (isinstance(value, (int, float, np.floating)) and not isinstance(value, bool)
                                      and np.isfinite(value) and value > 0):
            raise IdentificationError(f"decrease_tolerance must be a positive number or None, "
                                      f"got {self.decrease_tolerance!r}")
        if self.decrease_estimate not in ("extrapolated", "predicted"):
            raise IdentificationError(f"decrease_estimate {self.decrease_estimate!r}: choose 'extrapolated' or "
                                      "'predicted'")


class SingularInformationError(IdentificationError):
    """The data cannot determine every free parameter at the start (singular information
    matrix); ``identify.estimate(..., unidentifiable="fix")`` holds the undetermined ones instead.
    ``n_simulations``: simulations spent before the test failed; ``direction``: the free
    parameters of the (near-)null direction with their weights in it (largest first)."""

    n_simulations: int = 0
    direction: dict | None = None


class _State:
    """Current iterate: full vector, residuals, R and the objective."""

    def __init__(self, problem: FitProblem, theta: np.ndarray, predicted: np.ndarray):
        self.theta = theta
        self.free = theta[problem.free_index]
        self.predicted = predicted
        self.residuals = problem.observed - predicted
        self.objective, self.log_det_r = problem.objective(self.residuals, self.free)


class _Counter:
    def __init__(self) -> None:
        self.n = 0


def _evaluate(problem: FitProblem, thetas: np.ndarray, counter: _Counter) -> list[_State]:
    runs = problem.predictions.runs
    predicted = problem.predict(thetas)
    counter.n += problem.predictions.runs - runs
    return [_State(problem, thetas[i], predicted[i]) for i in range(thetas.shape[0])]


def _information(problem: FitProblem, state: _State, scale: np.ndarray, counter: _Counter, central: bool = True):
    """Scaled information matrix F and gradient G of V at ``state`` (R held fixed).

    Output sensitivities by finite differences, all perturbed vectors in ONE batched call
    (led by the current state when the integrator is adaptive): forward (p runs, enough to
    steer the iterations) or central (2p runs, for the Cramér-Rao bound at the estimate).
    """
    p = scale.size
    h = FD_RELATIVE_STEP * scale
    steps = np.zeros((2 * p if central else p, p))
    steps[:p][np.diag_indices(p)] = h
    if central:
        steps[p:][np.diag_indices(p)] = -h
    # an adaptive integrator: the current state leads the batch and every perturbed run takes
    # its step sequence, so the differences carry no step-selection noise (fixed steps need no
    # leader: the state's own prediction is the base)
    adaptive = problem.model.integrator != "rk4"
    free = np.vstack([state.free, state.free[None, :] + steps]) if adaptive else state.free[None, :] + steps
    thetas = problem.full_vectors(free, state.theta)
    runs = problem.predictions.runs
    predicted = problem.predict(thetas, share_steps=adaptive)
    counter.n += problem.predictions.runs - runs
    base, predicted = (predicted[0], predicted[1:]) if adaptive else (state.predicted, predicted)
    # S[k, c, j] = d y_kc / d s_j in scaled coordinates
    if central:
        sens = (predicted[:p] - predicted[p:]).transpose(1, 2, 0) / (2.0 * h) * scale
    else:
        sens = (predicted - base[None]).transpose(1, 2, 0) / h * scale
    r_inv = np.linalg.inv(covariance(state.residuals))
    weighted = np.einsum("kcj,cd->kdj", sens, r_inv)
    info = np.einsum("kdj,kdl->jl", weighted, sens)
    grad = -np.einsum("kdj,kd->j", weighted, state.residuals)
    pos, mean, std = problem.prior_terms()
    if pos.size:
        info[pos, pos] += (scale[pos] / std) ** 2
        grad[pos] += (state.free[pos] - mean) / std ** 2 * scale[pos]
    return 0.5 * (info + info.T), grad, sens


def _check_information(problem: FitProblem, info: np.ndarray, sens: np.ndarray) -> None:
    """Raise with the offending parameters named when F is (numerically) singular."""
    names = problem.parameters.free_names
    dead = [names[j] for j in range(len(names)) if not np.any(sens[:, :, j])]
    if dead:
        error = SingularInformationError(
            f"singular information matrix: {', '.join(dead)} has no effect on the channels "
            f"{', '.join(problem.channels)}; fix it (free=False) or add a channel that depends on it"
        )
        error.direction = {name: 1.0 for name in dead}
        raise error
    evals, evecs = np.linalg.eigh(info)
    if evals[0] <= SINGULAR_RCOND * evals[-1]:
        v = evecs[:, 0]
        members = [f"{v[j]:+.2f}*{names[j]}" for j in np.argsort(-np.abs(v)) if abs(v[j]) > 0.2]
        error = SingularInformationError(
            f"singular information matrix (condition {evals[-1] / max(evals[0], 1e-300):.1e}): the data cannot "
            f"separate the direction {' '.join(members)}; fix one of these parameters or add channels"
        )
        error.direction = {names[j]: float(v[j]) for j in np.argsort(-np.abs(v)) if abs(v[j]) > 0.2}
        raise error


def _bounded_step(problem: FitProblem, state: _State, matrix: np.ndarray, grad: np.ndarray,
                  scale: np.ndarray) -> np.ndarray:
    """Solve ``matrix Δs = -grad`` with parameters held that sit at a bound and would leave it.

    Clipping a full step instead would move the other parameters as if the bounded one had
    gone past its bound, and the iteration would stall away from the constrained optimum.
    """
    idx = problem.free_index
    lower, upper = problem.parameters.lower[idx], problem.parameters.upper[idx]
    at_lower = state.free <= lower
    at_upper = state.free >= upper
    held = np.zeros(scale.size, dtype=bool)
    for _ in range(scale.size):
        step = np.zeros(scale.size)
        keep = ~held
        step[keep] = -np.linalg.solve(matrix[np.ix_(keep, keep)], grad[keep])
        leaving = keep & ((at_lower & (step < 0)) | (at_upper & (step > 0)))
        if not leaving.any():
            return step * scale
        held |= leaving
        if held.all():
            return np.zeros(scale.size)
    return step * scale


def _project(problem: FitProblem, free: np.ndarray) -> np.ndarray:
    idx = problem.free_index
    return np.clip(free, problem.parameters.lower[idx], problem.parameters.upper[idx])


def _relative_change(old: _State, new: _State, n: int) -> float:
    """|(J_i - J_{i-1}) / J_i| with J = det R (times the prior factor when pseudo-measurements exist)."""
    return abs(np.expm1((old.objective - new.objective) * 2.0 / n))


def _promised_decrease(problem: FitProblem, state: "_State", info: np.ndarray, grad: np.ndarray,
                       scale: np.ndarray) -> float:
    """The decrease of 2V that the full Gauss-Newton step (bounded parameters held) promises at
    ``state``: gᵀ F⁻¹ g on the quadratic model, which near the optimum is the decrease still to come."""
    step = _bounded_step(problem, state, info, grad, scale) / scale
    return -float(grad @ step)


def _remaining_decrease(previous: float | None, last: float) -> float:
    """The decrease of 2V still to come after accepted decreases ``previous`` then ``last``
    (each of 2V), as the geometric series of their ratio; inf when the ratio is not below 1 or
    there is no previous decrease."""
    if previous is None or not previous > 0:
        return float("inf")
    ratio = last / previous
    return last * ratio / (1.0 - ratio) if ratio < 1.0 else float("inf")


def _record(history: list, iteration: int, state: _State, problem: FitProblem, counter: _Counter, **extra) -> None:
    names = problem.parameters.free_names
    entry = {"iteration": iteration, "cost": float(np.exp(state.log_det_r)), "log_det_R": state.log_det_r,
             "objective": state.objective, "n_simulations": counter.n,
             "theta": {n: float(v) for n, v in zip(names, state.free)}}
    entry.update(extra)
    history.append(entry)


def _gn_step(problem, state, info, grad, scale, settings, counter):
    """Solve F Δ = -G; halve the step until the objective decreases (eq. 51-52 with relaxation)."""
    delta = _bounded_step(problem, state, info, grad, scale)
    alpha = 1.0
    for halvings in range(settings.max_halvings + 1):
        trial_free = _project(problem, state.free + alpha * delta)
        trial = _evaluate(problem, problem.full_vectors(trial_free, state.theta), counter)[0]
        if trial.objective < state.objective:
            return trial, {"halvings": halvings, "step": alpha}
        alpha *= 0.5
    return None, {"halvings": settings.max_halvings}


class _LevenbergMarquardt:
    """Paper's steps: try λ and λ/ν, keep the larger reduction, adapt λ; raise λ by ν while neither reduces."""

    def __init__(self, settings: Settings):
        self.settings = settings
        self.lam = None

    def step(self, problem, state, info, grad, scale, settings, counter):
        if self.lam is None:
            self.lam = settings.lm_lambda0 * float(np.mean(np.diag(info)))
        eye = np.eye(info.shape[0])
        for increases in range(settings.lm_max_increases + 1):
            lams = (self.lam, self.lam / settings.lm_nu)
            frees = [_project(problem, state.free + _bounded_step(problem, state, info + lam * eye, grad, scale))
                     for lam in lams]
            trials = _evaluate(problem, problem.full_vectors(np.array(frees), state.theta), counter)
            best = int(np.argmin([t.objective for t in trials]))
            if trials[best].objective < state.objective:
                if best == 1:
                    self.lam = lams[1]
                return trials[best], {"lambda": lams[best], "increases": increases}
            self.lam *= settings.lm_nu
        return None, {"lambda": self.lam, "increases": settings.lm_max_increases}


def perturbed_start(parameters, fraction: float, seed: int, around: np.ndarray | None = None) -> np.ndarray:
    """Free parameters independently scaled by (1 + U(-fraction, fraction)), seeded, kept in bounds."""
    if not 0 <= fraction < 1:
        raise IdentificationError(f"perturbation fraction must be in [0, 1), got {fraction}")
    base = parameters.nominal if around is None else np.asarray(around, dtype=float)
    rng = np.random.default_rng(seed)
    factors = 1.0 + rng.uniform(-fraction, fraction, len(parameters))
    start = np.where(parameters.free_mask, base * factors, base)
    return np.clip(start, parameters.lower, parameters.upper)


def maximum_likelihood(problem: FitProblem, *, method: str = "gn", start: np.ndarray | None = None,
                       settings: Settings = Settings(), seed: int | None = None,
                       progress: Callable[[int, str], None] | None = None) -> FitResult:
    """Maximum-likelihood estimate of every free parameter of ``problem``.

    ``start`` is a full parameter vector (default: the set's nominal values) and must lie
    within bounds. Returns a :class:`FitResult` with Cramér-Rao standard deviations
    computed from the information matrix at the estimate. When the data cannot determine
    every free parameter at the start (singular information matrix) it raises
    :class:`SingularInformationError` naming the direction; :func:`ema_uq.identify.estimate`
    chooses between that and holding the undetermined parameters (:mod:`.reduction`).

    ``progress``: called after every accepted iteration with its number and a one-line state.
    """
    if method not in METHODS:
        raise IdentificationError(f"unknown method {method!r}; choose gn (Gauss-Newton) or lm (Levenberg-Marquardt)")
    params = problem.parameters
    start = params.nominal if start is None else np.asarray(start, dtype=float)
    params.check_within_bounds(start, what="start value")
    t0 = time.perf_counter()
    counter = _Counter()
    free0 = start[problem.free_index]
    scale = np.maximum(np.abs(free0), 1e-3 * np.abs(params.nominal[problem.free_index]))
    scale = np.where(scale > 0, scale, 1.0)

    state = _evaluate(problem, start[None, :], counter)[0]
    if not np.isfinite(state.objective):
        raise IdentificationError("the start values give a degenerate residual covariance (det R = 0 or NaN); "
                                  "check the data for constant or duplicated channels")
    history: list = []
    _record(history, 0, state, problem, counter)
    stepper = _gn_step if method == "gn" else _LevenbergMarquardt(settings).step
    converged, message, iteration = False, "maximum number of iterations reached", 0
    previous_decrease = None
    for iteration in range(1, settings.max_iterations + 1):
        info, grad, sens = _information(problem, state, scale, counter, central=False)
        if iteration == 1:
            try:
                _check_information(problem, info, sens)
            except SingularInformationError as exc:
                exc.n_simulations = counter.n
                raise
        if settings.decrease_tolerance is not None and settings.decrease_estimate == "predicted":
            promised = _promised_decrease(problem, state, info, grad, scale)
            if promised < settings.decrease_tolerance:
                converged, message = True, (f"decrease of 2V a full Gauss-Newton step promises {promised:.2e} < "
                                            f"{settings.decrease_tolerance:g}")
                iteration -= 1
                break
        new, extra = stepper(problem, state, info, grad, scale, settings, counter)
        if new is None:
            # exhausted step control is convergence only when the model promised no real decrease
            promised = 0.5 * _promised_decrease(problem, state, info, grad, scale)    # of V, not 2V
            converged = promised < settings.tolerance * problem.n_samples / 2
            message = ("no further decrease of det R along the step (at a minimum to numerical precision)"
                       if converged else
                       f"step control exhausted although a decrease of {promised:.3g} in the objective was "
                       "predicted: restart closer to the optimum or check bounds and data")
            iteration -= 1
            break
        change = _relative_change(state, new, problem.n_samples)
        decrease = 2.0 * (state.objective - new.objective)
        state = new
        _record(history, iteration, state, problem, counter, relative_change=change, **extra)
        if progress is not None:
            progress(iteration, f"log det R {state.log_det_r:.6g}, |dJ/J| {change:.2e}, {counter.n} simulations")
        if change < settings.tolerance:
            converged, message = True, f"|dJ/J| = {change:.2e} < {settings.tolerance:g}"
            break
        if settings.decrease_tolerance is not None and settings.decrease_estimate == "extrapolated":
            remaining = _remaining_decrease(previous_decrease, decrease)
            if remaining < settings.decrease_tolerance:
                converged, message = True, (f"decrease of 2V still to come {remaining:.2e} < "
                                            f"{settings.decrease_tolerance:g} (last two: {previous_decrease:.3g}, "
                                            f"{decrease:.3g})")
                break
        previous_decrease = decrease

    std = np.zeros(len(params))
    if settings.cramer_rao:
        info, _, sens = _information(problem, state, scale, counter)
        cov_scaled, warnings = _invert_information(problem, info)
        cov = cov_scaled * np.outer(scale, scale)
        std[problem.free_index] = np.sqrt(np.diag(cov))
    else:
        cov = np.full((scale.size, scale.size), np.nan)
        std[problem.free_index] = np.nan
        warnings = ["Cramér-Rao bounds not computed (Settings.cramer_rao=False)"]
    lower, upper = params.lower, params.upper
    at_bounds = [params.names[i] for i in problem.free_index
                 if state.theta[i] <= lower[i] or state.theta[i] >= upper[i]]
    if at_bounds:
        warnings.append(f"estimate at a bound for {', '.join(at_bounds)}: its Cramér-Rao σ is not a valid interval")
    return FitResult(
        concept=problem.model.name, method=method, names=params.names, units=params.units,
        free=params.free_mask, start=start, estimate=state.theta.copy(), std=std, covariance=cov,
        channels=tuple(problem.channels), residual_covariance=covariance(state.residuals),
        log_det_r=state.log_det_r, objective=state.objective, n_samples=problem.n_samples,
        converged=converged, message=message, iterations=iteration, n_simulations=counter.n,
        wall_time_s=time.perf_counter() - t0, history=history, at_bounds=at_bounds, warnings=warnings,
        seed=seed,
    )


def _invert_information(problem: FitProblem, info: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """Inverse of F; a rank-deficient F gives NaN bounds on its null space and a warning, never garbage."""
    evals, evecs = np.linalg.eigh(info)
    keep = evals > SINGULAR_RCOND * evals[-1]
    if keep.all():
        return np.linalg.inv(info), []
    inv = (evecs[:, keep] / evals[keep]) @ evecs[:, keep].T
    affected = np.any(np.abs(evecs[:, ~keep]) > 1e-3, axis=1)
    inv[affected, :] = np.nan
    inv[:, affected] = np.nan
    names = [n for n, a in zip(problem.parameters.free_names, affected) if a]
    return inv, [f"information matrix is rank-deficient; no Cramér-Rao bound for {', '.join(names)}"]
