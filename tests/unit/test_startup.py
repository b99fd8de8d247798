"""Start-up: the parser builds without numpy, numba or any model; the names the CLI keeps
for that agree with the package; ``import ema_uq`` is lazy; ``ema-uq compile`` runs every
kernel path."""
from __future__ import annotations

import json
import subprocess
import sys

from ema_uq import cli


def _modules_after(code: str) -> set[str]:
    out = subprocess.run([sys.executable, "-c", code + "\nimport sys, json; print(json.dumps(sorted(sys.modules)))"],
                         capture_output=True, text=True, check=True)
    return set(json.loads(out.stdout.strip().splitlines()[-1]))


def test_help_and_import_load_no_numerics():
    heavy = {"numpy", "numba", "scipy", "matplotlib", "xarray", "arviz", "emcee", "ema_uq.simulate"}
    loaded = _modules_after("from ema_uq import cli\ncli.build_parser().format_help()")
    assert not heavy & loaded
    assert not heavy & _modules_after("import ema_uq")


def test_fitting_modules_load_neither_scipy_stats_nor_matplotlib():
    # ~0.5 s each of a warm `identify` went to importing them; the fit needs neither
    loaded = _modules_after("import ema_uq.identify, ema_uq.identify.validation, ema_uq.statistics, "
                            "ema_uq.report.outputs")
    assert not {"scipy.stats", "matplotlib"} & loaded


def test_cli_names_agree_with_the_package():
    from ema_uq.experiments import EXPERIMENTS
    from ema_uq.models import concepts

    assert cli.CONCEPTS == concepts()
    assert cli.EXPERIMENT_NAMES == tuple(EXPERIMENTS)


def test_lazy_package_names_resolve():
    import ema_uq
    from ema_uq.simulate import simulate_batch

    assert ema_uq.simulate_batch is simulate_batch
    assert set(ema_uq.__all__) <= set(dir(ema_uq))
    try:
        ema_uq.no_such_name
    except AttributeError as exc:
        assert "no_such_name" in str(exc)
    else:
        raise AssertionError("unknown attribute resolved")


def test_get_model_loads_on_demand_and_refuses_unknown_concepts():
    from ema_uq.models import UnknownConceptError, get_model

    assert get_model("lths") is get_model("lths")
    try:
        get_model("nope")
    except UnknownConceptError as exc:
        assert "htls" in str(exc)
    else:
        raise AssertionError("unknown concept accepted")


def test_compile_verb_runs_every_path(tmp_path):
    out = tmp_path / "compiled.json"
    assert cli.main(["compile", "--concept", "htls", "--out", str(out)]) == 0
    rows = json.loads(out.read_text())["paths"]
    labels = [r["path"] for r in rows]
    assert {"htls rk4", "htls dopri5", "htls hybrid shared steps"} <= set(labels)
    assert any("+" in label for label in labels) and any("self-check" in label for label in labels)
    assert all(r["status"] == "ok" for r in rows)
