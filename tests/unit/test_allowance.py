"""The model-form allowance of the gap diagnosis (method version 2): the kinematic constants it
frees, the command lag's discretisation, bit-identity of a zero allowance, recovery of a known
kinematic offset and command lag, method version 1 reproduced with the allowance off, and bad
settings."""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from ema_uq import deploy_retract, get_model, simulate_batch, synthesize
from ema_uq.errors import EmaUqError
from ema_uq.experiments import Measurement, add_noise
from ema_uq.gap import DiagnosisSettings, diagnose
from ema_uq.gap.allowance import (LAG_NAME, AllowanceError, AllowedModel, ModelFormAllowance, actuator_allowance,
                                  command_lag, kinematic_constants, position_loop_time_constant)
from ema_uq.gap.strategy import DEFAULT_STRATEGY, method_switches
from ema_uq.gap.variants import simulate_variant
from ema_uq.identify import FitProblem, Settings, estimate


def test_the_kinematic_constants_are_the_drive_trains_geometry():
    assert kinematic_constants(get_model("htls")) == ("i_TP1", "i_TP2", "r", "gamma", "beta1", "beta2")
    assert kinematic_constants(get_model("lths")) == ("i_MG", "i_BG1", "i_BG2", "i_TP2", "r", "gamma", "beta1",
                                                      "beta2")
    # the lag bound: a tenth of the position loop's time constant (about 0.9 s on HT/LS)
    loop = position_loop_time_constant(get_model("htls"))
    assert 0.5 < loop < 2.0
    a = actuator_allowance(get_model("htls"))
    assert a.lag_max == pytest.approx(0.1 * loop) and a.tolerance == 0.05
    assert a.names[-1] == LAG_NAME and all(p.prior_std == 0.025 for p in a.parameters[:-1])


def test_command_lag_is_exact_for_a_ramp_and_smooth_down_to_zero():
    dt, tau = 0.01, 0.03
    t = np.arange(0.0, 1.0, dt)
    y = command_lag(t, tau, dt)
    np.testing.assert_allclose(y, t - tau * (1.0 - np.exp(-t / tau)), atol=1e-12)
    assert np.array_equal(command_lag(t, 0.0, dt), t)
    # far below a sample: a delay of tau (linear interpolation), not a step to no lag at all
    ramp = command_lag(t, 1e-4, dt)
    np.testing.assert_allclose(ramp[5:], t[5:] - 1e-4, atol=1e-12)


def test_a_zero_allowance_is_bit_identical_to_the_model_itself():
    ex = deploy_retract()
    for concept in ("htls", "lths"):
        base = get_model(concept)
        allowance = actuator_allowance(base)
        for model in (base, base.with_effects(["backlash"])):
            wrapped = allowance.wrap(model)
            assert isinstance(wrapped, AllowedModel) and wrapped.parameters.names[:len(model.parameters)] == \
                model.parameters.names
            theta = model.parameters.nominal
            thetas = np.stack([theta, np.clip(theta * 1.02, model.parameters.lower, model.parameters.upper)])
            plain = simulate_batch(model, thetas, ex.time, ex.input_matrix(model))
            zeros = np.zeros((2, len(allowance.names)))
            assert np.array_equal(simulate_batch(wrapped, np.hstack([thetas, zeros]), ex.time,
                                                 ex.input_matrix(model)), plain)
        # composing effects on a wrapped model keeps the allowance last
        wrapped = allowance.wrap(base).with_effects(["backlash"]).with_effects(["stribeck"])
        assert wrapped.parameters.names[-len(allowance.names):] == allowance.names
        assert set(wrapped.inner.effects) == {"backlash", "stribeck"}


def _fit_allowance(data, wrapped, free):
    problem = FitProblem([data], model=wrapped, parameters=wrapped.parameters.freeing_only(free),
                         channels=("Omega", "y1", "y2", "I_A"))
    return estimate(problem, method="gn", start=wrapped.parameters.nominal,
                    settings=Settings(max_iterations=20, tolerance=1e-8))


def test_the_allowance_recovers_a_kinematic_offset_of_the_independent_simulator():
    base = get_model("htls")
    ex = deploy_retract()
    offsets = {"i_TP1": 0.03, "i_TP2": -0.02}
    clean = simulate_variant("htls", ex, constant_offsets=offsets)
    values = add_noise(clean, 0.005, np.random.default_rng(3))
    data = Measurement("htls", ex, base.outputs, values, {})
    wrapped = actuator_allowance(base).wrap(base)
    fit = _fit_allowance(data, wrapped, ["mf_i_TP1", "mf_i_TP2", LAG_NAME])
    assert fit.value("mf_i_TP1") == pytest.approx(0.03, abs=0.002)
    assert fit.value("mf_i_TP2") == pytest.approx(-0.02, abs=0.002)
    assert fit.value(LAG_NAME) < 0.005


def test_the_allowance_recovers_a_command_lag():
    base = get_model("htls")
    wrapped = actuator_allowance(base).wrap(base)
    truth = wrapped.parameters.vector({LAG_NAME: 0.04})
    ex = deploy_retract()
    clean = simulate_batch(wrapped, truth, ex.time, ex.input_matrix(base))
    data = Measurement("htls", ex, base.outputs, add_noise(clean, 0.005, np.random.default_rng(4)), {})
    fit = _fit_allowance(data, wrapped, [LAG_NAME, "mf_i_TP1"])
    assert fit.value(LAG_NAME) == pytest.approx(0.04, abs=0.002)
    assert abs(fit.value("mf_i_TP1")) < 0.003


def test_bad_allowance_settings_are_one_line_errors():
    for make in (lambda: DiagnosisSettings(model_form_allowance="yes"),
                 lambda: ModelFormAllowance(("i_TP1",), tolerance=1.5),
                 lambda: ModelFormAllowance(("i_TP1",), lag_max=-0.01),
                 lambda: ModelFormAllowance((), lag_max=0.0),
                 lambda: ModelFormAllowance(("i_MG",)).wrap(get_model("htls"))):
        with pytest.raises(EmaUqError) as info:
            make()
        assert isinstance(info.value, AllowanceError) and "\n" not in str(info.value)


def test_the_allowance_is_off_for_fault_diagnosis_and_when_switched_off():
    base = get_model("htls")
    on, off = DiagnosisSettings(), DiagnosisSettings(model_form_allowance=False)
    assert on.model_form_allowance and DEFAULT_STRATEGY.allowance_for(base, on) is not None
    assert DEFAULT_STRATEGY.allowance_for(base, off) is None
    assert DEFAULT_STRATEGY.with_reference({}).allowance_for(base, on) is None


# method version 1 (frozen protocol): figures of this diagnosis before the allowance existed
V1_NONE = {"log_det_R": -57.633276480450995, "before": 0.0, "after": 0.0,
           "load_dependent_friction": -6.607029931321894, "sensor_delay": -7.8150975017565445}


def test_allowance_off_reproduces_method_version_1():
    est = synthesize("htls", deploy_retract(), noise=0.02, seed=41)
    r = diagnose([est], candidates=("load_dependent_friction", "sensor_delay"), seed=41,
                 settings=replace(DEFAULT_STRATEGY.settings, **method_switches(1)))
    assert "model_form_allowance" not in r.to_json()
    got = {"log_det_R": r.nominal["log_det_R"], "before": r.gap["before"], "after": r.gap["after"],
           **{c.effect: c.delta_bic for c in r.ranking}}
    assert r.verdict == "none"
    assert got == pytest.approx(V1_NONE, rel=1e-9)


def test_a_version_1_protocol_runs_without_the_allowance(tmp_path):
    import importlib.util
    from pathlib import Path

    root = Path(__file__).resolve().parents[2]
    spec = importlib.util.spec_from_file_location("gap_bench", root / "benchmarks" / "gap.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    committed = bench.load_protocol(root / "benchmarks" / "gap_protocol.yaml")
    assert bench.protocol_settings(committed).model_form_allowance is committed["settings"]["model_form_allowance"]
    # a protocol frozen before the allowance existed has no such setting: it runs as it was frozen
    v1 = {**committed, "settings": {k: v for k, v in committed["settings"].items() if k != "model_form_allowance"}}
    assert bench.protocol_settings(v1) == DiagnosisSettings(**method_switches(1))
    # a protocol frozen now records the setting, and runs with it
    frozen = bench.freeze(tmp_path / "protocol.yaml", development=[11], evaluation=[5201])
    assert frozen["settings"]["model_form_allowance"] is True
    assert frozen["settings"]["converged_step"] is DiagnosisSettings().converged_step
    assert bench.protocol_settings(frozen) == DiagnosisSettings()


def test_an_unrecorded_command_filter_is_no_sensor_delay_with_the_allowance():
    from ema_uq.gap.variants import make_records

    est, val, val2, _ = make_records("htls", None, None, seed=7, channels="realistic", base_perturbation=0.10,
                                     stress={"input_filter": 0.035})
    runs = {on: diagnose([est], [val, val2], candidates=("sensor_delay", "load_dependent_friction"), seed=7,
                         settings=replace(DEFAULT_STRATEGY.settings,
                                          **{**method_switches(4), "model_form_allowance": on}))
            for on in (False, True)}
    assert runs[False].verdict == "effect" and runs[False].effect == "sensor_delay"      # version 1's false alarm
    assert runs[True].verdict in ("none", "unexplained") and runs[True].effect is None
    lag = runs[True].model_form_allowance["fitted_nominal"][LAG_NAME]["estimate"]
    assert 0.02 < lag < 0.04       # the filter's 35 ms, less about half a sample (it acts one sample late)
    assert runs[True].gap["before"] < 0.5 * runs[False].gap["before"]
