"""The unmodelled-effect catalogue (ema_uq/models/effects.py) switched into HT/LS and LT/HS.

Checks: the API (catalogue, with_effects, parse_effect, one-line errors); every effect at its
``off`` values reproduces the nominal outputs bit for bit; the nominal models still match a
plain RK4 loop written here (the dispatch to the augmented kernels left them untouched);
each effect at nominal and half magnitude changes the rig channels clearly and in its own
regime, against analytic expectations (lost motion of the play, eq. 8, Stribeck and
load-dependent friction formulas, delay by interpolation, ripple frequencies, the two-inertia
mode of an independent linear model); batched == single; ``ema-uq simulate --effect``.
"""
from __future__ import annotations

import json
from dataclasses import replace
import math
import subprocess
import sys

import numpy as np
import pytest
from numba import njit

from ema_uq import ParameterError, deploy_retract, get_model, io, simulate_batch, synthesize
from ema_uq.models import htls, lths
from ema_uq.models.effect_kernels import effect_flags
from ema_uq.models.effects import (CATALOGUE, EXCLUSIVE, Effect, EffectError, SIGNATURES, delay_outputs,
                                   first_order_lag, parse_effect)
from ema_uq.params import Parameter

DEG = math.pi / 180.0
LEAD = 0.016 * math.tan(4 * DEG)  # m of carriage per screw radian
SPEC_EFFECTS = ("backlash", "stribeck", "shaft_compliance", "ujoint_kinematics", "load_dependent_friction",
                "sensor_delay", "torque_ripple")
#: the parameter that sets each effect's magnitude (halved for the "half" case)
MAGNITUDE = {"backlash": "backlash_delta", "stribeck": "stribeck_ratio", "shaft_compliance": "shaft_compliance_period",
             "ujoint_kinematics": "ujoint_kinematics_scale", "load_dependent_friction": "load_dependent_friction_mu",
             "sensor_delay": "sensor_delay_tau", "torque_ripple": "torque_ripple_amplitude",
             "backlash_compliant": "backlash_compliant_period", "backlash_output": "backlash_output_delta",
             "torque_ripple_harmonics": "torque_ripple_harmonics_amplitude",
             "ujoint_stations": "ujoint_stations_scale1", "stribeck_directional": "stribeck_directional_ratio",
             "load_friction_directional": "load_friction_directional_mu",
             "sensor_delay_dispersed": "sensor_delay_dispersed_tau",
             "torque_ripple_loaded": "torque_ripple_loaded_amplitude", "ujoint_stroke": "ujoint_stroke_scale",
             "shaft_compliance_loaded": "shaft_compliance_loaded_period"}
#: further forms of the spec effects' families (the catalogue after the seven), form -> family
FAMILY_FORMS = {"backlash_compliant": "backlash", "backlash_output": "backlash",
                "torque_ripple_harmonics": "torque_ripple", "ujoint_stations": "ujoint_kinematics",
                "stribeck_directional": "stribeck", "load_friction_directional": "load_dependent_friction",
                "sensor_delay_dispersed": "sensor_delay", "torque_ripple_loaded": "torque_ripple",
                "ujoint_stroke": "ujoint_kinematics", "shaft_compliance_loaded": "shaft_compliance"}
#: the spanning forms, each with its family's first form, the values at which they coincide, and a shape
#: only the spanning form has
NESTED = (("stribeck", {"stribeck_ratio": 0.8, "stribeck_speed": 1.5}, "stribeck_directional",
           {"stribeck_directional_ratio": 0.8, "stribeck_directional_asymmetry": 0.0,
            "stribeck_directional_speed": 1.5},
           {"stribeck_directional_asymmetry": 0.6}),
          ("load_dependent_friction", {"load_dependent_friction_mu": 0.01}, "load_friction_directional",
           {"load_friction_directional_mu": 0.01, "load_friction_directional_asymmetry": 0.0},
           {"load_friction_directional_asymmetry": -0.6}),
          ("sensor_delay", {"sensor_delay_tau": 0.0123}, "sensor_delay_dispersed",
           {"sensor_delay_dispersed_tau": 0.0123, "sensor_delay_dispersed_dispersion": 0.0},
           {"sensor_delay_dispersed_dispersion": 0.6}),
          ("torque_ripple", {"torque_ripple_amplitude": 0.4, "torque_ripple_phase": 0.7}, "torque_ripple_loaded",
           {"torque_ripple_loaded_amplitude": 0.4, "torque_ripple_loaded_phase": 0.7, "torque_ripple_loaded_share": 0.0},
           {"torque_ripple_loaded_share": 0.05}),
          ("ujoint_kinematics", {"ujoint_kinematics_scale": 6.0, "ujoint_kinematics_phase": 0.4}, "ujoint_stroke",
           {"ujoint_stroke_scale": 6.0, "ujoint_stroke_phase": 0.4, "ujoint_stroke_slope": 0.0},
           {"ujoint_stroke_slope": 0.8}),
          ("shaft_compliance", {"shaft_compliance_period": 0.02, "shaft_compliance_zeta": 0.1},
           "shaft_compliance_loaded",
           {"shaft_compliance_loaded_period": 0.02, "shaft_compliance_loaded_zeta": 0.1,
            "shaft_compliance_loaded_hardening": 0.0},
           {"shaft_compliance_loaded_hardening": 2.0}))
NOISE = 0.02  # fraction of channel RMS, docs/MODEL_SPEC.md, "hypothetical data"


@pytest.fixture(scope="module")
def experiment():
    return deploy_retract()


@pytest.fixture(scope="module")
def nominal_runs(experiment):
    """Nominal outputs of both concepts on deploy-retract."""
    out = {}
    for concept in ("htls", "lths"):
        m = get_model(concept)
        out[concept] = simulate_batch(m, m.parameters.nominal, experiment.time, experiment.input_matrix(m))
    return out


@njit(cache=True)
def _rhs(concept_id, flags, x, u, th, c, dx, y):
    """A concept's right-hand side with the effects of bit set ``flags`` (a runtime value here)."""
    if concept_id == 0:
        htls.evaluate(x, u, th, c, dx, y, True, flags)
    else:
        lths.evaluate(x, u, th, c, dx, y, True, flags)


def evaluate_effects(model, x, u, th, c, dx, y):
    """``dx`` and ``y`` of the augmented ``model`` at state ``x``, input ``u``."""
    _rhs(model.base_model.model_id, effect_flags(model.effects), x, u, th, c, dx, y)


def runs(model, thetas, experiment):
    return simulate_batch(model, np.atleast_2d(thetas), experiment.time, experiment.input_matrix(model))


def column(concept, channel):
    return get_model(concept).outputs.index(channel)


# --- API ------------------------------------------------------------------------------------
def test_catalogue_is_the_model_spec_table():
    """The seven docs/MODEL_SPEC.md effects first, each its own family, then further forms of those
    families (allowed beside the spec table: the diagnosis names the family)."""
    assert tuple(CATALOGUE) == SPEC_EFFECTS + tuple(FAMILY_FORMS)
    for name, effect in CATALOGUE.items():
        assert effect.family == FAMILY_FORMS.get(name, name) and effect.family in SPEC_EFFECTS
        assert isinstance(effect, Effect) and effect.name == name and effect.description
        assert 1 <= len(effect.parameters) <= (3 if name in SPEC_EFFECTS else 6)
        assert all(p.name.startswith(name + "_") and p.free for p in effect.parameters)
        assert set(effect.start) == set(effect.off) == set(effect.parameter_names)
        for p in effect.parameters:
            assert p.lower <= effect.off[p.name] <= p.upper and p.lower <= effect.start[p.name] <= p.upper
        # the start sits near off but not on it
        magnitude = MAGNITUDE[name]
        assert effect.magnitude == magnitude
        assert effect.off[magnitude] == 0.0 < effect.start[magnitude] < effect.nominal[magnitude]
        assert effect.signature and set(effect.signature) <= set(SIGNATURES)
    for concept in ("htls", "lths"):
        assert get_model(concept).available_effects == tuple(CATALOGUE)


@pytest.mark.parametrize("concept, extra_states", [
    ("htls", {"backlash": 2, "shaft_compliance": 2}), ("lths", {"backlash": 1, "shaft_compliance": 2})])
def test_with_effects_layout(concept, extra_states):
    base = get_model(concept)
    assert base.with_effects([]) is base and base.base_model is base and base.effects == ()
    names = ["torque_ripple", "backlash", "shaft_compliance"]
    aug = base.with_effects(names, {"backlash_delta": 0.03})
    assert aug.effects == tuple(names) and aug.base_model is base and aug.name == base.name
    assert aug.model_id not in (0, 1, 2)
    assert aug.outputs == base.outputs and aug.output_units == base.output_units
    assert aug.states[:base.n_states] == base.states
    assert aug.n_states == base.n_states + sum(extra_states.values())
    expected = base.parameters.names + tuple(n for e in names for n in CATALOGUE[e].parameter_names)
    assert aug.parameters.names == expected
    assert aug.parameters["backlash_delta"].nominal == 0.03
    assert aug.parameters["torque_ripple_amplitude"].nominal == CATALOGUE["torque_ripple"].nominal[
        "torque_ripple_amplitude"]
    np.testing.assert_array_equal(aug.parameters.nominal[:len(base.parameters)], base.parameters.nominal)
    # composing keeps the active effects and their current values
    more = aug.with_effects(["sensor_delay"])
    assert more.effects == tuple(names) + ("sensor_delay",) and more.parameters["backlash_delta"].nominal == 0.03
    assert more.base_model is base
    # --set reaches effect parameters
    params, consts = aug.split_assignments({"backlash_delta": 0.01, "r": 0.02})
    assert params == {"backlash_delta": 0.01} and consts == {"r": 0.02}


def test_kernel_layout_and_error_scales_come_from_the_effect_definitions():
    """Offsets of the kernel layout table follow EFFECT_ORDER and each effect's constants; an
    augmented model's states, error scales and constants are those its effects declare."""
    from ema_uq.models import effect_kernels
    from ema_uq.models.effects import EFFECT_ORDER, LAYOUT, LAYOUT_SIZE
    from ema_uq.simulate import error_scales

    position = 0
    for name in EFFECT_ORDER:
        assert LAYOUT[name] == position
        position += 2
        for short in CATALOGUE[name].constant_names:
            assert LAYOUT[f"{name}_{short}"] == position
            position += 1
    assert LAYOUT_SIZE == position
    assert (effect_kernels.FX_COMPLIANCE, effect_kernels.FX_RIPPLE_PERIODS) == (
        LAYOUT["shaft_compliance"], LAYOUT["torque_ripple_periods"])
    base = get_model("lths")
    aug = base.with_effects(["shaft_compliance", "backlash"])
    assert aug.states[base.n_states:] == ("shaft_twist", "shaft_twist_rate", "backlash_b")
    assert aug.state_scales == base.state_scales + (0.01, 1.0, 0.1)
    table = aug.kernel_constants()[-LAYOUT_SIZE:]
    assert table[LAYOUT["shaft_compliance_mode_omega_max"]] == 1.0 / 2e-4 and table[LAYOUT["backlash_relaxation"]] == 1e-3
    assert aug.parameters.names[len(base.parameters):][:3] == (
        "shaft_compliance_period", "shaft_compliance_zeta", "shaft_compliance_load_fraction")
    assert table[LAYOUT["backlash"] + 1] == base.n_states + 2 and table[LAYOUT["stribeck"]] == -1.0
    thetas = np.repeat(aug.parameters.nominal[None], 2, axis=0)
    thetas[1, aug.parameters.index("backlash_delta")] = 0.0      # the play's state feeds nothing: frozen
    scales = error_scales(aug, thetas)
    np.testing.assert_array_equal(scales[0], aug.state_scales)
    np.testing.assert_array_equal(scales[1], aug.state_scales[:-1] + (-1.0,))


@pytest.mark.parametrize("facts, fragment", [
    ({"extra_states": {"htls": ("toy_x",)}}, "extra state toy_x of concept htls has no positive error scale"),
    ({"magnitude": "toy_phase"}, "magnitude 'toy_phase' must be a parameter that is 0 at off"),
    ({"constants": {"htls": {"a": 1.0}, "lths": {"b": 1.0}}}, "concept lths gives kernel constants b; every concept"),
])
def test_inconsistent_kernel_facts_of_an_effect_are_one_line_errors(facts, fragment):
    parameter = Parameter("toy_phase", "rad", 0.5, -1.0, 1.0)
    with pytest.raises(EffectError, match=fragment):
        Effect("toy", "a toy", (parameter,), start={"toy_phase": 0.1}, off={"toy_phase": 0.5},
               signature=("periodic",), **facts)


@pytest.mark.parametrize("names, values, fragments", [
    (["friction"], None, ("effect 'friction' is not available for concept htls", "backlash", "torque_ripple")),
    (["backlash", "backlash"], None, ("backlash is named twice",)),
    (["backlash"], {"stribeck_ratio": 1.0}, ("'stribeck_ratio' does not belong", "backlash_delta")),
    (["backlash"], {"backlash_delta": -0.1}, ("backlash_delta = -0.1 lies outside its bounds",)),
    ([], {"backlash_delta": 0.1}, ("effect values given without effects",)),
])
def test_with_effects_errors_are_one_line(names, values, fragments):
    with pytest.raises(ParameterError) as info:
        get_model("htls").with_effects(names, values)
    message = str(info.value)
    assert "\n" not in message
    for fragment in fragments:
        assert fragment in message


def test_parse_effect():
    assert parse_effect("backlash") == ("backlash", {})
    assert parse_effect("backlash:delta=0.01") == ("backlash", {"backlash_delta": 0.01})
    assert parse_effect(" stribeck : ratio=2, stribeck_speed=0.5 ") == (
        "stribeck", {"stribeck_ratio": 2.0, "stribeck_speed": 0.5})
    for text, fragments in [
        ("gears:delta=1", ("unknown effect 'gears'", "backlash, stribeck")),
        ("backlash:gap=1", ("effect backlash has no parameter 'gap'", "delta", "backlash_delta")),
        ("backlash:delta", ("cannot read effect", "backlash:delta=")),
        ("backlash:delta=wide", ("'wide' is not a number",)),
        ("backlash:delta=nan", ("not finite",)),
        (":delta=1", ("cannot read effect",)),
    ]:
        with pytest.raises(EffectError) as info:
            parse_effect(text)
        assert isinstance(info.value, ParameterError) and "\n" not in str(info.value)
        for fragment in fragments:
            assert fragment in str(info.value), (text, str(info.value))


# --- exactness ------------------------------------------------------------------------------
@pytest.mark.parametrize("concept", ["htls", "lths"])
def test_effects_at_off_reproduce_nominal_bit_for_bit(concept, experiment, nominal_runs):
    base = get_model(concept)
    for name, effect in CATALOGUE.items():
        aug = base.with_effects([name])
        np.testing.assert_array_equal(runs(aug, aug.parameters.vector(effect.off), experiment)[0],
                                      nominal_runs[concept], err_msg=name)
    # every effect at once (of each exclusive group, one member at a time)
    groups = [sorted(group) for group in EXCLUSIVE]
    for i in range(max(map(len, groups))):
        left_out = {name for group in groups for name in group if name != group[i % len(group)]}
        everything = base.with_effects([n for n in CATALOGUE if n not in left_out])
        off = everything.parameters.vector({k: v for n, e in CATALOGUE.items() if n not in left_out
                                            for k, v in e.off.items()})
        np.testing.assert_array_equal(runs(everything, off, experiment)[0], nominal_runs[concept], err_msg=str(left_out))


@njit(cache=True)
def _plain_rk4(concept_id, th, c, inputs, x0, h, n_sub, n_outputs):
    """A plain RK4 loop over the nominal evaluate functions (the pre-effects kernel's arithmetic)."""
    n = inputs.shape[0]
    out = np.empty((n, n_outputs))
    x = x0.copy()
    k1 = np.empty_like(x)
    k2 = np.empty_like(x)
    k3 = np.empty_like(x)
    k4 = np.empty_like(x)
    y = np.empty(n_outputs)
    for k in range(n):
        u = inputs[k]
        for sub in range(n_sub):
            if concept_id == 0:
                htls.evaluate(x, u, th, c, k1, y)
            else:
                lths.evaluate(x, u, th, c, k1, y)
            if sub == 0:
                out[k] = y
                if k == n - 1:
                    return out
            xt = x + 0.5 * h * k1
            if concept_id == 0:
                htls.evaluate(xt, u, th, c, k2, y)
            else:
                lths.evaluate(xt, u, th, c, k2, y)
            xt = x + 0.5 * h * k2
            if concept_id == 0:
                htls.evaluate(xt, u, th, c, k3, y)
            else:
                lths.evaluate(xt, u, th, c, k3, y)
            xt = x + h * k3
            if concept_id == 0:
                htls.evaluate(xt, u, th, c, k4, y)
            else:
                lths.evaluate(xt, u, th, c, k4, y)
            for i in range(x.size):
                x[i] += h / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])
    return out


@pytest.mark.parametrize("concept", ["htls", "lths"])
def test_nominal_outputs_unchanged_by_the_effect_dispatch(concept, experiment, nominal_runs):
    m = get_model(concept)
    n_sub = int(round(experiment.dt / m.integration_step))
    plain = _plain_rk4(m.model_id, m.parameters.nominal, m.kernel_constants(), experiment.input_matrix(m),
                       np.zeros(m.n_states), experiment.dt / n_sub, n_sub, m.n_outputs)
    rk4 = simulate_batch(m, m.parameters.nominal, experiment.time, experiment.input_matrix(m), integrator="rk4")
    np.testing.assert_array_equal(rk4, plain)


# --- each effect visible, at nominal and half magnitude -------------------------------------
@pytest.mark.parametrize("concept", ["htls", "lths"])
def test_each_effect_is_visible_through_2_percent_noise(concept, experiment, nominal_runs):
    """Noise-normalised excess chi-square N sum_ch (NRMSE_ch / 0.02)^2 over the rig channels
    is >= 100 at half magnitude (clearly above the chi-square spread of a few tens)."""
    base = get_model(concept)
    rig = [c for c in ("Omega", "y1", "y2", "I_A", "U_A") if c in base.outputs]
    idx = base.output_index(rig)
    nominal = nominal_runs[concept][:, idx]
    rms = np.sqrt(np.mean(nominal ** 2, axis=0))
    for name in CATALOGUE:
        aug = base.with_effects([name])
        thetas = np.tile(aug.parameters.nominal, (2, 1))
        thetas[1, aug.parameters.index(CATALOGUE[name].magnitude)] *= 0.5
        out = runs(aug, thetas, experiment)[:, :, idx]
        nrmse = np.sqrt(np.mean((out - nominal) ** 2, axis=1)) / rms
        excess = experiment.n_samples * np.sum((nrmse / NOISE) ** 2, axis=1)
        assert excess.min() >= 100.0, (name, excess)
        assert np.all(nrmse < 0.5), (name, nrmse)  # an effect, not a different machine


@pytest.mark.parametrize("concept", ["htls", "lths"])
def test_backlash_carriage_stands_while_the_drive_crosses_the_play(concept, experiment, nominal_runs):
    base = get_model(concept)
    delta = 0.02
    aug = base.with_effects(["backlash"], {"backlash_delta": delta})
    out = runs(aug, aug.parameters.nominal, experiment)[0]
    nom = nominal_runs[concept]
    t = experiment.time
    omega, omega_tp1 = out[:, column(concept, "Omega")], out[:, column(concept, "Omega_TP1")]
    # after the reversal at 24 s the motor turns while the screw stands (the play is crossed)
    after = (t > 24.0) & (t < 24.5)
    crossing = after & (np.abs(omega) > 0.3) & (np.abs(omega_tp1) < 1e-2)
    assert crossing.sum() >= 2
    # ... so the carriage falls behind by at least the lost motion 2 delta r tan(gamma)
    lag = out[:, column(concept, "y1")] - nom[:, column(concept, "y1")]
    lost_motion = 2 * delta * LEAD
    assert lag[after].max() >= 0.95 * lost_motion
    assert lag[after].max() <= 2.5 * lost_motion
    assert np.abs(lag[(t > 20.0) & (t < 24.0)]).max() < 0.05 * lost_motion  # no lag before the reversal
    # ... and the load torque does not reach the motor meanwhile
    m_load = out[:, column(concept, "M_TPER1" if concept == "htls" else "M_TPER")]
    assert np.abs(m_load[crossing]).max() < 0.05 * np.abs(m_load[after & ~crossing]).max()


def _htls_state_and_constants(names, values):
    aug = get_model("htls").with_effects(names, values)
    x = np.zeros(aug.n_states)
    x[:4] = [24.0, 0.05, 0.051, 3.7]
    return aug, x, np.array([0.2, -12000.0, -9500.0, 0.0])


@pytest.mark.parametrize("scale, phase, theta", [(1.0, 0.3, 3.7), (6.0, -1.0, 10.2), (0.0, 0.5, 1.0)])
def test_ujoint_speed_factor_is_eq8(scale, phase, theta):
    aug, x, u = _htls_state_and_constants(["ujoint_kinematics"], {"ujoint_kinematics_scale": scale,
                                                                  "ujoint_kinematics_phase": phase})
    x[3] = theta
    dx, y = np.empty(aug.n_states), np.empty(aug.n_outputs)
    evaluate_effects(aug, x, u, aug.parameters.nominal, aug.kernel_constants(), dx, y)
    out = dict(zip(aug.outputs, y))
    for k, beta in ((1, 3 * DEG), (2, 5 * DEG)):
        g = math.cos(beta) / (1 - math.sin(beta) ** 2 * math.cos(theta / 2 + phase) ** 2)  # eq. 8, theta_TP = theta / i_TP
        assert out[f"Omega_U{k}"] == pytest.approx((1 + scale * (g - 1)) * out[f"Omega_TP{k}"], rel=1e-13)
        assert dx[k] == pytest.approx(LEAD * out[f"Omega_U{k}"], rel=1e-13)


def test_stribeck_and_load_dependent_friction_formulas():
    aug, x, u = _htls_state_and_constants(["stribeck", "load_dependent_friction"], {
        "stribeck_ratio": 0.8, "stribeck_speed": 2.0, "load_dependent_friction_mu": 0.004})
    for speed in (0.3, 1.5, 24.0):  # motor speed; the screw turns at half of it
        x[0] = speed
        dx, y = np.empty(aug.n_states), np.empty(aug.n_outputs)
        evaluate_effects(aug, x, u, aug.parameters.nominal, aug.kernel_constants(), dx, y)
        out = dict(zip(aug.outputs, y))
        w = speed / 2.0
        factor = 1 + 0.8 * math.exp(-(w / 2.0) ** 2)
        sign = math.tanh(w / 0.05)
        m_er1 = 0.016 * 12000.0 * math.sin(4 * DEG) * math.cos(4 * DEG)
        m_tser1 = 0.40 * w + (1.20 + 0.004 * 0.016 * 12000.0) * factor * sign + m_er1
        assert out["M_TSER1"] == pytest.approx(m_tser1, rel=1e-13)
        m_uer1 = m_tser1 / math.cos(3 * DEG) + 0.10 * w + 0.30 * factor * sign
        assert out["M_UER1"] == pytest.approx(m_uer1, rel=1e-13)
        assert out["M_TPER1"] == pytest.approx(m_uer1 / 2 + 0.20 * w + 0.60 * factor * sign, rel=1e-13)


@pytest.mark.parametrize("concept", ["htls", "lths"])
@pytest.mark.parametrize("parent, parent_values, form, form_values, shape", NESTED)
def test_a_spanning_form_is_its_family_s_first_form_at_zero_asymmetry_or_dispersion(
        concept, parent, parent_values, form, form_values, shape, experiment):
    first = get_model(concept).with_effects([parent], parent_values)
    spanning = get_model(concept).with_effects([form], form_values)
    alike = runs(spanning, spanning.parameters.nominal, experiment)
    np.testing.assert_array_equal(alike, runs(first, first.parameters.nominal, experiment))
    shaped = runs(spanning, spanning.parameters.vector({**form_values, **shape}), experiment)
    # on some channel by more than a thousandth of its range (a U-joint's ripple is small beside the motor's speed)
    assert np.max(np.max(np.abs(shaped - alike), axis=1) / np.max(np.abs(alike), axis=1)) > 1e-3


def test_each_form_declares_the_forms_it_nests():
    """``Effect.nests`` (what a diagnosis may leave out beside a form) is what the test above shows."""
    declared = {(parent, form) for form, effect in CATALOGUE.items() for parent in effect.nests}
    assert declared == {(parent, form) for parent, _, form, _, _ in NESTED}
    for parent, form in declared:
        assert CATALOGUE[parent].family == CATALOGUE[form].family


REDUCING = [(form, other) for form, effect in CATALOGUE.items() for other in effect.reduces_to]


def test_the_reductions_cover_every_nesting_and_the_forms_that_nest_without_being_declared():
    """Every declared ``nests`` is a reduction too (a fit of the form can start from the nested
    form's), and the forms a diagnosis must not leave out beside theirs reduce as well."""
    assert {(parent, form) for parent, _, form, _, _ in NESTED} <= {(other, form) for form, other in REDUCING}
    assert {("torque_ripple", "torque_ripple_harmonics"), ("ujoint_kinematics", "ujoint_stations")} <= \
        {(other, form) for form, other in REDUCING}


@pytest.mark.parametrize("concept", ["htls", "lths"])
@pytest.mark.parametrize("form, other", REDUCING)
def test_a_form_at_its_reduced_values_computes_the_other_form_bit_for_bit(concept, form, other, experiment):
    """``Effect.reduced_values``: at them the form's outputs are the other form's, for values of
    the other form drawn away from its start (so that a map onto the wrong parameter shows)."""
    first = get_model(concept).with_effects([other])
    values = {}
    for n in (n for n in first.parameters.names if n.startswith(other + "_")):
        p = first.parameters[n]
        values[n] = float(np.clip(1.37 * p.nominal if p.nominal else 0.7, p.lower, p.upper))
    first = get_model(concept).with_effects([other], values)
    reduced = CATALOGUE[form].reduced_values(other, values)
    spanning = get_model(concept).with_effects([form], reduced)
    np.testing.assert_array_equal(runs(spanning, spanning.parameters.nominal, experiment),
                                  runs(first, first.parameters.nominal, experiment))


def test_a_reduction_must_map_every_parameter_inside_its_bounds():
    effect = CATALOGUE["stribeck_directional"]
    with pytest.raises(EffectError, match="must map each of its parameters"):
        replace(effect, reduces_to={"stribeck": {"stribeck_directional_ratio": "stribeck_ratio"}})
    mapping = dict(effect.reduces_to["stribeck"], stribeck_directional_asymmetry=2.0)
    with pytest.raises(EffectError, match="outside"):
        replace(effect, reduces_to={"stribeck": mapping})
    mapping = dict(effect.reduces_to["stribeck"], stribeck_directional_speed="sensor_delay_tau")
    with pytest.raises(EffectError, match="not a parameter of stribeck"):
        replace(effect, reduces_to={"stribeck": mapping})
    with pytest.raises(EffectError, match="does not reduce to backlash"):
        effect.reduced_values("backlash", {})


def test_loaded_ripple_stroke_ujoint_and_stiffening_formulas():
    """torque_ripple_loaded (k_n A + r M) sin(n θ + φ); ujoint_stroke's scale a (1 + s ξ) per
    carriage; shaft_compliance_loaded's spring k_0 (1 + h |M| / M_ref), held under the step's limit."""
    amplitude, phase, share, slope, hardening = 0.3, 0.5, 0.04, 0.6, 1.5
    aug, x, u = _htls_state_and_constants(["torque_ripple_loaded", "ujoint_stroke"], {
        "torque_ripple_loaded_amplitude": amplitude, "torque_ripple_loaded_phase": phase,
        "torque_ripple_loaded_share": share, "ujoint_stroke_scale": 6.0, "ujoint_stroke_slope": slope})
    plain, _, _ = _htls_state_and_constants([], {})
    x[1], x[2] = 0.05, 0.21  # the carriages on either side of mid-stroke (0.13 m)
    th, c = aug.parameters.nominal, aug.kernel_constants()
    dx, y = np.empty(aug.n_states), np.empty(aug.n_outputs)
    evaluate_effects(aug, x, u, th, c, dx, y)
    out = dict(zip(aug.outputs, y))
    for k, beta in ((1, 3 * DEG), (2, 5 * DEG)):
        g = math.cos(beta) / (1 - math.sin(beta) ** 2 * math.cos(x[3] / 2) ** 2)
        scale = 6.0 * (1 + slope * (x[k] - 0.13) / 0.13)
        assert out[f"Omega_U{k}"] == pytest.approx((1 + scale * (g - 1)) * out[f"Omega_TP{k}"], rel=1e-13)
    # the ripple: the motor's net torque differs from the same state without the ripple by exactly it
    k_n, j = th[aug.parameters.index("k_n")], th[aug.parameters.index("J")]
    no_ripple = th.copy()
    no_ripple[aug.parameters.index("torque_ripple_loaded_amplitude")] = 0.0
    no_ripple[aug.parameters.index("torque_ripple_loaded_share")] = 0.0
    dx0 = np.empty(aug.n_states)
    evaluate_effects(aug, x, u, no_ripple, c, dx0, np.empty(aug.n_outputs))
    m_n = out["I_A"] * k_n
    ripple = (k_n * amplitude + share * m_n) * math.sin(6.0 * x[3] + phase)
    assert (dx[0] - dx0[0]) * j == pytest.approx(ripple, rel=1e-9)
    # the stiffening: the spring's ω² read from the twist's acceleration at two twists (the load
    # torque does not depend on the twist at rest), unloaded and stiffened by 1 + h |M| / M_ref
    aug = get_model("htls").with_effects(["shaft_compliance_loaded"], {
        "shaft_compliance_loaded_period": 0.02, "shaft_compliance_loaded_hardening": hardening})
    th, c = aug.parameters.nominal, aug.kernel_constants()
    i_q = aug.states.index("shaft_twist")
    omega_squared, load = [], 0.0
    for h in (0.0, hardening):
        th[aug.parameters.index("shaft_compliance_loaded_hardening")] = h
        rates = []
        for q in (0.0, 1e-4):
            x = np.zeros(aug.n_states)
            x[i_q] = q
            dx, y = np.empty(aug.n_states), np.empty(aug.n_outputs)
            evaluate_effects(aug, x, np.array([0.3, -12000.0, -9500.0, 0.0]), th, c, dx, y)
            rates.append(dx[i_q + 1])
            out = dict(zip(aug.outputs, y))
            load = out["M_TPER1"] + out["M_TPER2"]
        omega_squared.append((rates[0] - rates[1]) / 1e-4)
    assert omega_squared[0] == pytest.approx((2 * math.pi / 0.02) ** 2, rel=1e-6)
    assert omega_squared[1] == pytest.approx(omega_squared[0] * (1 + hardening * abs(load) / 30.0), rel=1e-6)
    assert abs(load) > 1.0  # the test has a load to stiffen with


def test_directional_stribeck_and_load_friction_formulas():
    """Breakaway excess ρ (1 + a) moving out, ρ (1 - a) moving in; load coefficient μ (1 + a) while
    the load opposes the motion (here: moving out against the test state's load), μ (1 - a) while
    it aids it."""
    rho, a_s, v_s, mu, a_l = 0.8, 0.5, 2.0, 0.004, -0.4
    aug, x, u = _htls_state_and_constants(["stribeck_directional", "load_friction_directional"], {
        "stribeck_directional_ratio": rho, "stribeck_directional_asymmetry": a_s, "stribeck_directional_speed": v_s,
        "load_friction_directional_mu": mu, "load_friction_directional_asymmetry": a_l})
    m_er1 = 0.016 * 12000.0 * math.sin(4 * DEG) * math.cos(4 * DEG)   # > 0: the load pushes the carriage in
    for speed in (0.3, 1.5, 24.0, -0.3, -1.5, -24.0):  # motor speed; the screw turns at half of it
        x[0] = speed
        dx, y = np.empty(aug.n_states), np.empty(aug.n_outputs)
        evaluate_effects(aug, x, u, aug.parameters.nominal, aug.kernel_constants(), dx, y)
        out = dict(zip(aug.outputs, y))
        w = speed / 2.0
        sign = math.tanh(w / 0.05)
        factor = 1 + rho * (1 + a_s if w > 0 else 1 - a_s) * math.exp(-(w / v_s) ** 2)
        opposing = 1.0 if w > 0 else -1.0
        c_ts = 1.20 + mu * (1 + a_l * abs(sign) * opposing) * 0.016 * 12000.0
        m_tser1 = 0.40 * w + c_ts * factor * sign + m_er1
        assert out["M_TSER1"] == pytest.approx(m_tser1, rel=1e-13)
        assert out["M_UER1"] == pytest.approx(m_tser1 / math.cos(3 * DEG) + 0.10 * w + 0.30 * factor * sign, rel=1e-13)


def test_dispersed_delay_is_a_pure_delay_then_a_first_order_lag(experiment, nominal_runs):
    tau, share = 0.02, 0.6
    aug = get_model("htls").with_effects(["sensor_delay_dispersed"], {
        "sensor_delay_dispersed_tau": tau, "sensor_delay_dispersed_dispersion": share})
    out = runs(aug, aug.parameters.nominal, experiment)[0]
    t, nom = experiment.time, nominal_runs["htls"]
    delayed = np.stack([np.interp(t - (1 - share) * tau, t, nom[:, j]) for j in range(nom.shape[1])], axis=1)
    expected = first_order_lag(delayed, share * tau, experiment.dt)
    scale = np.abs(nom).max(axis=0)
    assert np.all(np.abs(out - expected).max(axis=0) <= 1e-12 * scale)
    # the lag is exact for a ramp: past its transient a ramp comes out late by the lag's time constant
    ramp = first_order_lag(np.column_stack([t, 2 * t]), 0.05, experiment.dt)
    np.testing.assert_allclose(ramp[t > 1.0], np.column_stack([t - 0.05, 2 * (t - 0.05)])[t > 1.0], atol=1e-9)


def test_load_dependent_friction_raises_the_steady_current_by_the_extra_torque(experiment, nominal_runs):
    """In the steady extension before 9 s the speed loop supplies the extra screw friction
    sum_k mu r |F_ERk| / cos(beta_k) / i_TP as motor torque: Delta I_A = that / k_n."""
    mu = 0.005
    aug = get_model("htls").with_effects(["load_dependent_friction"], {"load_dependent_friction_mu": mu})
    out = runs(aug, aug.parameters.nominal, experiment)[0]
    t = experiment.time
    window = (t > 7.0) & (t < 8.9)
    f1, f2 = (np.abs(experiment.inputs[k][window]) for k in ("F_ER1", "F_ER2"))
    extra = mu * 0.016 * (f1 / math.cos(3 * DEG) + f2 / math.cos(5 * DEG)) / 2.0
    delta_i = out[window, 3] - nominal_runs["htls"][window, 3]
    np.testing.assert_allclose(delta_i, extra / 1.2, rtol=0.03)


def test_stribeck_shows_at_low_speed_only(experiment, nominal_runs):
    aug = get_model("lths").with_effects(["stribeck"])
    out = runs(aug, aug.parameters.nominal, experiment)[0]
    screw = np.abs(nominal_runs["lths"][:, column("lths", "Omega_TP1")])
    delta_i = np.abs(out[:, 3] - nominal_runs["lths"][:, 3])
    v_s = CATALOGUE["stribeck"].nominal["stribeck_speed"]
    slow, fast = (screw > 0.1) & (screw < v_s), screw > 4 * v_s
    assert delta_i[slow].mean() > 20 * delta_i[fast].mean()


def _peak_frequency(signal, dt):
    signal = signal - signal.mean()
    spectrum = np.abs(np.fft.rfft(signal * np.hanning(signal.size)))
    return np.fft.rfftfreq(signal.size, dt)[np.argmax(spectrum)]


@pytest.mark.parametrize("concept, screw_ratio", [("htls", 2.0), ("lths", 40.0)])
def test_ujoint_ripple_at_twice_the_shaft_rotation(concept, screw_ratio, experiment, nominal_runs):
    aug = get_model(concept).with_effects(["ujoint_kinematics"])
    out = runs(aug, aug.parameters.nominal, experiment)[0]
    window = (experiment.time > 4.5) & (experiment.time < 8.9)  # steady extension
    ripple = out[window, 0] - nominal_runs[concept][window, 0]
    shaft_hz = nominal_runs[concept][window, 0].mean() / screw_ratio / (2 * math.pi)
    assert _peak_frequency(ripple, experiment.dt) == pytest.approx(2 * shaft_hz, abs=0.3)


def test_torque_ripple_at_the_cogging_frequency(experiment, nominal_runs):
    aug = get_model("htls").with_effects(["torque_ripple"])
    out = runs(aug, aug.parameters.nominal, experiment)[0]
    window = (experiment.time > 4.5) & (experiment.time < 8.9)
    ripple = out[window, 3] - nominal_runs["htls"][window, 3]
    motor_hz = nominal_runs["htls"][window, 0].mean() / (2 * math.pi)
    assert _peak_frequency(ripple, experiment.dt) == pytest.approx(6 * motor_hz, abs=0.3)
    assert np.abs(ripple).max() > 0.3  # A (of 0.5 A equivalent ripple), most of it reaches the current


@pytest.mark.parametrize("tau", [0.03, 0.025, 0.0137])
def test_sensor_delay_is_a_pure_interpolated_lag(tau, experiment, nominal_runs):
    aug = get_model("htls").with_effects(["sensor_delay"], {"sensor_delay_tau": tau})
    out = runs(aug, aug.parameters.nominal, experiment)[0]
    t = experiment.time
    nom = nominal_runs["htls"]
    expected = np.stack([np.interp(t - tau, t, nom[:, j]) for j in range(nom.shape[1])], axis=1)
    scale = np.abs(nom).max(axis=0)
    assert np.all(np.abs(out - expected).max(axis=0) <= 1e-12 * scale)
    # the cross-correlation of the Omega increments peaks at the delay
    a, b = np.diff(nom[:, 0]), np.diff(out[:, 0])
    lags = np.arange(-10, 11)
    corr = [np.dot(a[max(0, -k):a.size - max(0, k)], b[max(0, k):b.size - max(0, -k)]) for k in lags]
    assert lags[int(np.argmax(corr))] == round(tau / experiment.dt)
    # delay_outputs on its own, batched over two delays
    thetas = np.vstack([aug.parameters.nominal, aug.parameters.vector({"sensor_delay_tau": 0.0})])
    both = delay_outputs(aug, thetas, t, np.stack([nom, nom]))
    assert np.all(np.abs(both[0] - expected).max(axis=0) <= 1e-12 * scale)
    np.testing.assert_array_equal(both[1], nom)


@pytest.mark.parametrize("concept", ["htls", "lths"])
def test_shaft_mode_matches_an_independent_two_inertia_model(concept):
    """Eigenvalues of the kernel's Jacobian at a steady operating point against a linear
    two-inertia model written from scratch: J_m dΩm = -p Ωm - T, J_L dΩL = T - B_L ΩL,
    T = k q + d dq, k = J_red ω², d = 2 ζ ω J_red (motor speed loop p; position loop ignored)."""
    period, zeta = 0.03, 0.05
    fraction = {"htls": 0.7, "lths": 0.6}[concept]     # not the old fixed splits (0.5, 0.3)
    aug = get_model(concept).with_effects(["shaft_compliance"], {"shaft_compliance_period": period,
                                                                 "shaft_compliance_zeta": zeta,
                                                                 "shaft_compliance_load_fraction": fraction})
    th, c = aug.parameters.nominal, aug.kernel_constants()
    names = aug.parameters.names
    J = th[names.index("J")]
    if concept == "htls":
        x = np.array([30.0, 0.05, 0.051, 3.7, 0.0, 0.0])
        p_speed = th[names.index("p_PCE")]
        u = np.array([0.155, -9000.0, -7000.0, 0.0])  # control unsaturated
        i1 = i2 = 2.0
        b_load = sum((th[names.index(f"B_TS{k}")] / math.cos(b) + th[names.index(f"B_U{k}")]) / 4.0
                     + th[names.index(f"B_TP{k}")] / 2.0 for k, b in ((1, 3 * DEG), (2, 5 * DEG)))
    else:
        x = np.array([20.0, 600.0, 0.05, 0.051, 3.7, 0.0, 0.0])
        k_n, r_a, l_a = th[names.index("k_n")], th[names.index("R_A")], th[names.index("L_A")]
        p_speed = None  # the current loop is part of the model below
        u = np.array([0.155, -9000.0, -7000.0, 0.0])  # control unsaturated
        # viscous load at the motor shaft (input shaft side of the magnetic gear, i_MG = 20)
        b_load = ((th[names.index("B_TS1")] / math.cos(3 * DEG) + th[names.index("B_U1")]) / 4.0
                  + th[names.index("B_TP1")] / 2.0
                  + (th[names.index("B_TS2")] / math.cos(5 * DEG) + th[names.index("B_U2")]) / 4.0
                  + th[names.index("B_TP2")] / 2.0) / 400.0
    j_m, j_l = (1 - fraction) * J, fraction * J
    j_red = j_m * j_l / J
    omega = 2 * math.pi / period
    k, d = j_red * omega ** 2, 2 * zeta * omega * j_red

    def rhs(state):
        dx, y = np.empty(aug.n_states), np.empty(aug.n_outputs)
        evaluate_effects(aug, state, u, th, c, dx, y)
        return dx

    jac = np.empty((x.size, x.size))
    for i in range(x.size):
        step = np.zeros(x.size)
        step[i] = 1e-6 * max(1.0, abs(x[i]))
        jac[:, i] = (rhs(x + step) - rhs(x - step)) / (2 * step[i])
    kernel = np.linalg.eigvals(jac)
    if concept == "htls":  # states Ωm, ΩL, q
        a = np.array([[(-p_speed - d) / j_m, d / j_m, -k / j_m],
                      [d / j_l, (-d - b_load) / j_l, k / j_l],
                      [1.0, -1.0, 0.0]])
    else:  # states I, Ωm, ΩL, q; U_A = (p_PCE/k_n)(Ω_r - Ωm)
        g = th[names.index("p_PCE")] / k_n
        a = np.array([[-r_a / l_a, (-th[names.index("k_s")] - g) / l_a, 0.0, 0.0],
                      [k_n / j_m, -d / j_m, d / j_m, -k / j_m],
                      [0.0, d / j_l, (-d - b_load) / j_l, k / j_l],
                      [0.0, 1.0, -1.0, 0.0]])
    model = np.linalg.eigvals(a)
    oscillatory = [z for z in model if z.imag > 1.0]
    assert oscillatory, model
    for z in oscillatory:
        nearest = kernel[np.argmin(np.abs(kernel - z))]
        assert abs(nearest - z) < 0.03 * abs(z), (z, nearest, kernel)


@pytest.mark.parametrize("concept", ["htls", "lths"])
def test_batched_equals_single(concept, experiment):
    # one member of each exclusive group
    names = [n for n in CATALOGUE if n not in ("backlash_compliant", "ujoint_stations", "shaft_compliance_loaded",
                                               "ujoint_stroke")]
    aug = get_model(concept).with_effects(names)
    nominal = aug.parameters.nominal
    thetas = np.stack([nominal, aug.parameters.vector({"backlash_delta": 0.01, "sensor_delay_tau": 0.013,
                                                       "shaft_compliance_period": 0.02}),
                       aug.parameters.vector({k: v for n in names for k, v in CATALOGUE[n].start.items()})])
    short = experiment.slice(0, 1500)  # through the first ramp and hold
    batch = simulate_batch(aug, thetas, short.time, short.input_matrix(aug))
    assert np.all(np.isfinite(batch))
    for i in range(thetas.shape[0]):
        np.testing.assert_array_equal(batch[i], simulate_batch(aug, thetas[i], short.time, short.input_matrix(aug)))


# --- command line ---------------------------------------------------------------------------
def run_cli(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ema_uq", *map(str, args)], capture_output=True, text=True,
                          timeout=300)


def test_simulate_with_effects_end_to_end(tmp_path):
    out = tmp_path / "bl.nc"
    result = run_cli("simulate", "--concept", "htls", "--experiment", "deploy-retract", "--noise", "0.02",
                     "--seed", "3", "--effect", "backlash:delta=0.03", "--effect", "sensor_delay",
                     "--set", "sensor_delay_tau=0.015", "--set", "J=0.055", "--out", out)
    assert result.returncode == 0, result.stderr
    line = result.stdout.strip()
    assert "\n" not in line and "backlash(delta=0.03)" in line and "sensor_delay(tau=0.015)" in line
    measurement = io.read_measurement(out, concept="htls")
    assert measurement.channels == get_model("htls").outputs  # same outputs as the nominal model
    assert "effect" not in json.dumps({k: str(v) for k, v in measurement.attrs.items()}).lower()
    assert b"backlash" not in out.read_bytes()  # the data never name the effect
    truth = json.loads((tmp_path / "bl.nc.truth.json").read_text())
    assert truth["concept"] == "htls"
    assert truth["effects"] == {"backlash": {"backlash_delta": 0.03}, "sensor_delay": {"sensor_delay_tau": 0.015}}
    aug = get_model("htls").with_effects(["backlash", "sensor_delay"])
    theta = aug.parameters.vector({"backlash_delta": 0.03, "sensor_delay_tau": 0.015, "J": 0.055})
    expected = synthesize(aug, deploy_retract(), theta, noise=0.02, seed=3)
    np.testing.assert_array_equal(measurement.values, expected.values)


@pytest.mark.parametrize("effect, fragments", [
    ("backlash:gap=0.1", ("effect backlash has no parameter 'gap'", "delta")),
    ("backlash:delta=-1", ("backlash_delta = -1 lies outside its bounds",)),
    ("gears", ("--effect of concept lths: unknown effect 'gears'", "backlash")),
])
def test_simulate_bad_effect_is_a_one_line_error(tmp_path, capsys, effect, fragments):
    from ema_uq.cli import main

    out = tmp_path / "x.nc"
    status = main(["simulate", "--concept", "lths", "--experiment", "deploy-retract", "--effect", effect,
                   "--out", str(out)])
    captured = capsys.readouterr()
    assert status == 2 and captured.out == ""
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("ema-uq: error: "), captured.err
    for fragment in fragments:
        assert fragment in lines[0], lines[0]
    assert not out.exists()


# --- families: the diagnosis names the family, forms of one family are no ambiguity ----------
def _row(effect, family, score):
    from ema_uq.gap.result import CandidateScore

    return CandidateScore(effect, score, 1.0, 0.05, 0.95, score, score, score, 0.5, 1,
                          selection_shrink=0.95, family=family)


def test_family_defaults_to_the_effect_and_forms_of_one_family_do_not_cut_the_margin():
    from ema_uq.gap.attribute import _verdict
    from ema_uq.gap.result import CandidateScore
    from ema_uq.gap.strategy import Thresholds

    assert all(e.family for e in CATALOGUE.values())
    assert CATALOGUE["stribeck"].family == "stribeck"
    assert CandidateScore("sensor_delay", 1.0, 1, 1, 0, 1, 1, 1, 0, 1).family == "sensor_delay"

    class Clean:
        structured = False

    th = Thresholds()
    close_forms = [_row("form_a", "play", 1000.0), _row("form_b", "play", 990.0), _row("other", "other", 100.0)]
    assert _verdict(th, close_forms, True, True, Clean(), Clean()) == ("effect", "form_a", "high")
    # another family within the margin (2 ln B < 10 on the evidence dBIC + gain): the data cannot tell them apart
    close_families = [_row("form_a", "play", 1000.0), _row("other", "other", 998.0), _row("form_b", "play", 900.0)]
    assert _verdict(th, close_families, True, True, Clean(), Clean())[0] == "ambiguous"


def test_a_candidate_that_fits_far_beyond_noise_but_fails_held_out_leaves_the_gap_unexplained_not_none():
    from ema_uq.gap.attribute import _verdict
    from ema_uq.gap.result import CandidateScore
    from ema_uq.gap.strategy import Thresholds

    class Clean:
        structured = False

    def row(delta_bic, gain):
        return CandidateScore("ripple", delta_bic + gain, 0.0, 0.0, float("nan"), delta_bic, delta_bic, gain, 0.5, 3,
                              selection_shrink=0.0, family="ripple")

    th = Thresholds()
    # residual tests pass, held-out gap insignificant: the noise explains it only if no candidate fits beyond it
    assert _verdict(th, [row(525.0, -20.0)], False, False, Clean(), Clean()) == ("unexplained", None, "high")
    assert _verdict(th, [row(-0.8, 3.0)], False, False, Clean(), Clean()) == ("none", None, "high")
    assert _verdict(th, [row(th.bic_min, 3.0)], False, False, Clean(), Clean())[0] == "none"
    assert _verdict(th, [row(525.0, 400.0)], False, False, Clean(), Clean())[:2] == ("effect", "ripple")


def test_with_replicates_the_shrink_test_reads_the_reproducible_part_of_the_gap():
    from ema_uq.gap.attribute import _reproducible_shrink, _verdict
    from ema_uq.gap.result import CandidateScore, _candidate_from_json
    from ema_uq.gap.strategy import Thresholds

    class Clean:
        structured = False

    def row(selection_shrink, reproducible_shrink=None):
        return CandidateScore("play", 900.0, 1.0, 0.5, 0.5, 500.0, 500.0, 400.0, 0.5, 1,
                              selection_shrink=selection_shrink, reproducible_shrink=reproducible_shrink,
                              family="play")

    th = Thresholds()
    # no replicates: the reproducible shrink is the selection shrink, and 0.3 is too little
    assert row(0.3).reproducible_shrink == 0.3
    assert _verdict(th, [row(0.3)], True, False, Clean(), Clean())[0] == "unexplained"
    # a candidate closing 0.3 of a gap of which 0.4 is reproducible closes 0.75 of what it could
    assert _reproducible_shrink(1.0, 0.7, 0.6) == pytest.approx(0.75)
    assert _reproducible_shrink(1.0, 0.7, None) == pytest.approx(0.3)
    assert np.isnan(_reproducible_shrink(1.0, 0.7, 1.0))          # nothing reproducible
    assert _verdict(th, [row(0.3, 0.75)], True, False, Clean(), Clean())[:2] == ("effect", "play")
    # ... but only where that reproducible part stands out of the noise
    assert _verdict(th, [row(0.3, 0.75)], True, False, Clean(), Clean(), reproducible=False)[0] == "unexplained"
    # a gap with nothing reproducible is surely no fixed effect's
    assert _verdict(th, [row(0.3, float("nan"))], True, False, Clean(), Clean(),
                    reproducible=False) == ("unexplained", None, "high")
    # an insignificant gap asks no shrink at all
    assert _verdict(th, [row(0.3, float("nan"))], False, False, Clean(), Clean(), reproducible=False)[0] == "effect"
    # GAP.json round trip: NaN is written as null and read back as NaN, not as the selection shrink
    back = _candidate_from_json(json.loads(json.dumps(row(0.3, float("nan")).to_json())))
    assert back.selection_shrink == 0.3 and np.isnan(back.reproducible_shrink)


def test_gap_json_carries_the_family_beside_the_form():
    from ema_uq.gap.result import GapResult

    ranking = [_row("form_a", "play", 1000.0), _row("other", "other", 10.0)]
    common = dict(concept="htls", confidence="high", ranking=ranking, where={"channels": [], "regimes": []},
                  gap={}, localization=None, localization_held_out=None, localization_after=None,
                  localization_after_held_out=None, where_source="estimation", held_out="", channels=[],
                  held_out_channels=[], nominal={}, effect_parameters={}, thresholds={}, wall_time_s=0.0,
                  n_simulations=0)
    r = GapResult(verdict="effect", effect="form_a", **common)
    assert r.family == "play"       # from the winner's ranking row when not given
    rows = [c.to_json() for c in r.ranking]
    assert [row["family"] for row in rows] == ["play", "other"]
    assert GapResult(verdict="none", effect=None, **common).family is None


# --- further forms of the backlash family -----------------------------------------------------
@pytest.mark.parametrize("concept", ["htls", "lths"])
def test_compliant_backlash_without_play_is_the_shaft_compliance(concept, experiment):
    base = get_model(concept)
    held = CATALOGUE["backlash_compliant"].constants[concept]["load_fraction"]     # the coupling's own split
    plain = base.with_effects(["shaft_compliance"], {"shaft_compliance_period": 0.025, "shaft_compliance_zeta": 0.1,
                                                     "shaft_compliance_load_fraction": held})
    played = base.with_effects(["backlash_compliant"], {"backlash_compliant_delta": 0.0,
                                                        "backlash_compliant_period": 0.025})
    np.testing.assert_array_equal(runs(played, played.parameters.nominal, experiment),
                                  runs(plain, plain.parameters.nominal, experiment))
    with pytest.raises(EffectError, match="same coupling"):
        base.with_effects(["shaft_compliance", "backlash_compliant"])


@pytest.mark.parametrize("concept", ["htls", "lths"])
def test_compliant_backlash_loses_the_play_at_a_reversal(concept, experiment, nominal_runs):
    """A force-transmitting play is crossed when the coupling's torque changes sign: without
    the (one-signed) flap load, at the motion reversal where the friction turns."""
    base = get_model(concept)
    delta = 0.02
    aug = base.with_effects(["backlash_compliant"], {"backlash_compliant_delta": delta})
    stiff = base.with_effects(["backlash_compliant"], {"backlash_compliant_delta": 0.0})
    unloaded = experiment.input_matrix(base).copy()
    unloaded[:, 1:3] = 0.0
    out, ref = (simulate_batch(m, m.parameters.nominal, experiment.time, unloaded) for m in (aug, stiff))
    t = experiment.time
    after = (t > 24.0) & (t < 24.5)
    lag = out[:, column(concept, "y1")] - ref[:, column(concept, "y1")]
    lost_motion = 2 * delta * LEAD
    assert 0.8 * lost_motion <= lag[after].max() <= 2.5 * lost_motion
    assert np.abs(lag[(t > 20.0) & (t < 24.0)]).max() < 0.1 * lost_motion


@pytest.mark.parametrize("concept", ["htls", "lths"])
def test_output_backlash_screw_turns_while_the_carriage_stands(concept, experiment, nominal_runs):
    base = get_model(concept)
    delta = 0.02
    aug = base.with_effects(["backlash_output"], {"backlash_output_delta": delta})
    out = runs(aug, aug.parameters.nominal, experiment)[0]
    nom = nominal_runs[concept]
    t = experiment.time
    after = (t > 24.0) & (t < 24.5)
    lag = out[:, column(concept, "y1")] - nom[:, column(concept, "y1")]
    lost_motion = 2 * delta * LEAD
    assert 0.95 * lost_motion <= lag[after].max() <= 2.5 * lost_motion
    assert np.abs(lag[(t > 20.0) & (t < 24.0)]).max() < 0.05 * lost_motion
    # unlike the gear play, the screw keeps turning while the carriage stands, and the load
    # force does not reach it meanwhile
    screw = out[:, column(concept, "Omega_TP1")]
    carriage_still = after & (np.abs(np.gradient(out[:, column(concept, "y1")], t)) < 0.02 * LEAD)
    crossing = carriage_still & (np.abs(screw) > 0.3)
    assert crossing.sum() >= 2
    m_er = out[:, column(concept, "M_ER1")]
    assert np.abs(m_er[crossing]).max() < 0.05 * np.abs(m_er[after & ~crossing]).max()


def test_ripple_harmonics_reduce_to_the_single_ripple_and_add_its_harmonics(experiment):
    base = get_model("lths")
    one = base.with_effects(["torque_ripple"], {"torque_ripple_amplitude": 0.5, "torque_ripple_phase": 0.3})
    three = base.with_effects(["torque_ripple_harmonics"], {
        "torque_ripple_harmonics_amplitude": 0.5, "torque_ripple_harmonics_phase": 0.3,
        "torque_ripple_harmonics_ratio2": 0.0, "torque_ripple_harmonics_ratio3": 0.0})
    single = runs(one, one.parameters.nominal, experiment)[0]
    np.testing.assert_allclose(runs(three, three.parameters.nominal, experiment)[0], single, rtol=1e-9, atol=1e-9)
    harmonics = runs(three, three.parameters.vector({"torque_ripple_harmonics_amplitude": 0.5,
                                                     "torque_ripple_harmonics_ratio2": 1.0}), experiment)[0]
    assert not np.allclose(harmonics, single, rtol=1e-3)


@pytest.mark.parametrize("concept", ["htls", "lths"])
def test_ujoint_stations_give_each_joint_its_own_scale_and_phase(concept, experiment):
    base = get_model(concept)
    shared = base.with_effects(["ujoint_kinematics"], {"ujoint_kinematics_scale": 6.0, "ujoint_kinematics_phase": 0.4})
    stations = base.with_effects(["ujoint_stations"])
    alike = stations.parameters.vector({"ujoint_stations_scale1": 6.0, "ujoint_stations_phase1": 0.4,
                                        "ujoint_stations_scale2": 6.0, "ujoint_stations_phase2": 0.4})
    np.testing.assert_array_equal(runs(stations, alike, experiment), runs(shared, shared.parameters.nominal, experiment))
    # station 2's joint ideal (a2 = 0): its U-joint turns with its screw shaft, station 1's does not
    only_one = runs(stations, stations.parameters.vector({"ujoint_stations_scale1": 6.0, "ujoint_stations_phase1": 0.4,
                                                          "ujoint_stations_scale2": 0.0}), experiment)[0]
    u1, tp1 = only_one[:, column(concept, "Omega_U1")], only_one[:, column(concept, "Omega_TP1")]
    u2, tp2 = only_one[:, column(concept, "Omega_U2")], only_one[:, column(concept, "Omega_TP2")]
    np.testing.assert_array_equal(u2, tp2)
    assert np.max(np.abs(u1 - tp1)) > 1e-3 * np.max(np.abs(tp1))
    # a phase of station 2's own moves station 2's ripple only where the shared form cannot
    turned = runs(stations, stations.parameters.vector({"ujoint_stations_scale1": 6.0, "ujoint_stations_phase1": 0.4,
                                                        "ujoint_stations_scale2": 6.0, "ujoint_stations_phase2": 2.0}),
                  experiment)[0]
    same = runs(stations, alike, experiment)[0]
    k2 = column(concept, "Omega_U2")
    assert np.max(np.abs(turned[:, k2] - same[:, k2])) > 1e-3 * np.max(np.abs(same[:, k2]))
    with pytest.raises(EffectError, match="same coupling"):
        base.with_effects(["ujoint_kinematics", "ujoint_stations"])
