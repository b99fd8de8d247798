"""ema_uq: modelling, identification and uncertainty quantification of electromechanical
flap actuators (HT/LS and LT/HS concepts)."""
from __future__ import annotations

__version__ = "0.1.0"

from .params import Parameter, ParameterError, ParameterSet
from .models import get_model, concepts
from .experiments import Experiment, Measurement, deploy_retract, validation, synthesize, get_experiment
from .simulate import Trajectory, simulate, simulate_batch

__all__ = [
    "Parameter", "ParameterError", "ParameterSet", "get_model", "concepts", "Experiment",
    "Measurement", "deploy_retract", "validation", "synthesize", "get_experiment", "Trajectory",
    "simulate", "simulate_batch", "__version__",
]
