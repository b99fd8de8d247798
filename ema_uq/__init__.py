"""ema_uq: modelling, identification and uncertainty quantification of electromechanical
flap actuators (HT/LS and LT/HS concepts).

The names below are loaded on first use (PEP 562): ``import ema_uq`` and ``ema-uq --help`` do
not import numba, the models or scipy; ``from ema_uq import simulate`` loads what it needs.
"""
from __future__ import annotations

from importlib import import_module

__version__ = "0.1.0"

#: public name -> the submodule that defines it
_LAZY = {
    "Parameter": "params", "ParameterError": "params", "ParameterSet": "params",
    "get_model": "models", "concepts": "models",
    "Experiment": "experiments", "Measurement": "experiments", "deploy_retract": "experiments",
    "validation": "experiments", "synthesize": "experiments", "get_experiment": "experiments",
    "Trajectory": "simulate", "simulate": "simulate", "simulate_batch": "simulate",
}

__all__ = [
    "Parameter", "ParameterError", "ParameterSet", "get_model", "concepts", "Experiment",
    "Measurement", "deploy_retract", "validation", "synthesize", "get_experiment", "Trajectory",
    "simulate", "simulate_batch", "__version__",
]


def __getattr__(name: str):
    module = _LAZY.get(name)
    if module is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(import_module(f".{module}", __name__), name)
    globals()[name] = value          # later look-ups skip this hook
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(__all__))
