"""Steps 2 to 5 of the gap diagnosis: the nominal fit and the localisation of its residual,
each candidate effect's refit (screening, then the leaders' final refit) and its scores
against the reference model, a round over the catalogue, and forward selection over rounds.

The procedure and every score are described in :mod:`ema_uq.gap.attribute`; the fitting
tools come from :mod:`ema_uq.gap.fitting`, the shared state from
:mod:`ema_uq.gap.diagnosis_state`.
"""

from __future__ import annotations

import time
from dataclasses import replace
from typing import Any, Sequence

import numpy as np

from .. import statistics
from ..identify import FitProblem, FitResult, IdentificationError, Settings
from ..params import ParameterError
from ..simulate import SimulationError
from .diagnosis_state import _Diagnosis, _Reference, _simulate_records
from .fitting import (_best_point, _effect_parameter_names, _finite_argmin, _full_objective, _is_phase,
                      _parameter_table, _profiled_start, _relevant_base, _robust_estimate, _start_grid,
                      _unidentifiable_parameters)
from .holdout import GapError
from .localize import ResidualRecord
from .predictable import state_predictable
from .result import CandidateScore
from .strategy import DECISION_TOLERANCE, DiagnosisSettings
from .structure import cell_energies, cell_masks
from .verdict import passes as _passes, reproducible_shrink as _reproducible_shrink

# a held-out prediction this many times the measured RMS (or not finite) has diverged: the
# candidate's fit is unstable away from the estimation profile and cannot be scored
DIVERGED_RELATIVE = 1e6


# ----------------------------------------------------------------------------------------
# the candidates and their refits
# ----------------------------------------------------------------------------------------
#: forms that give a family the freedom its mechanism has (a friction law per direction of motion or
#: of the power flow, a sensor delay with its filter), each nesting the family's first form; offered
#: from method version 4 on (``DiagnosisSettings.spanning_forms``)
SPANNING_FORMS = ("stribeck_directional", "load_friction_directional", "sensor_delay_dispersed")
#: forms whose magnitude follows the operating point it physically depends on (a ripple share that
#: follows the motor torque, a joint angle that changes along the stroke, a drive stiffness that
#: grows with the torque it carries), each nesting the family's first form; offered from method
#: version 5 on (``DiagnosisSettings.operating_point_forms``)
OPERATING_POINT_FORMS = ("torque_ripple_loaded", "ujoint_stroke", "shaft_compliance_loaded")


def offered_forms(effect_catalogue, settings=None) -> dict[str, Any]:
    """The candidate forms, name -> Effect, that ``settings`` (a :class:`DiagnosisSettings`;
    None: its defaults) offers out of a concept's ``effect_catalogue``: no compound that carries
    another family's mechanism (``Effect.combines``: a candidate is one mechanism); the
    :data:`SPANNING_FORMS` only with ``spanning_forms``, the :data:`OPERATING_POINT_FORMS` only
    with ``operating_point_forms``; without ``nested_forms``, no form that another offered form
    contains (``Effect.nests``: it adds nothing the nesting form cannot fit, and costs a refit)."""
    settings = DiagnosisSettings() if settings is None else settings
    spanning = bool(getattr(settings, "spanning_forms", False))
    operating_point = bool(getattr(settings, "operating_point_forms", False))
    offered = {name: effect for name, effect in (effect_catalogue or {}).items()
               if not getattr(effect, "combines", ())
               and (spanning or name not in SPANNING_FORMS)
               and (operating_point or name not in OPERATING_POINT_FORMS)}
    if not getattr(settings, "nested_forms", True):
        nested = {inner for effect in offered.values() for inner in getattr(effect, "nests", ())}
        offered = {name: effect for name, effect in offered.items() if name not in nested}
    return offered


def _catalogue(model, settings=None) -> dict[str, Any]:
    """The concept's candidate effects under ``settings`` (:func:`offered_forms` of
    ``Model.effect_catalogue``)."""
    catalogue = offered_forms(getattr(model, "effect_catalogue", None), settings)
    if not catalogue or not hasattr(model, "with_effects"):
        raise GapError(f"concept {model.name} has no catalogue of unmodelled effects; the gap diagnosis needs one")
    return catalogue


def _nested_points(augmented, reference: _Reference, effect, nested: dict) -> tuple[np.ndarray, list[str]]:
    """Points where the candidate's form computes a model already fitted
    (``DiagnosisSettings.nested_starts``): the reference model (every effect parameter at
    ``Effect.off``, the base at the reference fit) and each form of ``nested`` ({form it
    reduces to: that form's refit}) at its fit. Returns (points (n, n_params), their origins)."""
    params = augmented.parameters
    base = {k: v for k, v in reference.fit.as_dict().items() if k in params}
    points, origins = [params.vector({**base, **dict(effect.off)})], ["the reference model"]
    for other, (_, other_names, other_fit, _) in nested.items():
        values = other_fit.as_dict()
        carried = {k: v for k, v in values.items() if k in params and k not in other_names}
        points.append(params.vector({**carried, **effect.reduced_values(other, values)}))
        origins.append(f"{other}'s fit")
    return np.array(points), origins


def _refit(run: _Diagnosis, reference: _Reference, name: str, effect, start: np.ndarray | None = None,
           screening: bool = True, nested: dict | None = None):
    """ML refit of the reference model augmented by one effect.

    Screening (default): start from the best point of the start grid refined by
    :func:`_profiled_start` (for an effect with a phase, from the grid point too, the better fit
    kept), free the effect parameters and the ``screen_base_parameters`` most aliased base
    ones, Gauss-Newton capped at ``candidate_max_iterations`` (every parameter free when
    ``screen_base_parameters`` is None).
    Otherwise (the leaders' final refit): every parameter free from ``start``, capped at
    ``final_max_iterations``. With ``nested_starts`` a screening fit that ends below a model the
    form contains (:func:`_nested_points`; ``nested``: the refits of the forms this one reduces
    to) by more than ``nested_start_tolerance`` in 2V is refitted from that model's point, the
    better fit kept.
    Parameters the channels cannot determine, and with ``hold_base``
    every base parameter, stay held. Returns (augmented model, effect parameter names,
    FitResult, V of the estimate with every free parameter counted).
    """
    settings, base = run.settings, run.root
    augmented = base.with_effects(reference.effects + [name])
    names = _effect_parameter_names(augmented, reference.model)
    fixed = run.fixed
    problem = FitProblem(model=augmented, parameters=augmented.parameters.fixing(fixed), **run.problem_args)
    starts = [(start, None)]
    if start is None:
        grid = _start_grid(augmented, reference.fit.as_dict(), effect, names, run.strategy.start_multiples)
        best, objective, predicted = _best_point(problem, grid)
        profiled, profiled_prediction = _profiled_start(problem, grid[best], predicted[best], objective,
                                                           augmented.parameters, names,
                                                           run.strategy.start_multiples)
        starts = [(profiled, profiled_prediction)]
        if any(_is_phase(n, augmented.parameters[n]) for n in names) and not np.array_equal(profiled, grid[best]):
            # an amplitude profiled at a grid phase settles where that phase is least wrong, and the
            # refit from there can stop in a worse minimum than from the grid point (seed-2 HT/LS
            # ripple with harmonics: ΔBIC 2 549 against 11 333), or a better one (seed-2 LT/HS rig
            # ripple with harmonics: named only from the profile); both are refitted
            starts.append((grid[best], predicted[best]))
    fits = [_screened_fit(run, problem, augmented, names, s, p, screening) for s, p in starts]
    objectives = [_full_objective(problem, f.estimate, f.log_det_r) for f in fits]
    if start is None and settings.nested_starts:
        points, origins = _nested_points(augmented, reference, effect, nested or {})
        j, contained, predicted_points = _best_point(problem, points)
        shortfall = 2.0 * (np.nanmin(np.asarray(objectives + [np.inf])) - contained)
        if np.isfinite(contained) and 0 < shortfall <= settings.nested_start_tolerance:
            run.say(f"  {name}: its fit ended {shortfall:.3g} in 2V below {origins[j]}, which it contains, "
                    f"within the tolerance {settings.nested_start_tolerance:g}; not refitted")
        elif np.isfinite(contained) and not shortfall <= settings.nested_start_tolerance:
            run.say(f"  {name}: its fit ended {shortfall:.3g} in 2V below {origins[j]}, which it contains; "
                    "refitted from there")
            fits.append(_screened_fit(run, problem, augmented, names, points[j], predicted_points[j], screening))
            objectives.append(_full_objective(problem, fits[-1].estimate, fits[-1].log_det_r))
    k = _finite_argmin(objectives)
    fit = fits[k]
    # every run of the refit went through this problem's memo (the narrower refits share it):
    # start search, sensitivities, each start's fit, the attempts a robust fit discarded
    fit.n_simulations = problem.predictions.runs
    return augmented, names, fit, objectives[k]


def _screened_fit(run: _Diagnosis, problem: FitProblem, augmented, names: Sequence[str], start: np.ndarray,
                  start_prediction: np.ndarray | None, screening: bool) -> FitResult:
    """One refit of :func:`_refit` from ``start``; ``start_prediction`` (the simulated outputs
    there, known from the start search) picks the base parameters a screening refit frees, and
    is None for the final refit, which frees every parameter."""
    settings, base, fixed = run.settings, run.root, run.fixed
    fit_problem, cap = problem, settings.final_max_iterations
    if screening:
        cap = settings.candidate_max_iterations
        count = settings.screen_base_parameters
        if count is not None and count < len(base.parameters) and not run.strategy.hold_base:
            # the model-form allowance is free in every refit, beside the most aliased base parameters
            allowed = [] if run.allowance is None else [n for n in run.allowance.names if n not in fixed]
            keep = [n for n in _relevant_base(problem, start, start_prediction, names,
                                              count + len(fixed) + len(allowed))
                    if n not in fixed and n not in allowed][:count]
            fit_problem = FitProblem(model=augmented,
                                     parameters=augmented.parameters.freeing_only(keep + allowed + names),
                                     predictions=problem.predictions, **run.problem_args)
    return _robust_estimate(fit_problem, start, _fit_settings(settings, cap))


def _fit_settings(settings, max_iterations: int) -> Settings:
    """The estimator settings of one fit of the diagnosis under ``settings`` (a
    :class:`DiagnosisSettings`; ``decision_fits``: stop at :data:`DECISION_TOLERANCE`, judged as
    ``decision_stop`` says, no identifiable combinations)."""
    lean = bool(settings.decision_fits)
    return Settings(tolerance=settings.tolerance, max_iterations=max_iterations,
                    decrease_tolerance=DECISION_TOLERANCE if lean else None, combinations=not lean,
                    decrease_estimate=getattr(settings, "decision_stop", "extrapolated"))


# ----------------------------------------------------------------------------------------
# the steps: nominal fit, a candidate's scores, a round, forward selection
# ----------------------------------------------------------------------------------------
def _held_base_fit(run: _Diagnosis, theta: np.ndarray) -> FitResult:
    """The nominal model at the reference fit, evaluated (no parameter fitted): fault diagnosis."""
    problem = FitProblem(model=run.root, **run.problem_args)
    residual = problem.residuals(theta[None])[0]
    r = statistics.covariance(residual)
    logdet = statistics.log_det_r(r)
    p = run.root.parameters
    return FitResult(run.root.name, "held", tuple(p.names), tuple(q.unit for q in p.parameters),
                     np.zeros(len(p), dtype=bool), theta.copy(), theta.copy(), np.zeros(len(p)), np.zeros((0, 0)),
                     tuple(problem.channels), r, logdet, statistics.objective(problem.n_samples, logdet),
                     problem.n_samples, True, "base parameters held at the reference fit", 0, 1, 0.0)


def _fit_nominal(run: _Diagnosis):
    """Step 2: the nominal ML fit on the estimation data (or, holding the base parameters, the
    reference fit evaluated there) and the localisation of its residual on the estimation and
    the held-out data. Returns (reference, localisation on estimation, on held-out data)."""
    d, strategy, settings, base = run.data, run.strategy, run.settings, run.root
    run.problem_args = {"measurements": d.estimation, "channels": d.channels}
    if strategy.constants is not None:
        run.problem_args["constants"] = strategy.constants(d.estimation[0])
    reference = {k: v for k, v in (strategy.reference_fit or {}).items() if k in base.parameters}
    start = base.parameters.vector(reference)
    # the root model: the concept's own, or it with the model-form allowance's parameters appended
    problem = FitProblem(model=base, **run.problem_args)
    run.n_samples = problem.n_samples
    if strategy.hold_base:
        run.fixed = list(base.parameters.names)
        run.say(f"{base.name} held at the reference fit; {problem.n_samples} samples x {len(d.channels)} channels")
        nominal = _held_base_fit(run, start)
    else:
        run.fixed = _unidentifiable_parameters(problem, start)
        if run.fixed:
            problem = FitProblem(model=base, parameters=base.parameters.fixing(run.fixed),
                                 predictions=problem.predictions, **run.problem_args)
        run.say(f"nominal ML fit of {base.name} on {problem.n_samples} samples x {len(d.channels)} channels"
                + (f" ({', '.join(run.fixed)} held at nominal: these channels cannot determine them)"
                   if run.fixed else ""))
        nominal = _robust_estimate(problem, start, _fit_settings(settings, settings.nominal_max_iterations))
        nominal.n_simulations = problem.predictions.runs     # the identifiability test's runs too
    run.n_sims += nominal.n_simulations
    est_records = run.records(base, nominal.estimate, held=False)
    held_records = run.records(base, nominal.estimate, held=True)
    run.n_sims += len(d.estimation) + len(d.held)
    loc_est = run.localise(base, nominal.estimate, est_records, held=False)
    loc_held = run.localise(base, nominal.estimate, run.without_estimation_error(base, nominal, held_records),
                            held=True)
    before = run.parts(base, held_records, nominal.estimate)
    before["all"] = run.held_out_figures(base, held_records)
    run.ceiling = run.ceiling_of(base, est_records, held_records)
    columns = [d.channels.index(c) for c in d.held_channels]
    run.predictable = state_predictable([replace(r, observed=r.observed[:, columns], predicted=r.predicted[:, columns])
                                         for r in est_records], held_records, d.held_spread)
    if strategy.healthy_records:
        healthy = list(strategy.healthy_records)
        names = [f"healthy {i + 1}: {m.experiment.name}" for i, m in enumerate(healthy)]
        records = _simulate_records(base, nominal.estimate, healthy, d.held_channels, names, strategy)[0]
        run.n_sims += len(healthy)
        constants = strategy.constants_of(healthy[0])
        run.healthy_cells = cell_energies(records, d.held_channels, d.held_spread,
                                          cell_masks(records, base, nominal.estimate,
                                                     base.constants_vector() if constants is None else constants))
    run.say(f"nominal: log det R {nominal.log_det_r:.4g}, held-out gap {before['all']['gap']:.4g} "
            f"(z {before['all']['z']:.1f}); {'structured' if loc_est.structured else 'white'} residual")
    return _Reference(base, nominal, nominal.objective, before, []), loc_est, loc_held


def _score(run: _Diagnosis, reference: _Reference, name: str, effect, refit, seconds: float, stage: str,
           loc) -> tuple[CandidateScore, dict[str, Any]]:
    """Step 5: one refitted candidate's scores against the reference (module docstring, step 4)
    and its held-out figures (selection and scoring part)."""
    augmented, names, fit, objective = refit
    th = run.strategy.thresholds
    before = reference.figures
    lr = 2.0 * (reference.objective - objective)
    delta_bic = lr - len(names) * np.log(run.n_samples)
    held_records = run.records(augmented, fit.estimate, held=True)
    _check_not_diverged(held_records, run.data.held_spread)
    after = run.parts(augmented, held_records)
    chosen, scored = (before["selection"], after["selection"]), (before["scoring"], after["scoring"])
    gain = chosen[1]["n"] * (chosen[0]["log_det_r"] - chosen[1]["log_det_r"])
    selection_shrink, shrink = (1.0 - a["gap"] / b["gap"] if b["gap"] > 0 else 0.0 for b, a in (chosen, scored))
    reproducible = _reproducible_shrink(chosen[0]["gap"], chosen[1]["gap"], run.ceiling_gap("selection"))
    match = loc.signature_match(tuple(getattr(effect, "signature", ()) or ()))
    raw = delta_bic + gain if th.gain_in_score else delta_bic
    score = raw * (1.0 + th.signature_weight * match) if raw > 0 else raw
    of_reproducible = "" if run.ceiling is None else f", {reproducible:.2f} of its reproducible gap"
    run.say(f"  {name} ({stage}): dBIC {delta_bic:.1f}, held-out gain {gain:.1f}, shrink {selection_shrink:.2f} "
            f"(selection{of_reproducible}), {shrink:.2f} (scoring), {seconds:.1f} s")
    row = CandidateScore(
        name, float(score), scored[0]["gap"], scored[1]["gap"], float(shrink), float(lr), float(delta_bic),
        float(gain), float(match), len(names), _parameter_table(augmented, fit, names), fit.log_det_r,
        chosen[1]["log_det_r"], chosen[1]["nrmse"], chosen[1]["z"], bool(fit.converged), fit.iterations,
        fit.n_simulations, seconds, fit.message, fit.as_dict(), stage, list(fit.free_names),
        shrink_se=run.shrink_se(*scored), selection_gap_before=chosen[0]["gap"], selection_gap_after=chosen[1]["gap"],
        selection_shrink=float(selection_shrink), family=_family(name, effect), reproducible_shrink=reproducible)
    return row, after


def _check_not_diverged(records: Sequence[ResidualRecord], spread: np.ndarray) -> None:
    """SimulationError when a held-out prediction is not finite or over ``DIVERGED_RELATIVE``
    times the measured RMS of its channel."""
    for rec in records:
        with np.errstate(invalid="ignore", over="ignore"):
            size = np.max(np.abs(rec.predicted) / np.where(spread > 0, spread, 1.0))
        if not np.isfinite(size) or size > DIVERGED_RELATIVE:
            raise SimulationError(f"its prediction of {rec.name} diverges (peak {size:.3g} times the measured RMS): "
                                  "the fit is unstable away from the estimation profile")


def _candidate(run: _Diagnosis, reference: _Reference, name: str, effect, loc, fits: dict, **kwargs) -> CandidateScore:
    """Refit and score one candidate (a failed refit, or one whose held-out prediction
    diverges, scores -inf); its fit goes into ``fits``."""
    tc = time.perf_counter()
    try:
        # trial points that simulate to NaN have det R = NaN; the optimiser rejects them
        with np.errstate(invalid="ignore", over="ignore"):
            refit = _refit(run, reference, name, effect, **kwargs)
        stage = "screening" if kwargs.get("screening", True) else "final"
        row, after = _score(run, reference, name, effect, refit, time.perf_counter() - tc, stage, loc)
    except (IdentificationError, SimulationError, ParameterError, np.linalg.LinAlgError) as exc:
        # ParameterError: an effect that cannot join the selected ones (the same coupling twice)
        run.say(f"  {name}: refit failed ({exc})")
        return CandidateScore(name, float("-inf"), reference.figures["scoring"]["gap"], float("nan"), float("nan"),
                              float("nan"), float("nan"), float("nan"), 0.0, 0,
                              message=f"refit failed: {exc}", wall_time_s=time.perf_counter() - tc,
                              family=_family(name, effect))
    run.n_sims += refit[2].n_simulations + len(run.data.held)
    fits[name] = (refit, after)
    return row


def _family(name: str, effect) -> str:
    """The family an effect belongs to (``Effect.family``; itself when its catalogue has none)."""
    return getattr(effect, "family", None) or name


def _ranked(rows: list[CandidateScore]) -> list[CandidateScore]:
    return sorted(rows, key=lambda c: -c.score if np.isfinite(c.score) else np.inf)


def _fit_order(pool: dict[str, Any], nested_starts: bool) -> list[str]:
    """The order in which a round fits its candidates: the catalogue's, except that with
    ``nested_starts`` a form comes after the offered forms it reduces to (``Effect.reduces_to``),
    so that a fit of it that ends below theirs can be refitted from their fits."""
    order = list(pool)
    if not nested_starts:
        return order
    placed: list[str] = []
    while order:
        ready = [n for n in order if not any(o in order and o != n for o in getattr(pool[n], "reduces_to", {}))]
        if not ready:           # reductions in a circle: no form waits for another
            ready = order[:]
        placed += ready
        order = [n for n in order if n not in ready]
    return placed


def _candidate_round(run: _Diagnosis, reference: _Reference, pool: dict[str, Any], loc):
    """Steps 3-4: screening refit of every candidate in ``pool``, then the leaders' final
    refits with every parameter free. Returns (ranking, {name: (refit, held-out figures)})."""
    fits: dict[str, Any] = {}
    rows = {}
    for name in _fit_order(pool, run.settings.nested_starts):
        effect = pool[name]
        nested = {other: fits[other][0] for other in getattr(effect, "reduces_to", {}) if other in fits}
        rows[name] = _candidate(run, reference, name, effect, loc, fits, nested=nested)
    ranking = _ranked([rows[name] for name in pool])      # ties keep the catalogue's order
    if run.settings.screen_base_parameters is None:
        return ranking, fits
    leaders = [c for c in ranking[:run.settings.final_candidates] if np.isfinite(c.score)]
    for row in [c for i, c in enumerate(leaders) if i == 0 or c.score > 0]:
        screened = fits[row.effect][0][2]
        final = _candidate(run, reference, row.effect, pool[row.effect], loc, fits, start=screened.estimate,
                           screening=False)
        if not np.isfinite(final.score):
            continue
        final.wall_time_s += row.wall_time_s
        final.n_simulations += row.n_simulations
        ranking[ranking.index(row)] = final
    return _ranked(ranking), fits


def _forward_selection(run: _Diagnosis, nominal: _Reference, loc):
    """Steps 3-5 in rounds: a round's passing winner joins the reference model of the next.
    Returns (rounds of rankings, selected effects, per-round fits, the model after: (reference
    of the last selected effect, or of round 1's best candidate, and its score) or None)."""
    reference, selected, rounds, round_fits = nominal, [], [], []
    for _ in range(run.settings.max_effects):
        # a selected effect's family is done: its other forms are alternatives, not additions
        done = {_family(k, run.catalogue[k]) for k in selected}
        pool = {k: v for k, v in run.catalogue.items() if _family(k, v) not in done}
        if not pool:
            break
        ranking, fits = _candidate_round(run, reference, pool, loc)
        rounds.append(ranking)
        round_fits.append(fits)
        best = ranking[0] if ranking and np.isfinite(ranking[0].score) else None
        chosen = reference.figures["selection"]
        if not _passes(run.strategy.thresholds, best, chosen["significant"], run.reproducible_significant(chosen)):
            break
        selected.append(best.effect)
        (model, _, fit, objective), figures = fits[best.effect]
        reference = _Reference(model, fit, objective, figures, list(selected))
    return rounds, selected, round_fits


def _after_model(run: _Diagnosis, rounds, selected, round_fits):
    """The model the gap is measured after: that of the last selected effect, else round 1's
    best candidate. Returns (its CandidateScore, (model, fit), its held-out figures of the
    selection and scoring part) or Nones."""
    if selected:
        r, name = len(selected) - 1, selected[-1]
    elif rounds and rounds[0] and np.isfinite(rounds[0][0].score):
        r, name = 0, rounds[0][0].effect
    else:
        return None, None, None
    if name not in round_fits[r]:
        return None, None, None
    (model, _, fit, _), figures = round_fits[r][name]
    return next(c for c in rounds[r] if c.effect == name), (model, fit), dict(figures)

