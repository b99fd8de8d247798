"""The compiled, batched simulator.

One numba kernel integrates any registered concept for a batch of parameter vectors,
parallel over the batch. Inputs are sampled on a uniform grid and held over each sample
interval (zero-order hold); the output at t_k is computed from x(t_k) and u_k. Between
samples the state is advanced by ``n_sub`` classical RK4 steps ("rk4", the default of HT/LS
and LT/HS: smooth in the parameters, as fits need), by adaptive Dormand-Prince 5(4) steps
("dopri5": ~6x fewer evaluations than RK4 on HT/LS, for forward runs), or ("hybrid") by one
exact step over each interval where the concept is linear (every smoothed sign saturated, no
controller limit active, brake released: the zero-order-hold discretisation by the matrix
exponential, as ``c2d`` does for a linear model) and Dormand-Prince over the rest (its steps
held inside the stability region of the linear part's modes), 8x fewer
evaluations than "dopri5" on HT/LS and 20x on LT/HS. With ``share_steps`` a batch follows the
first set's step sequence (and its choice of exact intervals) so that finite differences stay
smooth.

Modules: ``dispatch`` (from a model to its right-hand side and effect set), ``integrators``
(the RK4 and Dormand-Prince loops and their batch entries), ``linear`` (the exact steps of
"hybrid"); this package's top level checks the arguments, runs the kernels and holds the
result types.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..models import Model, get_model
from .dispatch import (EFFECT_KERNELS, HTLS_EFFECTS_KERNEL, HTLS_KERNEL, LTHS_EFFECTS_KERNEL,  # noqa: F401
                       LTHS_KERNEL, NOMINAL_KERNELS, SimulationError, kernel_family, kernel_key)
from .integrators import (DP_A, DP_DIVERGED, DP_E, _dopri_batch, _dopri_batch_flags,  # noqa: F401
                          _dopri_batch_shared, _dopri_batch_shared_flags, _dopri_one, _dopri_one_nominal, _dp_error,
                          _dp_stage_state, _integrate_batch, _integrate_batch_flags)
from .specialise import run_rk4_effects
from .linear import (ZOH_CHECKS, _dp_stability_radius, _dp_stable_steps, _hybrid_setup,  # noqa: F401
                     _zoh_propagators, stable_steps)

INTEGRATORS = ("dopri5", "hybrid", "rk4")


def error_scales(model: Model, thetas: np.ndarray) -> np.ndarray:
    """(n_sets, n_states) absolute error scales of the adaptive integrator per parameter set:
    ``model.state_scales`` (an augmented model's include its effects' extra states), -1 where
    an extra state is frozen (its effect's ``magnitude`` parameter is zero in that set)."""
    if len(model.state_scales) != model.n_states:
        raise SimulationError(f"concept {model.name} has no state_scales for its {model.base_model.n_states} "
                              "states; give Model.state_scales or use integrator='rk4'")
    scales = np.empty((thetas.shape[0], model.n_states))
    scales[:] = model.state_scales
    catalogue = model.base_model.effect_catalogue
    for name in model.effects:
        effect = catalogue[name]
        extra = [model.states.index(s) for s in effect.extra_states.get(model.name, ())]
        if extra and effect.magnitude is not None:
            frozen = thetas[:, model.parameters.index(effect.magnitude)] == 0.0
            scales[np.ix_(frozen, extra)] = -1.0
    return scales


def _run_shared(kernel, args, out, n_samples):
    """A shared-steps kernel, its step record grown until the leading set's sequence fits."""
    counts = np.zeros(n_samples - 1, dtype=np.int64)
    capacity = 8 * n_samples
    while not kernel(*args, out, np.empty(capacity), counts):
        capacity *= 4
        counts[:] = 0


def substeps(model: Model, dt: float, step: float | None = None) -> tuple[int, float]:
    """Number of RK4 sub-steps per sample interval and the resulting step length [s]."""
    step = model.rk4_step if step is None else float(step)
    if not step > 0:
        raise SimulationError(f"integration step must be positive, got {step}")
    n_sub = max(1, int(np.ceil(dt / step - 1e-9)))
    return n_sub, dt / n_sub


def simulate_batch(
    model: Model | str,
    thetas: np.ndarray,
    time: np.ndarray,
    inputs: np.ndarray,
    *,
    constants: np.ndarray | None = None,
    x0: np.ndarray | None = None,
    step: float | None = None,
    integrator: str | None = None,
    rtol: float | None = None,
    share_steps: bool = False,
) -> np.ndarray:
    """Simulate a batch of parameter vectors on one experiment.

    Parameters
    ----------
    model : concept or its name. A model with a ``simulate_own`` method (the gap diagnosis's
        model-form allowance, :class:`ema_uq.gap.allowance.AllowedModel`) is simulated by it.
    thetas : (n_sets, n_params) or (n_params,) full parameter vectors in ``model.parameters`` order.
    time : (n_samples,) uniform sample times [s].
    inputs : (n_samples, 4) held inputs in ``model.inputs`` order (phi_r [rad], F_ER1 [N], F_ER2 [N], brake).
    constants : design constants in ``model.constants`` order (default: nominal).
    x0 : initial state (default: zeros, at rest).
    step : RK4 step [s] (default: the concept's converged step); giving it selects RK4.
    integrator : "dopri5" (adaptive, relative tolerance ``rtol``), "hybrid" (exact steps where
        the concept is linear, "dopri5" elsewhere; the augmented models with unmodelled effects
        declare no linear regime and run "dopri5" throughout) or "rk4" (fixed ``step``);
        default: ``model.integrator`` (RK4 when ``step`` is given).
    rtol : relative tolerance of "dopri5" and "hybrid" (default: ``model.rtol``).
    share_steps : "dopri5" and "hybrid" only: the first set chooses the step sequence and every other set
        follows it (for finite differences around the first set: independent step choices
        would add a noise of order rtol to each difference). The first set's outputs are the
        same as without sharing.

    Returns
    -------
    (n_sets, n_samples, n_outputs) array of outputs in ``model.outputs`` order
    ((n_samples, n_outputs) when ``thetas`` is one vector).
    """
    model = get_model(model) if isinstance(model, str) else model
    own = getattr(model, "simulate_own", None)
    if own is not None:  # a wrapper that turns parameters of its own into constants and inputs
        return own(thetas, time, inputs, constants=constants, x0=x0, step=step, integrator=integrator, rtol=rtol,
                   share_steps=share_steps)
    thetas = np.asarray(thetas, dtype=np.float64)
    single = thetas.ndim == 1
    thetas = np.ascontiguousarray(np.atleast_2d(thetas))
    if thetas.ndim != 2 or thetas.shape[1] != len(model.parameters):
        raise SimulationError(
            f"parameter array has shape {thetas.shape}; {model.name} needs (n_sets, {len(model.parameters)})"
        )
    if not np.all(np.isfinite(thetas)):
        row, col = np.argwhere(~np.isfinite(thetas))[0]
        raise SimulationError(f"parameter set {row} has {model.parameters.names[col]} = {thetas[row, col]}; "
                              "every parameter value must be a finite number")
    time = np.asarray(time, dtype=np.float64)
    inputs = np.ascontiguousarray(inputs, dtype=np.float64)
    if inputs.shape != (time.size, len(model.inputs)):
        raise SimulationError(
            f"inputs have shape {inputs.shape}; expected ({time.size}, {len(model.inputs)}) for {model.inputs}"
        )
    if time.size < 2:
        raise SimulationError("an experiment needs at least two samples")
    if not np.all(np.isfinite(inputs)):
        raise SimulationError("inputs contain NaN or infinite values; inputs must be complete")
    dt = float(time[1] - time[0])
    n_sub, h = substeps(model, dt, step)
    method = integrator or ("rk4" if step is not None else model.integrator)
    if method not in INTEGRATORS:
        raise SimulationError(f"unknown integrator {method!r}; choose one of {', '.join(INTEGRATORS)}")
    tol = model.rtol if rtol is None else float(rtol)
    if method != "rk4" and not 1e-14 < tol < 1e-2:
        raise SimulationError(f"rtol must lie in (1e-14, 1e-2), got {tol:g}")
    consts = model.constants_vector() if constants is None else np.ascontiguousarray(constants, dtype=np.float64)
    if consts.shape != (len(model.constants),):
        raise SimulationError(f"constants have shape {consts.shape}; expected ({len(model.constants)},)")
    if model.batch_simulator is not None:  # a concept with its own kernel (EMPS: discrete controller)
        out = model.batch_simulator(model, thetas, inputs, model.kernel_constants(consts), x0, dt, n_sub)
        if model.postprocess is not None:
            out = model.postprocess(model, thetas, time, out)
        return out[0] if single else out
    model_id, flags = kernel_key(model)
    nominal = kernel_family(model) == "nominal"
    x0 = np.zeros(model.n_states) if x0 is None else np.ascontiguousarray(x0, dtype=np.float64)
    out = np.empty((thetas.shape[0], time.size, model.n_outputs))
    kernel_consts = model.kernel_constants(consts)
    # a nominal model runs the entries compiled for the nominal equations, a model with effects
    # the entries that take its effects' bit set at run time (one compiled kernel for all sets)
    # or, for RK4 once the set has earned it, the entry compiled for its set (specialise.py)
    prefix = (model_id,) if nominal else (model_id, flags)
    if method == "rk4":
        kernel = _integrate_batch if nominal else run_rk4_effects
        kernel(*prefix, thetas, kernel_consts, inputs, x0, h, n_sub, out)
    else:  # no linear regime is declared for the augmented models: "hybrid" is Dormand-Prince there
        args = (*prefix, thetas, kernel_consts, inputs, x0, dt, tol, error_scales(model, thetas),
                *_hybrid_setup(model, thetas, kernel_consts, dt, method == "hybrid" and nominal))
        if share_steps and thetas.shape[0] > 1:
            _run_shared(_dopri_batch_shared if nominal else _dopri_batch_shared_flags, args, out, time.size)
        else:
            (_dopri_batch if nominal else _dopri_batch_flags)(*args, out)
    if model.postprocess is not None:  # output-side effects (sensor delay), batched in numpy
        out = model.postprocess(model, thetas, time, out)
    return out[0] if single else out


@dataclass(frozen=True)
class StepStatistics:
    """How an adaptive run of one parameter set spent its work (``solve_ivp``'s nfev, in kind)."""

    integrator: str
    intervals: int          #: held sample intervals
    exact_intervals: int    #: intervals taken by one exact linear-regime step ("hybrid" only)
    accepted: int           #: accepted Dormand-Prince steps
    rejected: int           #: rejected Dormand-Prince steps

    @property
    def evaluations(self) -> int:
        """Right-hand-side evaluations: one per sample (outputs and first stage), six per step."""
        return self.intervals + 1 + 6 * (self.accepted + self.rejected)

    def summary(self) -> str:
        return (f"{self.integrator}: {self.intervals} intervals, {self.exact_intervals} exact, "
                f"{self.accepted} steps accepted, {self.rejected} rejected, {self.evaluations} evaluations")


def step_statistics(model: Model | str, theta, time, inputs, *, integrator: str = "hybrid", constants=None,
                    rtol: float | None = None) -> StepStatistics:
    """Run one parameter vector on an adaptive integrator ("dopri5" or "hybrid") and count its work."""
    model = get_model(model) if isinstance(model, str) else model
    if integrator not in ("dopri5", "hybrid"):
        raise SimulationError(f"step statistics need an adaptive integrator (dopri5 or hybrid), got {integrator!r}")
    if model.batch_simulator is not None or kernel_family(model) != "nominal":
        raise SimulationError(f"step statistics cover the nominal HT/LS and LT/HS models, not {model.name}")
    theta = np.ascontiguousarray(theta, dtype=np.float64)
    time = np.asarray(time, dtype=np.float64)
    inputs = np.ascontiguousarray(inputs, dtype=np.float64)
    consts = model.constants_vector() if constants is None else np.ascontiguousarray(constants, dtype=np.float64)
    out = np.empty((time.size, model.n_outputs))
    counts = np.zeros(time.size - 1, dtype=np.int64)
    capacity = 8 * time.size
    dt = float(time[1] - time[0])
    kernel_consts = model.kernel_constants(consts)
    props, h_stable = _hybrid_setup(model, theta[None], kernel_consts, dt, integrator == "hybrid")
    while True:
        accepted, rejected = _dopri_one_nominal(model.model_id, theta, kernel_consts, inputs,
                                                np.zeros(model.n_states), dt,
                                                model.rtol if rtol is None else float(rtol),
                                                error_scales(model, theta[None])[0], props[0], h_stable[0],
                                                out, np.empty(capacity), counts)
        if accepted == DP_DIVERGED:
            raise SimulationError("the trajectory left the finite numbers (diverged); check the parameter values")
        if accepted >= 0:
            break
        capacity *= 4
        counts[:] = 0
    return StepStatistics(integrator, time.size - 1, int(np.sum(counts == 0)), int(accepted), int(rejected))


@dataclass(frozen=True)
class Trajectory:
    """Simulated outputs of one parameter vector on one experiment (named signals).

    ``outputs`` is (n_samples, n_outputs) in ``channels`` order; ``inputs`` is
    (n_samples, n_inputs) in ``input_names`` order.
    """

    concept: str
    time: np.ndarray
    inputs: np.ndarray
    input_names: tuple[str, ...]
    outputs: np.ndarray
    channels: tuple[str, ...]
    units: tuple[str, ...]
    parameters: dict[str, float] = field(default_factory=dict)

    def __getitem__(self, channel: str) -> np.ndarray:
        if channel in self.channels:
            return self.outputs[:, self.channels.index(channel)]
        if channel in self.input_names:
            return self.inputs[:, self.input_names.index(channel)]
        raise KeyError(f"no channel {channel!r}; channels: {', '.join(self.channels + self.input_names)}")

    def to_pandas(self):
        import pandas as pd

        data = {n: self.inputs[:, i] for i, n in enumerate(self.input_names)}
        data.update({n: self.outputs[:, i] for i, n in enumerate(self.channels)})
        return pd.DataFrame(data, index=pd.Index(self.time, name="time"))

    def summary(self) -> str:
        rows = [f"Trajectory of {self.concept}: {self.time.size} samples, {self.time[0]:g}..{self.time[-1]:g} s"]
        for i, ch in enumerate(self.channels):
            col = self.outputs[:, i]
            rows.append(f"  {ch:<10} [{self.units[i]:<6}] min {col.min():>11.4g}  max {col.max():>11.4g}")
        return "\n".join(rows)


def simulate(model: Model | str, experiment, theta=None, *, constants=None, step=None, integrator=None,
             rtol=None) -> Trajectory:
    """Simulate one parameter vector (default: nominal) on an :class:`~ema_uq.experiments.Experiment`."""
    model = get_model(model) if isinstance(model, str) else model
    theta = model.parameters.nominal if theta is None else np.asarray(theta, dtype=float)
    out = simulate_batch(model, theta, experiment.time, experiment.input_matrix(model),
                         constants=constants, step=step, integrator=integrator, rtol=rtol)
    return Trajectory(model.name, experiment.time, experiment.input_matrix(model), model.inputs, out,
                      model.outputs, model.output_units, model.parameters.as_dict(theta))
