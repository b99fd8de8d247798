"""EMPS concept: reader, control law, closed-loop simulation, effects and ML identification.

Tests that need the benchmark files skip when they are absent (set EMA_UQ_EMPS_DIR to the
folder holding DATA_EMPS.mat and DATA_EMPS_PULSES.mat). Tolerances are stated at each test;
the published numbers come from the benchmark description (Janot, Gautier, Brunot 2019).
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from ema_uq import Experiment, Measurement, get_model, io, simulate_batch
from ema_uq.rigs.emps import (EMPS_STRATEGY, emps_comparison, fit_emps, published_alignment_force_error,
                                   simulation_errors)
from ema_uq.gap import diagnose
from ema_uq.identify import FitProblem, estimate
from ema_uq.models import emps
from ema_uq.study import load_study

MODEL = get_model("emps")
AT_REST = emps.CONSTANTS.vector({"q0": 0.0, "qd0": 0.0, "u0": 0.0})
TRUTH = np.array([90.0, 180.0, 25.0, -2.0])        # EMPS-like, away from the published values
NOISE = np.array([1e-6, 0.02])                      # qm [m] (20 encoder quanta), vir [V]


# --------------------------------------------------------------------------------------
# fixtures
# --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def files():
    found = io.emps_files(must_exist=False)
    missing = [str(p) for p in found.values() if not p.is_file()]
    if missing:
        pytest.skip(f"EMPS benchmark files not found ({', '.join(missing)}); set {io.EMPS_DIR_ENV} "
                    "to the folder holding them")
    return found


@pytest.fixture(scope="module")
def estimation(files):
    return io.read_emps(files["estimation"])


@pytest.fixture(scope="module")
def validation(files):
    return io.read_emps(files["validation"])


@pytest.fixture(scope="module")
def nominal_fit(estimation):
    return fit_emps(estimation, method="gn")


@pytest.fixture(scope="module")
def synthetic():
    """Two strokes of the benchmark's trapezoidal profile (4.4 s), simulated at TRUTH from
    rest, with white noise NOISE on qm and vir (seeded)."""
    time, qg = emps.reference_trajectory(2)
    experiment = Experiment("synthetic", time, {"qg": qg})
    clean = simulate_batch(MODEL, TRUTH, time, experiment.input_matrix(MODEL), constants=AT_REST)
    rng = np.random.default_rng(5)
    values = clean[:, :2] + rng.standard_normal((time.size, 2)) * NOISE
    return Measurement("emps", experiment, ("qm", "vir"), values, {"source": "simulated"}), clean


def _write_mat(path, **overrides):
    """A small EMPS-like .mat file (100 samples) with ``overrides`` (None deletes a variable)."""
    from scipy.io import savemat

    n = 100
    t = np.arange(n)[:, None] * 1e-3
    data = {"t": t, "qm": 1e-3 * t, "qg": 1e-3 * t + 1e-6, "vir": np.full((n, 1), 0.5),
            "kp": np.array([[160.18]]), "kv": np.array([[243.45]]), "gtau": np.array([[35.15]])}
    for key, value in overrides.items():
        if value is None:
            data.pop(key)
        else:
            data[key] = value
    savemat(path, data)
    return path


# --------------------------------------------------------------------------------------
# reader
# --------------------------------------------------------------------------------------
def test_reader_round_trip(files, estimation, validation, tmp_path):
    from scipy.io import loadmat

    raw = loadmat(files["validation"])
    assert validation.concept == "emps" and validation.channels == ("qm", "vir")
    assert validation.time.size == 24841 and validation.experiment.dt == pytest.approx(1e-3, abs=1e-15)
    np.testing.assert_allclose(validation.time, raw["t"].ravel(), atol=1e-7)   # stamps jitter ~3e-8 s
    np.testing.assert_array_equal(validation["qm"], raw["qm"].ravel())
    np.testing.assert_array_equal(validation["vir"], raw["vir"].ravel())
    np.testing.assert_array_equal(validation["pulse"], raw["pulses_N"].ravel().astype(float))
    assert set(np.unique(validation["pulse"])) == {0.0, 5.0}
    assert "pulse" not in estimation.experiment.inputs
    assert validation.attrs["gtau"] == pytest.approx(35.15065188248547, rel=1e-15)
    assert estimation.attrs["q0"] == estimation["qm"][0]
    # through the generic reader, and through the package's own file format and back
    again = io.read_measurement(files["validation"], concept="emps")
    np.testing.assert_array_equal(again.values, validation.values)
    out = io.write_measurement(tmp_path / "pulses.nc", validation)
    back = io.read_measurement(out, concept="emps")
    np.testing.assert_array_equal(back.values, validation.values)
    np.testing.assert_array_equal(back["pulse"], validation["pulse"])
    assert back.attrs["kp"] == validation.attrs["kp"]
    # derived channels
    derived = io.read_emps(files["estimation"], channels=("qm", "force", "qd_hat"))
    np.testing.assert_allclose(derived["force"], estimation.attrs["gtau"] * estimation["vir"], rtol=1e-15)


@pytest.mark.parametrize("change, message", [
    ({"vir": None}, "missing variable(s) vir"),
    ({"qm": np.zeros((50, 1))}, "variable qm has shape"),
    ({"kp": np.array([[1.0, 2.0]])}, "gain kp must be one positive number"),
    ({"t": (np.arange(100) ** 1.1)[:, None] * 1e-3}, "not a uniform grid"),
    ({"qg": np.full((100, 1), np.nan)}, "input qg has NaN"),
    ({"qm": np.array([["a"] * 100]).T}, "must be numeric"),
])
def test_reader_rejects_bad_files(tmp_path, change, message):
    path = _write_mat(tmp_path / "bad.mat", **change)
    with pytest.raises(io.DataFileError, match=message.replace("(", r"\(").replace(")", r"\)")) as info:
        io.read_emps(path)
    assert "\n" not in str(info.value) and str(path) in str(info.value)


def test_reader_errors_on_wrong_file_or_request(tmp_path):
    good = io.read_emps(_write_mat(tmp_path / "ok.mat"))
    assert good.time.size == 100 and good.channels == ("qm", "vir")
    text = tmp_path / "text.mat"
    text.write_text("not a mat file\n")
    with pytest.raises(io.DataFileError, match="not a readable MATLAB .mat file"):
        io.read_emps(text)
    with pytest.raises(io.DataFileError, match="no such file"):
        io.read_emps(tmp_path / "absent.mat")
    with pytest.raises(io.DataFileError, match="not a .mat file"):
        io.read_emps(tmp_path / "data.csv")
    with pytest.raises(io.DataFileError, match="unknown EMPS channel"):
        io.read_emps(tmp_path / "ok.mat", channels=("Omega",))
    with pytest.raises(io.DataFileError, match="but htls was asked for"):
        io.read_measurement(tmp_path / "ok.mat", concept="htls")


def test_data_folder_resolution(tmp_path, monkeypatch):
    monkeypatch.delenv(io.EMPS_DIR_ENV, raising=False)
    root = io.repository_root()
    assert io.emps_data_dir() == (root / io.DEFAULT_EMPS_DIR).resolve()
    study = load_study(root / "studies" / "emps.yaml")
    assert study["concept"] == "emps" and study["data"]["channels"] == ["qm", "vir"]
    assert io.emps_data_dir({"data": {"path": "elsewhere/emps"}}) == (root / "elsewhere/emps").resolve()
    monkeypatch.setenv(io.EMPS_DIR_ENV, str(tmp_path))
    assert io.emps_data_dir(study) == tmp_path          # the environment wins over the study
    with pytest.raises(io.DataFileError, match=io.EMPS_DIR_ENV):
        io.emps_files(study)


# --------------------------------------------------------------------------------------
# control law and closed loop on the real data
# --------------------------------------------------------------------------------------
def test_controller_recomputes_logged_command(estimation, validation):
    """vir(k) = kv (kp (qg(k) - qm(k)) - qd_hat(k)) from the SAME sample reproduces the log to its
    precision: rms 0.0037 V (max 0.012 V, 1.5 encoder quanta through the gains) against 1.54 V
    rms; one sample later is 15x worse. In the pulse record the logged command holds the
    pulse: vir - law = 1.014 pulse (so the pulse is about 5.07 V of drive command, 178 N)."""
    kp, kv = estimation.attrs["kp"], estimation.attrs["kv"]
    law, _ = emps.controller_output(estimation["qm"], estimation["qg"], kp, kv, 1e-3)
    residual = (estimation["vir"] - law)[2:]       # the first two samples need qm before the record
    assert np.sqrt(np.mean(residual ** 2)) < 0.004
    assert np.max(np.abs(residual)) < 0.013
    late = np.concatenate([[law[0]], law[:-1]])
    assert np.sqrt(np.mean((estimation["vir"] - late)[2:] ** 2)) > 0.05

    pulse = validation["pulse"]
    law, _ = emps.controller_output(validation["qm"], validation["qg"], kp, kv, 1e-3)
    extra = (validation["vir"] - law)[2:]
    gain = float(extra @ pulse[2:] / (pulse[2:] @ pulse[2:]))
    assert gain == pytest.approx(1.014, abs=0.002)
    away = np.ones(pulse.size, bool)
    for edge in np.flatnonzero(np.diff(pulse)):
        away[edge - 1: edge + 3] = False
    # this record's qm is resampled (not on the encoder grid), hence 0.016 V rms here
    assert np.sqrt(np.mean((extra - gain * pulse[2:])[away[2:]] ** 2)) < 0.02


def test_closed_loop_at_published_values_tracks_the_rig(estimation, validation):
    """Simulated from qg alone, the loop at the published values follows the measured position
    within 15 µm (max, 0.0016 % relative) and reproduces the benchmark's published velocity
    error (0.229 %) and, in the benchmark's alignment, its force error (5.85 %)."""
    theta = MODEL.parameters.vector({k: v for k, (v, _) in emps.PUBLISHED_IDIM_LS.items()})
    errors = simulation_errors(MODEL, theta, estimation)
    y = simulate_batch(MODEL, theta, estimation.time, estimation.experiment.input_matrix(MODEL),
                       constants=emps.constants_for(estimation))
    assert np.max(np.abs(y[:, 0] - estimation["qm"])) < 15.5e-6
    assert errors["position"] < 0.002
    assert errors["velocity"] == pytest.approx(0.229, abs=0.005)
    assert published_alignment_force_error(MODEL, theta, estimation) == pytest.approx(5.85, abs=0.02)
    assert errors["force"] == pytest.approx(7.05, abs=0.05)          # same-sample alignment
    val = simulation_errors(MODEL, theta, validation)
    assert val["position"] < 0.003 and val["force"] < 10.0


# --------------------------------------------------------------------------------------
# numerics
# --------------------------------------------------------------------------------------
def test_step_halving_and_smoothing_converged(synthetic):
    """Halving the 0.1 ms RK4 step moves qm by < 0.1 µm (2 encoder quanta) and vir by < 5 mV
    (0.3 % of its rms, a quarter of the noise); v_eps / 3 moves vir by < 20 mV rms (the noise
    level): the largest change, 0.07 V for a few ms, is at breakaway from rest, where the
    smoothed sign stands in for stiction."""
    measurement, clean = synthetic
    inputs = measurement.experiment.input_matrix(MODEL)
    half = simulate_batch(MODEL, TRUTH, measurement.time, inputs, constants=AT_REST, step=5e-5)
    assert np.max(np.abs(half[:, 0] - clean[:, 0])) < 1e-7
    assert np.max(np.abs(half[:, 1] - clean[:, 1])) < 5e-3
    sharper = AT_REST.copy()
    sharper[emps.C_V_EPS] /= 3
    y = simulate_batch(MODEL, TRUTH, measurement.time, inputs, constants=sharper, step=3e-5)
    assert np.sqrt(np.mean((y[:, 1] - clean[:, 1]) ** 2)) < 0.02


def test_batch_rows_match_single_runs(synthetic):
    measurement, _ = synthetic
    inputs = measurement.experiment.input_matrix(MODEL)
    thetas = TRUTH * np.array([[1.0, 1, 1, 1], [1.1, 0.9, 1.2, 0.5], [0.8, 1.3, 0.7, 2.0]])
    batch = simulate_batch(MODEL, thetas, measurement.time, inputs, constants=AT_REST)
    for i, th in enumerate(thetas):
        np.testing.assert_array_equal(batch[i], simulate_batch(MODEL, th, measurement.time, inputs,
                                                               constants=AT_REST))


def test_effects_off_reproduce_nominal_bit_for_bit(synthetic):
    measurement, clean = synthetic
    assert set(MODEL.available_effects) == set(emps.EFFECTS)
    for name, effect in emps.EFFECTS.items():
        model = MODEL.with_effects([name])
        assert model.base_model is MODEL and model.effects == (name,)
        inputs = measurement.experiment.input_matrix(model)
        off = model.parameters.vector({**dict(zip(MODEL.parameters.names, TRUTH)), **effect.off})
        y = simulate_batch(model, off, measurement.time, inputs, constants=AT_REST)
        np.testing.assert_array_equal(y, clean, err_msg=name)
        on = model.parameters.vector({**dict(zip(MODEL.parameters.names, TRUTH)), **effect.start})
        y = simulate_batch(model, on, measurement.time, inputs, constants=AT_REST)
        assert np.max(np.abs(y[:, 1] - clean[:, 1])) > 1e-3, name


def test_pulse_enters_the_volt_channel():
    """A 5 V pulse on a resting axis: logged vir jumps by 5 V at once, the load starts to move
    one sample later (unit delay) with acceleration gtau*5/M."""
    time = np.arange(200) * 1e-3
    pulse = np.where((time >= 0.05) & (time < 0.1), 5.0, 0.0)
    experiment = Experiment("pulse", time, {"qg": np.zeros_like(time), "pulse": pulse})
    theta = np.array([95.0, 0.0, 0.0, 0.0])
    y = simulate_batch(MODEL, theta, time, experiment.input_matrix(MODEL), constants=AT_REST)
    k = 50
    assert y[k, 1] == pytest.approx(5.0) and y[k + 1, 4] == 0.0
    accel = (y[k + 2, 4] - y[k + 1, 4]) / 1e-3
    expected = AT_REST[emps.C_GTAU] * 5.0 / 95.0
    assert accel == pytest.approx(expected, rel=1e-3)
    # no unit delay (actuation_delay at -dt): the pulse acts in its own sample interval;
    # half a sample: half the velocity gain in that interval
    model = MODEL.with_effects(["actuation_delay"])
    for tau, fraction in ((-1e-3, 1.0), (-5e-4, 0.5)):
        y = simulate_batch(model, np.append(theta, tau), time, experiment.input_matrix(model), constants=AT_REST)
        assert y[k + 1, 4] / 1e-3 == pytest.approx(fraction * expected, rel=1e-3)


def test_stiff_compliance_approaches_the_rigid_model(synthetic):
    """A 400 Hz, well-damped load mode barely changes the closed loop (20 Hz bandwidth): vir
    within 0.01 V rms of the rigid model (half the noise); a 10 Hz mode changes it by > 0.1 V."""
    measurement, clean = synthetic
    model = MODEL.with_effects(["compliance"])
    inputs = measurement.experiment.input_matrix(model)
    stiff = np.concatenate([TRUTH, [0.5, 400.0, 0.7]])
    soft = np.concatenate([TRUTH, [0.5, 10.0, 0.1]])
    y = simulate_batch(model, np.vstack([stiff, soft]), measurement.time, inputs, constants=AT_REST)
    rms = np.sqrt(np.mean((y[:, :, 1] - clean[None, :, 1]) ** 2, axis=1))
    assert rms[0] < 0.01 and rms[1] > 0.1, rms


# --------------------------------------------------------------------------------------
# ML identification
# --------------------------------------------------------------------------------------
def test_ml_recovers_known_parameters_from_synthetic_data(synthetic):
    """GN from the published values recovers TRUTH within 4 Cramér-Rao σ and 0.5 %; det R on
    (qm, force) gives the same estimate as on (qm, vir) (force = gtau·vir, det R is
    invariant to scaling a channel)."""
    measurement, _ = synthetic
    fit = estimate(FitProblem([measurement], constants=AT_REST), method="gn")
    assert fit.converged
    z = (fit.estimate - TRUTH) / fit.std
    assert np.all(np.abs(z) < 4), z
    np.testing.assert_allclose(fit.estimate, TRUTH, rtol=5e-3)
    gtau = AT_REST[emps.C_GTAU]
    as_force = Measurement("emps", measurement.experiment, ("qm", "force"), measurement.values * [1.0, gtau])
    lm = estimate(FitProblem([as_force], constants=AT_REST), method="lm")
    np.testing.assert_allclose(lm.estimate, fit.estimate, rtol=1e-6)


def test_ml_on_the_real_data_near_published(nominal_fit, estimation, validation):
    """Nominal model, ML on (qm, vir) of DATA_EMPS.mat. M and the offset land on the published
    IDIM-LS values (0.14 %, 0.1 %: within 1.5 published σ); Fv and Fc move by 13 % and -11 %
    together (the unit-delay model's loop is less damped than the rig's, and friction
    absorbs it; see the next test). The published values are also a worse fit of our model."""
    pub = {k: v for k, (v, _) in emps.PUBLISHED_IDIM_LS.items()}
    est = nominal_fit.as_dict()
    assert nominal_fit.converged
    assert est["M"] == pytest.approx(pub["M"], rel=5e-3)
    assert est["offset"] == pytest.approx(pub["offset"], abs=0.05)
    assert est["Fv"] == pytest.approx(pub["Fv"], rel=0.15)
    assert est["Fc"] == pytest.approx(pub["Fc"], rel=0.15)
    table = emps_comparison(nominal_fit, estimation, validation)
    rows = table.to_pandas()
    assert list(rows.index) == ["M", "Fv", "Fc", "offset"]
    assert rows.loc["M", "published"] == 95.1089
    val = table.errors["validation"]
    assert val["ml"]["force"] < val["published_parameters"]["force"] < 9.5
    assert val["published"]["force"] == 8.94
    assert "IDIM-LS" in table.summary()


def test_corrected_model_matches_published_asymmetric_variant(estimation, nominal_fit):
    """Without the unit delay (actuation_delay at -dt) and with direction-dependent viscous
    friction, ML gives Fv+ - Fv- = -73.0 N s/m: the published asymmetric IDIM-LS variant has
    166.7061 - 240.4236 = -73.72 (tolerance 2 N s/m); its offset-equivalent Coulomb asymmetry
    (20.144 - 20.628)/2 = -0.24 N matches our offset (-0.27 N, tolerance 0.1 N)."""
    model = MODEL.with_effects(["actuation_delay", "asymmetric_friction"])
    fit = fit_emps(estimation, model, fix={"actuation_delay_tau": -1e-3})
    assert fit.converged
    pub = emps_report_published()
    assert fit.value("asymmetric_friction_dFv") == pytest.approx(pub["Fv+"] - pub["Fv-"], abs=2.0)
    assert fit.value("offset") == pytest.approx(0.5 * (pub["Fc+"] - pub["Fc-"]), abs=0.1)
    assert fit.log_det_r < nominal_fit.log_det_r - 2.0
    table = emps_comparison(fit)
    assert table.reference == "IDIM-LS asymmetric-friction variant"
    assert list(table.to_pandas().index) == ["M", "Fv+", "Fv-", "Fc", "offset"]


def emps_report_published():
    from ema_uq.rigs.emps import PUBLISHED_ASYMMETRIC

    return PUBLISHED_ASYMMETRIC


def test_gap_names_the_loop_delay(estimation, validation):
    """Of a delay effect and Stribeck friction, the diagnosis keeps the actuation delay (at its
    bound: no unit delay) and the validation force error shrinks from 9.07 % to 5.6 %."""
    settings = replace(EMPS_STRATEGY.settings, max_effects=1)
    gap = diagnose([estimation], [validation], candidates=["actuation_delay", "stribeck"], settings=settings)
    assert gap.verdict == "effect" and gap.effect == "actuation_delay"
    assert gap.gap["before"] == pytest.approx(9.07, abs=0.05)
    assert gap.gap["after"] == pytest.approx(5.61, abs=0.1)
    ranking = gap.to_json()["ranking"]
    assert ranking[0]["effect"] == "actuation_delay" and ranking[0]["shrink"] > 0.35
    # the reported shrink is scored on the second half of the validation record (the first selects)
    assert gap.gap["shrink_record"].startswith("second half of held-out record")
    assert gap.gap["shrink"] > 0.35 and 0 < gap.gap["shrink_se"] < 0.05
    assert ranking[1]["effect"] == "stribeck" and abs(ranking[1]["shrink"]) < 0.01


def test_fault_diagnosis_holds_the_base_at_a_reference_fit(estimation, validation, nominal_fit):
    """Fault-diagnosis mode: the base parameters are held at a reference fit (here the nominal
    ML fit on the same record), only the effect's parameter is fitted; the delay is still named."""
    strategy = EMPS_STRATEGY.with_reference(nominal_fit.as_dict())
    settings = replace(strategy.settings, max_effects=1)
    gap = diagnose([estimation], [validation], candidates=["actuation_delay"], settings=settings, strategy=strategy)
    assert gap.nominal["estimate"] == nominal_fit.as_dict() and gap.nominal["iterations"] == 0
    assert gap.ranking[0].free_parameters == ["actuation_delay_tau"]
    assert gap.verdict == "effect" and gap.effect == "actuation_delay"
    assert gap.gap["before"] == pytest.approx(9.07, abs=0.05)


@pytest.mark.slow
def test_full_gap_diagnosis(estimation, validation):
    """All five effects, two rounds: actuation delay then asymmetric friction, validation force
    error 9.07 % -> 4.85 %."""
    gap = diagnose([estimation], [validation], settings=replace(EMPS_STRATEGY.settings, max_effects=3))
    assert gap.selected == ["actuation_delay", "asymmetric_friction"]
    assert gap.gap["after"] == pytest.approx(4.85, abs=0.1)


@pytest.mark.slow
def test_posterior_converges(estimation, nominal_fit):
    """emcee on the nominal model: R-hat < 1.01 and bulk/tail ESS >= 400 on M, Fv, Fc, offset."""
    from ema_uq import bayes
    from ema_uq.rigs.emps import emps_problem

    posterior = bayes.sample(emps_problem([estimation]), nominal_fit, seed=1)
    table = posterior.summary()
    assert (table["r_hat"] < 1.01).all()
    assert (table["ess_bulk"] >= 400).all() and (table["ess_tail"] >= 400).all()
