"""Estimation on a sensor set that cannot determine every free parameter.

With the rig's sensors alone (HT/LS: Omega, y1, y2, I_A) the station losses enter the
measured channels only through their sum referred to the motor shaft, so the information
matrix of the full parameter set is singular. ``estimate(..., unidentifiable="fix")``
then:

1. computes the information matrix at the start (central differences, relative
   coordinates, rank tolerance :data:`ema_uq.identify.information.RANK_RTOL`);
2. keeps free a maximal well-determined subset, chosen greedily with the most informative
   parameter first (:func:`ema_uq.identify.information.identifiable_subset`; parameters at a
   bound last, as they cannot compensate in both directions): a candidate joins when at
   least :data:`HOLD_SCHUR_RTOL` of its information is its own, i.e. its Cramér-Rao σ
   among the chosen ones stays within 100 x its stand-alone σ. Every other free parameter is
   held at its start value (:data:`HOLD_RULE`) with its reason: the exact null direction it
   moves along, or the near-collinearity (LT/HS: C_MG against the station Coulomb losses,
   told apart only by the smoothing of sgn near zero speed);
3. estimates the reduced problem (a remaining singularity still raises);
4. reports the identifiable combination of each lumped group with its Cramér-Rao σ from the
   information matrix of the original free set at the estimate
   (:func:`ema_uq.identify.information.combinations`).

Along an exact null direction the likelihood depends on a group only through its
combination, so estimating the combination in its own coordinate would give the same value
and bound as this fit; a held member's value is arbitrary and carries no bound (std NaN).
"""
from __future__ import annotations

import time
from dataclasses import replace
from typing import Any

import numpy as np

from . import information as fim
from .estimators import Settings, SingularInformationError, maximum_likelihood
from .problem import FitProblem
from .result import FitResult

#: a candidate stays free when at least this fraction of its information is its own (Schur
#: complement over its diagonal): its bound inflates at most sqrt(1 / 1e-4) = 100 x by the others
HOLD_SCHUR_RTOL = 1e-4
HOLD_RULE = ("keep free a maximal well-determined subset (greedy, most informative first, each keeping at least "
             f"{HOLD_SCHUR_RTOL:g} of its information as its own); hold every other free parameter at its start value")


def held_parameters(problem: FitProblem, start: np.ndarray) -> tuple[dict[str, dict[str, Any]], int]:
    """{name: {"value", "reason"}} of the free parameters to hold at ``start`` (a full vector),
    and the number of simulations spent on the information matrix."""
    info, n_sims = fim.information(problem, start)
    free = list(problem.parameters.free_names)
    keep = fim.identifiable_subset(info, rtol=HOLD_SCHUR_RTOL,
                                     avoid=fim.near_bounds(problem.model, start, free))
    held = {name: {"value": float(start[problem.parameters.index(name)]),
                   "reason": _hold_reason(info, name, keep, problem.channels)}
            for name in free if name not in keep}
    return held, n_sims


def _hold_reason(info: fim.Information, name: str, keep: list[str], channels) -> str:
    """Why ``name`` cannot be estimated beside ``keep``: no effect on the channels, or the
    direction that moves it by +1 (relative change) and compensates with the free ones at the
    least cost in information (exact null direction, or near-null), with the fraction of its
    information that is its own."""
    j = info.names.index(name)
    if info.data_matrix[j, j] <= 0:
        return f"no effect on the channels {', '.join(channels)}"
    m = info.matrix
    k = [info.names.index(n) for n in keep]
    compensation = -np.linalg.solve(m[np.ix_(k, k)], m[k, j])
    own = max(float(m[j, j] + m[j, k] @ compensation) / m[j, j], 0.0)
    terms = [f"+1*{name}"] + [f"{compensation[i]:+.3g}*{keep[i]}" for i in np.argsort(-np.abs(compensation))
                              if abs(compensation[i]) > 1e-3]
    kind = "null direction" if info.in_null_space()[j] else "near-null direction"
    return f"{kind} {' '.join(terms)} (relative changes; {own:.1e} of its information is its own)"


def identifiable_combinations(problem: FitProblem, theta: np.ndarray) -> tuple[list[dict[str, Any]], int]:
    """The identifiable combination of every lumped group of ``problem``'s free parameters at
    the full vector ``theta`` (expression, coefficients, value, Cramér-Rao std), and the
    number of simulations spent."""
    info, n_sims = fim.information(problem, theta)
    model = problem.model
    values = {n: float(theta[model.parameters.index(n)]) for n in info.names}
    combos = fim.combinations(info, values, model, problem.constants)
    for c in combos:
        c["ci95"] = [c["value"] - fim.CRB_Z * c["std"], c["value"] + fim.CRB_Z * c["std"]]
    return combos, n_sims


def estimate_holding_unidentifiable(problem: FitProblem, *, method: str = "gn", start: np.ndarray | None = None,
                                    settings: Settings = Settings(), seed: int | None = None,
                                    progress=None) -> FitResult:
    """:func:`~ema_uq.identify.estimate` that answers a singular information matrix at the start
    by holding the undetermined parameters (module docstring); a regular problem is estimated
    exactly as with ``unidentifiable="error"``."""
    t0 = time.perf_counter()
    start = problem.parameters.nominal if start is None else np.asarray(start, dtype=float)
    try:
        fit = maximum_likelihood(problem, method=method, start=start, settings=settings, seed=seed,
                                 progress=progress)
        fit.unidentifiable, fit.hold_rule = "fix", HOLD_RULE
        return fit
    except SingularInformationError as exc:
        error, spent = exc, exc.n_simulations
    held, n_detect = held_parameters(problem, start)
    if not held:
        # singular to the optimiser's forward differences only (condition just above its limit,
        # e.g. LT/HS C_MG against the station Coulomb losses): hold the member that weighs most
        # in the direction it reported, and so on while the reduced problem stays singular
        held = _held_from_direction(error, start, problem)
    while True:  # every pass holds one more parameter or raises
        reduced = replace(problem, parameters=problem.parameters.fixing(list(held)))
        try:
            fit = maximum_likelihood(reduced, method=method, start=start, settings=settings, seed=seed,
                                     progress=progress)
            break
        except SingularInformationError as exc:
            spent += exc.n_simulations
            more = _held_from_direction(exc, start, problem)
            if not more or set(more) <= set(held):
                raise
            held = {**held, **more}
    combos, n_combos = identifiable_combinations(problem, fit.estimate) if settings.combinations else ([], 0)
    for name in held:
        fit.std[fit.names.index(name)] = np.nan
    fit.unidentifiable, fit.hold_rule, fit.fixed, fit.combinations = "fix", HOLD_RULE, held, combos
    fit.n_simulations += spent + n_detect + n_combos
    fit.wall_time_s = time.perf_counter() - t0
    return fit


def _held_from_direction(error: SingularInformationError, start: np.ndarray, problem: FitProblem
                         ) -> dict[str, dict[str, Any]]:
    """{name: {"value", "reason"}} of the free parameter weighing most in the direction a
    :class:`SingularInformationError` reported (empty when it reported none)."""
    direction = error.direction or {}
    if not direction:
        return {}
    name = max(direction, key=lambda n: abs(direction[n]))
    members = " ".join(f"{w:+.2f}*{n}" for n, w in direction.items())
    return {name: {"value": float(start[problem.parameters.index(name)]),
                   "reason": f"near-null direction {members} of the optimiser's information matrix at the start"}}
