"""Identifiability: information-matrix algebra on problems with known answers (a linear
Gaussian model with a rank deficiency, a pair of sensitivities at a known angle), the
profile interval and verdict rules, the drive-train structure against the compiled model,
and the HT/LS sensor-set study (full instrumentation vs the realistic rig set), IDENT.json
and the ``identifiability`` verb.

The HT/LS study runs on the estimation experiment alone with B_TS1 profiled on 5 points;
the complete study (every friction parameter profiled, both concepts) is marked slow.
"""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from ema_uq import cli, deploy_retract, get_model, io, synthesize, validation
from ema_uq import identifiability as ident
from ema_uq.models import htls, lths

FRICTION_HTLS = [n for n in get_model("htls").parameters.names if n[:2] in ("B_", "C_")]


# --------------------------------------------------------------------------------------
# information-matrix algebra
# --------------------------------------------------------------------------------------
def test_linear_gaussian_rank_deficiency_names_the_null_direction():
    rng = np.random.default_rng(4)
    x = rng.standard_normal((200, 4))
    x[:, 2] = x[:, 0] + 2.0 * x[:, 1]         # theta_c is not separable from a and b
    info = ident.information_from_sensitivities(x, ["a", "b", "c", "d"])
    assert info.rank == 3
    assert info.in_null_space().tolist() == [True, True, True, False]
    (direction,) = info.null_directions()
    expected = np.array([1.0, 2.0, -1.0]) / math.sqrt(6.0)   # x @ (1, 2, -1, 0) = 0
    got = np.array([direction.get(n, 0.0) for n in "abc"])
    np.testing.assert_allclose(np.abs(got), np.abs(expected), atol=1e-4)
    assert np.sign(got[0]) == np.sign(got[1]) == -np.sign(got[2])
    assert "d" not in direction
    # d is determined: its bound equals the exact one of the regular sub-problem
    sub = x[:, [0, 1, 3]]
    assert info.std()[3] == pytest.approx(math.sqrt(np.linalg.inv(sub.T @ sub)[2, 2]), rel=1e-8)
    assert np.all(np.isnan(info.std()[:3]))
    # an estimable combination of the lumped ones: a + 2 b and c are the same direction
    assert info.combination_std(np.array([1.0, 2.0, 0.0, 0.0])) == pytest.approx(
        info.combination_std(np.array([0.0, 0.0, 1.0, 0.0])), rel=1e-6)
    group = ident.lumped_groups(info)
    assert group == [["a", "b", "c"]]


def test_regular_problem_matches_the_inverse_and_scaling():
    rng = np.random.default_rng(1)
    x = rng.standard_normal((50, 3))
    scale = np.array([2.0, 0.5, 10.0])
    info = ident.information_from_sensitivities(x, ["a", "b", "c"], scale=scale)
    assert info.rank == 3 and info.null_directions() == []
    expected = np.linalg.inv(x.T @ x) * np.outer(scale, scale)
    np.testing.assert_allclose(info.covariance(), expected, rtol=1e-10)
    assert info.condition == pytest.approx(np.linalg.cond(x.T @ x), rel=1e-8)


@pytest.mark.parametrize("angle_deg", [90.0, 60.0, 10.0, 1.0])
def test_collinearity_index_of_a_known_pair(angle_deg):
    t = np.linspace(0, 1, 400)
    u = np.sin(2 * np.pi * t)
    v = np.cos(2 * np.pi * t)
    u, v = u / np.linalg.norm(u), v / np.linalg.norm(v)
    w = math.cos(math.radians(angle_deg)) * u + math.sin(math.radians(angle_deg)) * v
    info = ident.information_from_sensitivities(np.column_stack([3.0 * u, 0.2 * w]), ["p", "q"])
    rho = math.cos(math.radians(angle_deg))
    assert info.collinearity(["p", "q"]) == pytest.approx(1.0 / math.sqrt(1.0 - abs(rho)), rel=1e-9)


def test_identical_columns_and_dead_parameters_cap_the_index():
    x = np.column_stack([np.arange(5.0), 2 * np.arange(5.0), np.zeros(5)])
    info = ident.information_from_sensitivities(x, ["a", "b", "dead"])
    assert info.collinearity(["a", "b"]) > 1e6
    assert info.collinearity(["a", "dead"]) == ident.GAMMA_CAP


def test_identifiable_subset_keeps_one_member_per_lumped_group():
    rng = np.random.default_rng(2)
    base = rng.standard_normal((100, 3))
    # B1, B2, B3 act only through B1 + B2 + 2 B3; C alone; D alone
    x = np.column_stack([base[:, 0], base[:, 0], 2 * base[:, 0], base[:, 1], base[:, 2]])
    info = ident.information_from_sensitivities(x, ["B1", "B2", "B3", "C", "D"])
    chosen = ident.identifiable_subset(info)
    assert len(chosen) == 3 and {"C", "D"} <= set(chosen)
    assert "B3" in chosen                            # the most informative member represents the group
    assert "B3" not in ident.identifiable_subset(info, exclude=["B3"])


# --------------------------------------------------------------------------------------
# profile intervals and verdicts
# --------------------------------------------------------------------------------------
def _profile(grid, delta, estimate=1.0):
    return ident.Profile("x", estimate, np.asarray(grid, float), np.asarray(delta, float), ("y",), 0, 0.0)


def test_profile_interval_is_exact_for_a_quadratic_profile():
    sigma = 0.03
    grid = 1.0 + np.linspace(-4, 4, 9) * sigma
    prof = _profile(grid, 0.5 * ((grid - 1.0) / sigma) ** 2)
    lo, hi = prof.interval()
    assert lo == pytest.approx(1.0 - ident.CRB_Z * sigma, rel=1e-12)
    assert hi == pytest.approx(1.0 + ident.CRB_Z * sigma, rel=1e-12)
    assert ident.PROFILE_THRESHOLD == pytest.approx(1.9207294, rel=1e-6)


def test_verdict_rules():
    grid = np.linspace(0.5, 1.5, 9)
    closed = _profile(grid, 0.5 * ((grid - 1.0) / 0.05) ** 2)
    flat = _profile(grid, 1e-4 * np.abs(grid - 1.0))
    one_sided = _profile(grid, np.where(grid > 1, 10 * (grid - 1.0) ** 2 * 100, 0.01 * (1.0 - grid)))
    wide = _profile(grid, 0.5 * ((grid - 1.0) / 0.4) ** 2 * 8)
    kw = {"max_relative_width": 0.5}
    assert ident.classify_profile(closed, False, **kw)[0] == "identifiable"
    assert ident.classify_profile(flat, True, **kw)[0] == "structurally_non_identifiable"
    assert ident.classify_profile(flat, False, **kw)[0] == "practically_non_identifiable"
    verdict, reason = ident.classify_profile(one_sided, False, **kw)
    assert verdict == "practically_non_identifiable" and "open below" in reason
    verdict, reason = ident.classify_profile(wide, False, **kw)
    assert verdict == "practically_non_identifiable" and "wide" in reason
    assert ident.classify_information(1.0, 0.01, False, **kw)[0] == "identifiable"
    assert ident.classify_information(1.0, 0.3, False, **kw)[0] == "practically_non_identifiable"
    assert ident.classify_information(1.0, np.nan, True, **kw)[0] == "structurally_non_identifiable"


# --------------------------------------------------------------------------------------
# drive-train structure, checked against the compiled model equations
# --------------------------------------------------------------------------------------
@pytest.mark.parametrize("module", [htls, lths], ids=["htls", "lths"])
def test_motor_shaft_factors_match_the_model(module):
    """d(J dΩ/dt)/dθ_j = -f_j Ω for a viscous loss and -f_j for a Coulomb loss at high speed."""
    model = module.MODEL
    c = model.kernel_constants()
    x = np.zeros(model.n_states)
    omega = 400.0                                 # far above the smoothing speed on every shaft
    x[model.states.index("Omega")] = omega
    u = np.zeros(len(model.inputs))
    factors = model.loss_factors()
    j_pos = model.parameters.index("J")

    def accel(theta):
        dx, y = np.zeros(model.n_states), np.zeros(model.n_outputs)
        module.evaluate(x, u, theta, c, dx, y)
        return dx[model.states.index("Omega")] * theta[j_pos]

    nominal = model.parameters.nominal
    assert set(factors) == {n for n in model.parameters.names if n[:2] in ("B_", "C_")}
    for name, f in factors.items():
        theta = nominal.copy()
        theta[model.parameters.index(name)] += 1e-3
        slope = (accel(nominal) - accel(theta)) / 1e-3
        assert slope == pytest.approx(f * omega if name.startswith("B_") else f, rel=1e-6), name


def test_combination_expression_keeps_the_screw_cosine():
    model = get_model("htls")
    beta1 = model.constants_vector()[model.constants.index("beta1")]
    text = ident.combination_expression(["B_TS1", "B_U1", "B_TP1"], [1 / math.cos(beta1), 1.0, 2.0], model)
    assert text == "B_TS1/cos(beta1) + B_U1 + 2*B_TP1"


# --------------------------------------------------------------------------------------
# the HT/LS sensor-set study
# --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def htls_data():
    return synthesize("htls", deploy_retract(), noise=0.02, seed=1)


@pytest.fixture(scope="module")
def htls_study(htls_data):
    model = get_model("htls")
    return ident.sensor_set_study([htls_data], model.parameters.nominal, model.parameters.names,
                                  ("full", "realistic"), settings=ident.ProfileSettings(points=5),
                                  profile_names=["B_TS1"])


def test_full_instrumentation_identifies_every_parameter(htls_study):
    full = htls_study.sets["full"]
    assert full.info.rank == 16 and full.combinations == []
    assert all(v[0] == "identifiable" for v in full.verdicts.values()), full.verdicts
    assert full.verdicts["B_TS1"][1] == "profile"
    assert max(full.max_pair_collinearity(n)[0] for n in FRICTION_HTLS) < 20


def test_profile_agrees_with_the_cramer_rao_interval(htls_study):
    lo_ratio, hi_ratio = htls_study.sets["full"].crb_ratio("B_TS1")
    assert 0.8 < lo_ratio < 1.2 and 0.8 < hi_ratio < 1.2


def test_realistic_set_lumps_the_station_losses(htls_study):
    real = htls_study.sets["realistic"]
    assert real.info.rank == 6
    for n in FRICTION_HTLS:
        assert real.verdict(n) == "structurally_non_identifiable", n
    for n in ("J", "k_n", "p_ACE", "p_PCE"):
        assert real.verdict(n) == "identifiable", n
    prof = real.profiles["B_TS1"]
    assert max(prof.rise()) < 0.1 * ident.PROFILE_THRESHOLD and prof.interval() == (None, None)
    groups = {g["name"]: g["index"] for g in real.collinearity_groups}
    assert groups["station 1"] > 20 and groups["station 2"] > 20 and groups["all B"] > 20
    expressions = sorted(c["expression"] for c in real.combinations)
    assert expressions == ["B_TS1/cos(beta1) + B_U1 + 2*B_TP1 + B_TS2/cos(beta2) + B_U2 + 2*B_TP2",
                           "C_TS1/cos(beta1) + C_U1 + 2*C_TP1 + C_TS2/cos(beta2) + C_U2 + 2*C_TP2"]
    model = get_model("htls")
    truth = dict(zip(model.parameters.names, model.parameters.nominal))
    for c in real.combinations:
        exact = sum(a * truth[n] for n, a in c["coefficients"].items())
        assert abs(c["value"] - exact) < 4 * c["std"]            # the combination is estimated, with a bound
        assert c["relative_std"] < 0.02
    # every null direction trades one loss against the representative of its group
    for direction in real.info.null_directions(real.selected):
        kinds = {n[0] for n in direction}
        assert len(kinds) == 1 and 2 <= len(direction) <= 3


def test_ident_json_contract(htls_study, tmp_path):
    path = io.write_json(tmp_path / "ident.json", htls_study.to_json())
    data = json.loads(path.read_text())
    assert data["concept"] == "htls" and data["channels"] == list(get_model("htls").outputs)
    assert {"rank", "condition", "null_directions"} <= set(data["fim"])
    row = data["parameters"]["B_TS1"]
    assert {"verdict", "crb_std", "profile_ci", "collinearity"} <= set(row)
    real = data["sensor_sets"]["realistic"]
    assert real["fim"]["rank"] == 6 and len(real["fim"]["null_directions"]) == 10
    assert all({"expression", "std"} <= set(c) for c in real["combinations"])
    assert data["comparison"]["B_TS1"] == {"full": "identifiable", "realistic": "structurally_non_identifiable"}
    assert "structurally NI" in htls_study.summary()


def test_identifiability_figures(htls_study):
    from ema_uq.report import sensitivity_figures as figs

    fig = figs.profile_likelihoods(htls_study)
    assert fig.axes[0].get_title() == "B_TS1"
    fig = figs.sensor_set_verdicts(htls_study.to_json())
    assert "B_TS1/cos(beta1)" in fig.axes[0].get_xlabel()


def test_identifiability_verb(tmp_path, capsys):
    model = get_model("htls")
    data = tmp_path / "est.nc"
    io.write_measurement(data, synthesize("htls", validation(), noise=0.02, seed=2,
                                          channels=("Omega", "y1", "y2", "I_A")))
    fit = {"concept": "htls", "method": "gn", "converged": True, "iterations": 0, "channels": [],
           "parameters": {n: {"estimate": v, "std": 0.0, "free": True}
                          for n, v in zip(model.parameters.names, model.parameters.nominal)}}
    init = tmp_path / "fit.json"
    io.write_json(init, fit)
    out = tmp_path / "ident.json"
    args = ["identifiability", str(data), "--concept", "htls", "--init", str(init), "--sensor-sets", "realistic",
            "--profile", "C_TS2", "--profile-points", "3", "--quiet", "--out", str(out)]
    assert cli.main(args) == 0
    result = json.loads(out.read_text())
    assert result["sensor_set"] == "realistic" and result["fim"]["rank"] == 6
    assert result["parameters"]["C_TS2"]["verdict"] == "structurally_non_identifiable"
    assert "rank 6/16" in capsys.readouterr().out
    args[args.index("realistic")] = "full"
    assert cli.main(args) == 2
    assert "channel(s) Omega_TP1" in capsys.readouterr().err
    # without --sensor-sets the defaults are full and realistic: full cannot be assessed on rig data
    i = args.index("--sensor-sets")
    del args[i:i + 2]
    assert cli.main(args) == 0
    assert "full skipped (channel(s) Omega_TP1" in capsys.readouterr().out
    assert list(json.loads(out.read_text())["skipped_sensor_sets"]) == ["full"]


# --------------------------------------------------------------------------------------
# the complete study (slow)
# --------------------------------------------------------------------------------------
@pytest.mark.slow
@pytest.mark.parametrize("concept", ["htls", "lths"])
def test_complete_sensor_set_study(concept):
    model = get_model(concept)
    data = [synthesize(concept, deploy_retract(), noise=0.02, seed=1),
            synthesize(concept, validation(), noise=0.02, seed=1001)]
    study = ident.sensor_set_study(data, model.parameters.nominal, model.parameters.names)
    full, real = study.sets["full"], study.sets["realistic"]
    friction = [n for n in model.parameters.names if n[:2] in ("B_", "C_")]
    assert all(v[0] == "identifiable" for v in full.verdicts.values()), full.verdicts
    for n in friction:
        lo, hi = full.crb_ratio(n)
        assert 0.8 < lo < 1.2 and 0.8 < hi < 1.2, (n, lo, hi)
    station = [n for n in friction if n[-1].isdigit()]
    for n in station:
        assert real.verdict(n) == "structurally_non_identifiable", n
        assert real.max_pair_collinearity(n)[0] > 20
    assert len(real.combinations) == 2 and all(c["structural"] for c in real.combinations)


def test_sensor_sets_whose_channels_the_data_lacks_are_skipped_and_named():
    model = get_model("htls")
    rig = list(model.sensor_sets["realistic"])
    data = [synthesize("htls", deploy_retract(), noise=0.02, seed=1).select(rig)]
    study = ident.sensor_set_study(data, model.parameters.nominal, ["J", "k_n"], ("full", "realistic"),
                                   profile_names=[])
    assert list(study.sets) == ["realistic"]
    assert "Omega_TP1" in study.skipped["full"] and "not in the data" in study.skipped["full"]
    assert study.to_json()["skipped_sensor_sets"] == study.skipped
    assert "sensor set full skipped" in study.summary()
    with pytest.raises(ident.IdentifiabilityError, match="no sensor set can be assessed.*give --channels"):
        ident.sensor_set_study(data, model.parameters.nominal, ["J"], ("full",), profile_names=[])
