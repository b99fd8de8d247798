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
    from ema_uq.gap import variant_catalogue, variant_kernel

    # the simulator's rooms: the records, the variants' descriptions and the kernel
    tree = ast.Module(body=[node for module in (V, variant_catalogue, variant_kernel)
                            for node in ast.parse(inspect.getsource(module)).body], type_ignores=[])
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


@pytest.mark.parametrize("name", list(V.VARIANTS) + list(V.UNSEEN_VARIANTS) + list(V.UNSEEN_VARIANTS_2)
                         + list(V.UNSEEN_VARIANTS_3))
def test_every_variant_is_visible_at_its_weakest(name, nominal_outputs):
    experiment, nominal = nominal_outputs
    variant = V.get_variant(name)
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
    assert {v.family for v in V.UNSEEN_VARIANTS.values()} - {None} <= set(V.FAMILIES)
    assert not set(V.UNSEEN_VARIANTS) & set(V.VARIANTS)
    second = [v.family for v in V.UNSEEN_VARIANTS_2.values()]
    assert set(second) - {None} <= set(V.FAMILIES) and second.count(None) == 3
    assert len(set(second) - {None}) == 3                                  # at most one form per family
    assert not set(V.UNSEEN_VARIANTS_2) & (set(V.VARIANTS) | set(V.UNSEEN_VARIANTS))
    earlier = {v.kernel_id for v in [*V.VARIANTS.values(), *V.UNSEEN_VARIANTS.values()]}
    assert all(v.kernel_id == 0 or v.kernel_id > max(earlier) for v in V.UNSEEN_VARIANTS_2.values())
    third = [v.family for v in V.UNSEEN_VARIANTS_3.values()]
    assert set(third) - {None} <= set(V.FAMILIES) and third.count(None) == 3 and len(set(third) - {None}) == 3
    assert {"backlash", "shaft_compliance"} <= set(third)             # families no earlier unseen set took
    assert not set(V.UNSEEN_VARIANTS_3) & (set(V.VARIANTS) | set(V.UNSEEN_VARIANTS) | set(V.UNSEEN_VARIANTS_2))
    earlier |= {v.kernel_id for v in V.UNSEEN_VARIANTS_2.values()}
    assert all(v.kernel_id > max(earlier) for v in V.UNSEEN_VARIANTS_3.values())
    assert len({v.kernel_id for v in V.UNSEEN_VARIANTS_3.values()}) == len(V.UNSEEN_VARIANTS_3)
    for v in [*V.VARIANTS.values(), *V.UNSEEN_VARIANTS.values(), *V.UNSEEN_VARIANTS_2.values(),
              *V.UNSEEN_VARIANTS_3.values()]:
        assert v.description
        for p in v.parameters:
            for concept in ("htls", "lths"):
                low, high = p.draw_range(concept)
                if p.kind == "magnitude":
                    assert p.lower <= low < high <= p.upper, (v.name, p.name)


def test_draws_follow_their_ranges():
    rng = np.random.default_rng(7)
    for name, variant in [*V.VARIANTS.items(), *V.UNSEEN_VARIANTS.items(), *V.UNSEEN_VARIANTS_2.items(),
                          *V.UNSEEN_VARIANTS_3.items()]:
        for _ in range(20):
            values = V.draw_variant_parameters(name, rng, "lths")
            assert list(values) == list(variant.parameter_names)
            for p in variant.parameters:
                low, high = p.draw_range("lths")
                assert low <= values[p.name] <= high
            if "tau" in values and variant.family == "sensor_delay":
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


# --------------------------------------------------------------------------------------
# model-form stress of no-effect records
# --------------------------------------------------------------------------------------
def test_stress_draws_stay_in_their_stated_ranges():
    rng = np.random.default_rng(5)
    for concept in ("htls", "lths"):
        names = get_model(concept).constants.names
        for _ in range(30):
            stress = V.draw_stress(concept, rng)
            assert V.STRESS_RANGES["ar1"][0] <= stress["ar1"] <= V.STRESS_RANGES["ar1"][1]
            assert V.STRESS_RANGES["quantisation"][0] <= stress["quantisation"] <= V.STRESS_RANGES["quantisation"][1]
            assert V.STRESS_RANGES["input_filter"][0] <= stress["input_filter"] <= V.STRESS_RANGES["input_filter"][1]
            assert set(stress["constants"]) == {n for n in V.STRESS_CONSTANTS if n in names}
            assert max(abs(v) for v in stress["constants"].values()) <= V.STRESS_RANGES["constant_offset"]
    with pytest.raises(ValueError, match="unknown stress"):
        V.check_stress({"drift": 1.0})
    with pytest.raises(ValueError, match="outside"):
        V.check_stress({"ar1": 1.0})
    with pytest.raises(ValueError, match="no design constant"):
        V.simulate_variant("htls", deploy_retract(), constant_offsets={"i_MG": 0.01})


def test_coloured_noise_has_its_ar1_coefficient_and_white_variance():
    clean = np.full((40000, 2), 3.0)
    noisy = V.coloured_noise(clean, 0.02, 0.7, np.random.default_rng(1))
    e = (noisy - clean) / (0.02 * 3.0)
    for j in range(2):
        assert abs(np.corrcoef(e[:-1, j], e[1:, j])[0, 1] - 0.7) < 0.02
        assert abs(np.std(e[:, j]) - 1.0) < 0.05


def test_stressed_record_shows_quantisation_coloured_noise_offsets_and_command_shaping():
    stress = {"ar1": 0.6, "quantisation": 0.005, "constants": {"i_TP1": 0.03, "r": -0.02}, "input_filter": 0.04}
    est, val, val2, truth = V.make_records("htls", None, None, seed=21, channels="realistic", stress=stress)
    steps = np.array([truth["stress"]["steps"][ch] for ch in est.channels])
    for record in (est, val, val2):                       # every record on the same converter steps
        ratio = record.values / steps
        np.testing.assert_allclose(ratio, np.round(ratio), atol=1e-6)
    model = get_model("htls")
    index = [model.outputs.index(ch) for ch in est.channels]
    clean = V.simulate_variant("htls", deploy_retract(), truth["base_parameters"], constant_offsets=stress["constants"],
                               input_filter=stress["input_filter"])[:, index]
    np.testing.assert_allclose(steps, 0.005 * np.sqrt(np.mean(clean ** 2, axis=0)))
    noise = est.values - clean
    lag1 = [np.corrcoef(noise[:-1, j], noise[1:, j])[0, 1] for j in range(noise.shape[1])]
    assert min(lag1) > 0.5 and max(lag1) < 0.7              # the AR(1) colour (quantisation whitens a little)
    # the offsets and the command shaping are in the records: clean simulation without them differs
    plain = V.simulate_variant("htls", deploy_retract(), truth["base_parameters"])[:, index]
    sigma = 0.02 * np.sqrt(np.mean(plain ** 2, axis=0))
    assert np.max(np.abs(clean - plain) / sigma) > 1.0
    noiseless = V.make_records("htls", None, None, seed=21, channels="realistic", noise=0.0,
                               stress={"constants": stress["constants"], "input_filter": stress["input_filter"]})[0]
    np.testing.assert_allclose(noiseless.values, clean)
    omega = model.outputs.index("Omega")
    geared = V.simulate_variant("htls", deploy_retract(), constant_offsets={"i_TP1": 0.03, "i_TP2": 0.03})[:, omega]
    nominal = V.simulate_variant("htls", deploy_retract())[:, omega]
    assert np.sqrt(np.mean(geared ** 2)) / np.sqrt(np.mean(nominal ** 2)) == pytest.approx(1.03, abs=0.01)


def test_command_shaping_is_a_first_order_lag():
    dt, tau = 0.01, 0.04
    step = np.r_[0.0, np.ones(99)]
    out = V.shape_command(step, tau, dt)
    k = np.arange(100)
    np.testing.assert_allclose(out, np.where(k == 0, 0.0, 1.0 - np.exp(-k * dt / tau)), atol=1e-12)
    np.testing.assert_array_equal(V.shape_command(step, 0.0, dt), step)


# --- the variants written after method version 2 was frozen ---------------------------------
def _outputs(concept, name=None, params=None, experiment=None):
    model = get_model(concept)
    out = V.simulate_variant(concept, experiment or validation(), None, name, params)
    return {ch: out[:, i] for i, ch in enumerate(model.outputs)}


def test_sample_hold_reads_each_channel_at_the_last_sensor_instant():
    dt, period, offset = 0.01, 0.037, 0.4
    ramp = np.column_stack([np.arange(200) * dt, 3.0 - 2.0 * np.arange(200) * dt])
    held = V.sample_hold(ramp, period, offset, dt)
    t = np.arange(200) * dt
    first = offset * period
    last = first + period * np.floor((t - first) / period)
    after = t >= first
    assert np.allclose(held[after, 0], last[after]) and np.allclose(held[after, 1], 3.0 - 2.0 * last[after])
    assert np.all(held[~after] == ramp[0])
    lag = t[after] - last[after]
    assert 0.0 <= lag.min() and lag.max() < period and abs(lag.mean() - period / 2) < 0.1 * period


@pytest.mark.parametrize("concept", ["htls", "lths"])
def test_unseen_variants_reduce_to_their_parents_or_the_nominal_model(concept):
    nominal = _outputs(concept)
    linear = _outputs(concept, "load_friction_linear", {"mu": 0.01})
    assert all(np.array_equal(a, b) for a, b in zip(linear.values(),
                                                     _outputs(concept, "load_friction_efficiency",
                                                              {"mu": 0.01, "aid": 1.0}).values()))
    for name, params in (("friction_warm_up", {"drop": 0.0, "tau": 10.0}),
                         ("position_sensor_nonlinearity", {"amplitude": 0.0, "wavelength": 0.05, "phase1": 1.0,
                                                           "phase2": 2.0}),
                         ("load_force_offset", {"offset": 0.0, "direction": 1.0})):
        assert all(np.array_equal(nominal[ch], v) for ch, v in _outputs(concept, name, params).items()), name


@pytest.mark.parametrize("concept", ["htls", "lths"])
def test_unseen_variants_act_as_described(concept):
    nominal = _outputs(concept)
    # the load aiding the motion costs less friction than the load opposing it
    aided = _outputs(concept, "load_friction_efficiency", {"mu": 0.01, "aid": 0.2})
    full = _outputs(concept, "load_friction_linear", {"mu": 0.01})
    gap_aided = np.abs(aided["I_A"] - nominal["I_A"]).mean()
    assert 0.05 * np.abs(full["I_A"] - nominal["I_A"]).mean() < gap_aided < np.abs(full["I_A"] - nominal["I_A"]).mean()
    # a sensor reads y + A sin(phase) at the carriage's rest position 0
    reading = _outputs(concept, "position_sensor_nonlinearity",
                       {"amplitude": 1e-3, "wavelength": 0.05, "phase1": 0.7, "phase2": 2.0})
    assert reading["y1"][0] == pytest.approx(1e-3 * math.sin(0.7)) and reading["y2"][0] == pytest.approx(1e-3 * math.sin(2.0))
    # a force offset of either sign moves the current the opposite ways
    up = _outputs(concept, "load_force_offset", {"offset": 1000.0, "direction": 1.0})["I_A"] - nominal["I_A"]
    down = _outputs(concept, "load_force_offset", {"offset": 1000.0, "direction": -1.0})["I_A"] - nominal["I_A"]
    assert abs(up.mean()) > 1e-3 and abs(up.mean() + down.mean()) < 0.1 * abs(up.mean())
    # the warm-up lowers the losses more the longer the record runs
    warm = _outputs(concept, "friction_warm_up", {"drop": 0.2, "tau": 5.0})["I_A"] - nominal["I_A"]
    n = len(warm)
    assert np.abs(warm[: n // 8]).mean() < 0.5 * np.abs(warm[-n // 2:]).mean()


def test_asymmetric_stribeck_lowers_the_breakaway_of_the_negative_direction_only():
    from ema_uq.gap.variant_kernel import _coulomb
    from ema_uq.gap.variant_catalogue import V_STRIBECK_ASYMMETRIC

    vv = np.array([2.0, 1.0, 0.3, 0, 0, 0, 0, 0.0])
    eps, level, v = 0.05, 1.5, 0.4
    bump = math.exp(-v * v)
    positive = _coulomb(level, v, eps, V_STRIBECK_ASYMMETRIC, vv)
    negative = _coulomb(level, -v, eps, V_STRIBECK_ASYMMETRIC, vv)
    sign = math.tanh(v / eps)
    share_neg = 0.3 + 0.7 * 0.5 * (1.0 - sign)
    assert positive == pytest.approx(level * (1.0 + 2.0 * (0.3 + 0.7 * 0.5 * (1.0 + sign)) * bump) * sign)
    assert negative == pytest.approx(-level * (1.0 + 2.0 * share_neg * bump) * sign)
    assert abs(negative) < abs(positive)


# --- the variants written for the evaluation of method version 4 (UNSEEN_VARIANTS_2) --------
def test_window_average_is_the_mean_over_the_last_window():
    dt, window = 0.01, 0.037
    t = np.arange(400) * dt
    omega = 2 * np.pi * 0.7
    slow = np.column_stack([np.sin(omega * t), 3.0 - 2.0 * t])
    out = V.window_average(slow, window, dt)
    inside = (t >= window + dt) & (t <= t[-3])
    mean_sine = (np.cos(omega * (t - window)) - np.cos(omega * t)) / (omega * window)
    np.testing.assert_allclose(out[inside, 0], mean_sine[inside], atol=2e-4)
    np.testing.assert_allclose(out[inside, 1], 3.0 - 2.0 * (t[inside] - window / 2), atol=1e-12)  # a ramp: W/2 late
    assert np.all(out[0] == slow[0])                 # held at the first value before t_0
    np.testing.assert_array_equal(V.window_average(slow, 0.0, dt), slow)


@pytest.mark.parametrize("concept", ["htls", "lths"])
def test_second_unseen_variants_reduce_to_the_nominal_model_when_off(concept):
    nominal = _outputs(concept)
    for name, params in (("sensor_delay_window", {"window": 0.0}),
                         ("torque_constant_saturation", {"saturation": 0.0}),
                         ("speed_loop_integral", {"rate": 0.0}),
                         ("speed_feedforward", {"fraction": 0.0})):
        assert all(np.array_equal(nominal[ch], v) for ch, v in _outputs(concept, name, params).items()), name
    # the ripple runs at a finer RK4 step (as the harmonics variant): the nominal model at that step
    step = get_model(concept).integration_step / V.get_variant("torque_ripple_proportional").step_divisor
    fine = V.simulate_variant(concept, validation(), step=step)
    ripple = V.simulate_variant(concept, validation(), None, "torque_ripple_proportional", {"ratio": 0.0, "phase": 1.0})
    np.testing.assert_array_equal(ripple, fine)
    # a straight joint's ratio cos^2 + sin^2 of the yoke angle is 1 to rounding only
    straight = _outputs(concept, "ujoint_swivel", {"beta1": 0.0, "beta2": 0.0, "phase1": 0.3, "phase2": 1.0})
    for ch, v in straight.items():
        np.testing.assert_allclose(v, nominal[ch], rtol=0, atol=1e-12 * max(np.ptp(nominal[ch]), 1.0), err_msg=ch)


@pytest.mark.parametrize("concept", ["htls", "lths"])
def test_second_unseen_variants_act_as_described(concept):
    nominal = _outputs(concept)
    # the swivelling joint's speed ratio stays within cos(beta(y)) .. 1/cos(beta(y)), its ripple
    # small near the retracted end and large out along the stroke
    swivel = _outputs(concept, "ujoint_swivel", {"beta1": 0.3, "beta2": 0.3, "phase1": 0.0, "phase2": 1.0})
    moving = np.abs(swivel["Omega_TP1"]) > 1.0
    ratio = swivel["Omega_U1"][moving] / swivel["Omega_TP1"][moving]
    beta = 0.3 * swivel["y1"][moving] / 0.25
    assert np.all(ratio <= 1.0 / np.cos(beta) + 1e-9) and np.all(ratio >= np.cos(beta) - 1e-9)
    near, far = swivel["y1"][moving] < 0.05, swivel["y1"][moving] > 0.15
    assert np.abs(ratio[near] - 1).max() < 0.1 * np.abs(ratio[far] - 1).max()
    # a PI speed loop shrinks the standing position error at the end of each hold
    constants = dict(zip(get_model(concept).constants.names, get_model(concept).constants.nominal))
    phi = validation().inputs["phi_r"]
    held = np.array([k >= 150 and np.ptp(phi[k - 150:k + 1]) == 0 for k in range(len(phi))])

    def error(out):
        return np.abs(constants["k_y"] * phi - 0.5 * (out["y1"] + out["y2"]))

    pi = _outputs(concept, "speed_loop_integral", {"rate": 2.0})
    assert error(pi)[held].mean() < 0.85 * error(nominal)[held].mean()
    # speed feed-forward halves about the following error while the command moves
    fed = _outputs(concept, "speed_feedforward", {"fraction": 0.5})
    assert error(fed)[~held].mean() < 0.6 * error(nominal)[~held].mean()


def test_proportional_ripple_and_saturation_follow_the_motor_torque_and_current():
    from ema_uq.gap.variant_catalogue import V_RIPPLE, V_RIPPLE_PROPORTIONAL
    from ema_uq.gap.variant_kernel import _ripple, _saturation

    vv = np.array([0.05, 0.4, 6.0, 0, 0, 0, 0, 0.0])
    theta = 0.3
    for torque in (-20.0, 0.0, 7.5):
        expected = 0.05 * torque * math.sin(6 * theta + 0.4)
        assert _ripple(V_RIPPLE_PROPORTIONAL, theta, torque, vv) == pytest.approx(expected)
    assert _ripple(V_RIPPLE_PROPORTIONAL, theta, 0.0, vv) == 0.0        # no torque, no ripple
    assert _ripple(V_RIPPLE, theta, 0.0, np.array([0.1, 0, 0, 0, 0, 0, 6.0, 0])) != 0.0   # cogging has one
    saturation = np.array([0.2, 30.0, 0, 0, 0, 0, 0, 0.0])
    assert _saturation(30.0, saturation) == pytest.approx(1.0 / 1.2)
    assert _saturation(-30.0, saturation) == _saturation(30.0, saturation) and _saturation(0.0, saturation) == 1.0


# --- the variants written for the evaluation of method version 5 (UNSEEN_VARIANTS_3) --------
@pytest.mark.parametrize("concept", ["htls", "lths"])
def test_third_unseen_variants_reduce_to_the_nominal_model_or_their_parent_when_off(concept):
    nominal = _outputs(concept)
    for name, params in (("backlash_worn_screw", {"delta": 0.0, "extent": 0.1}),
                         ("stribeck_dwell", {"ratio": 0.0, "speed": 1.0, "rest_time": 2.0}),
                         ("screw_binding", {"binding": 0.0, "phase": 1.0}),
                         ("speed_sensor_eccentricity", {"amplitude": 0.0, "phase": 1.0}),
                         ("position_loop_deadband", {"width": 0.0})):
        assert all(np.array_equal(nominal[ch], v) for ch, v in _outputs(concept, name, params).items()), name
    # a coupling that does not stiffen is the linear two-mass spring
    mode = {"frequency": 40.0, "damping": 0.1, "load_share": 0.6}
    linear = _outputs(concept, "shaft_compliance_two_mass", mode)
    same = _outputs(concept, "shaft_compliance_progressive", {**mode, "stiffening": 0.0})
    assert all(np.array_equal(linear[ch], v) for ch, v in same.items())


def _chi_square(concept, a, b):
    """Largest rig channel's chi-square between two records at 2 % noise of the nominal model."""
    experiment = deploy_retract()
    model = get_model(concept)
    index = [model.outputs.index(ch) for ch in V.REALISTIC_CHANNELS[concept]]
    sigma = 0.02 * np.sqrt(np.mean(V.simulate_variant(concept, experiment)[:, index] ** 2, axis=0))
    first, second = (V.simulate_variant(concept, experiment, None, *v)[:, index] for v in (a, b))
    return float(np.sum(((first - second) / sigma) ** 2, axis=0).max())


@pytest.mark.parametrize("concept", ["htls", "lths"])
def test_third_unseen_family_forms_are_not_their_catalogue_laws(concept):
    # at its weakest each form shows what sets it apart from the catalogue's law of its family:
    # a stiffening spring, a breakaway that needs time at rest to build up, a play that narrows
    progressive = V.get_variant("shaft_compliance_progressive").weakest(concept)
    assert _chi_square(concept, ("shaft_compliance_progressive", progressive),
                       ("shaft_compliance_progressive", {**progressive, "stiffening": 0.0})) > VISIBLE
    dwell = V.get_variant("stribeck_dwell").weakest(concept)
    assert _chi_square(concept, ("stribeck_dwell", dwell), ("stribeck_dwell", {**dwell, "rest_time": 1e-3})) > VISIBLE
    worn = V.get_variant("backlash_worn_screw").weakest(concept)
    assert _chi_square(concept, ("backlash_worn_screw", worn),
                       ("backlash_worn_screw", {**worn, "extent": 10.0})) > VISIBLE   # ~one width over the stroke


def test_worn_play_narrows_along_the_stroke_and_couplings_stiffen_with_their_twist():
    from ema_uq.gap.variant_kernel import WORN_PLAY_FLOOR, _coupling_torque, _worn_half_play

    vv = np.array([1e-4, 0.1, 0, 0, 0, 0, 0, 0.0])
    assert _worn_half_play(0.0, vv) == pytest.approx(1e-4) and _worn_half_play(-0.01, vv) == pytest.approx(1e-4)
    assert _worn_half_play(0.1, vv) == pytest.approx(1e-4 * (WORN_PLAY_FLOOR + (1 - WORN_PLAY_FLOOR) / math.e))
    assert _worn_half_play(5.0, vv) == pytest.approx(WORN_PLAY_FLOOR * 1e-4)
    stiffness, reference, stiffening = 2000.0, 40.0, 3.0
    twist = reference / stiffness
    hardening = stiffening / twist ** 2
    assert _coupling_torque(twist, 0.0, stiffness, 5.0, 0.0, hardening) == pytest.approx(reference * (1 + stiffening))
    assert _coupling_torque(-0.1 * twist, 0.0, stiffness, 5.0, 0.0, hardening) == pytest.approx(
        -0.1 * reference * (1 + 0.01 * stiffening))


def test_breakaway_builds_up_at_rest_and_sliding_wipes_it_out():
    from ema_uq.gap.variant_catalogue import V_STRIBECK_DWELL
    from ema_uq.gap.variant_kernel import DWELL_SLIDE, S_BREAKAWAY, _breakaway_excess, _breakaway_rate

    vv = np.array([2.0, 1.0, 3.0, 0, 0, 0, 0, 0.0])
    x = np.zeros(11)
    x[S_BREAKAWAY] = 0.25
    assert _breakaway_rate(V_STRIBECK_DWELL, x, 0, 0.0, vv) == pytest.approx(0.75 / 3.0)   # over the rest time
    moving = _breakaway_rate(V_STRIBECK_DWELL, x, 0, 10.0, vv)
    assert moving == pytest.approx((math.exp(-100.0) - 0.25) * (1 / 3.0 + 10.0 / DWELL_SLIDE))
    assert moving < -20 * 0.25 / 3.0                                       # gone within a short slide
    assert _breakaway_excess(V_STRIBECK_DWELL, x, 0, vv) == pytest.approx(1.5)
    assert _breakaway_excess(0, x, 0, vv) == 1.0 and _breakaway_rate(0, x, 0, 0.0, vv) == 0.0


@pytest.mark.parametrize("concept", ["htls", "lths"])
def test_third_unseen_variants_act_as_described(concept):
    nominal = _outputs(concept)
    # each carriage starts on the flank its load (pulling the carriage in) presses it against
    worn = _outputs(concept, "backlash_worn_screw", {"delta": 1e-4, "extent": 0.1})
    assert worn["y1"][0] == pytest.approx(-1e-4) and worn["y2"][0] == pytest.approx(-1e-4)
    # only screw 1 binds: its torque changes, screw 2's hardly
    bound = _outputs(concept, "screw_binding", {"binding": 2.0, "phase": 0.5})
    first = np.abs(bound["M_TSER1"] - nominal["M_TSER1"]).mean()
    assert first > 0.3 and np.abs(bound["M_TSER2"] - nominal["M_TSER2"]).mean() < 0.1 * first
    # the recorded motor speed is the eccentric sensor's: the true speed times 1 + A cos(theta + phi)
    read = _outputs(concept, "speed_sensor_eccentricity", {"amplitude": 0.02, "phase": 0.3})
    true = 2.0 * read["Omega_TP1"] if concept == "htls" else 20.0 * read["Omega_MG"]
    moving = np.abs(true) > 1.0
    ratio = read["Omega"][moving] / true[moving]
    assert np.all(np.abs(ratio - 1.0) <= 0.02 + 1e-9) and ratio.min() < 0.985 and ratio.max() > 1.015
    # a dead band of width w adds about w to every error the position loop settles at
    constants = dict(zip(get_model(concept).constants.names, get_model(concept).constants.nominal))
    phi = validation().inputs["phi_r"]
    held = np.array([k >= 150 and np.ptp(phi[k - 150:k + 1]) == 0 for k in range(len(phi))])

    def error(out):
        return np.abs(constants["k_y"] * phi - 0.5 * (out["y1"] + out["y2"]))

    dead = _outputs(concept, "position_loop_deadband", {"width": 1e-3})
    assert error(dead)[held].mean() - error(nominal)[held].mean() == pytest.approx(1e-3, rel=0.1)


@pytest.mark.parametrize("name", list(V.UNSEEN_VARIANTS_3))
def test_third_unseen_records_differ_from_the_nominal_ones(name):
    for concept in ("htls", "lths"):
        params = V.draw_variant_parameters(name, np.random.default_rng(11), concept)
        varied = V.make_records(concept, name, params, seed=21, channels="realistic")
        plain = V.make_records(concept, None, None, seed=21, channels="realistic")
        assert varied[3]["variant"] == name and varied[3]["expected"] == (V.get_variant(name).family or "unexplained")
        for a, b in zip(varied[:3], plain[:3]):
            assert np.all(np.isfinite(a.values)) and not np.array_equal(a.values, b.values)
