"""Identification and identifiability on the rig's sensors alone (HT/LS: Omega, y1, y2, I_A),
where the station losses act only through their sums referred to the motor shaft: identify
holds the undetermined parameters and reports the identifiable combinations, identifiability
runs at a point before any fit."""
from __future__ import annotations

import json

import numpy as np
import pytest

from ema_uq import cli, io
from ema_uq import identifiability as ident
from ema_uq.experiments import deploy_retract, synthesize
from ema_uq.identify import FitProblem, FitResult, SingularInformationError, estimate, perturbed_start
from ema_uq.models import get_model

RIG = ("Omega", "y1", "y2", "I_A")
FRICTION = [n for n in get_model("htls").parameters.names if n[:2] in ("B_", "C_")]


def _record(seed: int):
    return synthesize("htls", deploy_retract(), noise=0.02, seed=seed, channels=RIG)


@pytest.fixture(scope="module")
def fits():
    """Fits on three noise seeds from perturbed starts, holding what the rig cannot determine."""
    model = get_model("htls")
    out = {}
    for seed in (1, 2, 3):
        problem = FitProblem([_record(seed)], parameters=model.parameters)
        start = perturbed_start(model.parameters, 0.3, seed)
        out[seed] = estimate(problem, start=start, seed=seed, unidentifiable="fix")
    return out


def test_fit_converges_holding_named_parameters(fits):
    fit = fits[1]
    assert fit.converged and fit.unidentifiable == "fix"
    # one loss of each kind stays free to carry its group; the other ten are held at their start
    assert len(fit.fixed) == 10 and set(fit.fixed) < set(FRICTION)
    assert sum(n.startswith("B_") for n in fit.free_names) == 1 and sum(n.startswith("C_") for n in fit.free_names) == 1
    assert {"J", "k_n", "p_ACE", "p_PCE"} < set(fit.free_names)
    for name, row in fit.fixed.items():
        i = fit.names.index(name)
        assert row["value"] == fit.start[i] == fit.estimate[i] and np.isnan(fit.std[i])
        assert row["reason"].startswith(f"null direction +1*{name} ")
    free_std = fit.std[[fit.names.index(n) for n in fit.free_names]]
    assert np.all(np.isfinite(free_std) & (free_std > 0))
    text = fit.summary()
    assert "unidentifiable     = fix (10 held" in text and "[[Identifiable combinations]]" in text


def test_true_combinations_lie_within_three_sigma(fits):
    model = get_model("htls")
    truth = dict(zip(model.parameters.names, model.parameters.nominal))
    for seed, fit in fits.items():
        expressions = sorted(c["expression"] for c in fit.combinations)
        assert expressions == ["B_TS1/cos(beta1) + B_U1 + 2*B_TP1 + B_TS2/cos(beta2) + B_U2 + 2*B_TP2",
                               "C_TS1/cos(beta1) + C_U1 + 2*C_TP1 + C_TS2/cos(beta2) + C_U2 + 2*C_TP2"]
        for c in fit.combinations:
            exact = sum(a * truth[n] for n, a in c["coefficients"].items())
            assert np.isfinite(c["std"]) and 0 < c["relative_std"] < 0.02
            assert abs(c["value"] - exact) < 3 * c["std"], (seed, c["expression"], c["value"], exact, c["std"])


def test_fit_json_carries_the_held_parameters(fits, tmp_path):
    fit = fits[1]
    path = io.write_json(tmp_path / "fit.json", fit.to_json())
    data = json.loads(path.read_text())
    assert data["unidentifiable"]["mode"] == "fix" and "most informative first" in data["unidentifiable"]["rule"]
    name = next(iter(fit.fixed))
    assert data["parameters"][name]["std"] is None and data["parameters"][name]["free"] is False
    assert set(data["fixed"][name]) == {"value", "reason"} and len(data["combinations"]) == 2
    back = FitResult.from_json(data)
    assert back.fixed == fit.fixed and back.free_names == fit.free_names and back.unidentifiable == "fix"


def test_a_regular_problem_is_untouched_by_fix():
    record = synthesize("htls", deploy_retract(), noise=0.02, seed=4)
    def problem():      # one each: a shared problem would serve the second fit's runs from the first's
        return FitProblem([record], parameters=get_model("htls").parameters.freeing_only(["J", "B_TS1", "k_n"]),
                          channels=RIG)
    plain = estimate(problem())
    held = estimate(problem(), unidentifiable="fix")
    assert held.fixed == {} and held.combinations == []
    np.testing.assert_array_equal(plain.estimate, held.estimate)
    assert plain.n_simulations == held.n_simulations


def test_error_mode_keeps_the_one_line_error(tmp_path, capsys):
    data = tmp_path / "est.nc"
    io.write_measurement(data, _record(1))
    args = ["identify", str(data), "--concept", "htls", "--unidentifiable", "error", "--out", str(tmp_path / "f.json")]
    assert cli.main(args) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert err.startswith("ema-uq: error: singular information matrix") and "fix one of these parameters" in err
    with pytest.raises(SingularInformationError):
        estimate(FitProblem([_record(1)]))


def test_identifiability_at_nominal_matches_the_analysis_after_a_fit(tmp_path, capsys):
    model = get_model("htls")
    data = tmp_path / "est.nc"
    io.write_measurement(data, _record(1))
    out = tmp_path / "at.json"
    assert cli.main(["identifiability", str(data), "--concept", "htls", "--at", "nominal", "--sensor-sets",
                     "realistic", "--out", str(out)]) == 0
    assert "realistic: rank 6/16, 4 identifiable, 0 practically and 12 structurally" in capsys.readouterr().out
    at = json.loads(out.read_text())
    assert at["at"] == "nominal" and at["fim"]["rank"] == 6
    assert all(row["profile_ci"] is None for row in at["parameters"].values())
    assert "profiles skipped" in at["sensor_sets"]["realistic"]["warnings"][0]

    fitted = ident.sensor_set_study([_record(1)], model.parameters.nominal, model.parameters.names, ("realistic",),
                                    settings=ident.ProfileSettings(points=3), profile_names=["B_TS1"])
    after = fitted.sets["realistic"]
    assert after.info.rank == at["fim"]["rank"]
    assert {n: row["verdict"] for n, row in at["parameters"].items()} == {n: after.verdict(n) for n in after.names}
    by_expression = {c["expression"]: c for c in after.combinations}
    for c in at["combinations"]:
        ref = by_expression[c["expression"]]
        assert abs(c["value"] - ref["value"]) < 3 * ref["std"] and 0.7 < c["std"] / ref["std"] < 1.3
    for n in ("J", "k_n", "p_ACE", "p_PCE"):
        ratio = at["parameters"][n]["crb_std"] / after.info.std()[after.names.index(n)]
        assert 0.7 < ratio < 1.3, (n, ratio)


def test_identifiability_at_a_parameter_file_without_data(tmp_path, capsys):
    point = tmp_path / "point.json"
    point.write_text(json.dumps({"B_TS1": 0.5, "C_MG": 0.3}))
    out = tmp_path / "at.json"
    args = ["identifiability", "--concept", "lths", "--at", str(point), "--experiment", "deploy-retract",
            "--sensor-sets", "realistic", "--noise", "0.01", "--out", str(out)]
    assert cli.main(args) == 0
    result = json.loads(out.read_text())
    assert result["parameters"]["B_TS1"]["estimate"] == 0.5
    assert result["parameters"]["B_TS1"]["verdict"] == "structurally_non_identifiable"
    assert result["parameters"]["k_n"]["verdict"] == "identifiable"
    capsys.readouterr()
    args[args.index(str(point))] = str(tmp_path / "missing.json")
    assert cli.main(args) == 2
    assert "missing.json" in capsys.readouterr().err
    assert cli.main(["identifiability", "--concept", "htls", "--at", "nominal", "--out", str(out)]) == 2
    assert "--at needs the experiment" in capsys.readouterr().err


def test_lths_rig_fit_reports_the_structural_sums():
    """LT/HS: a weak direction (C_MG against the station Coulomb losses) joins the viscous and
    Coulomb losses in one lumped group; the combinations are still each kind's motor-shaft sum."""
    model = get_model("lths")
    record = synthesize("lths", deploy_retract(), noise=0.02, seed=1, channels=("Omega", "y1", "y2", "I_A", "U_A"))
    fit = estimate(FitProblem([record], parameters=model.parameters),
                   start=perturbed_start(model.parameters, 0.3, 1), unidentifiable="fix")
    assert fit.converged and len(fit.fixed) == 12 and {"B_MG", "C_MG"} < set(fit.free_names)
    truth = dict(zip(model.parameters.names, model.parameters.nominal))
    assert sorted(c["expression"] for c in fit.combinations) == [
        "B_TS1/cos(beta1) + B_U1 + 2*B_TP1 + B_TS2/cos(beta2) + B_U2 + 2*B_TP2 + 80*B_MG",
        "C_TS1/cos(beta1) + C_U1 + 2*C_TP1 + C_TS2/cos(beta2) + C_U2 + 2*C_TP2 + 40*C_MG"]
    for c in fit.combinations:
        exact = sum(a * truth[n] for n, a in c["coefficients"].items())
        assert c["structural"] and abs(c["value"] - exact) < 3 * c["std"], (c["expression"], c["value"], exact)


def test_a_direction_only_the_optimiser_sees_is_held_member_by_member(monkeypatch):
    """When the central-difference detector keeps every parameter (a condition just above the
    optimiser's limit: LT/HS C_MG against the station Coulomb losses) the fit holds, one at a
    time, the member weighing most in the direction the optimiser reports, instead of failing."""
    from ema_uq.identify import reduction

    monkeypatch.setattr(reduction, "held_parameters", lambda problem, start: ({}, 0))
    model = get_model("htls")
    problem = FitProblem([_record(1)], parameters=model.parameters.freeing_only(["J", "B_TS1", "B_TS2", "k_n"]))
    with pytest.raises(SingularInformationError) as caught:
        estimate(problem, start=model.parameters.nominal)
    assert set(caught.value.direction) == {"B_TS1", "B_TS2"}
    fit = estimate(problem, start=model.parameters.nominal, unidentifiable="fix")
    assert fit.converged and len(fit.fixed) == 1 and set(fit.fixed) < {"B_TS1", "B_TS2"}
    name = next(iter(fit.fixed))
    assert "near-null direction" in fit.fixed[name]["reason"] and np.isnan(fit.std[fit.names.index(name)])
    assert set(fit.free_names) == {"J", "B_TS1", "B_TS2", "k_n"} - {name}


def _lumped_fit() -> FitResult:
    """A hand-made fit of three viscous losses lumped in one group (b1 free, b2 and b3 held)
    beside an ordinary parameter J."""
    names = ("J", "b1", "b2", "b3")
    return FitResult(
        concept="htls", method="gn", names=names, units=("kg m2", "N m s", "N m s", "N m s"),
        free=np.array([True, True, False, False]), start=np.array([1.0, 0.5, 0.65, 0.4]),
        estimate=np.array([1.1, 0.8, 0.65, 0.4]), std=np.array([0.01, 0.02, np.nan, np.nan]),
        covariance=np.diag([1e-4, 4e-4]), channels=("Omega",), residual_covariance=np.eye(1), log_det_r=0.0,
        objective=0.0, n_samples=10, converged=True, message="", iterations=3, n_simulations=9, wall_time_s=0.1,
        unidentifiable="fix", hold_rule="hold the rest",
        fixed={"b2": {"value": 0.65, "reason": "null direction"}, "b3": {"value": 0.4, "reason": "null direction"}},
        combinations=[{"parameters": ["b1", "b2", "b3"], "expression": "b1 + b2 + b3",
                       "coefficients": {"b1": 1.0, "b2": 1.0, "b3": 1.0}, "value": 1.85, "std": 0.02,
                       "relative_std": 0.02 / 1.85, "ci95": [1.81, 1.89]}])


def test_a_lumped_group_is_reported_as_what_it_is(tmp_path):
    fit = _lumped_fit()
    assert fit.roles() == {"J": "estimated", "b1": "kept", "b2": "held", "b3": "held"}
    lines = {line.split()[0]: line for line in fit.summary().splitlines() if " = " in line and "(init = " in line}
    assert "+/- 0.01" in lines["J"]
    # the kept member: no standalone bound, its σ labelled as holding only given the held ones
    assert "+/-" not in lines["b1"] and "(bound: its group)" in lines["b1"] and "conditional σ 0.02" in lines["b1"]
    assert "+/-" not in lines["b2"] and "(no bound)" in lines["b2"] and "held at its start" in lines["b2"]
    text = fit.summary()
    assert "b1 + b2 + b3 = 1.85 +/- 0.02" in text and "carried by b1; held: b2, b3" in text
    # FIT.json: the old keys unchanged, the roles added
    data = json.loads(io.write_json(tmp_path / "fit.json", fit.to_json()).read_text())
    assert data["parameters"]["b1"]["std"] == 0.02 and data["parameters"]["b1"]["role"] == "kept"
    assert data["parameters"]["b1"]["std_conditional"] is True and data["parameters"]["J"]["std_conditional"] is False
    assert [data["parameters"][n]["role"] for n in ("J", "b2")] == ["estimated", "held"]
    combo = data["combinations"][0]
    assert combo["kept"] == ["b1"] and combo["held"] == ["b2", "b3"] and combo["std"] == 0.02
    back = FitResult.from_json(data)
    assert back.roles() == fit.roles() and back.hold_rule == "hold the rest"


def test_rig_fit_roles(fits):
    fit = fits[1]
    roles = fit.roles()
    assert sorted(n for n, r in roles.items() if r == "kept") == sorted(
        n for n in fit.free_names if n in FRICTION)
    assert {n for n, r in roles.items() if r == "held"} == set(fit.fixed)
    assert all(roles[n] == "estimated" for n in ("J", "k_n", "p_ACE", "p_PCE"))
