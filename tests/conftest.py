"""Make ``tests/`` importable so tests and benchmarks can ``import reference_scipy``."""
import os
import sys

_HERE = os.path.dirname(os.path.abspath(__file__))
if _HERE not in sys.path:
    sys.path.insert(0, _HERE)


import pytest  # noqa: E402


@pytest.fixture(scope="session", autouse=True)
def compiled_simulator():
    """Compile (or load from numba's cache) the simulator once before any test, so that no CLI
    test sees the one-line first-compilation notice on stderr depending on which test ran first."""
    import ema_uq as eu

    model = eu.get_model("htls")
    experiment = eu.deploy_retract()
    eu.simulate_batch(model, model.parameters.nominal, experiment.time, experiment.input_matrix(model))


@pytest.fixture(scope="session")
def short_htls_record(tmp_path_factory):
    """A short HT/LS record as a CSV file (the first 2 s of deploy-retract, every channel, no noise)."""
    from ema_uq import get_model, io, simulate_batch
    from ema_uq.experiments import Measurement, deploy_retract

    model = get_model("htls")
    exp = deploy_retract().slice(0, 200)
    values = simulate_batch(model, model.parameters.nominal, exp.time, exp.input_matrix(model))
    path = tmp_path_factory.mktemp("records") / "est.csv"
    io.write_measurement(path, Measurement("htls", exp, model.outputs, values))
    return path
