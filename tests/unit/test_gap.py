"""Sim-to-real gap diagnosis: the systematic-energy estimator against analytic answers,
localisation of residuals with a known injected structure, the FitProblem ``model``
argument, quick end-to-end diagnoses of one HT/LS case per verdict kind (restricted
candidate lists keep them fast), the GAP.json contract, the ledger figure, the self-check's
cases and scoring on synthetic outcomes, one real self-check case, bad input, and (slow) the
full blind self-check against its targets.
"""
from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from ema_uq import get_model, io, simulate_batch, synthesize
from ema_uq.cli import main
from ema_uq.experiments import add_noise, deploy_retract, validation
from ema_uq.gap import GapError, GapResult, ResidualRecord, diagnose, localize, split_holdout, systematic_nrmse
from ema_uq.gap import selfcheck
from ema_uq.gap.allowance import actuator_allowance
from ema_uq.gap.localize import LAG_NORM, LAG_WEIGHTS, lag_products
from ema_uq.gap.strategy import DiagnosisSettings
from ema_uq.gap.variants import VARIANTS, make_records
from ema_uq.identify import FitProblem, IdentificationError

DT = 0.01


# --------------------------------------------------------------------------------------
# the estimator
# --------------------------------------------------------------------------------------
def test_lag_products_are_unbiased_for_noise_and_count_low_frequency_energy():
    rng = np.random.default_rng(0)
    n = 200_000
    noise = rng.standard_normal((n, 1)) * 3.0
    p = lag_products(noise)
    # white noise: mean 0 within 4 standard deviations σ² sqrt(Σw² / n)
    assert abs(np.nanmean(p)) < 4 * 9.0 * np.sqrt(LAG_NORM / n)
    t = np.arange(n) * DT
    for f, weight in ((0.5, 0.995), (2.0, 0.915), (5.0, 0.531)):
        s = np.sin(2 * np.pi * f * t)[:, None]
        # W(f) = Σ w_l cos(2π f l Δt): analytic weight of a sinusoid of energy 1/2
        expected = sum(w * np.cos(2 * np.pi * f * (l + 1) * DT) for l, w in enumerate(LAG_WEIGHTS))
        assert expected == pytest.approx(weight, abs=1e-3)
        assert np.nanmean(lag_products(s)) / 0.5 == pytest.approx(expected, rel=1e-3)


def test_systematic_nrmse_of_an_offset_plus_noise():
    rng = np.random.default_rng(1)
    n, rms = 20_000, np.array([2.0, 5.0])
    offset = np.array([0.1, 0.0])                      # systematic NRMSE 0.05 and 0
    e = offset + rng.standard_normal((n, 2)) * 0.04 * rms
    total, per_channel, z, factors = systematic_nrmse([e], rms)
    assert per_channel[0] == pytest.approx(0.05, rel=0.05)
    assert per_channel[1] < 0.01
    assert total == pytest.approx(np.sqrt((0.05 ** 2 + 0.0) / 2), rel=0.1)
    assert z > 20 and factors == 0
    # noise alone: z is a standard score
    assert abs(systematic_nrmse([rng.standard_normal((n, 2))], rms)[2]) < 4


def test_broadband_error_shared_by_channels_is_counted_and_independent_noise_is_not():
    rng = np.random.default_rng(2)
    n, m = 4000, 12
    shared = rng.standard_normal(n)                     # white in time: lag products cannot see it
    e = rng.standard_normal((n, m)) * rng.uniform(0.5, 1.0, m)
    noise_only = systematic_nrmse([e], np.sqrt(np.mean(e ** 2, axis=0)))
    assert noise_only[3] == 0 and noise_only[0] < 0.01
    e[:, :6] += 0.4 * shared[:, None] * np.arange(1, 7)
    rms = np.sqrt(np.mean(e ** 2, axis=0))
    total, per_channel, _, factors = systematic_nrmse([e], rms)
    truth = (0.4 * np.arange(1, 7)) / rms[:6]
    assert factors == 1
    # per channel within 4 standard deviations of the lag products of its noise, σ² / sqrt(n)
    np.testing.assert_allclose(per_channel[:6] ** 2, truth ** 2, atol=4 * 1.0 / np.sqrt(n) / rms[:6].min() ** 2)
    assert np.all(per_channel[6:] ** 2 < 4 / np.sqrt(n))      # noise-only channels: 4 σ of the lag products
    assert total == pytest.approx(np.sqrt(np.sum(truth ** 2) / m), rel=0.1)


# --------------------------------------------------------------------------------------
# localisation on residuals with a known structure
# --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def htls_clean():
    model = get_model("htls")
    experiment = deploy_retract()
    inputs = experiment.input_matrix(model)
    out = simulate_batch(model, model.parameters.nominal, experiment.time, inputs)
    return model, experiment, inputs, out


def _record(htls_clean, observed):
    model, experiment, inputs, out = htls_clean
    return ResidualRecord("dr", experiment.time, inputs, observed, out, out)


def test_white_residual_is_not_structured(htls_clean):
    model, _, _, out = htls_clean
    observed = add_noise(out, 0.02, np.random.default_rng(2))
    loc = localize([_record(htls_clean, observed)], model.outputs, model, model.parameters.nominal)
    assert not loc.structured, loc.reasons
    assert loc.where_regimes == [] and loc.where_channels() == []


def test_bias_is_judged_against_each_records_own_noise(htls_clean):
    """Two records of one channel set, the first ten times noisier (a larger-amplitude profile
    carries larger noise): a mean offset of 3.3 of its own σ/sqrt(n) is chance once two records
    are looked at, though it is over 4 of the pooled σ/sqrt(n); 8 of its own is a bias."""
    model, experiment, inputs, out = htls_clean
    rng = np.random.default_rng(5)
    n, channel = out.shape[0], model.outputs.index("I_A")

    def records(own_z):
        noisy = out + 10 * (add_noise(out, 0.02, rng) - out)
        noise = noisy[:, channel] - out[:, channel]
        sigma = np.sqrt(np.mean(np.diff(noise) ** 2) / 2)
        noisy[:, channel] += own_z * sigma / np.sqrt(n) - noise.mean()
        quiet = add_noise(out, 0.02, rng)
        return [ResidualRecord("noisy", experiment.time, inputs, noisy, out, out),
                ResidualRecord("quiet", experiment.time, inputs, quiet, out, out)]

    chance = localize(records(3.3), model.outputs, model, model.parameters.nominal)
    assert "I_A" not in chance.tests["biased"], chance.reasons
    row = next(c for c in chance.channels if c.channel == "I_A")
    assert 2.5 < row.bias_z < 3.3          # Bonferroni over the two records
    biased = localize(records(8.0), model.outputs, model, model.parameters.nominal)
    assert "I_A" in biased.tests["biased"]


def test_injected_delay_is_localised_with_its_size(htls_clean):
    model, _, _, out = htls_clean
    delayed = np.vstack([np.repeat(out[:2], 2, axis=0)[:2], out[:-2]])   # 2 samples = 20 ms late
    observed = add_noise(delayed, 0.02, np.random.default_rng(3))
    loc = localize([_record(htls_clean, observed)], model.outputs, model, model.parameters.nominal)
    assert loc.structured
    assert "delay" in loc.where_regimes
    omega = next(c for c in loc.channels if c.channel == "Omega")
    assert omega.delay_s == pytest.approx(0.020, abs=0.003)
    assert loc.signature_match(("delay",)) == 1.0


def test_injected_reversal_error_is_localised(htls_clean):
    model, experiment, _, out = htls_clean
    observed = out.copy()
    # a speed error for 0.3 s after the retraction starts (t = 24 s), as a dead band would give
    bump = np.exp(-((experiment.time - 24.2) / 0.12) ** 2)
    observed[:, model.outputs.index("Omega")] += 3.0 * bump
    observed = add_noise(observed, 0.02, np.random.default_rng(4))
    loc = localize([_record(htls_clean, observed)], model.outputs, model, model.parameters.nominal)
    assert loc.where_channels()[0] == "Omega"
    assert "reversal" in loc.where_regimes
    held = [loc.regime(name) for name in loc.where_regimes]
    assert max(held, key=lambda r: r.enrichment).name == "reversal"    # the most specific regime
    assert loc.regime("reversal").enrichment > 10
    window = loc.windows["dr"]
    worst = window["time"][int(np.argmax(window["systematic_nrmse"]))]
    assert 23.5 < worst < 25.0


def test_injected_shaft_order_ripple_is_a_periodic_peak(htls_clean):
    model, experiment, _, out = htls_clean
    omega = out[:, model.outputs.index("Omega")]
    angle = np.concatenate([[0.0], np.cumsum(0.5 * (omega[1:] + omega[:-1]) * DT)])
    observed = out.copy()
    observed[:, 0] += 0.4 * np.sin(angle)                      # order 1 of the motor
    observed = add_noise(observed, 0.02, np.random.default_rng(5))
    loc = localize([_record(htls_clean, observed)], model.outputs, model, model.parameters.nominal)
    assert "periodic" in loc.where_regimes
    peak = loc.peaks[0]
    assert peak.channel == "Omega" and peak.order == pytest.approx(1.0)


# --------------------------------------------------------------------------------------
# FitProblem with an augmented model
# --------------------------------------------------------------------------------------
def test_fit_problem_takes_an_augmented_model_of_the_same_concept():
    data = synthesize("htls", deploy_retract().slice(0, 300), noise=0.02, seed=1)
    augmented = get_model("htls").with_effects(["sensor_delay"])
    problem = FitProblem([data], model=augmented)
    assert problem.model is augmented and problem.parameters.names[-1] == "sensor_delay_tau"
    # at tau = 0 the augmented model predicts exactly what the nominal one does
    theta = augmented.parameters.vector({"sensor_delay_tau": 0.0})
    nominal = FitProblem([data]).predict(get_model("htls").parameters.nominal[None])
    np.testing.assert_array_equal(problem.predict(theta[None]), nominal)
    with pytest.raises(IdentificationError, match="built on concept lths"):
        FitProblem([data], model=get_model("lths").with_effects(["sensor_delay"]))


def test_parameters_the_channels_cannot_determine_are_held():
    from ema_uq.gap.attribute import _unidentifiable_parameters

    data = synthesize("htls", deploy_retract().slice(0, 800), noise=0.02, seed=1)
    nominal = get_model("htls").parameters.nominal
    assert _unidentifiable_parameters(FitProblem([data]), nominal) == []
    # without the current, k_n moves nothing; without torques only the loss totals are determined
    held = _unidentifiable_parameters(FitProblem([data.select(["Omega", "y1", "y2"])]), nominal)
    assert held[0] == "k_n" and len(held) >= 10 and not {"J", "p_ACE", "p_PCE"} & set(held)


def test_held_out_tests_allow_for_the_fits_own_estimation_error():
    """Held-out data made 2 standard errors off the fit along its least certain direction: the
    adjustment moves the prediction by the posterior mean of that error, about half of it where
    the held-out record is as informative as the estimation record (the prior keeps the rest).
    A current offset, only partly like a parameter error, keeps most of its size."""
    from dataclasses import replace

    from ema_uq.gap import attribute as A

    base = get_model("htls")
    est = synthesize("htls", deploy_retract(), noise=0.02, seed=61)
    val = synthesize("htls", validation(), noise=0.02, seed=62)
    strategy = A.strategy_for(base)
    run = A._Diagnosis(strategy, strategy.settings, A._split([est], [val], strategy, strategy.settings), base,
                       A._catalogue(base), lambda line: None, seed=61)
    fit = A._fit_nominal(run)[0].fit
    records = run.records(base, fit.estimate, held=True)
    evals, evecs = np.linalg.eigh(fit.covariance)
    off = fit.estimate.copy()
    off[fit.free] += 2.0 * np.sqrt(evals[-1]) * evecs[:, -1]
    shifted = run.records(base, off, held=True)
    noise = [r.residual for r in records]
    moved = [replace(r, observed=s.predicted + e) for r, s, e in zip(records, shifted, noise)]
    adjusted = run.without_estimation_error(base, fit, moved)
    error_before = np.concatenate([m.residual - e for m, e in zip(moved, noise)])
    error_after = np.concatenate([a.residual - e for a, e in zip(adjusted, noise)])
    assert np.sqrt(np.mean(error_after ** 2)) < 0.6 * np.sqrt(np.mean(error_before ** 2))

    channel = run.data.held_channels.index("I_A")
    offset = np.zeros(len(run.data.held_channels))
    offset[channel] = 0.01 * run.data.held_spread[channel]
    biased = [replace(r, observed=r.observed + offset) for r in records]
    kept = run.without_estimation_error(base, fit, biased)
    residual_mean = np.mean(np.concatenate([k.residual - e for k, e in zip(kept, noise)])[:, channel])
    assert residual_mean > 0.6 * offset[channel]


def test_a_candidate_whose_held_out_prediction_diverges_is_refused(htls_clean):
    """A refit stable on the estimation profile can blow up on a held-out one (seen: the
    compliant backlash at a drawn stiffness); it must fail as a candidate, not end the diagnosis."""
    from ema_uq.gap.attribute import _check_not_diverged
    from ema_uq.simulate import SimulationError

    model, experiment, inputs, out = htls_clean
    spread = np.sqrt(np.mean(out ** 2, axis=0))
    _check_not_diverged([_record(htls_clean, out)], spread)
    for bad in (np.nan, 1e9):
        blown = out.copy()
        blown[-1, 0] = bad * spread[0]
        record = ResidualRecord("held-out 1", experiment.time, inputs, out, blown, blown)
        with pytest.raises(SimulationError, match="held-out 1 diverges"):
            _check_not_diverged([record], spread)


def test_a_gauss_newton_fit_that_stalls_is_finished_by_levenberg_marquardt(monkeypatch):
    """A Gauss-Newton fit stopping early unconverged (here: cut after one iteration, as when its
    step halving runs out) must not be the reference: the candidates would be credited with
    finishing its descent. The robust fit continues it to the full fit's minimum."""
    from dataclasses import replace

    from ema_uq.gap import attribute as A
    from ema_uq.gap import fitting
    from ema_uq.identify import Settings

    data = synthesize("htls", deploy_retract().slice(0, 800), noise=0.02, seed=3)
    problem = FitProblem([data])
    start = problem.parameters.nominal * 1.3
    settings = Settings(tolerance=1e-6, max_iterations=20)
    full = A.estimate(problem, method="gn", start=start, settings=settings)
    real = A.estimate

    def stalling(problem, method, start, settings, **kwargs):
        if method == "gn":
            settings = replace(settings, max_iterations=1)
        return real(problem, method=method, start=start, settings=settings, **kwargs)

    # the robust fit calls the estimator of the module it lives in
    monkeypatch.setattr(fitting, "estimate", stalling)
    stalled = stalling(problem, "gn", start, settings)
    assert not stalled.converged and stalled.objective > full.objective + 100.0
    fit = A._robust_estimate(problem, start, settings)
    assert fit.converged and fit.iterations > 1 and "Levenberg-Marquardt after Gauss-Newton" in fit.message
    assert fit.objective == pytest.approx(full.objective, abs=1.0)
    assert fit.n_simulations > stalled.n_simulations


def test_the_start_profile_finds_a_magnitude_between_grid_points():
    """A magnitude twice the largest grid point (10 x start): the grid's best is 2x off, one
    pass of the fine profile lands within its 1.16x steps of the truth."""
    from ema_uq.gap import attribute as A

    base = get_model("htls")
    model = base.with_effects(["load_dependent_friction"])
    effect = base.effect_catalogue["load_dependent_friction"]
    mu = 20.0 * effect.start["load_dependent_friction_mu"]
    theta = model.parameters.vector({"load_dependent_friction_mu": mu})
    data = synthesize(model, deploy_retract().slice(0, 1500), theta, noise=0.02, seed=5)
    problem = FitProblem([data], model=model)
    names = ["load_dependent_friction_mu"]
    grid = A._start_grid(model, base.parameters.as_dict(base.parameters.nominal), effect, names)
    predicted = problem.predict(grid)
    objectives = [problem.objective(problem.observed - predicted[i], grid[i, problem.free_index])[0]
                  for i in range(grid.shape[0])]
    best = int(np.argmin(objectives))
    i = model.parameters.index(names[0])
    assert grid[best, i] == pytest.approx(mu / 2)
    runs = problem.predictions.runs
    start, prediction = A._profiled_start(problem, grid[best], predicted[best], objectives[best],
                                          model.parameters, names, A.statistics.START_MULTIPLES)
    # one pass of at most PROFILE_POINTS points (clipped duplicates and points the grid ran are not run again)
    assert 0 < problem.predictions.runs - runs <= A.PROFILE_POINTS
    assert abs(np.log(start[i] / mu)) < np.log(1.17)
    np.testing.assert_array_equal(prediction, problem.predict(start[None])[0])


def test_an_effect_with_a_phase_is_refitted_from_the_grid_point_and_the_profiled_start(monkeypatch):
    """The amplitude profiled at a grid phase can lead the refit into a better minimum or a
    worse one than the grid point does (seed-2 self-check: both happened); the screening refit
    runs from both starts and keeps the fit with the lower objective."""
    from ema_uq.gap import attribute as A
    from ema_uq.gap import candidates

    base = get_model("htls")
    model = base.with_effects(["torque_ripple"])
    effect = base.effect_catalogue["torque_ripple"]
    theta = model.parameters.vector({"torque_ripple_amplitude": 0.45, "torque_ripple_phase": 1.3})
    est = synthesize(model, deploy_retract().slice(0, 1500), theta, noise=0.02, seed=71)
    val = synthesize(model, validation().slice(0, 1500), theta, noise=0.02, seed=72)
    strategy = A.strategy_for(base)
    run = A._Diagnosis(strategy, strategy.settings, A._split([est], [val], strategy, strategy.settings), base,
                       A._catalogue(base), lambda line: None, seed=71)
    reference = A._fit_nominal(run)[0]
    seen = []
    real = A._screened_fit

    def recording(run_, problem, augmented, names, start, prediction, screening):
        fit = real(run_, problem, augmented, names, start, prediction, screening)
        seen.append((start.copy(), A._full_objective(problem, fit.estimate, fit.log_det_r)))
        return fit

    # the refit calls the screened fit of the module it lives in
    monkeypatch.setattr(candidates, "_screened_fit", recording)
    _, names, fit, objective = A._refit(run, reference, "torque_ripple", effect)
    assert len(seen) == 2
    amplitude = model.parameters.index("torque_ripple_amplitude")
    assert seen[0][0][amplitude] != seen[1][0][amplitude]
    assert objective == min(v for _, v in seen)


def test_a_fit_that_ends_below_a_model_it_contains_is_refitted_from_that_model(monkeypatch):
    """Method version 8: a screening fit from a start grid that misses (here made to: one point
    far off) ends below the form it reduces to, and is refitted from where the form computes
    that form's fit; the better fit is kept, so it is no worse than the model it contains. A fit
    above every model it contains is not refitted. Without
    ``nested_starts`` the fit from the grid stands."""
    from dataclasses import replace

    from ema_uq.gap import attribute as A
    from ema_uq.gap import candidates

    base = get_model("htls")
    model = base.with_effects(["sensor_delay"])
    theta = model.parameters.vector({"sensor_delay_tau": 0.02})
    est = synthesize(model, deploy_retract().slice(0, 1500), theta, noise=0.02, seed=81)
    val = synthesize(model, validation().slice(0, 1500), theta, noise=0.02, seed=82)
    strategy = A.strategy_for(base)
    settings = replace(strategy.settings, nested_starts=True)
    run = A._Diagnosis(strategy, settings, A._split([est], [val], strategy, settings), base,
                       A._catalogue(base, settings), lambda line: None, seed=81)
    reference = A._fit_nominal(run)[0]
    catalogue = base.effect_catalogue
    delay = A._refit(run, reference, "sensor_delay", catalogue["sensor_delay"])
    real_grid, real_fit, starts = candidates._start_grid, candidates._screened_fit, []

    def far_grid(augmented, base_values, effect, names, multiples):
        grid = real_grid(augmented, base_values, effect, names, multiples)
        far = grid[:1].copy()
        far[0, [augmented.parameters.index(n) for n in names]] = [0.4, 0.9]     # tau 0.4 s, mostly a lag
        return far

    def recording(run_, problem, augmented, names, start, prediction, screening):
        fit = real_fit(run_, problem, augmented, names, start, prediction, screening)
        starts.append((dict(zip(augmented.parameters.names, start)),
                       A._full_objective(problem, fit.estimate, fit.log_det_r)))
        return fit

    monkeypatch.setattr(candidates, "_start_grid", far_grid)
    monkeypatch.setattr(candidates, "_screened_fit", recording)
    dispersed = catalogue["sensor_delay_dispersed"]
    _, _, _, objective = A._refit(run, reference, "sensor_delay_dispersed", dispersed, nested={"sensor_delay": delay})
    assert len(starts) == 2 and starts[0][1] > delay[3]           # the grid's fit ended below sensor_delay's
    assert starts[1][0]["sensor_delay_dispersed_tau"] == pytest.approx(delay[2].value("sensor_delay_tau"), rel=1e-12)
    assert starts[1][0]["sensor_delay_dispersed_dispersion"] == 0.0
    assert objective == starts[1][1] <= delay[3] + 1e-9 * abs(delay[3])
    shortfall = 2 * (starts[0][1] - delay[3])

    for factor, refitted in ((1.05, False), (0.95, True)):     # version 9: a shortfall within the tolerance stands
        starts.clear()
        run.settings = replace(settings, nested_start_tolerance=factor * shortfall)
        A._refit(run, reference, "sensor_delay_dispersed", dispersed, nested={"sensor_delay": delay})
        assert len(starts) == (2 if refitted else 1)
    run.settings = settings

    starts.clear()      # the same fit does not end below the model it is added to: not refitted
    A._refit(run, reference, "sensor_delay_dispersed", dispersed, nested={})
    assert len(starts) == 1 and starts[0][1] < reference.objective

    starts.clear()
    run.settings = replace(settings, nested_starts=False)
    _, _, _, objective = A._refit(run, reference, "sensor_delay_dispersed", dispersed,
                                  nested={"sensor_delay": delay})
    assert len(starts) == 1 and objective > delay[3]


def test_a_form_is_fitted_after_the_forms_it_reduces_to_only_with_nested_starts():
    from ema_uq.gap.candidates import _fit_order

    catalogue = get_model("htls").effect_catalogue
    pool = {n: catalogue[n] for n in ("stribeck_directional", "backlash", "stribeck", "torque_ripple_harmonics",
                                      "torque_ripple")}
    assert _fit_order(pool, False) == list(pool)
    order = _fit_order(pool, True)
    assert sorted(order) == sorted(pool)
    assert order.index("stribeck") < order.index("stribeck_directional")
    assert order.index("torque_ripple") < order.index("torque_ripple_harmonics")


def test_method_version_8_is_version_4_with_nested_starts_only():
    from ema_uq.gap.strategy import DiagnosisSettings, method_switches, method_version_of

    assert method_switches(8) == {**method_switches(4), "nested_starts": True}
    assert all(method_switches(v)["nested_starts"] is False for v in range(1, 8))
    assert method_version_of(DiagnosisSettings(**method_switches(8))) == 8
    assert method_version_of(DiagnosisSettings()) == 4


def test_method_version_9_is_version_8_refitting_past_the_evidence_margin_only():
    from ema_uq.gap.strategy import DiagnosisSettings, method_switches, method_version_of
    from ema_uq.gap.verdict import MARGIN_EVIDENCE

    assert method_switches(9) == {**method_switches(8), "nested_start_tolerance": MARGIN_EVIDENCE}
    assert all(method_switches(v)["nested_start_tolerance"] == 0.0 for v in range(1, 9))
    assert method_version_of(DiagnosisSettings(**method_switches(9))) == 9
    for bad in (-1.0, float("nan"), float("inf"), True, "10"):
        with pytest.raises(ValueError, match="nested_start_tolerance must be a finite number"):
            DiagnosisSettings(nested_start_tolerance=bad)


# --------------------------------------------------------------------------------------
# end-to-end diagnoses (HT/LS, restricted candidates)
# --------------------------------------------------------------------------------------
CANDIDATES = ("load_dependent_friction", "sensor_delay")


def _effect_data(name, seed):
    base = get_model("htls")
    model = base.with_effects([name])
    theta = model.parameters.nominal
    return (synthesize(model, deploy_retract(), theta, noise=0.02, seed=seed),
            synthesize(model, validation(), theta, noise=0.02, seed=seed + 1))


@pytest.fixture(scope="module")
def effect_result():
    est, val = _effect_data("load_dependent_friction", 31)
    return diagnose([est], [val], candidates=CANDIDATES, seed=31)


@pytest.fixture(scope="module")
def none_result():
    est = synthesize("htls", deploy_retract(), noise=0.02, seed=41)
    return diagnose([est], candidates=CANDIDATES, seed=41)     # held out: last 30 %


def test_the_contract_step_covers_the_nominal_dynamics_and_effects_without_their_own():
    htls = get_model("htls")
    coarse = replace(htls, at_converged_step=True)
    assert htls.rk4_step == htls.integration_step == 5e-4 and coarse.rk4_step == htls.converged_step == 1e-3
    # friction laws, an output delay and kinematic ripple at screw-angle order add no faster dynamics
    for name in ("stribeck", "load_dependent_friction", "sensor_delay", "ujoint_kinematics"):
        assert coarse.with_effects([name]).rk4_step == 1e-3, name
    # a mode, a play's relaxation and a ripple at motor-angle order keep the fine step, also in compounds
    for names in (["shaft_compliance"], ["backlash"], ["torque_ripple"], ["stribeck", "backlash_output"]):
        assert coarse.with_effects(names).rk4_step == 5e-4, names
    # the model-form allowance's wrapper simulates its inner model at the same step
    wrapped = actuator_allowance(coarse).wrap(coarse).with_effects(["stribeck"])
    assert wrapped.rk4_step == wrapped.inner.rk4_step == 1e-3
    # a concept without a contract step keeps its own
    cranfield = replace(get_model("cranfield"), at_converged_step=True)
    assert cranfield.converged_step is None and cranfield.rk4_step == cranfield.integration_step
    with pytest.raises(ValueError, match="converged_step must be true or false"):
        DiagnosisSettings(converged_step="yes")


def test_effect_is_found_with_its_size(effect_result):
    r = effect_result
    assert r.verdict == "effect" and r.effect == "load_dependent_friction" and r.confidence == "high"
    assert [c.effect for c in r.ranking] == list(CANDIDATES)
    best = r.ranking[0]
    assert best.delta_bic > 1000 and best.held_out_gain > 1000 and best.shrink > 0.8
    mu = get_model("htls").effect_catalogue["load_dependent_friction"].parameters[0].nominal
    p = r.effect_parameters["load_dependent_friction_mu"]
    assert abs(p["estimate"] - mu) < 4 * p["std"]
    assert r.gap["before"] > 5 * r.gap["after"]
    assert {"M_TSER1", "M_TSER2"} <= set(r.where["channels"])
    assert r.localization.structured and not r.localization_after.structured
    assert not r.localization_after_held_out.structured
    # honest shrink: scored on the second half of the validation record, which did not select
    g = r.gap
    assert g["shrink_record"].startswith("second half of held-out record validation")
    assert g["shrink"] == pytest.approx(1 - g["shrink_gap_after"] / g["shrink_gap_before"])
    assert g["shrink"] > 0.8 and 0 < g["shrink_se"] < 0.2 and g["selection_shrink"] > 0.8
    assert best.shrink == pytest.approx(g["shrink"]) and best.selection_shrink == pytest.approx(g["selection_shrink"])
    assert "scored on the second half" in r.summary() and "not resolved" not in r.summary()


def test_a_shrink_within_two_standard_errors_of_zero_is_reported_as_not_resolved(effect_result):
    from ema_uq.gap.result import shrink_resolved
    from ema_uq.report.html_gap import _honest_shrink

    assert shrink_resolved(0.3, 0.1) and not shrink_resolved(0.3, 0.2) and not shrink_resolved(-0.46, 0.55)
    assert not shrink_resolved(float("nan"), 0.1) and not shrink_resolved(0.5, float("nan"))
    assert not shrink_resolved(None, None)
    # the verdict stands on the selection part; the report says the scoring record does not confirm it
    weak = replace(effect_result, gap={**effect_result.gap, "shrink": -0.46, "shrink_se": 0.55})
    assert weak.verdict == "effect" and "shrink not resolved" in weak.summary()
    assert "Not resolved" in _honest_shrink(weak.gap) and "Not resolved" not in _honest_shrink(effect_result.gap)


def test_clean_data_give_none(none_result):
    r = none_result
    assert r.verdict == "none" and r.effect is None
    assert not r.localization.structured
    assert all(c.delta_bic < 10 for c in r.ranking)
    assert r.held_out.startswith("last 30%")
    # no effect: no shrink shown; the candidates' own shrinks are signed, with their error
    assert r.gap["shrink"] is None and r.to_json()["gap"]["shrink"] is None and "shrink    " not in r.summary()
    assert all(np.isfinite(c.shrink) and c.shrink_se > 0 for c in r.ranking)


def test_selection_and_scoring_parts_of_the_held_out_data():
    from ema_uq.gap.attribute import _selection_and_scoring

    one = synthesize("htls", deploy_retract().slice(0, 400), noise=0.02, seed=1)
    parts, record = _selection_and_scoring([one], ["y1", "y2"])
    (first,), (second,) = parts["selection"], parts["scoring"]
    assert not np.any(first & second) and np.all(first | second)
    assert first.sum() == 200 and np.flatnonzero(first).max() < np.flatnonzero(second).min()
    assert record.startswith("second half of held-out record")
    two = [one, synthesize("htls", deploy_retract().slice(0, 300), noise=0.02, seed=2)]
    parts, record = _selection_and_scoring(two, ["y1"])
    assert parts["selection"][0].all() and not parts["selection"][1].any()
    assert parts["scoring"][1].all() and not parts["scoring"][0].any()
    assert record == f"held-out record {two[1].experiment.name}"


def test_out_of_catalogue_current_offset_is_unexplained():
    est, val, _val2, truth = make_records("htls", "current_sensor_error", {"gain": 0.03, "offset": 0.8}, seed=51)
    assert "effect" not in est.attrs and truth["expected"] == "unexplained"
    r = diagnose([est], [val], candidates=("sensor_delay",), seed=51)
    assert r.verdict == "unexplained"
    assert r.where["channels"][0] == "I_A"


def test_gap_json_contract_and_round_trip(effect_result, tmp_path):
    data = effect_result.to_json()
    assert {"verdict", "effect", "ranking", "where"} <= set(data)
    assert data["verdict"] in ("effect", "none", "unexplained")
    for row in data["ranking"]:
        assert {"effect", "score", "gap_before", "gap_after", "shrink"} <= set(row)
        assert row["shrink"] == pytest.approx(1 - row["gap_after"] / row["gap_before"])
    # channels and regimes as always; "stroke" was added beside them (where along the stroke the gap lies)
    assert set(data["where"]) == {"channels", "regimes", "stroke"} and isinstance(data["where"]["stroke"], list)
    assert {"shrink", "shrink_se", "shrink_record"} <= set(data["gap"])
    # the step the default method runs the nominal model at: the contract's converged one or the model's own
    htls = get_model("htls")
    step = htls.converged_step if DiagnosisSettings().converged_step else htls.integration_step
    assert data["nominal"]["integration_step_s"] == step
    path = tmp_path / "gap.json"
    io.write_json(path, data)
    back = GapResult.from_json(json.loads(path.read_text()))
    assert back.verdict == effect_result.verdict and back.effect == effect_result.effect
    assert back.ranking[0].shrink == pytest.approx(effect_result.ranking[0].shrink)
    assert back.localization.where_regimes == effect_result.localization.where_regimes
    assert "load_dependent_friction" in back.summary()


def test_gap_ledger_figure(effect_result):
    from ema_uq.report.gap_figures import gap_ledger

    fig = gap_ledger(effect_result)
    titles = [ax.get_title(loc="left") for ax in fig.axes]
    assert any(t.startswith("estimation") for t in titles) and any(t.startswith("held-out") for t in titles)
    assert "by regime (* holds the gap)" in titles
    assert "load_dependent_friction" in fig._suptitle.get_text()


# --------------------------------------------------------------------------------------
# self-check cases and scoring
# --------------------------------------------------------------------------------------
def test_self_check_cases_cover_every_variant_on_both_concepts_and_sensor_sets():
    cases = selfcheck.build_cases(seed=2024)
    assert len({c.seed for c in cases}) == len(cases)
    assert not {c.seed for c in cases} & set(selfcheck.CALIBRATION_SEEDS)      # never the calibration seeds
    for concept in ("htls", "lths"):
        for sensors in ("full", "realistic"):
            mine = [c for c in cases if c.concept == concept and c.sensors == sensors]
            assert {c.variant for c in mine if c.variant} == set(VARIANTS)
            assert sum(c.kind == "none" for c in mine) == selfcheck.NONE_PER_SET
    assert sum(c.kind == "none" for c in cases) >= 20
    for c in cases:
        assert c.expected == {"effect": c.family, "none": "none", "out_of_catalogue": "unexplained",
                              "left_out": "unexplained"}[c.kind]
        assert (c.family is None) == (c.kind not in ("effect", "left_out"))
    # a case's seed depends on (seed, concept, sensor set, slot) only: the quick cases are full cases
    quick = selfcheck.build_cases(["htls"], seed=2024, quick=True)
    assert 3 <= len(quick) <= 4 and set(quick) <= set(cases)
    inside = sum(v.family is not None for v in VARIANTS.values())
    assert len(selfcheck.build_cases(["lths"], sensors=["realistic"], none_per_set=0)) == len(VARIANTS) + inside
    # one kind alone: the same cases (seeds) as in the full list, e.g. more none cases for the false-alarm rate
    nones = selfcheck.build_cases(seed=2024, kinds=["none"], none_per_set=8)
    assert len(nones) == 4 * 8 and {c.kind for c in nones} == {"none"}
    assert {c for c in cases if c.kind == "none"} < set(nones)
    # numbered on from an earlier run's count: the next none cases, none repeated
    more = selfcheck.build_cases(seed=2024, kinds=["none"], none_per_set=3, none_first=8)
    assert len(more) == 4 * 3 and not set(more) & set(nones)
    assert set(more) < set(selfcheck.build_cases(seed=2024, kinds=["none"], none_per_set=11))
    with pytest.raises(selfcheck.SelfCheckError, match="none_first"):
        selfcheck.build_cases(none_first=-1)
    with pytest.raises(selfcheck.SelfCheckError, match="case kind 'nothing'"):
        selfcheck.build_cases(kinds=["nothing"])
    with pytest.raises(selfcheck.SelfCheckError, match="sensor set"):
        selfcheck.build_cases(sensors=["all"])
    with pytest.raises(selfcheck.SelfCheckError, match="concept"):
        selfcheck.build_cases(["emps"])


def test_self_check_case_records_are_seeded_draws_of_the_variant():
    case = selfcheck.build_cases(["htls"], quick=True)[0]
    a, b = selfcheck.case_records(case), selfcheck.case_records(case)
    np.testing.assert_array_equal(a[0].values, b[0].values)
    assert a[3]["parameters"] == b[3]["parameters"] and a[3]["variant"] == case.variant
    assert a[0].channels == ("Omega", "y1", "y2", "I_A")          # the realistic sensor set
    base = get_model("htls").parameters
    spread = [abs(a[3]["base_parameters"][p.name] / p.nominal - 1) for p in base if p.nominal]
    assert max(spread) <= 0.10 + 1e-12 and max(spread) > 0.01     # base parameters off nominal


def _outcome(kind, family, verdict, found, shrink=float("nan"), confidence="high", sensors="full", stressed=False):
    variant = {"effect": f"{family}_variant", "left_out": f"{family}_variant", "none": None,
               "out_of_catalogue": "gremlin"}[kind]
    case = selfcheck.Case(f"htls/{sensors}/{variant}", "htls", sensors, kind, variant,
                          family if kind in ("effect", "left_out") else None, 11, stressed)
    return selfcheck.CaseOutcome(case, verdict, found and f"{found}_form", found if verdict == "effect" else None,
                                 confidence, shrink, 0.05, "held-out record validation-scaled", 0.02,
                                 0.02 * (1 - shrink) if np.isfinite(shrink) else 0.02, {}, 1.0)


def test_self_check_scores_synthetic_outcomes():
    result = selfcheck.SelfCheckResult([
        _outcome("effect", "backlash", "effect", "backlash", 0.9),
        _outcome("effect", "stribeck", "effect", "stribeck", 0.7),
        _outcome("effect", "stribeck", "effect", "stribeck", -0.2, sensors="realistic"),   # right, shrink < 0
        _outcome("effect", "sensor_delay", "effect", "backlash", 0.95),      # wrong family
        _outcome("effect", "torque_ripple", "unexplained", None),             # missed
        *[_outcome("none", None, "none", None) for _ in range(19)],
        _outcome("none", None, "effect", "stribeck", 0.1),                    # false alarm
        _outcome("out_of_catalogue", None, "unexplained", None),
        _outcome("out_of_catalogue", None, "unexplained", None),
        _outcome("out_of_catalogue", None, "unexplained", None),
        _outcome("out_of_catalogue", None, "effect", "stribeck", 0.3, "low"),  # low confidence: still a miss
        _outcome("out_of_catalogue", None, "ambiguous", None),               # a flag too
        _outcome("out_of_catalogue", None, "none", None),
    ], seed=5, quick=False, wall_time_s=7.0)
    # pytest >= 9 refuses approx() of a nested dict, so the scalar fields are compared apart
    assert {k: result.top1[k] for k in ("value", "count", "n")} == pytest.approx({"value": 0.6, "count": 3, "n": 5})
    lo, hi = result.top1["interval95"]
    assert set(result.top1) == {"value", "count", "n", "interval95"} and lo < 0.6 < hi
    assert result.false_alarm_rate == pytest.approx(0.05) and result.out_of_catalogue_rate == pytest.approx(4 / 6)
    # 1 alarm in 20 shows neither <= 0.05 nor > 0.05 at 95 %; nothing is met on so few cases
    assert result.status["false_alarm_rate"] == "n too small" and not any(result.met.values())
    # 0 alarms: met at 95 % from 60 none cases, at least 40 % of them stressed
    for n, stressed, shown in ((58, 29, False), (60, 10, False), (60, 30, True)):
        clean = selfcheck.SelfCheckResult([_outcome("none", None, "none", None, stressed=i < stressed)
                                           for i in range(n)], 5, False, 1.0)
        assert clean.met["false_alarm_rate"] is shown and clean.status["top1_accuracy"] == "n too small"
        assert ("false-alarm rate" in clean.summary() and
                ("target <= 0.05: met" in clean.summary()) is shown)
    s = result.shrink                                      # signed, unclipped, right family only
    assert s["n"] == 3 and s["median"] == pytest.approx(0.7) and s["min"] == pytest.approx(-0.2)
    assert s["not_resolved"] == 1 and "1 less than 2 se above zero" in result.summary()   # the -0.2 +- 0.05
    low, high = result.false_alarms["interval95"]
    assert 0.001 < low < 0.002 and 0.24 < high < 0.25       # Clopper-Pearson of 1/20
    assert selfcheck.clopper_pearson(0, 20)[1] == pytest.approx(1 - 0.025 ** (1 / 20))
    matrix = result.confusion()
    assert matrix["sensor_delay"] == {"backlash": 1} and matrix["none"] == {"none": 19, "stribeck": 1}
    assert matrix["outside catalogue"] == {"unexplained": 3, "stribeck": 1, "none": 1, "ambiguous": 1}
    assert result.by_set()["htls/realistic"]["top1_accuracy"] == 1.0
    text = result.summary()
    assert "n too small" in text and "false-alarm rate" in text and "sensor_delay_variant" in text
    assert result.wrong_family_confident["count"] == 1      # sensor_delay named backlash, high confidence
    back = selfcheck.SelfCheckResult.from_json(json.loads(json.dumps(result.to_json())))
    assert back.to_json() == result.to_json()


def test_a_case_whose_diagnosis_raises_is_an_error_outcome_and_the_others_are_kept(monkeypatch):
    cases = [selfcheck._case(3, "htls", "realistic", "load_friction_linear"),
             selfcheck._case(3, "htls", "realistic", None, 0)]

    def failing(measurements, validation, **kwargs):
        if kwargs["seed"] == cases[0].seed:
            raise np.linalg.LinAlgError("Singular matrix")
        raise RuntimeError("second")

    monkeypatch.setattr(selfcheck, "diagnose", failing)
    lines = []
    result = selfcheck.self_check(cases=cases, jobs=1, progress=lines.append)
    assert [o.verdict for o in result.outcomes] == ["error", "error"]
    assert result.outcomes[0].message == "LinAlgError: Singular matrix" and not result.outcomes[0].correct
    assert result.top1["count"] == 0 and result.false_alarms["count"] == 1
    assert "WRONG" in lines[0] and lines[0].endswith("LinAlgError: Singular matrix")
    back = selfcheck.SelfCheckResult.from_json(json.loads(json.dumps(result.to_json())))
    assert back.outcomes[1].message == "RuntimeError: second"


def test_self_check_report_section_and_confusion_figure(tmp_path):
    from ema_uq.report.gap_figures import selfcheck_confusion
    from ema_uq.report.html import _selfcheck_section

    result = selfcheck.SelfCheckResult([_outcome("effect", "backlash", "effect", "backlash", 0.9),
                                        _outcome("none", None, "effect", "stribeck", 0.1),
                                        _outcome("out_of_catalogue", None, "unexplained", None)], 5, True, 3.0)
    data = result.to_json()
    fig = selfcheck_confusion(data)
    assert fig.axes[0].get_ylabel() == "truth family"
    io.write_json(tmp_path / "selfcheck.json", data)
    text = _selfcheck_section(tmp_path)
    assert "data:image/png;base64" in text and "n too small" in text and "backlash_variant" in text
    from ema_uq.report.html import _judged

    # a self-check file without its own judgement is judged on the two-sided interval
    assert "NOT met" in _judged(0.5, 0.8, 0.9, "≥") and ">met<" in _judged(0.91, 1.0, 0.9, "≥")
    assert ">met<" in _judged(0.0, 0.049, 0.05, "≤") and "NOT met" in _judged(0.06, 0.2, 0.05, "≤")


def test_the_report_shows_the_default_methods_evaluation_block_beside_the_run(tmp_path, capsys):
    """The out-of-sample figures (the frozen protocol's evaluation block) sit beside the study's own
    self-check, whose seed the method may have been built on; a wrong file is a one-line error."""
    from ema_uq.cli import main as cli_main
    from ema_uq.report.html import _selfcheck_section

    run = selfcheck.SelfCheckResult([_outcome("effect", "backlash", "effect", "backlash", 0.9)], 5, True, 3.0)
    io.write_json(tmp_path / "selfcheck.json", run.to_json())
    block = selfcheck.SelfCheckResult([_outcome("effect", "backlash", "effect", "backlash", 0.9),
                                       _outcome("effect", "stribeck", "unexplained", None)], 5205, False, 9.0)
    evaluation = {**block.to_json(), "settings": {"seeds": [5205], "sources_sha256": "8e978d655b46c18d"}}
    assert "Out of sample" not in _selfcheck_section(tmp_path)
    text = _selfcheck_section(tmp_path, evaluation)
    assert "Out of sample" in text and "seeds 5205, 2 cases" in text and "8e978d655b46" in text
    assert "0.5 (1/2)" in text                           # the block's top-1, not the run's 1/1
    bad = tmp_path / "bad.json"
    io.write_json(bad, {"verdict": "none"})
    study = Path(__file__).resolve().parents[2] / "studies" / "smoke.yaml"
    for given, message in ((tmp_path / "missing.json", "no such file"), (bad, "not a self-check result")):
        code = cli_main(["report", "--study", str(study), "--results", str(tmp_path), "--out", str(tmp_path / "r.html"),
                         "--selfcheck-evaluation", str(given)])
        err = capsys.readouterr().err
        assert code == 2 and message in err and err.count("\n") == 1, err
    assert not (tmp_path / "r.html").exists()


def test_one_real_self_check_case_is_diagnosed_blind():
    case = selfcheck.build_cases(["htls"], quick=True)[1]          # a no-effect case, rig sensors
    assert case.kind == "none"
    outcome = selfcheck.run_case(case)
    assert outcome.verdict == "none" and outcome.correct
    assert not np.isfinite(outcome.shrink)                      # shown only for an effect verdict


# --------------------------------------------------------------------------------------
# bad input
# --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("gap")
    short = deploy_retract().slice(0, 400)
    io.write_measurement(d / "htls.nc", synthesize("htls", short, noise=0.02, seed=1))
    io.write_measurement(d / "lths.nc", synthesize("lths", short, noise=0.02, seed=1))
    io.write_measurement(d / "htls_y.nc", synthesize("htls", short, noise=0.02, seed=2, channels=("y1", "y2")))
    io.write_measurement(d / "htls_i.nc", synthesize("htls", short, noise=0.02, seed=3, channels=("I_A",)))
    return d


def _one_line_error(capsys, argv, *fragments):
    assert main(argv) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("ema-uq: error: "), captured.err
    for fragment in fragments:
        assert fragment in lines[0], lines[0]


def test_cli_validation_data_of_another_concept(files, capsys):
    _one_line_error(capsys, ["gap", str(files / "htls.nc"), "--concept", "htls", "--validate",
                             str(files / "lths.nc"), "--out", str(files / "gap.json")], "lths.nc", "lths")
    assert not (files / "gap.json").exists()


def test_cli_validation_data_without_a_common_channel(files, capsys):
    _one_line_error(capsys, ["gap", str(files / "htls_y.nc"), "--concept", "htls", "--validate",
                             str(files / "htls_i.nc"), "--out", str(files / "gap.json")],
                    "no channel in common", "y1")


def test_cli_gap_writes_gap_json_and_the_ledger(tmp_path, capsys):
    model = get_model("htls").with_effects(["load_dependent_friction"])
    short = deploy_retract().slice(0, 1500)             # deploy to 20 deg and hold
    io.write_measurement(tmp_path / "rig.nc", synthesize(model, short, model.parameters.nominal, noise=0.02, seed=8))
    out, fig = tmp_path / "gap.json", tmp_path / "ledger.png"
    assert main(["gap", str(tmp_path / "rig.nc"), "--concept", "htls", "--candidates", "load_dependent_friction",
                 "--quiet", "--figure", str(fig), "--out", str(out)]) == 0
    line = capsys.readouterr().out.strip()
    assert line.startswith(f"wrote {out}") and "load_dependent_friction" in line
    data = json.loads(out.read_text())
    assert data["verdict"] == "effect" and data["effect"] == "load_dependent_friction"
    assert data["held_out"].startswith("last 30%") and data["provenance"]["inputs"]
    assert fig.stat().st_size > 10_000


def test_library_refuses_mixed_concepts_and_unknown_candidates(files):
    htls, lths = (io.read_measurement(files / f"{c}.nc") for c in ("htls", "lths"))
    with pytest.raises(GapError, match="validation data are of concept lths"):
        diagnose([htls], [lths])
    with pytest.raises(GapError, match="unknown candidate effect"):
        diagnose([htls], candidates=("gremlins",))
    with pytest.raises(GapError, match="too few"):
        split_holdout([htls.select(["y1"])], 0.9)


# --------------------------------------------------------------------------------------
# the full blind self-check (long)
# --------------------------------------------------------------------------------------
@pytest.mark.slow
def test_full_blind_self_check_meets_the_targets():
    result = selfcheck.self_check(seed=selfcheck.DEFAULT_SEED, jobs=2)
    assert all(result.met.values()), result.summary()


def test_candidate_refit_holds_a_base_parameter_the_rig_sensors_cannot_separate():
    """The LT/HS rig sensors cannot determine every base parameter (in the diagnosis of a
    Stribeck record C_TS2 alone); a candidate refit that freed such a parameter used to fail at
    its start, the candidate was lost and the record came out 'unexplained'. The refit now holds
    what the sensors cannot separate at its start value and names it."""
    from ema_uq.gap import variants
    from ema_uq.gap.attribute import _robust_estimate
    from ema_uq.identify import FitProblem, Settings, SingularInformationError, estimate
    from ema_uq.models import get_model

    estimation, *_ = variants.make_records("lths", "stribeck_gaussian", {"ratio": 0.5, "speed": 1.4},
                                           seed=4242, channels="realistic")
    model = get_model("lths").with_effects(["stribeck"])
    problem = FitProblem([estimation], model=model)  # every base parameter free with the effect's
    settings = Settings(max_iterations=3)
    with pytest.raises(SingularInformationError):
        estimate(problem, method="lm", settings=settings)
    fit = _robust_estimate(problem, model.parameters.nominal.copy(), settings)
    assert fit.fixed and not set(fit.fixed) & set(fit.free_names)
    assert {"stribeck_ratio", "stribeck_speed"} <= set(fit.free_names)
