"""``ema-uq simulate`` run as a user runs it (``python -m ema_uq``, a fresh process)."""
from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest

from ema_uq import get_model, io, synthesize
from ema_uq.experiments import deploy_retract


def run_cli(*args, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ema_uq", *map(str, args)],
                          capture_output=True, text=True, cwd=cwd, timeout=300)


def assert_one_line_error(result: subprocess.CompletedProcess, *fragments: str) -> str:
    assert result.returncode == 2, result.stderr
    assert result.stdout == ""
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1, result.stderr  # one line, no traceback
    assert lines[0].startswith("ema-uq: error: "), lines[0]
    for fragment in fragments:
        assert fragment in lines[0], lines[0]
    return lines[0]


SIMULATE = ("simulate", "--concept", "htls", "--experiment", "deploy-retract")


@pytest.fixture(scope="module")
def simulated(tmp_path_factory):
    """Three runs: seed 0 to NetCDF and to CSV, seed 1 to NetCDF."""
    d = tmp_path_factory.mktemp("simulate")
    runs = {"a.nc": 0, "b.csv": 0, "c.nc": 1}
    results = {name: run_cli(*SIMULATE, "--seed", seed, "--out", d / name) for name, seed in runs.items()}
    return d, results


def test_simulate_success_writes_a_readable_file(simulated):
    d, results = simulated
    for name, result in results.items():
        assert result.returncode == 0, result.stderr
        assert result.stderr == ""
        summary = result.stdout.strip().splitlines()
        assert len(summary) == 1 and name in summary[0] and "3800 samples x 16 channels" in summary[0]
    m = io.read_measurement(d / "a.nc", concept="htls")
    assert m.channels == get_model("htls").outputs
    assert m.experiment.name == "deploy-retract" and m.experiment.n_samples == 3800
    assert m.attrs["noise_fraction"] == 0.02 and m.attrs["seed"] == 0 and m.attrs["source"] == "simulated"


def test_simulate_matches_the_library_and_is_seeded(simulated):
    d, _ = simulated
    a, b, c = (io.read_measurement(d / name) for name in ("a.nc", "b.csv", "c.nc"))
    np.testing.assert_array_equal(a.values, b.values)  # same seed: identical, in either format
    assert not np.allclose(a.values, c.values)          # another seed: other noise
    expected = synthesize("htls", deploy_retract(), noise=0.02, seed=0)
    np.testing.assert_array_equal(a.values, expected.values)
    assert c.attrs["seed"] == 1


def test_simulate_set_channels_and_no_noise(tmp_path):
    out = tmp_path / "lths.csv"
    result = run_cli("simulate", "--concept", "lths", "--experiment", "deploy-retract", "--noise", "0",
                     "--set", "J=5e-4", "--set", "r=0.018", "--channels", "Omega,y1", "U_A", "--out", out)
    assert result.returncode == 0, result.stderr
    m = io.read_measurement(out, concept="lths")
    assert m.channels == ("Omega", "y1", "U_A")
    model = get_model("lths")
    expected = synthesize(model, deploy_retract(), model.parameters.vector({"J": 5e-4}), noise=0.0,
                          channels=m.channels, constants=model.constants_vector({"r": 0.018}))
    np.testing.assert_array_equal(m.values, expected.values)


@pytest.mark.parametrize("args, fragments", [
    (("simulate", "--concept", "xyz", "--experiment", "deploy-retract"), ("invalid choice: 'xyz'", "htls", "lths")),
    (SIMULATE + ("--set", "J_x=1"), ("unknown parameter or constant 'J_x'", "parameters: J")),
    (SIMULATE + ("--set", "J=-1"), ("J = -1 lies outside its bounds",)),
    (SIMULATE + ("--set", "J"), ("cannot read 'J'", "NAME=VALUE")),
    (SIMULATE + ("--noise", "-0.1"), ("argument --noise",)),
    (SIMULATE + ("--channels", "Omega", "Volts"), ("unknown output channel 'Volts'",)),
    (SIMULATE + ("--effect", "friction_x:delta=0.001"), ("--effect of concept htls: unknown effect 'friction_x'", "backlash")),
    (SIMULATE + ("--effect", "backlash:delta"), ("cannot read effect 'backlash:delta'",)),
    (SIMULATE + ("--effect", "backlash:delta=nan"), ("backlash_delta = nan is not finite",)),
], ids=["unknown-concept", "unknown-set-name", "set-out-of-bounds", "malformed-set", "negative-noise",
        "unknown-channel", "unknown-effect", "malformed-effect", "infinite-effect"])
def test_simulate_bad_input(tmp_path, args, fragments):
    out = tmp_path / "x.nc"
    assert_one_line_error(run_cli(*args, "--out", out), *fragments)
    assert not out.exists()


def test_simulate_without_out():
    assert_one_line_error(run_cli(*SIMULATE), "the following arguments are required: --out")


def test_simulate_bad_extension(tmp_path):
    out = tmp_path / "x.txt"
    assert_one_line_error(run_cli(*SIMULATE, "--out", out), str(out), "unknown file extension '.txt'")
    assert not out.exists()


def test_simulate_unwritable_out(tmp_path):
    blocker = tmp_path / "plain-file"
    blocker.write_text("not a directory")
    assert_one_line_error(run_cli(*SIMULATE, "--out", blocker / "x.nc"), "is a file, not a directory")


def test_no_verb_is_a_one_line_error():
    assert_one_line_error(run_cli(), "required", "simulate")


# --------------------------------------------------------------------------------------
# study settings: one route (--study + ema_uq.study.settings_for), options override it
# --------------------------------------------------------------------------------------
STUDY = {"name": "t", "concept": "htls", "seed": 5,
         "data": {"noise": 0.01, "set": {"J": 0.06, "k_y": 1.1}, "channels": ["Omega", "y1"]},
         "identify": {"methods": ["gn"], "perturb": 0.1, "max_iterations": 7, "fix": ["J"]},
         "sample": {"ensembles": 3, "integrator": "hybrid"},
         "identifiability": {"profile_points": 5},
         "gap": {"rig_effects": ["backlash"], "candidates": ["backlash"], "selfcheck": "quick"}}


@pytest.fixture()
def study_file(tmp_path):
    import yaml

    path = tmp_path / "t.yaml"
    path.write_text(yaml.safe_dump(STUDY))
    return path


def parsed(*argv):
    from ema_uq.cli import _apply_study, _given_options, build_parser

    args = build_parser().parse_args(list(map(str, argv)))
    _apply_study(args, _given_options(list(map(str, argv))))
    return args


def test_every_study_verb_takes_its_settings_from_the_study_and_data_set_reaches_it(study_file):
    from ema_uq.study import STUDY_VERBS, load_study, settings_for

    study = load_study(study_file)
    assert settings_for(study, "simulate", role="rig_validation") == {
        "experiment": "validation", "noise": 0.01, "seed": 3005, "set": {"J": 0.06, "k_y": 1.1},
        "channels": ["Omega", "y1"], "effect": ["backlash"]}
    assert settings_for(study, "simulate", role="estimation")["effect"] == []
    for verb in ("identify", "sample", "identifiability", "gap"):
        assert settings_for(study, verb)["set"] == {"J": 0.06, "k_y": 1.1}, verb
    assert set(STUDY_VERBS) >= {"simulate", "identify", "sample", "sensitivity", "identifiability", "gap",
                                "gap-selfcheck"}
    a = parsed("identify", "d.nc", "--concept", "htls", "--study", study_file, "--out", "f.json")
    assert (a.seed, a.perturb, a.max_iterations, a.fix, a.channels) == (5, 0.1, 7, ["J"], ["Omega", "y1"])
    assert a.set == ["J=0.06", "k_y=1.1"]
    s = parsed("sample", "d.nc", "--concept", "htls", "--study", study_file, "--init", "f.json", "--out", "p.nc")
    assert (s.chains, s.integrator, s.max_steps, s.set) == (3, "hybrid", 20000, ["J=0.06", "k_y=1.1"])
    g = parsed("gap", "d.nc", "--concept", "htls", "--study", study_file, "--out", "g.json")
    assert (g.candidates, g.channels, g.set) == (["backlash"], ["Omega", "y1"], ["J=0.06", "k_y=1.1"])
    i = parsed("identifiability", "d.nc", "--concept", "htls", "--study", study_file, "--init", "f.json",
               "--out", "i.json")
    assert (i.profile_points, i.profile_sigmas, i.sensor_sets) == (5, 4.0, ["full", "realistic"])
    c = parsed("gap-selfcheck", "--study", study_file, "--out", "s.json")
    assert (c.seed, c.quick, c.concepts) == (5, True, ["htls"])


def test_options_on_the_command_line_override_the_study(study_file):
    a = parsed("identify", "d.nc", "--concept", "htls", "--study", study_file, "--perturb", "0", "--seed", "0",
               "--set", "J=0.07", "--out", "f.json")
    assert (a.perturb, a.seed, a.max_iterations) == (0.0, 0, 7)
    assert a.set == ["J=0.06", "k_y=1.1", "J=0.07"]  # the later item wins, name by name
    i = parsed("identifiability", "d.nc", "--concept", "htls", "--study", study_file, "--init", "f.json",
               "--profile-points", "9", "--out", "i.json")
    assert i.profile_points == 9
    plain = parsed("identify", "d.nc", "--concept", "htls", "--out", "f.json")
    assert (plain.perturb, plain.seed, plain.set) == (0.0, 0, [])  # no study: the verb's own defaults


def test_simulate_from_a_study_role_equals_the_explicit_options(study_file, tmp_path):
    by_study = run_cli("simulate", "--concept", "htls", "--study", study_file, "--role", "rig_estimation",
                       "--out", tmp_path / "a.nc")
    assert by_study.returncode == 0, by_study.stderr
    explicit = run_cli(*SIMULATE, "--noise", "0.01", "--seed", "2005", "--set", "J=0.06", "--set", "k_y=1.1",
                       "--channels", "Omega", "y1", "--effect", "backlash", "--out", tmp_path / "b.nc")
    assert explicit.returncode == 0, explicit.stderr
    a, b = io.read_measurement(tmp_path / "a.nc"), io.read_measurement(tmp_path / "b.nc")
    assert a.channels == b.channels == ("Omega", "y1") and np.array_equal(a.values, b.values)
    assert_one_line_error(run_cli("simulate", "--concept", "htls", "--role", "estimation", "--out", tmp_path / "c.nc"),
                          "--study")
    assert_one_line_error(run_cli("simulate", "--concept", "lths", "--study", study_file, "--role", "estimation",
                                  "--out", tmp_path / "c.nc"), "concept htls")
    assert_one_line_error(run_cli("simulate", "--concept", "htls", "--out", tmp_path / "c.nc"), "--experiment")
