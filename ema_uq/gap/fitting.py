"""Fitting tools of the gap diagnosis: start grids and fine start profiles of an effect's
parameters, a Gauss-Newton fit that Levenberg-Marquardt rescues or finishes, the base
parameters a candidate's screening refit frees, and those the channels cannot determine.

None of them knows the diagnosis's state: they take a :class:`~ema_uq.identify.FitProblem`
and parameter vectors, so that :mod:`ema_uq.gap.candidates` composes them into the nominal
fit and the candidates' refits.
"""

from __future__ import annotations

from dataclasses import replace
from typing import Sequence

import numpy as np

from .. import statistics
from ..identify import FitProblem, FitResult, IdentificationError, Settings, SingularInformationError, estimate

PHASE_STARTS = statistics.PHASE_STARTS
MAX_GRID = statistics.MAX_GRID
# points of each effect parameter's fine start profile (:func:`_profiled_start`): steps of 1.16x
# between the neighbouring points (x/3.3, x3.3) of the default grid
PROFILE_POINTS = 17
SINGULAR_RELATIVE = 1e-10


def _effect_parameter_names(augmented, base) -> list[str]:
    return [n for n in augmented.parameters.names if n not in base.parameters.names]


def _is_phase(name: str, parameter) -> bool:
    """An angle on a turn (its start grid spans the turn, not multiples of the start)."""
    return parameter.unit == "rad" and "phase" in name


def _start_grid(augmented, base_values, effect, names: Sequence[str],
                multiples: Sequence[float] = statistics.START_MULTIPLES) -> np.ndarray:
    """Full start vectors (n_starts, n_params): base parameters at ``base_values`` (the reference
    fit), effect parameters on the grid of :func:`ema_uq.statistics.start_values` around
    ``Effect.start`` (every combination when at most ``MAX_GRID``, else one at a time)."""
    params = augmented.parameters
    start = dict(getattr(effect, "start", {}) or {})
    centre = params.vector({**{k: v for k, v in base_values.items() if k in params},
                            **{n: start[n] for n in names if n in start}})
    values = [statistics.start_values(centre[params.index(n)], params[n].lower, params[n].upper,
                                      phase=_is_phase(n, params[n]), multiples=multiples,
                                      phase_starts=PHASE_STARTS) for n in names]
    return statistics.start_grid(centre, [params.index(n) for n in names], values, MAX_GRID)


def _profiled_start(problem: FitProblem, start: np.ndarray, prediction: np.ndarray, objective: float,
                    params, names: Sequence[str], multiples: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """The grid's best start refined by one pass of fine 1-D profiles: each effect parameter in
    turn at ``PROFILE_POINTS`` geometric steps from its value over to its neighbouring grid
    points (÷ and × the grid's widest step), the others held, the best point kept. Why: the
    objective of a play is ragged at finer spacing than the grid's factor of 3 (contact
    switches a step earlier or later), and Gauss-Newton stops in the first dip: an LT/HS nut
    play of the seed-2 self-check has its profile minimum at 2.2x the best grid point, and the
    refit from that point stopped at 1x.
    Phases stay at their grid value (they have their own grid over the turn).
    Returns (start, its prediction); the runs are counted by ``problem.predictions``."""
    ordered = np.sort(np.asarray(multiples, dtype=float))
    step = float(np.max(ordered[1:] / ordered[:-1])) if ordered.size > 1 else 1.0
    if step <= 1.0:
        return start, prediction
    for name in names:
        i, parameter = params.index(name), params[name]
        if start[i] <= 0 or _is_phase(name, parameter):
            continue
        values = np.unique(np.clip(start[i] * np.geomspace(1.0 / step, step, PROFILE_POINTS),
                                   parameter.lower, parameter.upper))
        trial = np.repeat(start[None], values.size, axis=0)
        trial[:, i] = values
        k, score, predicted = _best_point(problem, trial)
        if score < objective:
            start, prediction, objective = trial[k], predicted[k], score
    return start, prediction


def _best_point(problem: FitProblem, thetas: np.ndarray) -> tuple[int, float, np.ndarray]:
    """(index, V, predictions of all sets) of the set of ``thetas`` with the lowest objective,
    one batched simulator call; sets that simulate to NaN count as infinitely bad."""
    predicted = problem.predict(thetas)
    objectives = [problem.objective(problem.observed - predicted[i], thetas[i, problem.free_index])[0]
                  for i in range(thetas.shape[0])]
    best = _finite_argmin(objectives)
    return best, float(objectives[best]), predicted


def _finite_argmin(values: Sequence[float]) -> int:
    """Index of the smallest value, NaN counting as infinitely large."""
    values = np.asarray(values, dtype=float)
    return int(np.argmin(np.where(np.isfinite(values), values, np.inf)))


def _full_objective(problem: FitProblem, theta: np.ndarray, log_det_r: float) -> float:
    """V of ``problem`` at ``theta`` given log det R there, the rig terms over its free
    parameters, so that fits with different free sets compare."""
    return statistics.objective(problem.n_samples, log_det_r, theta[problem.free_index], problem.parameters,
                                problem.free_index)


def _stepped_sets(theta: np.ndarray, index: np.ndarray, relative: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Parameter sets for relative forward differences: (thetas, h, scale) with thetas row 0 =
    ``theta`` and row 1 + i = ``theta`` with entry ``index[i]`` raised by h_i = ``relative`` x
    scale_i, scale = |value| (1 where the value is 0)."""
    scale = np.where(np.abs(theta[index]) > 0, np.abs(theta[index]), 1.0)
    h = relative * scale
    thetas = np.repeat(theta[None], index.size + 1, axis=0)
    thetas[1 + np.arange(index.size), index] += h
    return thetas, h, scale


def _relevant_base(problem: FitProblem, theta: np.ndarray, predicted: np.ndarray, effect_names: Sequence[str],
                   count: int) -> list[str]:
    """The ``count`` base parameters most aliased with the effect parameters at ``theta``: largest
    |correlation| in the information metric (forward differences, one batched simulator call)."""
    params = problem.parameters
    idx = problem.free_index
    thetas, h, scale = _stepped_sets(theta, idx, 1e-5)    # the base prediction is given: row 0 not run
    sens = (problem.predict(thetas[1:]) - predicted[None]) / (h / scale)[:, None, None]     # (p, N, m)
    residual = problem.observed - predicted
    r_inv = np.linalg.inv(residual.T @ residual / residual.shape[0])
    info = statistics.information(sens, r_inv)
    d = np.sqrt(np.maximum(np.diag(info), 1e-300))
    corr = np.abs(info / np.outer(d, d))
    names = [params.names[i] for i in idx]
    eff = [names.index(n) for n in effect_names]
    relevance = {n: float(np.max(corr[j, eff])) for j, n in enumerate(names) if n not in effect_names}
    return sorted(relevance, key=lambda n: -relevance[n])[:count]


def _unidentifiable_parameters(problem: FitProblem, theta: np.ndarray) -> list[str]:
    """Free parameters the fitted channels cannot determine at ``theta``: those that move no
    channel, then, while the information matrix (relative sensitivities, forward differences
    in one batched call, R of the residual at ``theta``) has a direction with eigenvalue below
    ``SINGULAR_RELATIVE`` of the largest, the parameter weighing most in it (rig-measured
    gains last). E.g. k_n without a current channel, or the friction split without torque channels."""
    names = problem.parameters.names
    idx = problem.free_index
    thetas, h, scale = _stepped_sets(theta, idx, 1e-4)
    predicted = problem.predict(thetas, share_steps=True)     # row 0, the base, sets the steps
    sens = (predicted[1:] - predicted[0][None]) / (h / scale)[:, None, None]
    residual = problem.observed - predicted[0]
    r_inv = np.linalg.inv(residual.T @ residual / residual.shape[0])
    info = statistics.information(sens, r_inv)
    fixed = [names[i] for j, i in enumerate(idx) if not np.any(sens[j])]
    while True:
        keep = [j for j, i in enumerate(idx) if names[i] not in fixed]
        if len(keep) < 2:
            break
        evals, evecs = np.linalg.eigh(info[np.ix_(keep, keep)])
        if evals[0] > SINGULAR_RELATIVE * evals[-1]:
            break
        weight = np.abs(evecs[:, 0]) * [0.5 if problem.parameters.parameters[idx[j]].prior_std else 1.0 for j in keep]
        fixed.append(names[idx[keep[int(np.argmax(weight))]]])
    return fixed


def _robust_estimate(problem: FitProblem, start: np.ndarray, settings: Settings) -> FitResult:
    """Gauss-Newton, retried by Levenberg-Marquardt when a step goes singular: an effect
    parameter at a bound where another loses its effect (an amplitude at its off bound leaves
    its phase free, Stribeck Fs = 0 leaves v_s free) makes the Gauss-Newton matrix singular,
    which the damping survives. When the start itself cannot separate some freed base
    parameter (a reduced sensor set: on the LT/HS rig sensors C_TS2 alone), those parameters are
    held at their start values as ``identify`` does (named in the fit) rather than losing the
    candidate. A Gauss-Newton fit that stops early without converging (its step halving
    exhausted while the model still promised a decrease: on the LT/HS rig sensors a nominal fit
    stopped after 2 of 30 iterations 12 500 short in 2V of its minimum, and every candidate was
    then credited with finishing that descent) is continued by Levenberg-Marquardt for the
    remaining iterations. A start whose information matrix Gauss-Newton found singular goes
    straight to the Levenberg-Marquardt fit that holds the undetermined parameters: a plain
    Levenberg-Marquardt attempt would compute the same matrix at the same start and stop there
    too (a Jacobian's simulations for nothing). The fit returned counts its own runs; those of a
    discarded attempt show in the problem's ``predictions.runs``, which the diagnosis reports."""
    try:
        fit = estimate(problem, method="gn", start=start, settings=settings)
    except SingularInformationError:
        return estimate(problem, method="lm", start=start, settings=settings, unidentifiable="fix")
    except (IdentificationError, np.linalg.LinAlgError):
        return _levenberg_marquardt(problem, start, settings)
    if fit.converged or fit.iterations >= settings.max_iterations:
        return fit
    rest = replace(settings, max_iterations=settings.max_iterations - fit.iterations)
    try:
        more = _levenberg_marquardt(problem, fit.estimate, rest)
    except (IdentificationError, np.linalg.LinAlgError):
        return fit
    if not more.objective < fit.objective:
        return fit
    return replace(more, start=fit.start, iterations=fit.iterations + more.iterations,
                   n_simulations=fit.n_simulations + more.n_simulations,
                   wall_time_s=fit.wall_time_s + more.wall_time_s,
                   message=f"{more.message} (Levenberg-Marquardt after Gauss-Newton stopped: {fit.message})")


def _levenberg_marquardt(problem: FitProblem, start: np.ndarray, settings: Settings) -> FitResult:
    try:
        return estimate(problem, method="lm", start=start, settings=settings)
    except SingularInformationError:
        return estimate(problem, method="lm", start=start, settings=settings, unidentifiable="fix")



def _parameter_table(model, fit: FitResult, names: Sequence[str]) -> dict[str, dict[str, float]]:
    """{name: {"estimate", "std" (Cramér-Rao), "unit"}} of parameters ``names`` of a fit."""
    return {p: {"estimate": fit.value(p), "std": float(fit.std[fit.names.index(p)]),
                "unit": model.parameters[p].unit} for p in names}
