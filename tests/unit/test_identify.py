"""ML identification: det R objective, NaN handling, joint fits, GN/LM convergence, step
halving, bad input, Cramér-Rao bounds, FIT.json and the ``identify`` verb.

Everything runs on HT/LS with 2 % noise; the expensive full fits (16 parameters, all
channels) are module fixtures shared by several tests.
"""
from __future__ import annotations

import dataclasses
import json
import subprocess
import sys

import numpy as np
import pytest

from ema_uq import Measurement, ParameterError, deploy_retract, get_model, io, simulate_batch, synthesize, validation
from ema_uq.identify import FitProblem, FitResult, IdentificationError, Settings, covariance, estimate, perturbed_start
from ema_uq.identify import estimators as est

MEASURED = ("Omega", "y1", "y2", "I_A")


@pytest.fixture(scope="module")
def model():
    return get_model("htls")


@pytest.fixture(scope="module")
def truth(model):
    return model.parameters.nominal


@pytest.fixture(scope="module")
def data():
    return synthesize("htls", deploy_retract(), noise=0.02, seed=1)


@pytest.fixture(scope="module")
def short():
    """First 5 s of deploy-retract: 1 s at rest, then deploying (cheap, and the motor moves)."""
    return synthesize("htls", deploy_retract().slice(0, 500), noise=0.02, seed=1)


@pytest.fixture(scope="module")
def problem(data):
    return FitProblem([data])


@pytest.fixture(scope="module")
def start(model, truth):
    return perturbed_start(model.parameters, 0.3, seed=3, around=truth)


@pytest.fixture(scope="module")
def gn_fit(problem, start):
    return estimate(problem, method="gn", start=start, seed=3)


@pytest.fixture(scope="module")
def lm_fit(problem, start):
    return estimate(problem, method="lm", start=start, seed=3)


def objective_at(problem: FitProblem, theta: np.ndarray) -> float:
    return problem.objective(problem.residuals(theta[None])[0], theta[problem.free_index])[0]


def hand_objective(residuals: np.ndarray, prior: float = 0.0) -> float:
    """(N/2) log det R + prior, with R summed sample by sample."""
    n, c = residuals.shape
    r = np.zeros((c, c))
    for e in residuals:
        r += np.outer(e, e)
    r /= n
    return 0.5 * n * np.log(np.linalg.det(r)) + prior


def with_values(m: Measurement, values: np.ndarray, experiment=None) -> Measurement:
    return Measurement(m.concept, experiment or m.experiment, m.channels, values, m.attrs)


# --------------------------------------------------------------------------------------
# objective
# --------------------------------------------------------------------------------------
def test_covariance_and_objective_match_a_hand_computation(model, short, truth):
    channels = ("Omega", "y1", "I_A")
    params = model.parameters.freeing_only(["J", "k_n", "p_ACE"])
    problem = FitProblem([short], parameters=params, channels=channels)
    theta = truth.copy()
    theta[params.index("J")] *= 1.1
    theta[params.index("p_ACE")] *= 1.05  # off the rig value: the pseudo-measurement term is non-zero

    y = simulate_batch(model, theta, short.time, short.experiment.input_matrix(model))
    e = short.select(channels).values - y[:, model.output_index(channels)]
    np.testing.assert_allclose(problem.residuals(theta[None])[0], e, rtol=0, atol=1e-12)
    assert problem.n_samples == 500

    r_hand = sum(np.outer(ek, ek) for ek in e) / e.shape[0]
    np.testing.assert_allclose(covariance(e), r_hand, rtol=1e-12)
    batch = np.stack([e, 2 * e])
    np.testing.assert_allclose(covariance(batch), np.stack([r_hand, 4 * r_hand]), rtol=1e-12)

    p_ace = params["p_ACE"]
    prior = 0.5 * ((theta[params.index("p_ACE")] - p_ace.nominal) / p_ace.prior_std) ** 2
    assert prior == pytest.approx(0.5 * 2.5 ** 2)
    v, logdet = problem.objective(e, theta[problem.free_index])
    assert logdet == pytest.approx(np.log(np.linalg.det(r_hand)), rel=1e-12)
    assert v == pytest.approx(hand_objective(e, prior), rel=1e-12)

    # a pseudo-measurement of a FIXED parameter does not enter the objective
    fixed = FitProblem([short], parameters=model.parameters.freeing_only(["J", "k_n"]), channels=channels)
    assert fixed.objective(e, theta[fixed.free_index])[0] == pytest.approx(hand_objective(e), rel=1e-12)


# --------------------------------------------------------------------------------------
# missing samples
# --------------------------------------------------------------------------------------
def test_nan_samples_are_skipped(model, data, truth):
    values = data.values.copy()
    rng = np.random.default_rng(0)
    values[100:150, data.channels.index("Omega")] = np.nan
    values[rng.choice(3800, 200, replace=False), data.channels.index("I_A")] = np.nan
    values[3000:3010, :] = np.nan
    complete = np.flatnonzero(np.all(np.isfinite(values), axis=1))
    holed = with_values(data, values)

    problem = FitProblem([holed])
    assert problem.n_samples == complete.size < 3800
    assert problem.observed.shape == (complete.size, 16) and np.all(np.isfinite(problem.observed))

    # the NaN-free data restricted to the same rows gives the same residuals and objective
    theta = truth * 1.05
    clean = FitProblem([data]).residuals(theta[None])[0][complete]
    e = problem.residuals(theta[None])[0]
    np.testing.assert_array_equal(e, clean)
    gains = [model.parameters.index(n) for n in ("p_ACE", "p_PCE")]
    prior = 0.5 * np.sum(((theta[gains] - truth[gains]) / (0.02 * truth[gains])) ** 2)
    assert problem.objective(e, theta[problem.free_index])[0] == pytest.approx(hand_objective(clean, prior), rel=1e-10)

    # missing tail samples equal a shorter experiment without NaN
    tail = data.values.copy()
    tail[3700:, :2] = np.nan
    cut = with_values(data, data.values[:3700], data.experiment.slice(0, 3700))
    a, b = FitProblem([with_values(data, tail)]), FitProblem([cut])
    assert a.n_samples == b.n_samples == 3700
    assert objective_at(a, theta) == pytest.approx(objective_at(b, theta), rel=1e-12)

    params = model.parameters.freeing_only(["J", "B_TS1", "C_TS1", "k_n"])
    fit = estimate(FitProblem([holed], parameters=params), start=perturbed_start(params, 0.3, seed=2, around=truth))
    assert fit.converged and fit.n_samples == complete.size
    free = params.free_index
    assert np.all(np.isfinite(fit.std[free])) and np.all(np.abs(fit.estimate[free] - truth[free]) < 4 * fit.std[free])


# --------------------------------------------------------------------------------------
# joint fit
# --------------------------------------------------------------------------------------
def test_joint_fit_of_two_experiments(model, data, truth):
    values = synthesize("htls", validation(), noise=0.02, seed=2).values
    values[10:20, 0] = np.nan
    val = Measurement("htls", validation(), data.channels, values)
    params = model.parameters.freeing_only(["J", "B_TS1", "C_TS1", "k_n", "p_PCE"])
    single, second = FitProblem([data], parameters=params), FitProblem([val], parameters=params)
    joint = FitProblem([data, val], parameters=params)
    assert single.n_samples == 3800 and second.n_samples == 3990
    assert joint.n_samples == 3800 + 3990
    assert joint.predict(truth[None]).shape == (1, 7790, 16)

    # R of the joint fit pools the samples of both: N R = N1 R1 + N2 R2
    theta = truth * 0.97
    e1, e2 = single.residuals(theta[None])[0], second.residuals(theta[None])[0]
    k = params.index("p_PCE")
    prior = 0.5 * ((theta[k] - truth[k]) / (0.02 * truth[k])) ** 2
    assert objective_at(joint, theta) == pytest.approx(hand_objective(np.concatenate([e1, e2]), prior), rel=1e-10)

    start = perturbed_start(params, 0.3, seed=4, around=truth)
    fit = estimate(joint, start=start)
    alone = estimate(single, start=start)
    assert fit.converged and fit.n_samples == 7790
    assert fit.objective <= objective_at(joint, truth)
    free = params.free_index
    assert np.all(fit.std[free] < alone.std[free])  # the second experiment adds information


# --------------------------------------------------------------------------------------
# convergence of GN and LM
# --------------------------------------------------------------------------------------
def test_gn_and_lm_converge_from_a_perturbed_start(model, problem, truth, start, gn_fit, lm_fit):
    free = problem.free_index
    assert np.all(np.abs(start[free] / truth[free] - 1) <= 0.3) and np.any(np.abs(start[free] / truth[free] - 1) > 0.2)
    at_truth = objective_at(problem, truth)
    for fit in (gn_fit, lm_fit):
        assert fit.converged, fit.message
        assert fit.objective <= at_truth
        assert np.all(np.isfinite(fit.std[free])) and np.all(fit.std[free] > 0)
        assert np.all(np.abs(fit.estimate[free] - truth[free]) < 4.5 * fit.std[free])
    # both reach the same minimum
    assert np.max(np.abs(gn_fit.estimate[free] - lm_fit.estimate[free]) / gn_fit.std[free]) < 0.1 * 0.1
    assert gn_fit.objective == pytest.approx(lm_fit.objective, abs=1e-3)


def test_gn_history_decreases_and_stops_by_the_relative_change_rule(problem, gn_fit):
    h = gn_fit.history
    assert [e["iteration"] for e in h] == list(range(gn_fit.iterations + 1))
    v = np.array([e["objective"] for e in h])
    assert np.all(np.diff(v) < 0)
    # J = det R times the pseudo-measurement factor exp(2 prior / N), so that V = (N/2) log J
    j = np.exp(2.0 * v / problem.n_samples)
    change = np.abs((j[1:] - j[:-1]) / j[1:])
    np.testing.assert_allclose([e["relative_change"] for e in h[1:]], change, rtol=1e-6)
    assert change[-1] < 1e-5 and np.all(change[:-1] >= 1e-5), change
    assert "< 1e-05" in gn_fit.message
    # the recorded cost is det R at the recorded parameters
    r = covariance(problem.residuals(gn_fit.estimate[None])[0])
    assert h[-1]["cost"] == pytest.approx(np.linalg.det(r), rel=1e-8)
    assert gn_fit.cost == pytest.approx(h[-1]["cost"])
    assert h[-1]["n_simulations"] <= gn_fit.n_simulations


def test_lm_history_records_lambda(lm_fit):
    lams = np.array([e["lambda"] for e in lm_fit.history[1:]])
    assert lams.size == lm_fit.iterations >= 2
    assert np.all(np.isfinite(lams)) and np.all(lams > 0)
    # λ moves only by powers of ν = 10, and relaxes towards Gauss-Newton near the minimum
    powers = np.log10(lams[1:] / lams[:-1])
    np.testing.assert_allclose(powers, np.round(powers), atol=1e-9)
    assert lams[-1] < lams[0]
    assert all("increases" in e for e in lm_fit.history[1:])


# --------------------------------------------------------------------------------------
# step halving
# --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def far(model, data, truth):
    """J and k_n free, started at 3x their truth: the first full GN step overshoots."""
    params = model.parameters.freeing_only(["J", "k_n"])
    start = truth.copy()
    start[params.free_index] *= 3.0
    return FitProblem([data], parameters=params), start


def test_step_halving_in_a_fit(far, truth):
    problem, start = far
    fit = estimate(problem, start=start)
    halvings = [e["halvings"] for e in fit.history[1:]]
    assert halvings[0] >= 1, halvings
    for e in fit.history[1:]:
        assert e["step"] == 0.5 ** e["halvings"]
    assert np.all(np.diff([e["objective"] for e in fit.history]) < 0)
    assert fit.converged and fit.objective <= objective_at(problem, truth)


def test_gn_step_halves_an_overshooting_step(far):
    problem, start = far
    counter = est._Counter()
    state = est._evaluate(problem, start[None], counter)[0]
    scale = np.abs(start[problem.free_index])
    info, grad, _ = est._information(problem, state, scale, counter)
    full = problem.full_vectors(state.free - np.linalg.solve(info, grad) * scale, state.theta)
    assert est._evaluate(problem, full, counter)[0].objective >= state.objective  # the full step overshoots

    new, extra = est._gn_step(problem, state, info, grad, scale, Settings(), counter)
    assert extra["halvings"] >= 1 and extra["step"] == 0.5 ** extra["halvings"]
    assert new.objective < state.objective
    np.testing.assert_allclose(new.free, state.free - extra["step"] * np.linalg.solve(info, grad) * scale)

    # no halving allowed: no accepted step; an ascent direction is never accepted
    assert est._gn_step(problem, state, info, grad, scale, Settings(max_halvings=0), counter)[0] is None
    assert est._gn_step(problem, state, info, -grad, scale, Settings(max_halvings=4), counter)[0] is None


# --------------------------------------------------------------------------------------
# bad input
# --------------------------------------------------------------------------------------
def test_mixed_concepts_are_refused(short):
    lths = Measurement("lths", short.experiment, ("Omega",), short["Omega"][:, None])
    with pytest.raises(IdentificationError, match=r"mix concepts \['htls', 'lths'\]"):
        FitProblem([short, lths])


def test_no_usable_channel(short):
    with pytest.raises(IdentificationError, match="no usable channel"):
        FitProblem([short], channels=[])
    a, b = short.select(["Omega"]), short.select(["y1"])
    with pytest.raises(IdentificationError, match="no usable channel"):
        FitProblem([a, b])
    with pytest.raises(IdentificationError, match=r"channel\(s\) I_A missing"):
        FitProblem([short, a], channels=["Omega", "I_A"])


def test_all_nan_channel(short):
    values = short.values.copy()
    values[:, short.channels.index("y2")] = np.nan
    with pytest.raises(IdentificationError, match=r"channel y2 .* no valid sample \(all NaN\)"):
        FitProblem([with_values(short, values)])


def test_start_outside_bounds_names_the_parameter(short, truth):
    problem = FitProblem([short], channels=MEASURED)
    for name, value in (("J", -0.01), ("B_TS1", -0.1)):
        bad = truth.copy()
        bad[problem.parameters.index(name)] = value
        with pytest.raises(ParameterError, match=rf"start value of {name} = .* outside its bounds"):
            estimate(problem, start=bad)


def test_singular_information_names_the_parameters(model, short):
    # k_n only converts the motor torque into I_A
    dead = FitProblem([short], parameters=model.parameters.freeing_only(["J", "k_n"]), channels=("Omega", "y1"))
    with pytest.raises(IdentificationError, match="singular information matrix") as exc:
        estimate(dead)
    assert "k_n" in str(exc.value) and "J" not in str(exc.value)

    # B_TS1 and B_U1 enter the measured channels only as B_TS1/cos(beta1) + B_U1
    collinear = FitProblem([short], parameters=model.parameters.freeing_only(["B_TS1", "B_U1"]), channels=MEASURED)
    with pytest.raises(IdentificationError, match=r"cannot separate the direction .*(B_U1.*B_TS1|B_TS1.*B_U1)"):
        estimate(collinear)


def test_parameter_without_effect_is_named_as_such(model, short):
    """A parameter with exactly zero sensitivity gets the specific advice, not a generic direction."""
    dead = FitProblem([short], parameters=model.parameters.freeing_only(["J", "k_n"]), channels=("Omega", "y1"))
    with pytest.raises(IdentificationError, match="k_n has no effect on the channels Omega, y1; fix it"):
        estimate(dead)


def test_unknown_method(short):
    with pytest.raises(IdentificationError, match="unknown method 'newton'.*gn.*lm"):
        estimate(FitProblem([short]), method="newton")


# --------------------------------------------------------------------------------------
# results, FIT.json and Cramér-Rao bounds
# --------------------------------------------------------------------------------------
def test_fit_result_json_round_trip(gn_fit):
    back = FitResult.from_json(json.loads(json.dumps(gn_fit.to_json())))
    np.testing.assert_array_equal(back.estimate, gn_fit.estimate)
    np.testing.assert_array_equal(back.std, gn_fit.std)
    np.testing.assert_array_equal(back.covariance, gn_fit.covariance)
    np.testing.assert_array_equal(back.free, gn_fit.free)
    assert back.names == gn_fit.names and back.channels == gn_fit.channels
    assert back.converged is gn_fit.converged and back.iterations == gn_fit.iterations
    assert len(back.history) == len(gn_fit.history) and back.log_det_r == gn_fit.log_det_r
    assert back.seed == 3


def test_fit_json_has_the_interface_keys(gn_fit):
    out = gn_fit.to_json()
    for key in ("concept", "method", "converged", "iterations", "cost", "n_simulations", "wall_time_s",
                "parameters", "correlation", "history"):
        assert key in out, key
    assert out["concept"] == "htls" and out["method"] == "gn" and out["converged"] is True
    assert out["cost"] == pytest.approx(np.exp(gn_fit.log_det_r)) and out["n_simulations"] > 0
    assert set(out["parameters"]) == set(gn_fit.names)
    for name, p in out["parameters"].items():
        assert p["std"] > 0 and np.isfinite(p["estimate"]), name
    corr = np.array(out["correlation"], dtype=float)
    assert corr.shape == (16, 16) and np.allclose(np.diag(corr), 1.0) and np.allclose(corr, corr.T)
    assert all({"iteration", "cost"} <= set(e) for e in out["history"])
    assert out["history"][0]["iteration"] == 0 and len(out["history"]) == gn_fit.iterations + 1


def test_high_correlations_are_flagged(model, data, truth):
    # from the measured channels alone, B_TS1 and the speed-loop gain are hard to tell apart
    params = model.parameters.freeing_only(["J", "B_TS1", "C_TS1", "k_n", "p_ACE", "p_PCE"])
    fit = estimate(FitProblem([data], parameters=params, channels=MEASURED),
                   start=perturbed_start(params, 0.3, seed=7, around=truth))
    corr = fit.correlation
    expected = {(a, b) for i, a in enumerate(fit.free_names) for j, b in enumerate(fit.free_names)
                if i < j and abs(corr[i, j]) > 0.9}
    assert ("B_TS1", "p_PCE") in expected
    assert {(a, b) for a, b, _ in fit.high_correlations()} == expected
    flagged = fit.to_json()["high_correlations"]
    assert {(f["a"], f["b"]) for f in flagged} == expected and all(abs(f["rho"]) > 0.9 for f in flagged)
    assert "[[Correlations]]" in fit.summary() and "C(B_TS1, p_PCE)" in fit.summary()


def test_active_bound_is_flagged(model):
    # C_U1 is truly 0; with this noise seed its estimate without the bound is -1.2 σ
    truth = model.parameters.vector({"C_U1": 0.0})
    data = synthesize("htls", deploy_retract(), truth, noise=0.02, seed=4)
    params = model.parameters.freeing_only(["J", "B_U1", "C_U1", "C_TS1", "k_n"])
    start = perturbed_start(params, 0.3, seed=5, around=truth)
    start[params.index("C_U1")] = 0.1
    fit = estimate(FitProblem([data], parameters=params), start=start)
    assert fit.value("C_U1") == 0.0
    assert fit.at_bounds == ["C_U1"]
    assert any("at a bound for C_U1" in w for w in fit.warnings)
    out = fit.to_json()
    assert out["parameters"]["C_U1"]["at_bound"] is True and out["at_bounds"] == ["C_U1"]
    assert not any(p["at_bound"] for n, p in out["parameters"].items() if n != "C_U1")
    assert "(at bound)" in fit.summary()


def test_active_bound_reaches_the_constrained_optimum(model):
    truth = model.parameters.vector({"C_U1": 0.0})
    data = synthesize("htls", deploy_retract(), truth, noise=0.02, seed=3)
    names = ["J", "B_U1", "C_U1", "C_TS1", "k_n"]
    params = model.parameters.with_updates(C_U1={"lower": 0.05}).freeing_only(names)
    start = perturbed_start(params, 0.3, seed=5, around=np.maximum(truth, params.lower))
    start[params.index("C_U1")] = 0.1
    fit = estimate(FitProblem([data], parameters=params), start=start)
    # the same fit with C_U1 held at its bound is the constrained optimum
    held = params.with_updates(C_U1={"nominal": 0.05}).freeing_only([n for n in names if n != "C_U1"])
    start[params.index("C_U1")] = 0.05
    reference = estimate(FitProblem([data], parameters=held), start=start)
    assert fit.value("C_U1") == 0.05
    assert fit.objective <= reference.objective + 0.05


def test_rank_deficient_information_gives_nan_bounds_and_a_warning(model, short, gn_fit, tmp_path):
    problem = FitProblem([short], parameters=model.parameters.freeing_only(["J", "B_TS1", "B_U1"]))
    singular = np.array([[1.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.0, 0.0, 2.0]])
    inv, warnings = est._invert_information(problem, singular)
    assert np.all(np.isnan(inv[:2])) and np.all(np.isnan(inv[:, :2]))
    assert inv[2, 2] == pytest.approx(0.5)
    assert len(warnings) == 1 and "rank-deficient" in warnings[0] and "J, B_TS1" in warnings[0]
    assert "B_U1" not in warnings[0]

    full = np.diag([4.0, 2.0, 1.0]) + 0.1
    inv, warnings = est._invert_information(problem, full)
    np.testing.assert_allclose(inv, np.linalg.inv(full), rtol=1e-12)
    assert warnings == []

    # NaN bounds survive FIT.json as null and read back as NaN
    cov = gn_fit.covariance.copy()
    cov[0, :] = cov[:, 0] = np.nan
    std = gn_fit.std.copy()
    std[0] = np.nan
    nan_fit = dataclasses.replace(gn_fit, covariance=cov, std=std)
    out = nan_fit.to_json()
    assert out["correlation"][0][1] is None and out["correlation"][1][2] is not None
    io.write_json(tmp_path / "FIT.json", out)  # strict JSON: NaN becomes null
    back = FitResult.from_json(io.read_json(tmp_path / "FIT.json"))
    assert np.isnan(back.std[0]) and np.isnan(back.covariance[0, 0])
    np.testing.assert_array_equal(back.std[1:], gn_fit.std[1:])


# --------------------------------------------------------------------------------------
# command line
# --------------------------------------------------------------------------------------
def run_cli(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ema_uq", *map(str, args)],
                          capture_output=True, text=True, timeout=300)


def assert_one_line_error(result: subprocess.CompletedProcess, *fragments: str) -> None:
    assert result.returncode == 2, result.stderr
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("ema-uq: error: "), result.stderr
    for fragment in fragments:
        assert fragment in lines[0], lines[0]


@pytest.fixture(scope="module")
def cli_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("identify")
    for name, experiment, seed in (("dr.nc", "deploy-retract", 1), ("val.csv", "validation", 2)):
        r = run_cli("simulate", "--concept", "htls", "--experiment", experiment, "--seed", seed, "--out", d / name)
        assert r.returncode == 0, r.stderr
    return d


def test_cli_identify_with_validation(cli_files):
    d = cli_files
    out = d / "FIT.json"
    r = run_cli("identify", d / "dr.nc", "--concept", "htls", "--method", "gn", "--perturb", "0.3",
                "--seed", "5", "--validate", d / "val.csv", "--out", out)
    assert r.returncode == 0, r.stderr
    assert len(r.stdout.strip().splitlines()) == 1 and "converged" in r.stdout and "validation" in r.stdout
    fit = json.loads(out.read_text())
    assert fit["concept"] == "htls" and fit["method"] == "gn" and fit["converged"] is True
    assert set(fit["parameters"]) == set(get_model("htls").parameters.names)
    (v,) = fit["validation"]
    assert v["experiment"] == "validation"
    assert set(v["channels"]) == set(fit["channels"]) == set(get_model("htls").outputs)
    for ch, c in v["channels"].items():
        assert 90.0 < c["fit_percent"] <= 100.0, (ch, c)
    assert FitResult.from_json(fit).converged


def test_cli_wrong_concept_data(cli_files):
    d = cli_files
    out = d / "wrong.json"
    r = run_cli("identify", d / "dr.nc", "--concept", "lths", "--out", out)
    assert_one_line_error(r, "holds concept htls", "lths was asked for")
    assert not out.exists()


def test_cli_start_of_another_concept(cli_files):
    d = cli_files
    fit = {"concept": "lths", "method": "gn", "converged": True, "iterations": 1,
           "parameters": {"J": {"estimate": 4e-4, "std": 1e-6}}}
    (d / "lths_fit.json").write_text(json.dumps(fit))
    out = d / "other.json"
    r = run_cli("identify", d / "dr.nc", "--concept", "htls", "--start", d / "lths_fit.json", "--out", out)
    assert_one_line_error(r, "holds a fit of concept lths", "--concept htls")
    assert not out.exists()


def test_a_fit_without_cramer_rao_bounds_reaches_the_same_estimate_for_fewer_runs(problem, start, gn_fit):
    # a problem of its own: on the shared one every run would be served from the first fit's
    bare = estimate(FitProblem(list(problem.measurements)), start=start, settings=Settings(cramer_rao=False))
    np.testing.assert_array_equal(bare.estimate, gn_fit.estimate)
    assert bare.objective == gn_fit.objective
    free = problem.free_index
    assert np.all(np.isnan(bare.std[free])) and np.all(np.isnan(bare.covariance))
    # the central-difference information at the estimate: 2 p runs saved
    assert gn_fit.n_simulations - bare.n_simulations == 2 * free.size
    assert any("not computed" in w for w in bare.warnings)


# --------------------------------------------------------------------------------------
# predictions already simulated are copied, not run again
# --------------------------------------------------------------------------------------
def test_a_repeated_vector_is_served_with_the_same_numbers_and_no_run(short, truth):
    problem = FitProblem([short])
    thetas = np.array([truth, truth * 1.01, truth * 0.99])
    first = problem.predict(thetas[:2])
    assert problem.predictions.runs == 2
    mixed = problem.predict(thetas[[1, 2, 0, 2]])     # two known, one new asked twice
    assert problem.predictions.runs == 3
    fresh = FitProblem([short]).predict(thetas)       # every vector run, in another batch
    np.testing.assert_array_equal(mixed, fresh[[1, 2, 0, 2]])
    np.testing.assert_array_equal(first, fresh[:2])
    mixed[0] = 0.0                                    # the caller owns its result
    np.testing.assert_array_equal(problem.predict(thetas[1]), fresh[1:2])


def test_a_full_memo_drops_its_oldest_vectors_without_losing_a_batch(short, truth, monkeypatch):
    one_row = FitProblem([short]).predict(truth).nbytes
    monkeypatch.setattr("ema_uq.identify.problem.PREDICTION_MEMO_BYTES", 2 * one_row)
    problem = FitProblem([short])
    thetas = truth * np.linspace(0.98, 1.02, 4)[:, None]
    problem.predict(thetas[:2])
    out = problem.predict(thetas)               # storing the two new vectors drops the two known
    np.testing.assert_array_equal(out, FitProblem([short]).predict(thetas))
    assert problem.predictions.runs == 4
    problem.predict(thetas[:1])                 # dropped: run again
    assert problem.predictions.runs == 5


def test_a_fit_reaches_the_same_estimate_with_or_without_the_memo(short, truth, monkeypatch):
    parameters = get_model("htls").parameters.freeing_only(["J", "B_TS1", "C_TS1", "k_n"])
    start = perturbed_start(parameters, 0.2, seed=5, around=truth)
    served = estimate(FitProblem([short], parameters=parameters), start=start)
    monkeypatch.setattr("ema_uq.identify.problem.PREDICTION_MEMO_BYTES", 0)
    unserved_problem = FitProblem([short], parameters=parameters)
    unserved = estimate(unserved_problem, start=start)
    assert unserved_problem.predictions.runs == unserved.n_simulations
    np.testing.assert_array_equal(served.estimate, unserved.estimate)
    np.testing.assert_array_equal(served.std, unserved.std)
    assert served.objective == unserved.objective and served.iterations == unserved.iterations
    # the final central differences repeat the last forward ones (+h) when the last step failed
    assert served.n_simulations <= unserved.n_simulations


def test_the_memo_follows_the_prediction_inputs(short, data, truth):
    problem = FitProblem([short], parameters=get_model("htls").parameters.freeing_only(["J"]))
    problem.predict(truth)
    narrower = dataclasses.replace(problem, parameters=get_model("htls").parameters.freeing_only(["k_n"]))
    assert narrower.predictions is problem.predictions          # same model and data: shared
    other_model = dataclasses.replace(problem, model=dataclasses.replace(problem.model, integrator="dopri5"))
    assert other_model.predictions is not problem.predictions
    other_data = FitProblem([data], predictions=problem.predictions)
    assert other_data.predictions is not problem.predictions
    other_channels = FitProblem([short], channels=("Omega",), predictions=problem.predictions)
    assert other_channels.predictions is not problem.predictions
    # an adaptive batch that shares the first set's steps is run whole, and not kept
    runs = other_model.predictions.runs
    other_model.predict(np.array([truth, truth * 1.01]), share_steps=True)
    other_model.predict(np.array([truth, truth * 1.01]), share_steps=True)
    assert other_model.predictions.runs == runs + 4
