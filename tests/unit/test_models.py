"""The two concept models against docs/MODEL_SPEC.md, and the compiled simulator against an
independent scipy reference (tests/reference_scipy.py).

Expected values of the hand-computed states are written out from the spec formulas and the
spec's nominal tables, not read from the package. Relative errors of trajectories are per
channel: max |difference| over the run divided by max |value| of that channel.
"""
from __future__ import annotations

import math

import numpy as np
import pytest

from ema_uq import deploy_retract, get_model, simulate_batch
from ema_uq.models import htls, lths
from reference_scipy import OUTPUTS, RHS, reference_simulate

DEG = math.pi / 180.0
EPS = 0.05  # rad/s, nominal omega_eps

#: Accuracy targets of the lead's brief (relative, per channel, whole deploy-retract run).
STEP_HALVING_TOL = 1e-6
REFERENCE_TOL = 1e-5

# --- docs/MODEL_SPEC.md nominal tables, typed in from the spec ---------------------------------
STATION_LOSSES = {"B_TS1": 0.40, "C_TS1": 1.20, "B_U1": 0.10, "C_U1": 0.30,
                  "B_TS2": 0.44, "C_TS2": 1.35, "B_U2": 0.09, "C_U2": 0.33}
SPEC_HTLS = {"J": 0.05, "k_n": 1.2, "B_TP1": 0.20, "C_TP1": 0.60, "B_TP2": 0.22, "C_TP2": 0.55,
             "p_ACE": 2000.0, "p_PCE": 10.0, **STATION_LOSSES}
SPEC_LTHS = {"J": 4e-4, "k_n": 0.08, "B_TP1": 0.05, "C_TP1": 0.30, "B_TP2": 0.11, "C_TP2": 0.28,
             "B_MG": 0.01, "C_MG": 0.40, "R_A": 0.3, "L_A": 1e-3, "k_s": 0.08,
             "p_ACE": 35000.0, "p_PCE": 0.08, **STATION_LOSSES}
COMMON_CONSTANTS = {"r": 0.016, "gamma": 4 * DEG, "beta1": 3 * DEG, "beta2": 5 * DEG,
                    "k_y": 0.3 / (40 * DEG), "M_Bmax": 100.0, "K_b": 1.0, "Omega_half": 1.0,
                    "omega_eps": EPS}
SPEC_HTLS_CONSTANTS = {"i_TP1": 2.0, "i_TP2": 2.0, "M_min": -80.0, "M_max": 80.0, **COMMON_CONSTANTS}
SPEC_LTHS_CONSTANTS = {"i_MG": 20.0, "i_BG1": 2.0, "i_BG2": 1.0, "i_TP2": 2.0, "U_max": 135.0,
                       "D_IS": 0.0, **COMMON_CONSTANTS}

K_Y = 0.3 / (40 * DEG)
SG, CG, TG = math.sin(4 * DEG), math.cos(4 * DEG), math.tan(4 * DEG)
CB1, CB2 = math.cos(3 * DEG), math.cos(5 * DEG)
LEAD = 0.016 * TG  # m/rad, carriage travel per screw radian (eq. 12)


def s(v):
    return math.tanh(v / EPS)


def brake_magnitude(v):
    """Eq. 3 with M_Bmax = 100 N m, K_b = 1, Omega_half = 1 rad/s."""
    return 100.0 - 0.5 * 100.0 * (1.0 - math.exp(-abs(v) / 1.0))


def evaluate(concept, x, u, constants=None):
    """Call the package's compiled right-hand side at nominal parameters: (dx, outputs by name)."""
    model = get_model(concept)
    module = htls if concept == "htls" else lths
    dx = np.full(model.n_states, np.nan)
    y = np.full(model.n_outputs, np.nan)
    c = model.kernel_constants(model.constants_vector(constants))
    module.evaluate(np.asarray(x, float), np.asarray(u, float), model.parameters.nominal, c, dx, y)
    assert np.all(np.isfinite(dx)) and np.all(np.isfinite(y)), "evaluate left entries unset"
    return dx, dict(zip(model.outputs, y))


def check(actual: dict, expected: dict, rtol=1e-12, atol=1e-12):
    for name, value in expected.items():
        assert actual[name] == pytest.approx(value, rel=rtol, abs=atol), name


def rel_error(a, b):
    """(n_outputs,) max |a - b| per channel over max |b| per channel."""
    return np.abs(a - b).max(axis=0) / np.abs(b).max(axis=0)


# --- layouts and nominal values -------------------------------------------------------
@pytest.mark.parametrize("concept, params, consts", [("htls", SPEC_HTLS, SPEC_HTLS_CONSTANTS),
                                                     ("lths", SPEC_LTHS, SPEC_LTHS_CONSTANTS)])
def test_nominal_values_and_layout_match_spec(concept, params, consts):
    model = get_model(concept)
    assert model.outputs == OUTPUTS[concept]
    assert set(model.parameters.names) == set(params)
    assert len(model.parameters) == (16 if concept == "htls" else 21)
    for name, value in params.items():
        assert model.parameters[name].nominal == pytest.approx(value, rel=1e-15), name
    assert set(model.constants.names) == set(consts)
    for name, value in consts.items():
        assert model.constants[name].nominal == pytest.approx(value, rel=1e-15, abs=0), name
    for k in (1, 2):  # effect_kernels.stations reads station k's losses from the position of B_TSk on
        first = model.parameters.index(f"B_TS{k}")
        assert [model.parameters.index(f"{n}{k}") for n in ("C_TS", "B_U", "C_U")] == [first + 1, first + 2, first + 3]


# --- HT/LS at hand-computed states ------------------------------------------------------
def htls_expected(omega, y1, y2, phi_r, f1, f2, m_n):
    """Every HT/LS output and derivative from eqs. 4-15, 36 for a given motor torque m_n."""
    w = omega / 2.0  # Omega_TP = Omega_U, i_TP = 2, g_U = 1
    m_er1, m_er2 = -0.016 * f1 * SG * CG, -0.016 * f2 * SG * CG
    m_tser1 = 0.40 * w + 1.20 * s(w) + m_er1
    m_tser2 = 0.44 * w + 1.35 * s(w) + m_er2
    m_uer1 = m_tser1 / CB1 + 0.10 * w + 0.30 * s(w)
    m_uer2 = m_tser2 / CB2 + 0.09 * w + 0.33 * s(w)
    m_tper1 = m_uer1 / 2.0 + 0.20 * w + 0.60 * s(w)
    m_tper2 = m_uer2 / 2.0 + 0.22 * w + 0.55 * s(w)
    outputs = {"Omega": omega, "y1": y1, "y2": y2, "I_A": m_n / 1.2,
               "Omega_TP1": w, "Omega_TP2": w, "Omega_U1": w, "Omega_U2": w,
               "M_ER1": m_er1, "M_ER2": m_er2, "M_TSER1": m_tser1, "M_TSER2": m_tser2,
               "M_UER1": m_uer1, "M_UER2": m_uer2, "M_TPER1": m_tper1, "M_TPER2": m_tper2}
    dx = [(m_n - m_tper1 - m_tper2) / 0.05, LEAD * w, LEAD * w, omega]
    return dx, outputs


def htls_command(omega, y1, y2, phi_r):
    """Unclipped motor torque p_PCE (p_ACE (k_y phi_r - y_s) - Omega) [N m] (eqs. 32-35)."""
    return 10.0 * (2000.0 * (K_Y * phi_r - 0.5 * (y1 + y2)) - omega)


@pytest.mark.parametrize("phi_r, regime", [(0.045, "linear"), (0.06, "upper limit"), (-0.05, "lower limit")])
def test_htls_relations_at_hand_computed_state(phi_r, regime):
    omega, y1, y2, theta, f1, f2 = 12.3, 0.01, 0.012, 0.7, -8000.0, -6500.0
    command = htls_command(omega, y1, y2, phi_r)
    m_n = {"linear": command, "upper limit": 80.0, "lower limit": -80.0}[regime]
    if regime == "linear":
        assert abs(command) < 80.0
    else:
        assert abs(command) > 80.0 and math.copysign(1, command) == math.copysign(1, m_n)
    dx, y = evaluate("htls", [omega, y1, y2, theta], [phi_r, f1, f2, 0.0])
    dx_exp, y_exp = htls_expected(omega, y1, y2, phi_r, f1, f2, m_n)
    check(y, y_exp)
    np.testing.assert_allclose(dx, dx_exp, rtol=1e-12, atol=1e-12)


def test_htls_theta_feeds_nothing():
    u = [0.045, -8000.0, -6500.0, 0.0]
    dx_a, y_a = evaluate("htls", [12.3, 0.01, 0.012, 0.7], u)
    dx_b, y_b = evaluate("htls", [12.3, 0.01, 0.012, 123.4], u)
    assert np.array_equal(dx_a, dx_b) and y_a == y_b
    assert dx_a[3] == 12.3


@pytest.mark.parametrize("concept", ["htls", "lths"])
def test_eq13_sign_convention(concept):
    """F_ER < 0 (load opposing extension) gives M_ER > 0, which decelerates an extending motor."""
    x = [12.3, 0.01, 0.012, 0.0] if concept == "htls" else [5.0, 300.0, 0.01, 0.012, 0.0]
    i_omega = 0 if concept == "htls" else 1
    dx_0, y_0 = evaluate(concept, x, [0.045, 0.0, 0.0, 0.0])
    dx_load, y_load = evaluate(concept, x, [0.045, -8000.0, -6500.0, 0.0])
    dx_aid, y_aid = evaluate(concept, x, [0.045, 8000.0, 6500.0, 0.0])
    assert y_0["M_ER1"] == 0.0 and y_0["M_ER2"] == 0.0
    assert y_load["M_ER1"] == pytest.approx(0.016 * 8000.0 * SG * CG, rel=1e-14) and y_load["M_ER1"] > 0
    assert y_aid["M_ER2"] == pytest.approx(-0.016 * 6500.0 * SG * CG, rel=1e-14)
    assert dx_load[i_omega] < dx_0[i_omega] < dx_aid[i_omega]


@pytest.mark.parametrize("omega", [12.3, 0.7, -0.7])
@pytest.mark.parametrize("b", [1.0, 0.5])
def test_htls_brake(omega, b):
    """Eq. 3 brakes act against motion, scaled by the brake input: M_B1 on the motor shaft,
    M_B2k inside M_TPERk at the bevel-gear output speed Omega_TPk (where the spec adds them)."""
    x, u = [omega, 0.01, 0.012, 0.0], [0.045, -8000.0, -6500.0, 0.0]
    dx_0, y_0 = evaluate("htls", x, u)
    dx_b, y_b = evaluate("htls", x, u[:3] + [b])
    w = omega / 2.0
    m_b2 = b * brake_magnitude(w) * s(w)
    m_b1 = b * brake_magnitude(omega) * s(omega)
    assert math.copysign(1, m_b1) == math.copysign(1, omega)  # against motion
    assert y_b["M_TPER1"] - y_0["M_TPER1"] == pytest.approx(m_b2, rel=1e-12)
    assert y_b["M_TPER2"] - y_0["M_TPER2"] == pytest.approx(m_b2, rel=1e-12)
    assert dx_b[0] - dx_0[0] == pytest.approx(-(m_b1 + 2 * m_b2) / 0.05, rel=1e-10)
    untouched = [k for k in y_0 if k not in ("M_TPER1", "M_TPER2")]
    assert all(y_b[k] == y_0[k] for k in untouched)
    assert np.array_equal(dx_b[1:], dx_0[1:])


# --- LT/HS at hand-computed states ------------------------------------------------------
def lths_expected(i_a, omega, y1, y2, theta, f1, f2, u_a, d_is=0.0):
    """Every LT/HS output and derivative from eqs. 16-31, 39 for a given armature voltage."""
    w_mg = omega / 20.0
    w_tp1 = w_mg / 2.0
    w_mg2 = w_mg / 1.0
    w_tp2 = w_mg2 / 2.0
    m_er1, m_er2 = -0.016 * f1 * SG * CG, -0.016 * f2 * SG * CG
    m_tser1 = 0.40 * w_tp1 + 1.20 * s(w_tp1) + m_er1
    m_tser2 = 0.44 * w_tp2 + 1.35 * s(w_tp2) + m_er2
    m_uer1 = m_tser1 / CB1 + 0.10 * w_tp1 + 0.30 * s(w_tp1)
    m_uer2 = m_tser2 / CB2 + 0.09 * w_tp2 + 0.33 * s(w_tp2)
    m_mg2 = m_uer2 / 2.0 + 0.11 * w_tp2 + 0.28 * s(w_tp2)
    m_tper = m_uer1 / 2.0 + m_mg2 / 1.0 + 0.05 * w_tp1 + 0.30 * s(w_tp1)
    m_iser = m_tper + d_is * theta / 20.0  # eq. 22 with theta_MG = theta / i_MG
    m_mger = m_iser / 20.0 + 0.01 * w_mg + 0.40 * s(w_mg)
    outputs = {"Omega": omega, "y1": y1, "y2": y2, "I_A": i_a, "U_A": u_a,
               "Omega_MG": w_mg, "Omega_TP1": w_tp1, "Omega_MG2": w_mg2, "Omega_TP2": w_tp2,
               "Omega_U1": w_tp1, "Omega_U2": w_tp2, "M_ER1": m_er1, "M_ER2": m_er2,
               "M_TSER1": m_tser1, "M_TSER2": m_tser2, "M_UER1": m_uer1, "M_UER2": m_uer2,
               "M_MG2": m_mg2, "M_TPER": m_tper, "M_MGER": m_mger}
    dx = [(-0.3 * i_a - 0.08 * omega + u_a) / 1e-3, (0.08 * i_a - m_mger) / 4e-4,
          LEAD * w_tp1, LEAD * w_tp2, omega]
    return dx, outputs


@pytest.mark.parametrize("y_r, regime", [(0.020, "linear"), (0.030, "upper limit"), (0.0, "lower limit")])
def test_lths_relations_at_hand_computed_state(y_r, regime):
    i_a, omega, y1, y2, theta, f1, f2 = 5.0, 300.0, 0.01, 0.012, 3.0, -8000.0, -6500.0
    phi_r = y_r / K_Y
    command = (0.08 / 0.08) * (35000.0 * (y_r - 0.011) - omega)  # eq. 41 before clipping
    u_a = {"linear": command, "upper limit": 135.0, "lower limit": -135.0}[regime]
    if regime == "linear":
        assert command == pytest.approx(15.0) and abs(command) < 135.0
    else:
        assert abs(command) > 135.0 and math.copysign(1, command) == math.copysign(1, u_a)
    dx, y = evaluate("lths", [i_a, omega, y1, y2, theta], [phi_r, f1, f2, 0.0])
    dx_exp, y_exp = lths_expected(i_a, omega, y1, y2, theta, f1, f2, u_a)
    check(y, y_exp)
    np.testing.assert_allclose(dx, dx_exp, rtol=1e-12, atol=1e-9)


def test_lths_shaft_stiffness_uses_angle():
    """Ambiguity 6: D_IS multiplies theta_MG = theta / i_MG (zero nominal, so theta feeds nothing)."""
    x, u = [5.0, 300.0, 0.01, 0.012, 3.0], [0.020 / K_Y, -8000.0, -6500.0, 0.0]
    dx_0, y_0 = evaluate("lths", x, u)
    dx_far, y_far = evaluate("lths", x[:4] + [-50.0], u)
    assert np.array_equal(dx_0[:4], dx_far[:4]) and y_0 == y_far
    dx_d, y_d = evaluate("lths", x, u, constants={"D_IS": 2.5})
    dx_exp, y_exp = lths_expected(*x, -8000.0, -6500.0, 15.0, d_is=2.5)
    check(y_d, y_exp)
    np.testing.assert_allclose(dx_d, dx_exp, rtol=1e-12, atol=1e-9)
    assert y_d["M_MGER"] - y_0["M_MGER"] == pytest.approx(2.5 * 3.0 / 20.0 / 20.0, rel=1e-9)


@pytest.mark.parametrize("omega", [300.0, 14.0, -14.0])
def test_lths_brake(omega):
    """Brakes M_B2 (in M_TPER, at Omega_TP1) and M_B22 (in M_MG2, at Omega_TP2); eq. 18 has
    no motor brake. They act against motion and scale with the brake input."""
    x, u = [5.0, omega, 0.01, 0.012, 0.0], [0.020 / K_Y, -8000.0, -6500.0, 0.0]
    dx_0, y_0 = evaluate("lths", x, u)
    dx_b, y_b = evaluate("lths", x, u[:3] + [0.5])
    w_tp1 = w_tp2 = omega / 40.0
    m_b22 = 0.5 * brake_magnitude(w_tp2) * s(w_tp2)
    m_b2 = 0.5 * brake_magnitude(w_tp1) * s(w_tp1)
    assert math.copysign(1, m_b2) == math.copysign(1, omega)
    assert y_b["M_MG2"] - y_0["M_MG2"] == pytest.approx(m_b22, rel=1e-12)
    assert y_b["M_TPER"] - y_0["M_TPER"] == pytest.approx(m_b2 + m_b22, rel=1e-12)
    assert y_b["M_MGER"] - y_0["M_MGER"] == pytest.approx((m_b2 + m_b22) / 20.0, rel=1e-10)
    assert dx_b[1] - dx_0[1] == pytest.approx(-(m_b2 + m_b22) / 20.0 / 4e-4, rel=1e-9)
    assert dx_b[0] == dx_0[0]


@pytest.mark.parametrize("concept", ["htls", "lths"])
def test_rhs_matches_reference_at_random_states(concept):
    """Package right-hand side vs reference_scipy at random states, brake inputs and D_IS."""
    model = get_model(concept)
    module = htls if concept == "htls" else lths
    rng = np.random.default_rng(7)
    scale = [30.0, 0.1, 0.1, 50.0] if concept == "htls" else [20.0, 900.0, 0.1, 0.1, 50.0]
    th, c = model.parameters.nominal, model.constants.nominal
    th_d, c_d = model.parameters.as_dict(th), model.constants.as_dict(c)
    c = model.kernel_constants(c)
    if concept == "lths":
        c_d["D_IS"] = 1.7
        c = model.kernel_constants(model.constants_vector({"D_IS": 1.7}))
    dx, y = np.empty(model.n_states), np.empty(model.n_outputs)
    for _ in range(200):
        x = rng.normal(size=model.n_states) * scale
        u = [rng.uniform(-0.1, 0.7), rng.uniform(-3e4, 1e4), rng.uniform(-3e4, 1e4), rng.choice([0.0, 0.3, 1.0])]
        module.evaluate(x, np.array(u), th, c, dx, y)
        dx_ref, y_ref = RHS[concept](x, u, th_d, c_d)
        np.testing.assert_allclose(dx, dx_ref, rtol=1e-12, atol=1e-12 * np.abs(dx_ref).max())
        np.testing.assert_allclose(y, y_ref, rtol=1e-12, atol=1e-12 * np.abs(y_ref).max())


# --- trajectories -----------------------------------------------------------------------
@pytest.fixture(scope="module")
def experiment():
    return deploy_retract()


@pytest.fixture(scope="module")
def nominal_runs(experiment):
    """Nominal deploy-retract outputs at the default step, per concept: (n_samples, n_outputs)."""
    return {c: simulate_batch(c, get_model(c).parameters.nominal, experiment.time,
                              experiment.input_matrix()) for c in ("htls", "lths")}


@pytest.mark.parametrize("concept", ["htls", "lths"])
def test_batch_equals_single_bit_for_bit(concept, experiment):
    model = get_model(concept)
    rng = np.random.default_rng(11)
    thetas = model.parameters.nominal * rng.uniform(0.8, 1.2, size=(5, len(model.parameters)))
    inputs = experiment.input_matrix()
    batch = simulate_batch(model, thetas, experiment.time, inputs)
    assert batch.shape == (5, experiment.n_samples, model.n_outputs)
    for i in range(5):
        assert np.array_equal(batch[i], simulate_batch(model, thetas[i], experiment.time, inputs)), i
    assert not np.array_equal(batch[0], batch[1])  # the sets really differ


@pytest.mark.parametrize("concept", ["htls", "lths"])
def test_the_contract_step_stays_far_under_the_noise(concept, experiment):
    """``converged_step`` (the model contract's RK4 step, which the gap diagnosis fits at) moves
    no output by more than 5e-5 of its range: under 1/400 of the 2 % noise."""
    model = get_model(concept)
    assert model.integration_step < model.converged_step
    fine, contract = (simulate_batch(model, model.parameters.nominal, experiment.time, experiment.input_matrix(),
                                     integrator="rk4", step=step)
                      for step in (model.integration_step, model.converged_step))
    span = np.ptp(fine, axis=0)
    err = np.max(np.abs(contract - fine), axis=0) / span
    worst = model.outputs[int(np.argmax(err))]
    assert err.max() < 5e-5, f"{concept}: the contract step changes {worst} by {err.max():.2e}"
    assert err.max() > 0.0                       # the two steps really ran


@pytest.mark.parametrize("concept", ["htls", "lths"])
def test_halving_the_step_changes_little(concept, experiment):
    """The fixed-step RK4 alternative at its converged step."""
    model = get_model(concept)
    full, half = (simulate_batch(model, model.parameters.nominal, experiment.time, experiment.input_matrix(),
                                 integrator="rk4", step=step)
                  for step in (model.integration_step, model.integration_step / 2))
    err = rel_error(full, half)
    worst = int(np.argmax(err))
    assert err.max() < STEP_HALVING_TOL, (
        f"{concept}: halving the step {model.integration_step:g} s changes {model.outputs[worst]} "
        f"by {err.max():.2e} (relative), tolerance {STEP_HALVING_TOL:g}")


@pytest.mark.parametrize("method", ["dopri5", "hybrid"])
@pytest.mark.parametrize("concept", ["htls", "lths"])
def test_halving_the_tolerance_changes_little(concept, method, experiment):
    """The adaptive integrators at the concept's tolerance; a 100x looser one must show a change
    (the tolerance really steers the steps)."""
    model = get_model(concept)
    base, tighter, looser = (simulate_batch(model, model.parameters.nominal, experiment.time,
                                            experiment.input_matrix(), integrator=method, rtol=rtol)
                             for rtol in (model.rtol, model.rtol / 2, model.rtol * 100))
    err = rel_error(base, tighter)
    worst = int(np.argmax(err))
    assert err.max() < STEP_HALVING_TOL, (
        f"{concept}: halving rtol {model.rtol:g} changes {model.outputs[worst]} "
        f"by {err.max():.2e} (relative), tolerance {STEP_HALVING_TOL:g}")
    assert rel_error(base, looser).max() > 10 * err.max()


def test_unknown_integrator_is_a_one_line_error(experiment):
    with pytest.raises(ValueError, match="unknown integrator 'euler'; choose one of dopri5, hybrid, rk4"):
        simulate_batch("htls", get_model("htls").parameters.nominal, experiment.time, experiment.input_matrix(),
                       integrator="euler")


@pytest.mark.parametrize("integrator", ["rk4", "dopri5", "hybrid"])
@pytest.mark.parametrize("concept, effects", [("htls", ()), ("lths", ("backlash",))])
def test_a_model_with_an_unknown_kernel_id_is_refused(concept, effects, integrator, experiment):
    """An id no compiled kernel knows is refused before the kernel runs (the dispatch once ran
    LT/HS for any id but HT/LS's)."""
    import dataclasses

    from ema_uq.simulate import SimulationError

    model = dataclasses.replace(get_model(concept).with_effects(effects), model_id=7)
    with pytest.raises(SimulationError, match=r"^model '\w+' has kernel id 7, which no compiled kernel knows "
                                              r"\(known: 0, 1, 100, 101\); .*KERNEL_IDS$"):
        simulate_batch(model, model.parameters.nominal, experiment.time, experiment.input_matrix(model),
                       integrator=integrator)


def test_every_concept_is_registered_with_its_own_kernel_ids():
    from ema_uq.models import KERNEL_IDS, concepts

    assert concepts() == tuple(sorted(KERNEL_IDS))
    ids = [i for pair in KERNEL_IDS.values() for i in pair if i is not None]
    assert len(ids) == len(set(ids))
    for name, (nominal, augmented) in KERNEL_IDS.items():
        model = get_model(name)
        assert model.name == name and model.model_id == nominal
        if augmented is not None:
            assert model.with_effects(model.available_effects[:1]).model_id == augmented


@pytest.mark.parametrize("concept", ["htls", "lths"])
def test_simulator_matches_scipy_reference(concept, experiment, nominal_runs):
    """Full deploy-retract run against DOP853 (rtol 1e-10) of the independent reference, for
    both integrators (the concept's default is ``nominal_runs``)."""
    model = get_model(concept)
    ref = reference_simulate(concept, model.parameters.as_dict(model.parameters.nominal),
                             model.constants.as_dict(model.constants.nominal),
                             experiment.time, experiment.input_matrix())
    for method in ("dopri5", "hybrid", "rk4"):
        run = (nominal_runs[concept] if method == model.integrator else
               simulate_batch(model, model.parameters.nominal, experiment.time, experiment.input_matrix(),
                              integrator=method))
        err = rel_error(run, ref)
        worst = int(np.argmax(err))
        assert err.max() < REFERENCE_TOL, (
            f"{concept} {method}: {model.outputs[worst]} differs from the scipy reference by {err.max():.2e} "
            f"(relative), tolerance {REFERENCE_TOL:g}")


@pytest.mark.parametrize("concept, peak_extend, peak_retract",
                         [("htls", 33.0, -47.0), ("lths", 670.0, -935.0)])
def test_reference_figures(concept, peak_extend, peak_retract, experiment, nominal_runs):
    out = nominal_runs[concept]
    omega = out[:, 0]
    assert omega.max() == pytest.approx(peak_extend, rel=0.03)
    assert omega.min() == pytest.approx(peak_retract, rel=0.03)
    lag = K_Y * experiment.inputs["phi_r"] - 0.5 * (out[:, 1] + out[:, 2])
    ramp = (experiment.time >= 5.0) & (experiment.time < 9.0)  # steady part of the first deploy
    assert np.all((lag[ramp] > 0.015) & (lag[ramp] < 0.03)), (lag[ramp].min(), lag[ramp].max())


@pytest.mark.parametrize("concept", ["htls", "lths"])
def test_results_converge_as_omega_eps_shrinks(concept, experiment):
    """Changes between eps, eps/2, eps/4 must shrink (RMS over the run, worst channel)."""
    model = get_model(concept)
    runs = []
    for eps, step in ((0.05, None), (0.025, None), (0.0125, model.integration_step / 2)):
        consts = model.constants_vector({"omega_eps": eps})
        runs.append(simulate_batch(model, model.parameters.nominal, experiment.time,
                                   experiment.input_matrix(), constants=consts, step=step))
    rms = np.sqrt(np.mean(runs[0] ** 2, axis=0))
    first = (np.sqrt(np.mean((runs[0] - runs[1]) ** 2, axis=0)) / rms).max()
    second = (np.sqrt(np.mean((runs[1] - runs[2]) ** 2, axis=0)) / rms).max()
    assert first < 0.01  # omega_eps = 0.05 is already close to the limit
    assert second < 0.9 * first, (first, second)
    assert rel_error(runs[1], runs[2]).max() < rel_error(runs[0], runs[1]).max()


# --- shared step sequences (finite differences with the adaptive integrator) -------------
@pytest.mark.parametrize("method", ["dopri5", "hybrid"])
@pytest.mark.parametrize("concept", ["htls", "lths"])
def test_shared_steps_keep_the_leading_set_and_make_differences_smooth(concept, method, experiment):
    model = get_model(concept)
    theta = model.parameters.nominal
    j = model.parameters.index("B_TS1")
    rel = np.array([0.0, 1e-5, 1e-7, 0.0])          # the leader, two perturbed sets, the leader again
    thetas = theta[None] * np.ones((4, 1))
    thetas[:, j] *= 1.0 + rel
    time, inputs = experiment.time, experiment.input_matrix(model)
    shared = simulate_batch(model, thetas, time, inputs, integrator=method, share_steps=True)
    alone = simulate_batch(model, thetas, time, inputs, integrator=method)
    # the leader is the same run as without sharing, and a replay of the leader repeats it bit for bit
    np.testing.assert_array_equal(shared[0], alone[0])
    np.testing.assert_array_equal(shared[3], shared[0])
    # difference quotients at a 1e-5 relative step against a fine fixed-step reference: along
    # one step sequence only the scheme's own error remains (HT/LS 1.4 % at rtol 5e-8, from a
    # coarse step across a reversal; LT/HS 1e-4); independent step choices add noise that
    # swamps the difference on LT/HS
    fine = simulate_batch(model, thetas[:2], time, inputs, step=model.integration_step / 4)
    k = model.outputs.index("Omega")
    dh = rel[1] * theta[j]
    reference = (fine[1, :, k] - fine[0, :, k]) / dh

    def error(out):
        return np.abs((out[1, :, k] - out[0, :, k]) / dh - reference).max() / np.abs(reference).max()

    assert error(shared) < 0.05
    if concept == "lths" and method == "dopri5":
        assert error(alone) > 0.5 > 100 * error(shared)


def test_shared_steps_grow_their_record_when_a_run_needs_more_steps(experiment, monkeypatch):
    import importlib

    sim = importlib.import_module("ema_uq.simulate")

    model = get_model("htls")
    thetas = np.repeat(model.parameters.nominal[None], 2, axis=0)
    thetas[1, 0] *= 1.001
    time, inputs = experiment.time, experiment.input_matrix(model)
    expected = simulate_batch(model, thetas, time, inputs, integrator="dopri5", share_steps=True)
    calls = []
    kernel = sim._dopri_batch_shared

    def tiny_record(*args):
        steps = args[-2]
        calls.append(steps.size)
        return kernel(*args[:-2], steps[: max(1, steps.size // 1000)] if len(calls) == 1 else steps, args[-1])

    monkeypatch.setattr(sim, "_dopri_batch_shared", tiny_record)
    np.testing.assert_array_equal(simulate_batch(model, thetas, time, inputs, integrator="dopri5", share_steps=True),
                                  expected)
    assert len(calls) == 2 and calls[1] > calls[0]


def test_written_out_dormand_prince_coefficients_match_the_tableau():
    """The kernel spells the Butcher tableau and error weights out as literals (for speed);
    they must equal DP_A / DP_E, the tableau as published."""
    import importlib

    sim = importlib.import_module("ema_uq.simulate")
    rng = np.random.default_rng(3)
    x, k, h = rng.standard_normal(5), rng.standard_normal((7, 5)), 0.37
    xt = np.empty(5)
    for s in range(1, 7):
        sim._dp_stage_state(x, k, s, h, xt)
        np.testing.assert_allclose(xt, x + h * sim.DP_A[s, :s] @ k[:s], rtol=1e-14, atol=1e-14)
    xn, scale, rtol = x + 0.1, np.array([1.0, 0.0, 2.0, 0.5, 3.0]), 1e-6
    want = h * sim.DP_E @ k / (rtol * (scale + np.maximum(np.abs(x), np.abs(xn))))
    assert sim._dp_error(x, xn, k, h, rtol, scale) == pytest.approx(np.sqrt(np.mean(want[scale > 0] ** 2)), rel=1e-12)


# --- the hybrid integrator: exact steps over the linear regime -----------------------------
MODULES = {"htls": htls, "lths": lths}


def random_parameters(concept, seed, spread=0.3):
    model = get_model(concept)
    rng = np.random.default_rng(seed)
    return model.parameters.nominal * rng.uniform(1 - spread, 1 + spread, len(model.parameters))


def moving_state(concept, th, omega, speed_error, i_a=0.0):
    """A state turning at ``omega`` whose carriages lag the reference ``phi_r = 0.3`` rad so
    that the position loop asks for ``omega + speed_error``: the controller output stays small."""
    model = get_model(concept)
    p_ace = th[model.parameters.index("p_ACE")]
    y_s = K_Y * 0.3 - (omega + speed_error) / p_ace
    x = np.zeros(model.n_states)
    x[model.states.index("Omega")] = omega
    x[model.states.index("y1")] = y_s + 1e-4
    x[model.states.index("y2")] = y_s - 1e-4
    x[model.states.index("theta")] = 123.0
    if concept == "lths":
        x[model.states.index("I_A")] = i_a
    return x


def rhs(concept, x, u, th, c):
    model = get_model(concept)
    dx, y = np.empty(model.n_states), np.empty(model.n_outputs)
    MODULES[concept].evaluate(np.asarray(x, float), np.asarray(u, float), th, c, dx, y)
    return dx


@pytest.mark.parametrize("concept", ["htls", "lths"])
def test_the_model_is_affine_with_the_state_matrix_in_its_linear_regime(concept):
    """f(x2) - f(x1) = A (x2 - x1) for states in the regime, random parameters and loads
    (and a non-zero input-shaft spring on LT/HS, the one entry that couples the angle)."""
    model = get_model(concept)
    module = MODULES[concept]
    rng = np.random.default_rng(21)
    c = model.kernel_constants(model.constants_vector({"D_IS": 1.7} if concept == "lths" else None))
    omega = 30.0 if concept == "htls" else 600.0
    for trial in range(20):
        th = random_parameters(concept, trial)
        a = np.empty((model.n_states, model.n_states))
        module.linear_state_matrix(th, c, a)
        u = np.array([0.3, rng.uniform(-3e4, 1e4), rng.uniform(-3e4, 1e4), 0.0])
        sign = rng.choice([-1.0, 1.0])
        x1 = moving_state(concept, th, sign * omega, rng.normal() * 0.5, i_a=rng.normal() * 5)
        x2 = moving_state(concept, th, sign * omega * rng.uniform(0.7, 1.3), rng.normal() * 0.5, i_a=rng.normal() * 5)
        x2[model.states.index("theta")] += rng.normal() * 50
        for x in (x1, x2):
            assert module.linear_regime(x, rhs(concept, x, u, th, c), u, th, c, 0.0), (trial, x)
        df = rhs(concept, x2, u, th, c) - rhs(concept, x1, u, th, c)
        np.testing.assert_allclose(df, a @ (x2 - x1), rtol=1e-9, atol=1e-9 * np.abs(df).max())


@pytest.mark.parametrize("concept", ["htls", "lths"])
def test_the_linear_regime_excludes_brake_slow_shafts_limits_and_crossings_ahead(concept):
    from ema_uq.models.components import LINEAR_REGIME_MARGIN, SIGN_SATURATED_ARGUMENT

    # the threshold is where tanh becomes exactly ±1 in double precision
    assert math.tanh(SIGN_SATURATED_ARGUMENT) == 1.0 and math.tanh(19.0) < 1.0
    model = get_model(concept)
    module = MODULES[concept]
    th = model.parameters.nominal
    c = model.kernel_constants()
    slowest = 2.0 if concept == "htls" else 40.0                      # motor turns per bevel-gear turn
    omega_min = LINEAR_REGIME_MARGIN * SIGN_SATURATED_ARGUMENT * EPS * slowest
    u = np.array([0.3, 1000.0, 1000.0, 0.0])

    def inside(x, u=u, delta=0.0, dx=None):
        return module.linear_regime(x, rhs(concept, x, u, th, c) if dx is None else dx, u, th, c, delta)

    assert inside(moving_state(concept, th, 1.01 * omega_min, 0.0))
    assert not inside(moving_state(concept, th, 0.99 * omega_min, 0.0))              # a sign not yet saturated
    assert not inside(moving_state(concept, th, -0.99 * omega_min, 0.0))
    assert not inside(moving_state(concept, th, 30.0 * slowest, 0.0), u=u + [0, 0, 0, 0.5])  # brake applied
    limit = 80.0 / 10.0 if concept == "htls" else 135.0 / (0.08 / 0.08)  # speed error that saturates
    assert inside(moving_state(concept, th, 30.0 * slowest, 0.9 * limit))
    assert not inside(moving_state(concept, th, 30.0 * slowest, 1.1 * limit))      # controller limit
    assert not inside(moving_state(concept, th, 30.0 * slowest, -1.1 * limit))
    # the tangent test: decelerating fast enough to reach the threshold within delta
    x = moving_state(concept, th, 2.0 * omega_min, 0.0)
    dx = rhs(concept, x, u, th, c)
    k = model.states.index("Omega")
    dx[k] = -omega_min / 1e-3
    assert inside(x, delta=0.9e-3, dx=dx) and not inside(x, delta=1.1e-3, dx=dx)


@pytest.mark.parametrize("concept", ["htls", "lths"])
def test_exact_step_propagators_match_the_matrix_exponential(concept):
    """Φ(t) = e^{At} and Γ(t) = ∫_0^t e^{As} ds at the checked points, against scipy's expm of
    the augmented matrix [[A, I], [0, 0]]."""
    import importlib

    from scipy.linalg import expm

    sim = importlib.import_module("ema_uq.simulate")
    model = get_model(concept)
    c = model.kernel_constants(model.constants_vector({"D_IS": 1.7} if concept == "lths" else None))
    n = model.n_states
    for seed in range(3):
        th = random_parameters(concept, seed)
        a = np.empty((n, n))
        MODULES[concept].linear_state_matrix(th, c, a)
        delta = 0.01 / sim.ZOH_CHECKS
        props = sim._zoh_propagators(a, delta, sim.ZOH_CHECKS)
        augmented = np.zeros((2 * n, 2 * n))
        augmented[:n, :n], augmented[:n, n:] = a, np.eye(n)
        for p in range(sim.ZOH_CHECKS):
            e = expm(augmented * delta * (p + 1))
            for got, want in ((props[p, 0], e[:n, :n]), (props[p, 1], e[:n, n:])):
                assert np.abs(got - want).max() < 1e-12 * np.abs(want).max(), (seed, p)


@pytest.mark.parametrize("concept", ["htls", "lths"])
def test_hybrid_steps_most_intervals_exactly_at_the_accuracy_of_dopri5(concept):
    """Random parameter sets on both experiments (and a soft input-shaft spring on LT/HS): against
    Dormand-Prince at a 100x tighter tolerance the hybrid integrator is as accurate as plain
    Dormand-Prince, while at least 70 % of the intervals take the exact step."""
    from ema_uq.experiments import validation
    from ema_uq.simulate import step_statistics

    model = get_model(concept)
    consts = model.constants_vector({"D_IS": 0.2} if concept == "lths" else None)
    thetas = np.array([random_parameters(concept, seed) for seed in range(6)])
    for ex in (deploy_retract(), validation()):
        time, inputs = ex.time, ex.input_matrix(model)
        reference = simulate_batch(model, thetas, time, inputs, constants=consts, integrator="dopri5",
                                   rtol=model.rtol / 100)
        errors = {}
        for method in ("dopri5", "hybrid"):
            out = simulate_batch(model, thetas, time, inputs, constants=consts, integrator=method)
            errors[method] = np.array([rel_error(out[i], reference[i]).max() for i in range(len(thetas))])
        assert np.all(errors["hybrid"] <= 2.0 * errors["dopri5"] + 1e-7), (ex.name, errors)
        for theta in thetas[:2]:
            stats = step_statistics(model, theta, time, inputs, constants=consts)
            assert stats.exact_intervals >= 0.7 * stats.intervals, (ex.name, stats.summary())
            plain = step_statistics(model, theta, time, inputs, constants=consts, integrator="dopri5")
            assert plain.exact_intervals == 0 and stats.evaluations < plain.evaluations / 4


def test_hybrid_equals_dopri5_where_the_model_is_never_linear(experiment):
    """With the brake applied throughout, no interval is exact: the two integrators are one."""
    model = get_model("htls")
    inputs = experiment.input_matrix(model).copy()
    inputs[:, 3] = 0.2
    runs = [simulate_batch(model, model.parameters.nominal, experiment.time, inputs, integrator=m)
            for m in ("dopri5", "hybrid")]
    np.testing.assert_array_equal(runs[0], runs[1])


def test_step_statistics_refuse_what_they_cannot_count(experiment):
    from ema_uq.simulate import step_statistics

    with pytest.raises(ValueError, match="step statistics need an adaptive integrator"):
        step_statistics("htls", get_model("htls").parameters.nominal, experiment.time, experiment.input_matrix(),
                        integrator="rk4")


def test_dormand_prince_stability_radius_and_the_hybrid_step_cap():
    """The boundary of |R(z)| <= 1 of the 5th-order solution (3.307 on the negative real axis,
    3.40 at 120 degrees), and the cap on LT/HS: its current-speed mode (|lambda| ~ 466 /s at
    109 degrees) allows Dormand-Prince steps up to ~6.3 ms, HT/LS (~200 /s, real) 15 ms."""
    import importlib

    sim = importlib.import_module("ema_uq.simulate")

    def stability(z):
        return abs(1 + z + z**2 / 2 + z**3 / 6 + z**4 / 24 + z**5 / 120 + z**6 / 600)

    for degrees, radius in ((180.0, 3.3066), (120.0, 3.3990)):
        angle = math.radians(degrees)
        r = sim._dp_stability_radius(angle)
        assert r == pytest.approx(radius, abs=2e-4)
        assert stability(0.999 * r * complex(math.cos(angle), math.sin(angle))) <= 1.0
        assert stability(1.001 * r * complex(math.cos(angle), math.sin(angle))) > 1.0
    caps = {c: sim.stable_steps(get_model(c), get_model(c).parameters.nominal)[0] for c in ("htls", "lths")}
    assert caps["lths"] == pytest.approx(6.3e-3, rel=0.03)
    assert caps["htls"] == pytest.approx(0.9 * 3.3066 / 200.0, rel=0.05)
    assert sim._dp_stable_steps(np.zeros((1, 2), dtype=complex))[0] == np.inf       # nothing decays: no cap
    model = get_model("lths")
    thetas = np.repeat(model.parameters.nominal[None], 2, axis=0)
    thetas[1, model.parameters.index("J")] = 1e-310                                  # overflowing entries
    assert sim.stable_steps(model, thetas)[1] == np.inf


def test_a_non_finite_parameter_is_a_one_line_error(experiment):
    model = get_model("htls")
    thetas = np.repeat(model.parameters.nominal[None], 2, axis=0)
    thetas[1, model.parameters.index("B_U2")] = np.inf
    with pytest.raises(ValueError, match=r"parameter set 1 has B_U2 = inf; every parameter value must be a finite number"):
        simulate_batch(model, thetas, experiment.time, experiment.input_matrix(), integrator="hybrid")


def test_a_diverging_run_ends_in_nan_on_every_integrator(experiment):
    """An unstable current loop (negative inductance) overflows after ~2 s: every integrator
    returns NaN from the same sample on. The adaptive ones once retried ever shorter steps
    forever on a NaN error norm; a finite-difference batch led by a diverged set is all NaN."""
    from ema_uq.simulate import step_statistics

    model = get_model("lths")
    theta = model.parameters.nominal.copy()
    theta[model.parameters.index("L_A")] = -1e-3
    time, inputs = experiment.time, experiment.input_matrix(model)
    first_nan = {}
    for method in ("rk4", "dopri5", "hybrid"):
        out = simulate_batch(model, theta, time, inputs, integrator=method)
        bad = np.isnan(out).any(axis=1)
        first_nan[method] = int(np.argmax(bad))
        assert 0 < first_nan[method] < 400 and bad[first_nan[method]:].all(), method
        assert np.isfinite(out[:first_nan[method]]).all()
    assert len(set(first_nan.values())) == 1, first_nan
    shared = simulate_batch(model, np.vstack([theta, theta * 1.0001]), time, inputs, integrator="hybrid",
                            share_steps=True)
    assert np.isnan(shared[1]).all() and np.array_equal(np.isnan(shared[0]).any(axis=1), bad)
    with pytest.raises(ValueError, match="the trajectory left the finite numbers"):
        step_statistics(model, theta, time, inputs)
    # the augmented models' adaptive kernel has the same guard
    augmented = model.with_effects(["backlash"])
    theta_aug = augmented.parameters.nominal.copy()
    theta_aug[augmented.parameters.index("L_A")] = -1e-3
    out = simulate_batch(augmented, theta_aug, time, inputs, integrator="dopri5")
    assert np.isnan(out[-1]).all() and np.isfinite(out[0]).all()
