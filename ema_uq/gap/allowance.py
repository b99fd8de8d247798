"""The model-form allowance of the gap diagnosis (method version 2): nuisance freedoms every rig has.

Why
---
A rig with no unmodelled mechanism still differs from its model in two ways the diagnosis
cannot know in advance, and which leave a deterministic, state-predictable residual that looks
like a mechanism:

* **kinematic tolerance**: the drive train's geometry is known to drawing and assembly
  tolerance only. The *kinematic design constants* are those that fix the geometry of the power
  path between motor and carriage: every transmission ratio (constants ``i_*``: bevel gears,
  magnetic gearbox), the ball screw's rolling radius ``r`` and lead angle ``gamma``, and the
  U-joint angles (``beta*``). They are a physical class, selected by :func:`kinematic_constants`
  from the concept's constants; excluded are software settings (the command scaling ``k_y``, the
  controller and voltage limits, the brake law, the smoothing widths), which a rig sets exactly,
  and stiffnesses that are zero nominally (a relative offset of zero is none). Each constant gets
  a relative offset ``delta`` (c -> c (1 + delta)), bounded by ``tolerance`` (5 %: the usual
  manufacturing and assembly tolerance of a gear ratio, a screw's effective radius or a joint
  angle) and carrying a weak Gaussian prior of standard deviation ``tolerance / 2`` (the
  tolerance as a 2-sigma band), so that directions the data barely see stay near zero.
* **command lag**: a rig's command path conditions the position command (a smoothing filter,
  a rate limit) and the record does not say so. The allowance is a first-order lag of the
  position command ``phi_r``, time constant in ``[0, tau_max]``, applied to the inputs before
  simulation, exact for a command that is linear between samples (first-order hold), so that it
  is smooth in tau down to zero (a lag much shorter than a sample acts as a delay of tau).
  ``tau_max`` is a tenth of the position loop's time constant (the slowest closed-loop mode of
  the nominal model's linear regime: about 0.9 s on HT/LS, 1.1 s on LT/HS): a conditioning filter
  is kept a decade above the loop's bandwidth, else it would be part of the loop's design and on
  record.

The allowance parameters (``mf_<constant>``, ``mf_command_lag``) are fitted in the nominal model
and in every candidate model alike (free in every refit, the screening refit included), never
candidates and never named. They count equally in every model, so they cancel in every
comparison (ΔBIC, held-out gain, family evidence). A catalogue effect has to beat the nominal
model *with* the allowance: a pure command lag no longer reads as a sensor delay.

How it simulates
----------------
:meth:`ModelFormAllowance.wrap` turns a model (nominal or with effects) into an
:class:`AllowedModel`: the same model with the allowance parameters appended to its parameter
set. :func:`ema_uq.simulate.simulate_batch` hands an ``AllowedModel`` to its ``simulate_own``,
which groups the parameter sets by their allowance values and runs the wrapped model once per
distinct group with those constants and that filtered command (a finite-difference column of an
allowance parameter is one extra call of one set). The compiled kernels are untouched: with the
allowance off nothing of this runs, and with every allowance value zero the wrapped model's
outputs are bit for bit those of the model itself.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Any, Mapping, Sequence

import numpy as np

from ..errors import EmaUqError
from ..models.base import Model
from ..models.effects import first_order_lag
from ..params import Parameter, ParameterSet
from ..simulate import simulate_batch
from ..simulate.dispatch import SimulationError, kernel_family
from ..simulate.linear import linear_state_matrices

#: relative tolerance of a kinematic design constant (the bound of its offset)
KINEMATIC_TOLERANCE = 0.05
#: the command lag's bound as a fraction of the position loop's time constant
COMMAND_LAG_FRACTION = 0.1
PREFIX = "mf_"
LAG_NAME = PREFIX + "command_lag"
COMMAND_INPUT = "phi_r"


class AllowanceError(EmaUqError):
    """A model-form allowance that cannot be built (bad tolerance or lag bound, no such constant)."""


def kinematic_constants(model: Model) -> tuple[str, ...]:
    """The kinematic design constants of a concept (module docstring): transmission ratios
    (``i_*``), screw rolling radius ``r`` and lead angle ``gamma``, U-joint angles ``beta*``,
    each with a non-zero nominal value."""
    names = model.constants.names
    nominal = model.constants_vector()
    out = []
    for name, value in zip(names, nominal):
        geometric = name.startswith("i_") or name in ("r", "gamma") or (name.startswith("beta") and name[4:].isdigit())
        if geometric and value != 0.0:
            out.append(name)
    return tuple(out)


def position_loop_time_constant(model: Model) -> float | None:
    """1 / |slowest non-zero closed-loop mode| of the concept's linear regime at its nominal
    parameters and constants (the position loop); None for a concept without a linear regime."""
    try:
        family = kernel_family(model)
    except SimulationError:  # a concept with a simulator of its own (EMPS, Cranfield) declares none
        return None
    base = model if family == "nominal" else model.base_model
    a = linear_state_matrices(base, base.parameters.nominal)[0]
    rates = np.abs(np.linalg.eigvals(a).real)
    rates = rates[rates > 1e-9 * max(float(np.max(rates)), 1e-300)]
    return None if rates.size == 0 else float(1.0 / np.min(rates))


def command_lag(values: np.ndarray, tau: float, dt: float) -> np.ndarray:
    """``values`` (n,) through the first-order lag of time constant ``tau`` [s] of
    :func:`ema_uq.models.effects.first_order_lag` (exact for an input linear between samples,
    unit static gain, smooth down to tau = 0). A negative tau (finite differences at the bound)
    is a lead of |tau| by linear interpolation."""
    values = np.asarray(values, dtype=float)
    if tau == 0.0 or values.size < 2:
        return values.copy()
    if tau < 0.0:
        # below the bound (a central finite difference at tau = 0): the continuation of the small-tau
        # limit, a lead of |tau| by linear interpolation, capped at one sample
        f = min(-tau / dt, 1.0)
        return np.concatenate([values[:-1] + f * np.diff(values), values[-1:]])
    return first_order_lag(values, tau, dt)


@dataclass(frozen=True)
class ModelFormAllowance:
    """Relative offsets of ``constants`` (each within +-``tolerance``, prior sd ``tolerance / 2``)
    and a first-order lag of the position command within [0, ``lag_max``] s (0: no lag freedom)."""

    constants: tuple[str, ...]
    tolerance: float = KINEMATIC_TOLERANCE
    lag_max: float = 0.0
    position_loop_time_constant: float | None = None

    def __post_init__(self) -> None:
        if not (math.isfinite(self.tolerance) and 0.0 < self.tolerance < 1.0):
            raise AllowanceError(f"kinematic tolerance must lie in (0, 1), got {self.tolerance!r}")
        if not (math.isfinite(self.lag_max) and self.lag_max >= 0.0):
            raise AllowanceError(f"command lag bound must be finite and >= 0 s, got {self.lag_max!r}")
        if not self.constants and self.lag_max == 0.0:
            raise AllowanceError("a model-form allowance needs kinematic constants or a command lag bound > 0")

    @property
    def parameters(self) -> tuple[Parameter, ...]:
        out = [Parameter(PREFIX + c, "1", 0.0, -self.tolerance, self.tolerance, prior_std=self.tolerance / 2.0,
                         description=f"relative offset of design constant {c} (model-form allowance)")
               for c in self.constants]
        if self.lag_max > 0.0:
            out.append(Parameter(LAG_NAME, "s", 0.0, 0.0, self.lag_max,
                                 description="first-order lag of the position command (model-form allowance)"))
        return tuple(out)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.parameters)

    def wrap(self, model: Model) -> "AllowedModel":
        """``model`` with the allowance parameters appended (an AllowedModel is re-wrapped from its inner model)."""
        inner = model.inner if isinstance(model, AllowedModel) else model
        missing = [c for c in self.constants if c not in inner.constants.names]
        if missing:
            raise AllowanceError(f"concept {inner.name} has no design constant {missing[0]!r}; "
                                 f"its constants: {', '.join(inner.constants.names)}")
        if self.lag_max > 0.0 and COMMAND_INPUT not in inner.inputs:
            raise AllowanceError(f"concept {inner.name} has no position command {COMMAND_INPUT!r} to lag")
        clash = [n for n in self.names if n in inner.parameters.names]
        if clash:
            raise AllowanceError(f"model-form allowance parameter {clash[0]} clashes with a parameter of {inner.name}")
        values = {f.name: getattr(inner, f.name) for f in fields(Model)}
        values["parameters"] = ParameterSet(tuple(inner.parameters) + self.parameters)
        return AllowedModel(**values, inner=inner, allowance=self)

    def apply(self, values: np.ndarray, constants: np.ndarray, inputs: np.ndarray, dt: float, model: Model
              ) -> tuple[np.ndarray, np.ndarray]:
        """(constants, inputs) of one set of allowance ``values`` (in :attr:`names` order); both
        unchanged (the same arrays) where every value is zero."""
        k = len(self.constants)
        offsets = values[:k]
        if np.any(offsets != 0.0):
            constants = np.array(constants, dtype=np.float64, copy=True)
            index = [model.constants.names.index(c) for c in self.constants]
            constants[index] = constants[index] * (1.0 + offsets)
        if self.lag_max > 0.0 and values[k] != 0.0:
            inputs = np.array(inputs, dtype=np.float64, copy=True)
            j = model.inputs.index(COMMAND_INPUT)
            inputs[:, j] = command_lag(inputs[:, j], float(values[k]), dt)
        return constants, inputs

    def to_json(self) -> dict[str, Any]:
        return {"kinematic_constants": list(self.constants), "tolerance": self.tolerance,
                "prior_std": self.tolerance / 2.0, "command_lag_max_s": self.lag_max,
                "command_lag_fraction": COMMAND_LAG_FRACTION,
                "position_loop_time_constant_s": self.position_loop_time_constant}


@dataclass(frozen=True)
class AllowedModel(Model):
    """A model (``inner``, nominal or with effects) with the model-form allowance's parameters
    appended; :func:`ema_uq.simulate.simulate_batch` runs it through :meth:`simulate_own`."""

    inner: Any = field(default=None, compare=False, repr=False)
    allowance: Any = field(default=None, compare=False, repr=False)

    def with_effects(self, names: Sequence[str], values: Mapping[str, float] | None = None) -> "AllowedModel":
        return self.allowance.wrap(self.inner.with_effects(names, values))

    def simulate_own(self, thetas: np.ndarray, time: np.ndarray, inputs: np.ndarray, *,
                     constants: np.ndarray | None = None, **options) -> np.ndarray:
        """Outputs (n_sets, n_samples, n_outputs) of full parameter vectors of this model: the
        wrapped model run once per distinct set of allowance values (first-appearance order, so
        that the first set still leads a ``share_steps`` batch of its own group)."""
        thetas = np.asarray(thetas, dtype=np.float64)
        single = thetas.ndim == 1
        thetas = np.atleast_2d(thetas)
        if thetas.ndim != 2 or thetas.shape[1] != len(self.parameters):
            raise SimulationError(f"parameter array has shape {thetas.shape}; {self.name} with its model-form "
                                  f"allowance needs (n_sets, {len(self.parameters)})")
        n = len(self.inner.parameters)
        extra = np.ascontiguousarray(thetas[:, n:])
        if not np.all(np.isfinite(extra)):
            raise SimulationError("model-form allowance values must be finite numbers")
        time = np.asarray(time, dtype=np.float64)
        dt = float(time[1] - time[0]) if time.size > 1 else 1.0
        consts = self.inner.constants_vector() if constants is None else np.asarray(constants, dtype=np.float64)
        keys, first, inverse = np.unique(extra, axis=0, return_index=True, return_inverse=True)
        inverse = np.asarray(inverse).ravel()
        out = None
        for g in np.argsort(first):
            rows = np.flatnonzero(inverse == g)
            c, u = self.allowance.apply(keys[g], consts, inputs, dt, self.inner)
            part = simulate_batch(self.inner, thetas[rows, :n], time, u, constants=c, **options)
            if out is None:
                out = np.empty((thetas.shape[0],) + part.shape[1:])
            out[rows] = part
        return out[0] if single else out


def actuator_allowance(model: Model) -> ModelFormAllowance | None:
    """The default allowance of an actuator concept: its kinematic constants at
    :data:`KINEMATIC_TOLERANCE` and a command lag up to :data:`COMMAND_LAG_FRACTION` of its
    position loop's time constant; None for a concept with neither."""
    constants = kinematic_constants(model)
    loop = position_loop_time_constant(model) if COMMAND_INPUT in model.inputs else None
    lag = 0.0 if loop is None else COMMAND_LAG_FRACTION * loop
    if not constants and lag == 0.0:
        return None
    return ModelFormAllowance(constants, KINEMATIC_TOLERANCE, lag, loop)


def allowance_values(model: Model, theta: np.ndarray, std: np.ndarray | None = None) -> dict[str, dict[str, float]]:
    """{allowance parameter: {"estimate", "std", "unit", "lower", "upper"}} of a fitted AllowedModel."""
    if not isinstance(model, AllowedModel):
        return {}
    out = {}
    for p in model.allowance.parameters:
        i = model.parameters.index(p.name)
        out[p.name] = {"estimate": float(theta[i]), "std": float("nan") if std is None else float(std[i]),
                       "unit": p.unit, "lower": p.lower, "upper": p.upper}
    return out
