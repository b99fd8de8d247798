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
    (SIMULATE + ("--effect", "friction_x:delta=0.001"), ("unknown effect 'friction_x'", "backlash")),
    (SIMULATE + ("--effect", "backlash:delta"), ("cannot read --effect",)),
], ids=["unknown-concept", "unknown-set-name", "set-out-of-bounds", "malformed-set", "negative-noise",
        "unknown-channel", "unknown-effect", "malformed-effect"])
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
