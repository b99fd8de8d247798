"""Sobol sensitivity: the SALib wrapper against the analytic Ishigami indices, the
vectorised time-resolved estimator against SALib's own, the convergence rule, exact
chunk-then-gather, the QoI against independent computations, the study section, SOBOL.json,
the figures and the ``sensitivity`` verb.

The actuator checks run on the first 6 s of the estimation experiment with N = 4 base
samples (104 runs): enough to exercise every path, not to estimate indices.
"""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from ema_uq import cli, get_model, simulate_batch
from ema_uq import sensitivity as sobol
from ema_uq.study import StudyError, validate_study

SHORT = 600  # samples of the shortened experiment (6 s: at rest, then deploying)


def _agree_all(estimate: dict, reference: dict) -> bool:
    iu = np.triu_indices(3, 1)
    checks = [sobol.indices_agree(estimate[k], estimate[f"{k}_conf"], reference[k], 0.0) for k in ("S1", "ST")]
    checks.append(sobol.indices_agree(estimate["S2"][iu], estimate["S2_conf"][iu], reference["S2"][iu], 0.0))
    return all(bool(np.all(c)) for c in checks)


@pytest.fixture(scope="module")
def ishigami_estimate():
    x = sobol.sample(sobol.ISHIGAMI_PROBLEM, 1024, seed=11)
    return x, sobol.analyze(sobol.ISHIGAMI_PROBLEM, sobol.ishigami(x), seed=12)


def test_ishigami_analytic_values():
    ref = sobol.ishigami_indices()
    # Saltelli et al. (2008), Global Sensitivity Analysis: The Primer, a = 7, b = 0.1
    np.testing.assert_allclose(ref["S1"], [0.3139, 0.4424, 0.0], atol=1e-4)
    np.testing.assert_allclose(ref["ST"], [0.5576, 0.4424, 0.2437], atol=1e-4)
    assert ref["S2"][0, 2] == pytest.approx(ref["ST"][2])


def test_ishigami_indices_within_their_confidence_intervals(ishigami_estimate):
    _, est = ishigami_estimate
    assert _agree_all(est, sobol.ishigami_indices())
    assert not est["degenerate"]
    assert np.all(est["S1_conf"] < 0.1)  # the intervals are informative, not vacuous


@pytest.mark.parametrize("wrong", [
    sobol.ishigami_indices(a=5.0),                                        # another function
    {k: v[[1, 0, 2]] if v.ndim == 1 else v for k, v in sobol.ishigami_indices().items()},  # x1, x2 swapped
])
def test_wrong_reference_is_rejected(ishigami_estimate, wrong):
    _, est = ishigami_estimate
    assert not _agree_all(est, wrong)


def test_first_half_of_a_design_is_the_design_of_half_the_size():
    full = sobol.sample(sobol.ISHIGAMI_PROBLEM, 64, seed=3)
    half = sobol.sample(sobol.ISHIGAMI_PROBLEM, 32, seed=3)
    np.testing.assert_array_equal(full[: half.shape[0]], half)


def test_time_resolved_estimator_reproduces_salib_analyze(ishigami_estimate):
    x, est = ishigami_estimate
    y = sobol.ishigami(x)
    series = np.column_stack([y, 3.0 * y + 1.0, np.zeros_like(y)])   # affine copy; a column at rest
    tr = sobol.analyze_time_resolved(sobol.ISHIGAMI_PROBLEM, series, seed=12)
    for key in ("S1", "S1_conf", "ST", "ST_conf"):
        np.testing.assert_allclose(tr[key][:, 0], est[key], rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(tr[key][:, 1], est[key], rtol=1e-9, atol=1e-12)
        assert np.all(np.isnan(tr[key][:, 2]))


def test_constant_output_is_flagged_degenerate():
    x = sobol.sample(sobol.ISHIGAMI_PROBLEM, 8, seed=1)
    res = sobol.analyze(sobol.ISHIGAMI_PROBLEM, np.full(x.shape[0], 2.5), seed=1)
    assert res["degenerate"] and np.all(res["ST"] == 0)


def test_bad_design_sizes_are_rejected():
    with pytest.raises(sobol.SensitivityError, match="power of 2"):
        sobol.sample(sobol.ISHIGAMI_PROBLEM, 1000, seed=1)
    with pytest.raises(sobol.SensitivityError, match="multiple of 8"):
        sobol.analyze(sobol.ISHIGAMI_PROBLEM, np.ones(10), seed=1)


def _indices(s1, s1c, st, stc):
    return {"S1": np.array(s1), "S1_conf": np.array(s1c), "ST": np.array(st), "ST_conf": np.array(stc)}


def test_convergence_rule_uses_the_wider_interval_plus_slack():
    names = ["a", "b"]
    full = {"q": _indices([0.50, 0.10], [0.02, 0.01], [0.60, 0.10], [0.02, 0.01])}
    near = {"q": _indices([0.53, 0.10], [0.04, 0.01], [0.62, 0.11], [0.03, 0.01])}
    report = sobol.check_convergence(near, full, names, atol=0.0)
    assert report["converged"] and report["qoi"]["q"]["converged"]
    moved = {"q": _indices([0.50, 0.10], [0.02, 0.01], [0.60, 0.16], [0.02, 0.02])}
    report = sobol.check_convergence(moved, full, names, atol=0.0)
    assert not report["converged"]
    assert report["qoi"]["q"]["worst"]["parameter"] == "b" and report["qoi"]["q"]["worst"]["index"] == "ST"
    assert sobol.check_convergence(moved, full, names, atol=0.05)["converged"]  # within the absolute slack


def test_chunk_rows_cover_the_design_once():
    edges = [sobol.chunk_rows(104, i, 5) for i in range(5)]
    assert edges[0][0] == 0 and edges[-1][1] == 104
    assert all(a[1] == b[0] for a, b in zip(edges, edges[1:]))
    with pytest.raises(sobol.SensitivityError, match="numbered from 0"):
        sobol.chunk_rows(104, 5, 5)


# --------------------------------------------------------------------------------------
# the actuator study (shortened)
# --------------------------------------------------------------------------------------
STUDY = {"name": "t", "concept": "htls", "seed": 5,
         "sensitivity": {"n_base": 4, "time_points": 30, "batch_size": 40, "bootstrap": 50}}


@pytest.fixture(scope="module")
def setup():
    full = sobol.setup_from_study(validate_study(STUDY))
    exp = full.experiment.slice(0, SHORT)
    return dataclasses.replace(full, experiment=exp, reference=full.reference[:SHORT],
                               time_index=np.unique(np.linspace(0, SHORT - 1, 30).round().astype(int)))


@pytest.fixture(scope="module")
def one_shot(setup):
    return sobol.run(setup)


def test_setup_from_study_defaults(setup):
    model = get_model("htls")
    assert setup.names == tuple(n for n in model.parameters.names if n[:2] in ("B_", "C_"))
    nominal = model.parameters.nominal[[model.parameters.index(n) for n in setup.names]]
    np.testing.assert_allclose(setup.bounds, np.column_stack([0.5 * nominal, 1.5 * nominal]))
    assert setup.seed == 5 + 7000
    assert "rms_M_ER1" not in setup.qoi_names      # input-driven: no parameter moves it
    assert {"cost", "rms_Omega", "tracking_error", "peak_torque", "peak_current", "energy"} <= set(setup.qoi_names)


def test_qoi_against_independent_computation(setup):
    model = setup.model
    rows = np.vstack([setup.nominal[[model.parameters.index(n) for n in setup.names]], setup.bounds[:, 1]])
    qoi, series = sobol.evaluate(setup, rows)
    q = dict(zip(setup.qoi_names, qoi.T))
    exp = setup.experiment
    outs = simulate_batch(model, setup.thetas(rows), exp.time, exp.input_matrix(model), integrator=sobol.INTEGRATOR)
    assert q["rms_Omega"][0] == 0.0 and q["rms_I_A"][0] == 0.0
    omega, i_a = outs[1][:, 0], outs[1][:, 3]
    assert q["rms_Omega"][1] == pytest.approx(np.sqrt(np.mean((omega - outs[0][:, 0]) ** 2)), rel=1e-12)
    torque = 1.2 * i_a                                    # k_n nominal
    assert q["peak_current"][1] == pytest.approx(np.abs(i_a).max())
    assert q["peak_torque"][1] == pytest.approx(np.abs(torque).max())
    assert q["energy"][1] == pytest.approx(np.sum(np.maximum(torque * omega, 0)) * 0.01, rel=1e-12)
    y_r = model.constants_vector()[model.constants.index("k_y")] * exp.inputs["phi_r"]
    assert q["tracking_error"][1] == pytest.approx(np.sqrt(np.mean((y_r - 0.5 * (outs[1][:, 1] + outs[1][:, 2])) ** 2)))
    resid = setup.reference - outs[0][:, model.output_index(setup.reference_channels)]
    assert q["cost"][0] == pytest.approx(np.linalg.slogdet(resid.T @ resid / SHORT)[1], rel=1e-10)
    np.testing.assert_array_equal(series[1], outs[1][setup.time_index][:, [0, 1, 3]].T)


def test_chunk_then_gather_equals_one_shot_exactly(setup, one_shot, tmp_path):
    design = setup.design()
    paths = []
    for i in range(3):
        paths.append(sobol.evaluate_chunk(setup, design, i, 3).save(tmp_path / f"c{i}.npz"))
    gathered = sobol.analyze_chunks(setup, [sobol.SobolChunk.load(p) for p in reversed(paths)])
    for q in one_shot.qoi:
        for key in ("S1", "S1_conf", "ST", "ST_conf", "S2", "S2_conf"):
            np.testing.assert_array_equal(gathered.qoi[q][key], one_shot.qoi[q][key])
    for out in one_shot.time_resolved:
        for key, v in one_shot.time_resolved[out].items():
            np.testing.assert_array_equal(gathered.time_resolved[out][key], v)
    with pytest.raises(sobol.SensitivityError, match=r"missing \[1\]"):
        sobol.gather(setup, [sobol.SobolChunk.load(paths[0]), sobol.SobolChunk.load(paths[2])])
    other = dataclasses.replace(setup, seed=setup.seed + 1)
    with pytest.raises(sobol.SensitivityError, match="another study or design"):
        sobol.gather(other, [sobol.SobolChunk.load(p) for p in paths])


def test_result_json_round_trip_and_contract(one_shot):
    data = json.loads(json.dumps(one_shot.to_json(), allow_nan=True))
    assert {"concept", "n_base", "converged", "qoi"} <= set(data)
    assert set(data["qoi"]["cost"]) >= {"S1", "S1_conf", "ST", "ST_conf", "S2", "S2_conf"}
    assert set(data["qoi"]["cost"]["S1"]) == set(one_shot.names)
    back = sobol.SobolResult.from_json(data)
    np.testing.assert_array_equal(back.qoi["cost"]["ST"], one_shot.qoi["cost"]["ST"])
    np.testing.assert_array_equal(back.time_resolved["I_A"]["S1"], one_shot.time_resolved["I_A"]["S1"])
    table = one_shot.to_df()
    assert table.loc[("cost", "B_TS1"), "ST"] == one_shot.qoi["cost"]["ST"][0]
    assert "cost" in one_shot.summary()


def test_figures(one_shot):
    from ema_uq.report import sensitivity_figures as figs

    fig = figs.sobol_bars(one_shot)
    assert len([a for a in fig.axes if a.get_visible()]) == 6
    fig2 = figs.time_resolved(one_shot.to_json())
    assert len(fig2.axes) == 6        # three outputs, each with the flap-command twin axis
    with pytest.raises(ValueError, match="no Sobol indices for nope"):
        figs.sobol_bars(one_shot, "nope")


def test_study_section_defaults_and_checks():
    study = validate_study({"name": "s", "concept": "lths"})
    assert study["sensitivity"]["n_base"] == 1024 and study["sensitivity"]["range_fraction"] == 0.5
    assert study["identifiability"]["sensor_sets"] == ["full", "realistic"]
    bad = [({"range_fraction": 1.2}, "sensitivity.range_fraction"),
           ({"n_base": 1000}, "power of 2"),
           ({"parameters": {"B_XX": [0.1, 0.2]}}, "sensitivity.parameters"),
           ({"parameters": {"B_MG": [0.02, 0.01]}}, "sensitivity.parameters.B_MG"),
           ({"rms_channels": ["Torque"]}, "sensitivity.rms_channels"),
           ({"chunk": 3}, "sensitivity.chunk")]
    for section, where in bad:
        with pytest.raises(StudyError, match=where.replace(".", r"\.")):
            validate_study({"name": "s", "concept": "lths", "sensitivity": section})
    with pytest.raises(StudyError, match="identifiability.profile_parameters"):
        validate_study({"name": "s", "concept": "htls", "identifiability": {"profile_parameters": ["B_MG"]}})


def test_sensitivity_verb_chunks_and_gather(tmp_path, capsys):
    study = tmp_path / "study.yaml"
    study.write_text(json.dumps(STUDY))
    chunks = [str(tmp_path / f"c{i}.npz") for i in range(2)]
    for i, path in enumerate(chunks):
        assert cli.main(["sensitivity", "--concept", "htls", "--study", str(study), "--chunk", f"{i}/2",
                         "--n-base", "2", "--out", path]) == 0
    out = tmp_path / "sobol.json"
    assert cli.main(["sensitivity", "--concept", "htls", "--study", str(study), "--gather", *chunks,
                     "--n-base", "2", "--out", str(out)]) == 0
    data = json.loads(out.read_text())
    assert data["concept"] == "htls" and data["n_base"] == 2 and data["n_evaluations"] == 52
    assert cli.main(["sensitivity", "--concept", "lths", "--study", str(study), "--out", str(out)]) == 2
    assert "study of concept htls" in capsys.readouterr().err


@pytest.mark.slow
def test_htls_study_converges_at_the_default_budget():
    """N = 1024 (26 624 runs): the N/2 vs N check passes and the indices are consistent."""
    result = sobol.run(sobol.setup_from_study(validate_study({"name": "s", "concept": "htls"})))
    assert result.converged, result.summary()
    for q, r in result.qoi.items():
        if r["degenerate"]:
            continue
        assert np.sum(r["S1"]) <= 1.0 + np.sqrt(np.sum(r["S1_conf"] ** 2)), q
        assert np.all(r["ST"] + r["ST_conf"] >= r["S1"] - r["S1_conf"]), q
