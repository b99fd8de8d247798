"""The identifiability of one sensor set (a choice of measured channels) and the sensor-set
study: around a maximum-likelihood fit of the data (:func:`assess_sensor_set`), or at a point
before any fit, from the information the rig's noise would leave (:func:`assess_at_point`)."""
from __future__ import annotations

import time as _time
from typing import Any, Mapping, Sequence

import numpy as np

from ..errors import EmaUqError
from ..experiments import Measurement
from ..identify import FitProblem, IdentificationError
from ..identify.information import (collinearity_tables, combinations, identifiable_subset, information, near_bounds,
                                    station_groups)
from ..models import Model, get_model
from .profiles import (PROFILE_THRESHOLD, Profile, _fit_with_handover, classify_information, classify_profile,
                       profile_grid, profile_likelihood)
from .result import IdentifiabilityResult, ProfileSettings, SensorSetResult


class IdentifiabilityError(EmaUqError):
    """Bad input to the identifiability analysis (unknown sensor set or parameter, no free
    parameter, data without the channels of a sensor set)."""


# --------------------------------------------------------------------------------------
# sensor sets
# --------------------------------------------------------------------------------------
def sensor_set(model: Model, item: str | Mapping[str, Any]) -> tuple[str, tuple[str, ...]]:
    """(name, channels) of a sensor set the concept defines (``Model.sensor_sets``: ``"full"``
    = every output, ``"realistic"`` = rig sensors) or of ``{"name": ..., "channels": [...]}``."""
    if isinstance(item, Mapping):
        channels = tuple(item["channels"])
        model.output_index(channels)
        return str(item["name"]), channels
    if item in model.sensor_sets:
        return item, tuple(model.sensor_sets[item])
    if item == "full":
        return "full", tuple(model.outputs)
    if item == "realistic":
        raise IdentifiabilityError(f"no realistic sensor set is defined for concept {model.name}; give channels")
    known = ", ".join(dict.fromkeys(("full", *model.sensor_sets)))
    raise IdentifiabilityError(f"unknown sensor set {item!r}; use {known} or a name with channels")


# --------------------------------------------------------------------------------------
# one sensor set around a fit, and the sensor-set study
# --------------------------------------------------------------------------------------
def assess_sensor_set(measurements: Sequence[Measurement], start: np.ndarray, free: Sequence[str],
                      channels: Sequence[str], *, name: str = "custom", settings: ProfileSettings = ProfileSettings(),
                      profile_names: Sequence[str] | None = None, constants: np.ndarray | None = None,
                      progress=None) -> SensorSetResult:
    """Identifiability of ``free`` parameters from ``channels`` of ``measurements``.

    ``start`` is a full parameter vector (e.g. an ML estimate from all channels); the
    reference fit re-estimates the identifiable subset with these channels from there.
    ``profile_names`` default: every free B_*/C_*; the other free parameters are judged from
    the information matrix.
    """
    t0 = _time.perf_counter()
    measurements = list(measurements)
    model = get_model(measurements[0].concept)
    constants = model.constants_vector() if constants is None else np.asarray(constants, dtype=float)
    free = [n for n in model.parameters.names if n in set(free)]
    if not free:
        raise IdentifiabilityError("no free parameter to assess; free at least one")
    unknown = [n for n in (profile_names or []) if n not in free]
    if unknown:
        raise IdentifiabilityError(f"cannot profile {', '.join(unknown)}: not free in the fit; free parameters: "
                                   f"{', '.join(free)}")
    missing = [c for c in channels if any(c not in m.channels for m in measurements)]
    if missing:
        raise IdentifiabilityError(f"sensor set {name}: channel(s) {', '.join(missing)} missing from the data; "
                                   "simulate data with every channel or choose another set")
    if profile_names is None:
        profile_names = [n for n in free if n.startswith(("B_", "C_"))]
    channels = tuple(channels)
    problem = FitProblem(measurements, parameters=model.parameters.freeing_only(free), channels=channels,
                         constants=constants)
    start = np.clip(np.asarray(start, dtype=float), model.parameters.lower, model.parameters.upper)
    info, n_sims = information(problem, start)
    selected = identifiable_subset(info, avoid=near_bounds(model, start, free))
    say = progress or (lambda _msg: None)
    say(f"{name}: reference fit of {len(selected)} identifiable parameters ({len(free) - len(selected)} lumped)")
    try:
        fit, v_min, _, n = _fit_with_handover(
            measurements, model, channels, constants, selected, start,
            lambda theta: identifiable_subset(info, avoid=near_bounds(model, theta, free)))
    except IdentificationError as exc:
        raise IdentifiabilityError(f"sensor set {name}: reference fit failed: {exc}") from None
    n_sims += n
    theta_hat = fit.estimate.copy()
    info, n = information(problem, theta_hat)
    n_sims += n
    at_bounds = near_bounds(model, theta_hat, free)
    selected = identifiable_subset(info, avoid=at_bounds)
    std = info.std()
    in_null = info.in_null_space()
    warnings = [] if fit.converged else [f"reference fit not converged: {fit.message}"]
    if at_bounds:
        warnings.append(f"reference estimate at or near a bound for {', '.join(at_bounds)}: the data push the "
                        "weakly determined direction they belong to towards the edge of the admissible range")

    profiles: dict[str, Profile] = {}
    for pname in profile_names:
        j = info.names.index(pname)
        i = model.parameters.index(pname)
        grid = profile_grid(theta_hat[i], std[j], model.parameters.lower[i], model.parameters.upper[i],
                            points=settings.points, sigmas=settings.sigmas, span=settings.span)
        others = identifiable_subset(info, exclude=[pname], avoid=at_bounds)
        say(f"{name}: profile {pname} on {grid.size} points, re-optimising {len(others)} parameters")
        prof = profile_likelihood(
            measurements, model, channels, constants, theta_hat, v_min, pname, grid, others,
            reselect=lambda theta, pname=pname: identifiable_subset(info, exclude=[pname],
                                                                    avoid=near_bounds(model, theta, free)))
        profiles[pname] = prof
        n_sims += prof.n_simulations
        warnings += prof.failures
    # a profile point below the reference minimum means the reference fit stopped short
    lowest = min([v_min] + [float(p.objective.min()) for p in profiles.values()])
    if lowest < v_min - 0.05 * PROFILE_THRESHOLD:
        warnings.append(f"a profile found an objective {v_min - lowest:.3g} below the reference fit; "
                        "intervals are measured from the lower value")
    for p in profiles.values():
        p.v_min = min(lowest, v_min)

    verdicts = {}
    for j, pname in enumerate(info.names):
        if pname in profiles:
            v, reason = classify_profile(profiles[pname], bool(in_null[j]),
                                         max_relative_width=settings.max_relative_width)
            verdicts[pname] = (v, "profile", reason)
        else:
            v, reason = classify_information(theta_hat[model.parameters.index(pname)], std[j], bool(in_null[j]),
                                             max_relative_width=settings.max_relative_width)
            verdicts[pname] = (v, "fim", reason)
    friction = [n for n in info.names if n.startswith(("B_", "C_"))]
    pairs, groups, triples = collinearity_tables(info, friction, station_groups(info.names))
    combos = combinations(info, {n: theta_hat[model.parameters.index(n)] for n in info.names}, model, constants)
    estimate_free = theta_hat[[model.parameters.index(n) for n in info.names]]
    return SensorSetResult(
        name=name, concept=model.name, channels=channels, names=info.names, estimate=estimate_free,
        objective=v_min, info=info, selected=tuple(selected), profiles=profiles, verdicts=verdicts,
        collinearity_pairs=pairs, collinearity_groups=groups, collinearity_triples=triples, combinations=combos,
        settings=settings, n_simulations=n_sims, wall_time_s=_time.perf_counter() - t0, warnings=warnings,
    )


def sensor_set_study(measurements: Sequence[Measurement], start: np.ndarray, free: Sequence[str],
                     sets: Sequence[str | Mapping[str, Any]] = ("full", "realistic"), *,
                     settings: ProfileSettings = ProfileSettings(), profile_names: Sequence[str] | None = None,
                     constants: np.ndarray | None = None, progress=None) -> IdentifiabilityResult:
    """:func:`assess_sensor_set` for each sensor set, from the same start and data.

    A set whose channels are not all in every record is skipped, with the reason in
    ``IdentifiabilityResult.skipped`` (rig data has only the rig's channels, so the default
    "full" set cannot be assessed on it); when no set is left that is an error naming the
    channels the data has."""
    measurements = list(measurements)
    if not measurements:
        raise IdentifiabilityError("no measurement given; pass the estimation (and validation) data")
    model = get_model(measurements[0].concept)
    present = [c for c in model.outputs if all(c in m.channels for m in measurements)]
    results, skipped = {}, {}
    for item in sets:
        name, channels = sensor_set(model, item)
        if name in results or name in skipped:
            raise IdentifiabilityError(f"sensor set {name} given twice; name each set once")
        missing = [c for c in channels if c not in present]
        if missing:
            skipped[name] = f"channel(s) {', '.join(missing)} not in the data"
            continue
        results[name] = assess_sensor_set(measurements, start, free, channels, name=name, settings=settings,
                                          profile_names=profile_names, constants=constants, progress=progress)
    if not results:
        raise IdentifiabilityError(
            "no sensor set can be assessed on this data (" + "; ".join(f"{k}: {v}" for k, v in skipped.items())
            + f"); the data has {', '.join(present) or 'no output channel'}: give --channels with a subset of them")
    if skipped and progress is not None:
        progress("skipped " + "; ".join(f"sensor set {k}: {v}" for k, v in skipped.items()))
    return IdentifiabilityResult(model.name, results, skipped=skipped)


# --------------------------------------------------------------------------------------
# before any fit: the expected information at a point
# --------------------------------------------------------------------------------------
def expected_records(model: Model, experiments: Sequence, theta: np.ndarray,
                     constants: np.ndarray | None = None) -> list[Measurement]:
    """Noise-free records of every output of ``model`` at the full vector ``theta`` on each
    experiment: what the data would be if ``theta`` were the truth."""
    from ..experiments import synthesize

    return [synthesize(model, e, theta, noise=0.0, seed=None, constants=constants) for e in experiments]


def assess_at_point(records: Sequence[Measurement], theta: np.ndarray, free: Sequence[str],
                    channels: Sequence[str], *, noise: float, name: str = "custom",
                    settings: ProfileSettings = ProfileSettings(), constants: np.ndarray | None = None
                    ) -> SensorSetResult:
    """Identifiability of ``free`` from ``channels`` at ``theta`` without a fit, to choose sensors.

    ``records`` are the noise-free outputs at ``theta`` (:func:`expected_records`); R is the
    noise the rig would add, diag((``noise`` x each channel's RMS over the records)²), so the
    information matrix is the expected one. Profiles are skipped: they measure the rise of
    the likelihood from its minimum on measured data, which a point without data has not;
    every verdict comes from the information matrix (:func:`classify_information`).
    """
    from ..experiments import noise_std

    t0 = _time.perf_counter()
    model = get_model(records[0].concept)
    constants = model.constants_vector() if constants is None else np.asarray(constants, dtype=float)
    free = [n for n in model.parameters.names if n in set(free)]
    if not free:
        raise IdentifiabilityError("no free parameter to assess; free at least one")
    channels = tuple(channels)
    problem = FitProblem(records, parameters=model.parameters.freeing_only(free), channels=channels,
                         constants=constants)
    sigma = noise_std(problem.observed, noise)
    if not np.all(sigma > 0):
        raise IdentifiabilityError(f"sensor set {name}: a channel is identically zero at this point, or the noise "
                                   "level is 0; give a noise fraction > 0 (e.g. --noise 0.02)")
    theta = np.asarray(theta, dtype=float)
    info, n_sims = information(problem, theta, noise_covariance=np.diag(sigma ** 2))
    std, in_null = info.std(), info.in_null_space()
    values = theta[[model.parameters.index(n) for n in info.names]]
    verdicts = {}
    for j, pname in enumerate(info.names):
        v, reason = classify_information(values[j], std[j], bool(in_null[j]),
                                         max_relative_width=settings.max_relative_width)
        verdicts[pname] = (v, "fim", reason)
    friction = [n for n in info.names if n.startswith(("B_", "C_"))]
    pairs, groups, triples = collinearity_tables(info, friction, station_groups(info.names))
    combos = combinations(info, dict(zip(info.names, values)), model, constants)
    return SensorSetResult(
        name=name, concept=model.name, channels=channels, names=info.names, estimate=values,
        objective=float("nan"), info=info, selected=tuple(identifiable_subset(info)), profiles={}, verdicts=verdicts,
        collinearity_pairs=pairs, collinearity_groups=groups, collinearity_triples=triples, combinations=combos,
        settings=settings, n_simulations=n_sims, wall_time_s=_time.perf_counter() - t0,
        warnings=[f"no fit: expected information at the given point with noise {noise:g} x each channel's RMS; "
                  "profiles skipped (they need the likelihood minimum of measured data), verdicts from the "
                  "information matrix"],
    )


def sensor_set_study_at(model: Model, experiments: Sequence, theta: np.ndarray, free: Sequence[str],
                        sets: Sequence[str | Mapping[str, Any]] = ("full", "realistic"), *, noise: float,
                        settings: ProfileSettings = ProfileSettings(),
                        constants: np.ndarray | None = None) -> IdentifiabilityResult:
    """:func:`assess_at_point` for each sensor set on the noise-free records of ``experiments``
    at ``theta``: the sensor-set study before any fit."""
    if not experiments:
        raise IdentifiabilityError("no experiment given; pass data files or an experiment name")
    records = expected_records(model, experiments, theta, constants)
    results = {}
    for item in sets:
        name, channels = sensor_set(model, item)
        if name in results:
            raise IdentifiabilityError(f"sensor set {name} given twice; name each set once")
        results[name] = assess_at_point(records, theta, free, channels, noise=noise, name=name, settings=settings,
                                        constants=constants)
    return IdentifiabilityResult(model.name, results)
