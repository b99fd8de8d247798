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
