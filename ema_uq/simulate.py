"""The compiled, batched fixed-step simulator.

One numba kernel integrates any registered concept for a batch of parameter vectors,
parallel over the batch. Inputs are sampled on a uniform grid and held over each sample
interval (zero-order hold); the output at t_k is computed from x(t_k) and u_k. Between
samples the state is advanced by ``n_sub`` classical RK4 steps.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numba import njit, prange

from .models import Model, get_model
from .models import htls, lths
from .models.effect_kernels import evaluate_htls_effects, evaluate_lths_effects


class SimulationError(ValueError):
    """Inputs or parameter arrays of the wrong shape, or a non-finite trajectory."""


@njit(cache=True, inline="always", error_model="numpy")
def _evaluate(model_id, x, u, th, c, dx, y):
    if model_id == 0:
        htls.evaluate(x, u, th, c, dx, y)
    else:
        lths.evaluate(x, u, th, c, dx, y)


@njit(cache=True, error_model="numpy")
def _integrate_one(model_id, th, consts, inputs, x0, h, n_sub, out):
    """Integrate one parameter vector; writes outputs (n_samples, n_outputs) into ``out``."""
    n_x = x0.shape[0]
    n_y = out.shape[1]
    x = x0.copy()
    xt = np.empty(n_x)
    k1 = np.empty(n_x)
    k2 = np.empty(n_x)
    k3 = np.empty(n_x)
    k4 = np.empty(n_x)
    scratch = np.empty(n_y)
    n_samples = inputs.shape[0]
    for k in range(n_samples):
        u = inputs[k]
        # outputs at t_k and the first RK4 stage of the next interval share one evaluation
        _evaluate(model_id, x, u, th, consts, k1, out[k])
        if k == n_samples - 1:
            break
        for sub in range(n_sub):
            if sub > 0:
                _evaluate(model_id, x, u, th, consts, k1, scratch)
            for i in range(n_x):
                xt[i] = x[i] + 0.5 * h * k1[i]
            _evaluate(model_id, xt, u, th, consts, k2, scratch)
            for i in range(n_x):
                xt[i] = x[i] + 0.5 * h * k2[i]
            _evaluate(model_id, xt, u, th, consts, k3, scratch)
            for i in range(n_x):
                xt[i] = x[i] + h * k3[i]
            _evaluate(model_id, xt, u, th, consts, k4, scratch)
            for i in range(n_x):
                x[i] += h / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])


@njit(cache=True, parallel=True, error_model="numpy")
def _integrate_batch(model_id, thetas, consts, inputs, x0, h, n_sub, out):
    """Kernel entry: thetas (n_sets, n_params) -> out (n_sets, n_samples, n_outputs)."""
    for s in prange(thetas.shape[0]):
        _integrate_one(model_id, thetas[s], consts, inputs, x0, h, n_sub, out[s])


# --- models with unmodelled effects (models/effects.py) -------------------------------------
# A second entry with the same RK4 loop around the augmented right-hand sides. Kept apart
# so that the nominal kernel above is exactly the nominal one (and compiles as fast), and the
# larger effect equations are compiled, inlined, only when an augmented model is first used.
EFFECT_MODEL_IDS = (100, 101)


@njit(cache=True, inline="always", error_model="numpy")
def _evaluate_effects(model_id, x, u, th, c, dx, y):
    if model_id == 100:
        evaluate_htls_effects(x, u, th, c, dx, y)
    else:
        evaluate_lths_effects(x, u, th, c, dx, y)


@njit(cache=True, error_model="numpy")
def _integrate_one_effects(model_id, th, consts, inputs, x0, h, n_sub, out):
    """``_integrate_one`` for an augmented model: the same RK4 arithmetic, written with one
    call site of the inlined right-hand side (inlined at four call sites like the nominal
    kernel, the larger effect equations take minutes to compile; called, not inlined, they
    cost ~60 ns more per evaluation)."""
    n_x = x0.shape[0]
    x = x0.copy()
    xt = np.empty(n_x)
    stages = np.empty((4, n_x))
    scratch = np.empty(out.shape[1])
    n_samples = inputs.shape[0]
    for k in range(n_samples):
        u = inputs[k]
        last = k == n_samples - 1
        for sub in range(n_sub):
            for stage in range(4):
                if stage == 0:
                    for i in range(n_x):
                        xt[i] = x[i]
                elif stage < 3:
                    for i in range(n_x):
                        xt[i] = x[i] + 0.5 * h * stages[stage - 1, i]
                else:
                    for i in range(n_x):
                        xt[i] = x[i] + h * stages[2, i]
                # outputs at t_k and the first RK4 stage of the next interval share one evaluation
                target = out[k] if sub == 0 and stage == 0 else scratch
                _evaluate_effects(model_id, xt, u, th, consts, stages[stage], target)
                if last:
                    break
            if last:
                break
            for i in range(n_x):
                x[i] += h / 6.0 * (stages[0, i] + 2.0 * stages[1, i] + 2.0 * stages[2, i] + stages[3, i])


@njit(cache=True, parallel=True, error_model="numpy")
def _integrate_batch_effects(model_id, thetas, consts, inputs, x0, h, n_sub, out):
    """``_integrate_batch`` for an augmented model."""
    for s in prange(thetas.shape[0]):
        _integrate_one_effects(model_id, thetas[s], consts, inputs, x0, h, n_sub, out[s])


def substeps(model: Model, dt: float, step: float | None = None) -> tuple[int, float]:
    """Number of RK4 sub-steps per sample interval and the resulting step length [s]."""
    step = model.integration_step if step is None else float(step)
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
) -> np.ndarray:
    """Simulate a batch of parameter vectors on one experiment.

    Parameters
    ----------
    model : concept or its name.
    thetas : (n_sets, n_params) or (n_params,) full parameter vectors in ``model.parameters`` order.
    time : (n_samples,) uniform sample times [s].
    inputs : (n_samples, 4) held inputs in ``model.inputs`` order (phi_r [rad], F_ER1 [N], F_ER2 [N], brake).
    constants : design constants in ``model.constants`` order (default: nominal).
    x0 : initial state (default: zeros, at rest).
    step : RK4 step [s] (default: the concept's converged step).

    Returns
    -------
    (n_sets, n_samples, n_outputs) array of outputs in ``model.outputs`` order
    ((n_samples, n_outputs) when ``thetas`` is one vector).
    """
    model = get_model(model) if isinstance(model, str) else model
    thetas = np.asarray(thetas, dtype=np.float64)
    single = thetas.ndim == 1
    thetas = np.ascontiguousarray(np.atleast_2d(thetas))
    if thetas.ndim != 2 or thetas.shape[1] != len(model.parameters):
        raise SimulationError(
            f"parameter array has shape {thetas.shape}; {model.name} needs (n_sets, {len(model.parameters)})"
        )
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
    consts = model.constants_vector() if constants is None else np.ascontiguousarray(constants, dtype=np.float64)
    if consts.shape != (len(model.constants),):
        raise SimulationError(f"constants have shape {consts.shape}; expected ({len(model.constants)},)")
    if model.batch_simulator is not None:  # a concept with its own kernel (EMPS: discrete controller)
        out = model.batch_simulator(model, thetas, inputs, model.kernel_constants(consts), x0, dt, n_sub)
        if model.postprocess is not None:
            out = model.postprocess(model, thetas, time, out)
        return out[0] if single else out
    x0 = np.zeros(model.n_states) if x0 is None else np.ascontiguousarray(x0, dtype=np.float64)
    out = np.empty((thetas.shape[0], time.size, model.n_outputs))
    kernel = _integrate_batch_effects if model.model_id in EFFECT_MODEL_IDS else _integrate_batch
    kernel(model.model_id, thetas, model.kernel_constants(consts), inputs, x0, h, n_sub, out)
    if model.postprocess is not None:  # output-side effects (sensor delay), batched in numpy
        out = model.postprocess(model, thetas, time, out)
    return out[0] if single else out


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


def simulate(model: Model | str, experiment, theta=None, *, constants=None, step=None) -> Trajectory:
    """Simulate one parameter vector (default: nominal) on an :class:`~ema_uq.experiments.Experiment`."""
    model = get_model(model) if isinstance(model, str) else model
    theta = model.parameters.nominal if theta is None else np.asarray(theta, dtype=float)
    out = simulate_batch(model, theta, experiment.time, experiment.input_matrix(model),
                         constants=constants, step=step)
    return Trajectory(model.name, experiment.time, experiment.input_matrix(model), model.inputs, out,
                      model.outputs, model.output_units, model.parameters.as_dict(theta))
