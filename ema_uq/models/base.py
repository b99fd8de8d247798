"""The model description shared by every concept: named states, inputs, outputs,
estimated parameters and design constants (python-control style named signals).

The equations themselves live in numba functions in each concept module; this object
only carries names, units, layouts and defaults so that numerics stay array-based.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import numpy as np

from ..params import ParameterError, ParameterSet

#: Inputs every EMA concept accepts, in kernel column order. ``brake`` is optional in
#: data files (absent = released, as in every rig identification run).
INPUTS = ("phi_r", "F_ER1", "F_ER2", "brake")
REQUIRED_INPUTS = ("phi_r", "F_ER1", "F_ER2")
INPUT_UNITS = {"phi_r": "rad", "F_ER1": "N", "F_ER2": "N", "brake": "1"}


@dataclass(frozen=True)
class Model:
    """A concept's signature and defaults.

    Attributes
    ----------
    name, model_id : registry name and the integer the compiled kernel dispatches on.
    states : names of the integrated states, in state-vector order.
    outputs : names of the measurable output channels, in output-array order.
    output_units : unit of each output channel.
    parameters : the estimated parameters Θ (their nominal values are the defaults).
    constants : design constants and model settings (all fixed), in kernel order.
    integration_step : fixed RK4 step [s] known to be converged below the noise level.
    derive : constants computed once per simulation from ``constants`` (appended in kernel order).
    """

    name: str
    model_id: int
    title: str
    states: tuple[str, ...]
    outputs: tuple[str, ...]
    output_units: tuple[str, ...]
    parameters: ParameterSet
    constants: ParameterSet
    integration_step: float
    derive: Callable[[np.ndarray], np.ndarray]
    inputs: tuple[str, ...] = INPUTS
    required_inputs: tuple[str, ...] = REQUIRED_INPUTS

    @property
    def n_states(self) -> int:
        return len(self.states)

    @property
    def n_outputs(self) -> int:
        return len(self.outputs)

    def output_index(self, channels) -> np.ndarray:
        """Positions of the named channels in the output array (unknown names are an error)."""
        index = []
        for ch in channels:
            if ch not in self.outputs:
                raise ParameterError(
                    f"unknown output channel {ch!r} for concept {self.name}; "
                    f"known channels: {', '.join(self.outputs)}"
                )
            index.append(self.outputs.index(ch))
        return np.array(index, dtype=np.int64)

    def unit_of(self, channel: str) -> str:
        if channel in INPUT_UNITS:
            return INPUT_UNITS[channel]
        return self.output_units[self.output_index([channel])[0]]

    def constants_vector(self, overrides: dict[str, float] | None = None) -> np.ndarray:
        return self.constants.vector(overrides)

    def kernel_constants(self, constants: np.ndarray | None = None) -> np.ndarray:
        """Design constants followed by the values derived from them, as the kernel reads them."""
        c = self.constants_vector() if constants is None else np.asarray(constants, dtype=np.float64)
        return np.ascontiguousarray(np.concatenate([c, self.derive(c)]))

    def split_assignments(self, values: dict[str, float]) -> tuple[dict[str, float], dict[str, float]]:
        """Sort ``NAME=VALUE`` settings into estimated parameters and design constants."""
        params, consts = {}, {}
        for name, value in values.items():
            if name in self.parameters:
                params[name] = value
            elif name in self.constants:
                consts[name] = value
            else:
                raise ParameterError(
                    f"unknown parameter or constant {name!r} for concept {self.name}; parameters: "
                    f"{', '.join(self.parameters.names)}; constants: {', '.join(self.constants.names)}"
                )
        return params, consts
