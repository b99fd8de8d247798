"""The model description shared by every concept: named states, inputs, outputs,
estimated parameters and design constants (python-control style named signals).

The equations themselves live in numba functions in each concept module; this object
only carries names, units, layouts and defaults so that numerics stay array-based.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from ..params import ParameterError, ParameterSet

#: Inputs every EMA concept accepts, in kernel column order. ``brake`` is optional in
#: data files (absent = released, as in every rig identification run).
INPUTS = ("phi_r", "F_ER1", "F_ER2", "brake")
REQUIRED_INPUTS = ("phi_r", "F_ER1", "F_ER2")
INPUT_UNITS = {"phi_r": "rad", "F_ER1": "N", "F_ER2": "N", "brake": "1",
               "qg": "m", "pulse": "V",  # qg, pulse: EMPS (reference position, drive pulse)
               "x_sp": "m", "F_load": "N"}  # x_sp, F_load: Cranfield (position set point, load force)

#: The one table of compiled-kernel ids: concept -> (id of its nominal right-hand side, id of
#: its right-hand side with the unmodelled effects of ``effect_kernels.py``, or None). The
#: registry (``models/__init__.py``) holds exactly the concepts named here, each concept module
#: takes its ``model_id`` from here, and ``simulate.py`` has one static branch per id in its
#: dispatch helpers (numba compiles branches, not look-ups in a table of functions) and refuses
#: every other id. A new concept: its module, its line here, its branches in ``simulate.py``
#: (none for a concept with its own ``batch_simulator``, as EMPS).
KERNEL_IDS: dict[str, tuple[int, int | None]] = {
    "htls": (0, 100),
    "lths": (1, 101),
    "emps": (2, None),  # its own compiled simulator (Model.batch_simulator)
    "cranfield": (3, None),  # its own compiled simulator (Model.batch_simulator)
}


@dataclass(frozen=True)
class Model:
    """A concept's signature and defaults.

    Attributes
    ----------
    name, model_id : registry name and the integer the compiled kernel dispatches on
        (:data:`KERNEL_IDS`).
    states : names of the integrated states, in state-vector order.
    outputs : names of the measurable output channels, in output-array order.
    output_units : unit of each output channel.
    parameters : the estimated parameters Θ (their nominal values are the defaults).
    constants : design constants and model settings (all fixed), in kernel order.
    integration_step : fixed RK4 step [s] of every simulation, converged to ~1e-6 of each output's range.
    converged_step : the coarser RK4 step the model contract states converged well under the noise
        (docs/MODEL_SPEC.md: HT/LS 1 ms, LT/HS 0.5 ms) for the nominal dynamics; None: none stated.
    at_converged_step : integrate by RK4 at ``converged_step`` (see :attr:`rk4_step`), for
        campaigns of many fits where an output error of ~1e-5 of its range is immaterial (the gap
        diagnosis's ``converged_step`` option). Augmented models inherit the flag.
    integrator : "dopri5" (adaptive Dormand-Prince 5(4), tolerance ``rtol``, absolute
        tolerance ``rtol * state_scales``), "hybrid" (exact steps over the sample intervals
        where the concept is linear, "dopri5" elsewhere) or "rk4" (fixed :attr:`rk4_step`).
    state_scales : typical magnitude of each state (state units), the adaptive error scale.
    derive : constants computed once per simulation from ``constants`` (appended in kernel order).
    sensor_sets : named sets of output channels, e.g. ``"full"`` (every output) and
        ``"realistic"`` (the sensors of the rig), as the identifiability study compares them.
    loss_referral : ``f(constants by name) -> {loss parameter: factor}``, how each friction
        and damping parameter is referred to the motor shaft (see :meth:`loss_factors`).
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
    integrator: str = "rk4"
    rtol: float = 3e-8
    converged_step: float | None = None
    at_converged_step: bool = False
    state_scales: tuple[float, ...] = ()
    sensor_sets: Mapping[str, tuple[str, ...]] = field(default_factory=dict, compare=False, repr=False)
    loss_referral: Callable[[Mapping[str, float]], dict[str, float]] | None = field(
        default=None, compare=False, repr=False)
    #: a concept with its own compiled simulator (e.g. a discrete controller around a
    #: continuous plant) sets this; ``simulate_batch`` then calls
    #: ``batch_simulator(model, thetas, inputs, kernel_constants, x0, dt, n_sub)``.
    batch_simulator: Callable | None = None
    #: unmodelled effects (models/effects.py): the active effects of this model object,
    #: the effects the concept supports (name -> Effect), the concept's builder of augmented
    #: models ``augment(model, names, values) -> Model``, an optional output post-processing
    #: step ``postprocess(model, thetas, time, out) -> out`` run by ``simulate_batch`` after
    #: the kernel, and the nominal model an augmented one was built from.
    effects: tuple[str, ...] = ()
    effect_catalogue: Mapping[str, Any] = field(default_factory=dict, compare=False, repr=False)
    augment: Callable | None = field(default=None, compare=False, repr=False)
    postprocess: Callable | None = field(default=None, compare=False, repr=False)
    built_from: "Model | None" = field(default=None, compare=False, repr=False)

    def __post_init__(self) -> None:
        for set_name, channels in self.sensor_sets.items():
            stray = [ch for ch in channels if ch not in self.outputs]
            if stray:
                raise ParameterError(f"sensor set {set_name!r} of concept {self.name} names unknown output "
                                     f"{stray[0]!r}; outputs: {', '.join(self.outputs)}")

    @property
    def rk4_step(self) -> float:
        """The fixed RK4 step [s] a simulation of this model takes: ``converged_step`` when
        ``at_converged_step`` is set and no active effect brings dynamics faster than the nominal
        ones (``Effect.fast_dynamics``: a mode, a play's relaxation, a forcing at motor-angle
        order), which the contract's step was not verified for; else ``integration_step``."""
        if not self.at_converged_step or self.converged_step is None:
            return self.integration_step
        catalogue = self.base_model.effect_catalogue
        if any(getattr(catalogue.get(name), "fast_dynamics", False) for name in self.effects):
            return self.integration_step
        return self.converged_step

    # --- drive-train structure ------------------------------------------------------
    def loss_factors(self, constants: np.ndarray | None = None) -> dict[str, float]:
        """Factor f_j with which each loss parameter enters the load torque at the motor shaft
        (MODEL_SPEC: M = Σ f_B B Ω + Σ f_C C sgn(·)) at the design ``constants`` (default:
        nominal); losses with the same speed argument whose factors are known act only through
        Σ f_j θ_j. Empty for a concept without ``loss_referral``."""
        if self.loss_referral is None:
            return {}
        c = self.constants_vector() if constants is None else constants
        return self.loss_referral(dict(zip(self.constants.names, c)))

    # --- unmodelled effects ---------------------------------------------------------
    @property
    def base_model(self) -> "Model":
        """The nominal model this one was built from (``self`` for a nominal model)."""
        return self if self.built_from is None else self.built_from

    @property
    def available_effects(self) -> tuple[str, ...]:
        """Names of the effects ``with_effects`` accepts for this concept."""
        return tuple(self.base_model.effect_catalogue)

    def with_effects(self, names: Sequence[str], values: Mapping[str, float] | None = None) -> "Model":
        """The model with the named effects switched on (``self`` for an empty list).

        Parameters are the nominal ones followed by each effect's (in ``names`` order) with the
        effect's nominal values, overridden by ``values`` (full parameter names, e.g.
        ``backlash_delta``). On an augmented model the new effects join the active ones (their
        current values kept). Unknown, unavailable or repeated names are a one-line ``ParameterError``.
        """
        if isinstance(names, str):
            names = (names,)
        names = tuple(names)
        values = dict(values or {})
        if not names:
            if values:
                raise ParameterError("effect values given without effects; name the effects to switch on")
            return self
        base = self.base_model
        if self.effects:  # compose: rebuild from the nominal model, keeping current effect values
            current = {n: p.nominal for n, p in zip(self.parameters.names, self.parameters)
                       if n not in base.parameters}
            return base.with_effects(self.effects + names, {**current, **values})
        available = self.available_effects
        unknown = [n for n in names if n not in available]
        if unknown:
            raise ParameterError(f"effect {unknown[0]!r} is not available for concept {self.name}; "
                                 f"available effects: {', '.join(available) or 'none'}")
        repeated = sorted({n for n in names if names.count(n) > 1})
        if repeated:
            raise ParameterError(f"effect {repeated[0]} is named twice; switch each effect on once")
        allowed = [p.name for n in names for p in self.effect_catalogue[n].parameters]
        stray = [k for k in values if k not in allowed]
        if stray:
            raise ParameterError(f"value for {stray[0]!r} does not belong to effect(s) {', '.join(names)}; "
                                 f"their parameters: {', '.join(allowed)}")
        if self.augment is None:
            raise ParameterError(f"concept {self.name} cannot add effects (no augment function)")
        return self.augment(self, names, values)

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
