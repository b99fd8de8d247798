"""The independent record generator of the gap self-check (ema_uq/gap/variants.py)."""
from __future__ import annotations

import ast
import inspect
import math

import numpy as np
import pytest

from ema_uq.experiments import deploy_retract, validation
from ema_uq.gap import variants as V
from ema_uq.models import get_model
from ema_uq.simulate import simulate_batch

N_SAMPLES = 3800  # deploy-retract
VISIBLE = 2.0 * math.sqrt(2.0 * N_SAMPLES)  # twice the chi-square's pure-noise spread


def test_module_uses_no_package_equations():
    tree = ast.parse(inspect.getsource(V))
    imported = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            imported.add(node.module or "")
            imported.update(f"{node.module}.{a.name}" for a in node.names)
        elif isinstance(node, ast.Import):
            imported.update(a.name for a in node.names)
    forbidden = ("simulate", "effect_kernels", "components", "htls", "lths", "effects")
    assert not [m for m in imported if any(part in forbidden for part in m.split("."))], imported


@pytest.mark.parametrize("concept", ["htls", "lths"])
def test_nominal_matches_the_package_simulator(concept):
    model = get_model(concept)
    assert set(V.KERNEL_OUTPUTS[concept]) == set(model.outputs)
    theta = model.parameters.nominal * np.linspace(0.93, 1.07, len(model.parameters))
    for experiment in (deploy_retract(), validation()):
        ours = V.simulate_variant(concept, experiment, theta)
        package = simulate_batch(model, theta, experiment.time, experiment.input_matrix(model), integrator="rk4")
        span = np.ptp(package, axis=0)
        assert np.all(np.abs(ours - package) <= 1e-4 * np.where(span > 0, span, 1.0))


@pytest.fixture(scope="module")
def nominal_outputs():
    experiment = deploy_retract()
    out = {}
    for concept in ("htls", "lths"):
        model = get_model(concept)
        index = [model.outputs.index(ch) for ch in V.REALISTIC_CHANNELS[concept]]
        out[concept] = (index, V.simulate_variant(concept, experiment)[:, index])
    return experiment, out


@pytest.mark.parametrize("name", list(V.VARIANTS))
def test_every_variant_is_visible_at_its_weakest(name, nominal_outputs):
    experiment, nominal = nominal_outputs
    variant = V.VARIANTS[name]
    for concept in ("htls", "lths"):
        index, clean = nominal[concept]
        varied = V.simulate_variant(concept, experiment, None, name, variant.weakest(concept))[:, index]
        assert np.all(np.isfinite(varied))
        sigma = 0.02 * np.sqrt(np.mean(clean ** 2, axis=0))
        excess = np.sum(((varied - clean) / sigma) ** 2, axis=0)
        assert excess.max() > VISIBLE, f"{concept} {name}: chi-square excess {excess.max():.0f} <= {VISIBLE:.0f}"


def test_families_and_descriptions():
    assert {v.family for v in V.VARIANTS.values()} - {None} == set(V.FAMILIES)
    assert sum(v.family is None for v in V.VARIANTS.values()) >= 3
    assert {v.family for v in V.VARIANTS.values() if v.name.startswith("backlash")} == {"backlash"}
    for v in V.VARIANTS.values():
        assert v.description
        for p in v.parameters:
            for concept in ("htls", "lths"):
                low, high = p.draw_range(concept)
                if p.kind == "magnitude":
                    assert p.lower <= low < high <= p.upper, (v.name, p.name)


def test_draws_follow_their_ranges():
    rng = np.random.default_rng(7)
    for name, variant in V.VARIANTS.items():
        for _ in range(20):
            values = V.draw_variant_parameters(name, rng, "lths")
            assert list(values) == list(variant.parameter_names)
            for p in variant.parameters:
                low, high = p.draw_range("lths")
                assert low <= values[p.name] <= high
            if variant.family == "sensor_delay":
                lag = values["tau"] / 0.01
                assert abs(lag - round(lag)) >= V.DELAY_CLEARANCE
    log_taus = np.log([V.draw_variant_parameters("sensor_delay_hermite", rng)["tau"] for _ in range(400)])
    assert abs(np.median(log_taus) - np.log(math.sqrt(0.006 * 0.035))) < 0.15  # log-uniform, not uniform
    with pytest.raises(ValueError, match="concept"):
        V.draw_variant_parameters("torque_ripple_harmonics", rng)


def test_records_reproduce_from_their_seed():
    name = "load_friction_power"
    params = V.draw_variant_parameters(name, np.random.default_rng(3))
    first = V.make_records("htls", name, params, seed=11, channels="realistic")
    again = V.make_records("htls", name, params, seed=11, channels="realistic")
    other = V.make_records("htls", name, params, seed=12, channels="realistic")
    for a, b, c in zip(first[:3], again[:3], other[:3]):
        assert a.channels == V.REALISTIC_CHANNELS["htls"]
        np.testing.assert_array_equal(a.values, b.values)
        assert not np.array_equal(a.values, c.values)
        assert "variant" not in a.attrs and "family" not in a.attrs
    assert first[3] == again[3]
    truth = first[3]
    assert truth["family"] == truth["expected"] == "load_dependent_friction"
    assert truth["parameters"] == params and truth["seed"] == 11
    assert truth["experiments"] == ["deploy-retract", "validation", "validation-scaled"]
    base = get_model("htls").parameters
    for p in base:
        spread = V.RIG_PERTURBATION if p.prior_std is not None else 0.10
        assert abs(truth["base_parameters"][p.name] / p.nominal - 1.0) <= spread
    assert V.make_records("htls", None, None, seed=1, channels=["y1"])[3]["expected"] == "none"
    assert V.make_records("htls", "motor_torque_lag", {"tau": 0.01}, seed=1, channels=["y1"])[3]["expected"] \
        == "unexplained"


@pytest.mark.parametrize("call, message", [
    (lambda: V.make_records("htls", "backlash_gears", {}, seed=0), "unknown variant"),
    (lambda: V.make_records("htls", "motor_torque_lag", {"tau": -1.0}, seed=0), "outside"),
    (lambda: V.make_records("htls", "motor_torque_lag", {"tau": 0.01, "gain": 1.0}, seed=0), "no parameter"),
    (lambda: V.make_records("htls", "motor_torque_lag", {}, seed=0), "needs a value"),
    (lambda: V.make_records("htls", "motor_torque_lag", {"tau": "fast"}, seed=0), "not a number"),
    (lambda: V.make_records("htls", None, {"tau": 0.01}, seed=0), "without a variant"),
    (lambda: V.make_records("emps", None, None, seed=0), "unknown concept"),
    (lambda: V.make_records("htls", None, None, seed=0, channels=["Omega", "U_A"]), "unknown channel"),
    (lambda: V.draw_variant_parameters("nope", np.random.default_rng(0)), "unknown variant"),
])
def test_bad_input_is_a_one_line_error(call, message):
    with pytest.raises(ValueError, match=message) as info:
        call()
    assert "\n" not in str(info.value)


def test_fractional_delays():
    dt, tau = 0.01, 0.0237
    t = np.arange(0.0, 4.0, dt)
    slow = np.column_stack([np.sin(2 * np.pi * 0.5 * t), 3.0 + t])
    late = t >= 0.5
    for delay in (V.delay_hermite, V.delay_allpass):
        out = delay(slow, tau, dt)
        np.testing.assert_allclose(out[late, 0], np.sin(2 * np.pi * 0.5 * (t[late] - tau)), atol=2e-3)
        np.testing.assert_allclose(out[late, 1], 3.0 + t[late] - tau, atol=1e-6 if delay is V.delay_hermite else 1e-3)
        assert out[0, 1] == 3.0
    for lag, order in ((0.4, 1), (2.37, 2), (2.9, 3)):
        a = V.thiran_coefficients(lag, order)
        assert np.all(np.abs(np.roots(a)) < 1.0)  # a stable all-pass
