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
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numba import njit, prange

from .models import KERNEL_IDS, Model, get_model
from .models import htls, lths
from .models.effect_kernels import evaluate_htls_effects, evaluate_lths_effects
from .errors import EmaUqError


class SimulationError(EmaUqError):
    """Inputs or parameter arrays of the wrong shape, an unknown kernel id, or a non-finite trajectory."""


# --- kernel dispatch -------------------------------------------------------------------------
# The ids come from models.base.KERNEL_IDS (module constants: numba compiles them in). numba
# needs a static branch per right-hand side, so a new concept adds its branch to each helper
# below and its id to NOMINAL_KERNELS / EFFECT_KERNELS; an id without a branch is refused by
# ``kernel_family`` before any kernel runs, and raises inside a kernel rather than running
# another concept's equations.
HTLS_KERNEL, HTLS_EFFECTS_KERNEL = KERNEL_IDS["htls"]
LTHS_KERNEL, LTHS_EFFECTS_KERNEL = KERNEL_IDS["lths"]
#: ids of the nominal right-hand sides (_integrate_batch, _dopri_batch) and of the
#: right-hand sides with unmodelled effects (_integrate_batch_effects, _dopri_batch_effects)
NOMINAL_KERNELS = (HTLS_KERNEL, LTHS_KERNEL)
EFFECT_KERNELS = (HTLS_EFFECTS_KERNEL, LTHS_EFFECTS_KERNEL)


def kernel_family(model: Model) -> str:
    """``"nominal"`` or ``"effects"``: the compiled entry that runs ``model.model_id``; any
    other id is a one-line :class:`SimulationError`."""
    if model.model_id in NOMINAL_KERNELS:
        return "nominal"
    if model.model_id in EFFECT_KERNELS:
        return "effects"
    raise SimulationError(f"model {model.name!r} has kernel id {model.model_id}, which no compiled kernel knows "
                          f"(known: {', '.join(map(str, NOMINAL_KERNELS + EFFECT_KERNELS))}); take the model "
                          "from get_model or with_effects, or register its kernel in models.base.KERNEL_IDS")


@njit(cache=True, inline="always", error_model="numpy")
def _evaluate(model_id, x, u, th, c, dx, y, outputs=True):
    if model_id == HTLS_KERNEL:
        htls.evaluate(x, u, th, c, dx, y, outputs)
    elif model_id == LTHS_KERNEL:
        lths.evaluate(x, u, th, c, dx, y, outputs)
    else:
        raise ValueError("unknown kernel id")


@njit(cache=True, inline="always", error_model="numpy")
def _linear_state_matrix(model_id, th, c, a):
    if model_id == HTLS_KERNEL:
        htls.linear_state_matrix(th, c, a)
    elif model_id == LTHS_KERNEL:
        lths.linear_state_matrix(th, c, a)
    else:
        raise ValueError("unknown kernel id")


@njit(cache=True, inline="always", error_model="numpy")
def _linear_regime(model_id, x, dx, u, th, c, delta):
    if model_id == HTLS_KERNEL:
        return htls.linear_regime(x, dx, u, th, c, delta)
    if model_id == LTHS_KERNEL:
        return lths.linear_regime(x, dx, u, th, c, delta)
    raise ValueError("unknown kernel id")


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
                _evaluate(model_id, x, u, th, consts, k1, scratch, False)
            for i in range(n_x):
                xt[i] = x[i] + 0.5 * h * k1[i]
            _evaluate(model_id, xt, u, th, consts, k2, scratch, False)
            for i in range(n_x):
                xt[i] = x[i] + 0.5 * h * k2[i]
            _evaluate(model_id, xt, u, th, consts, k3, scratch, False)
            for i in range(n_x):
                xt[i] = x[i] + h * k3[i]
            _evaluate(model_id, xt, u, th, consts, k4, scratch, False)
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
@njit(cache=True, inline="always", error_model="numpy")
def _evaluate_effects(model_id, x, u, th, c, dx, y):
    if model_id == HTLS_EFFECTS_KERNEL:
        evaluate_htls_effects(x, u, th, c, dx, y)
    elif model_id == LTHS_EFFECTS_KERNEL:
        evaluate_lths_effects(x, u, th, c, dx, y)
    else:
        raise ValueError("unknown kernel id")


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


# --- adaptive Dormand-Prince 5(4) -----------------------------------------------------------
# The RK4 step is set by the motion reversals (the tanh-smoothed Coulomb terms switch within
# ~0.2 ms) and by the controller transient that every 10 ms reference step starts; in between,
# the trajectory is smooth. An embedded pair spends its steps where they are needed.
# Each held sample interval is integrated on its own (the input jumps at its start); the output
# evaluation at t_k is the first stage of the interval, the last stage of an accepted step is
# the first of the next (FSAL). Row 6 of DP_A is the 5th-order solution. The kernels spell
# DP_A and DP_E out as literals (_dp_stage_state, _dp_error); these arrays are the published
# tableau the unit tests check those literals against.
DP_A = np.array([
    [0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
    [1 / 5, 0.0, 0.0, 0.0, 0.0, 0.0],
    [3 / 40, 9 / 40, 0.0, 0.0, 0.0, 0.0],
    [44 / 45, -56 / 15, 32 / 9, 0.0, 0.0, 0.0],
    [19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729, 0.0, 0.0],
    [9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656, 0.0],
    [35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84],
])
#: 5th- minus 4th-order weights (the local error estimate is h * DP_E . k)
DP_E = np.array([71 / 57600, 0.0, -71 / 16695, 71 / 1920, -17253 / 339200, 22 / 525, -1 / 40])
# step-size controller: safety factor and bounds of the factor. Plain (I) control: a PI
# controller (beta 0.04-0.08) took 15-65 % more steps here, because each interval is short
# and the step has to grow again after every restart.
DP_SAFETY = 0.9
DP_GROW_MAX = 5.0
DP_SHRINK_MAX = 0.2
#: error norms below this give a factor above DP_GROW_MAX
DP_ERR_GROW_MAX = (DP_GROW_MAX / DP_SAFETY) ** -5.0


@njit(cache=True, inline="always", error_model="numpy")
def _dp_stage_state(x, k, s, h, xt):
    """xt = x + h sum_j DP_A[s, j] k_j (the state where stage s is evaluated), written out per
    stage with literal coefficients: the generic loop over a row of DP_A cost a third of the
    right-hand side."""
    for i in range(x.shape[0]):
        if s == 1:
            acc = (1 / 5) * k[0, i]
        elif s == 2:
            acc = (3 / 40) * k[0, i] + (9 / 40) * k[1, i]
        elif s == 3:
            acc = (44 / 45) * k[0, i] + (-56 / 15) * k[1, i] + (32 / 9) * k[2, i]
        elif s == 4:
            acc = ((19372 / 6561) * k[0, i] + (-25360 / 2187) * k[1, i] + (64448 / 6561) * k[2, i]
                   + (-212 / 729) * k[3, i])
        elif s == 5:
            acc = ((9017 / 3168) * k[0, i] + (-355 / 33) * k[1, i] + (46732 / 5247) * k[2, i]
                   + (49 / 176) * k[3, i] + (-5103 / 18656) * k[4, i])
        else:
            acc = ((35 / 384) * k[0, i] + (500 / 1113) * k[2, i] + (125 / 192) * k[3, i]
                   + (-2187 / 6784) * k[4, i] + (11 / 84) * k[5, i])
        xt[i] = x[i] + h * acc


@njit(cache=True, inline="always", error_model="numpy")
def _dp_error(x, xn, k, h, rtol, scale):
    """RMS over the controlled states (scale > 0) of local error / (rtol (scale + |x|)); the
    error weights DP_E written out (the generic loop cost a tenth of a step)."""
    total = 0.0
    n = 0
    for i in range(x.shape[0]):
        if scale[i] > 0.0:
            e = ((71 / 57600) * k[0, i] + (-71 / 16695) * k[2, i] + (71 / 1920) * k[3, i]
                 + (-17253 / 339200) * k[4, i] + (22 / 525) * k[5, i] + (-1 / 40) * k[6, i])
            r = h * e / (rtol * (scale[i] + max(abs(x[i]), abs(xn[i]))))
            total += r * r
            n += 1
    return math.sqrt(total / n)


@njit(cache=True, inline="always", error_model="numpy")
def _dp_factor(err):
    """Step-size factor from the error norm of a step (err <= 1: accepted)."""
    if err <= DP_ERR_GROW_MAX:  # the factor is capped anyway: spare the power function
        return DP_GROW_MAX
    return min(DP_GROW_MAX, max(DP_SHRINK_MAX, DP_SAFETY * err ** -0.2))


#: a rejected step shorter than this fraction of the sample interval means the trajectory
#: left the finite numbers (a NaN error norm never accepts a step): the run ends there
DP_MIN_STEP_FRACTION = 1e-12
#: accepted-step count returned by a run that diverged (its remaining outputs are NaN)
DP_DIVERGED = -2


@njit(cache=True, error_model="numpy")
def _fill_nan(out, start):
    """out[start:] = NaN, as a loop (a slice assignment adds seconds to the kernel's compile time)."""
    for j in range(start, out.shape[0]):
        for i in range(out.shape[1]):
            out[j, i] = np.nan


@njit(cache=True, inline="always", error_model="numpy")
def _dp_diverged(err, h, dt):
    return not (err < np.inf and h > DP_MIN_STEP_FRACTION * dt)


@njit(cache=True, inline="always", error_model="numpy")
def _dp_accept(x, stages, xt):
    for i in range(x.shape[0]):
        x[i] = xt[i]
        stages[0, i] = stages[6, i]


@njit(cache=True, inline="always", error_model="numpy")
def _dp_sample(model_id, x, inputs, j, u, th, consts, stages, k, scratch, out):
    """Outputs at sample j into ``out[j]`` and the first stage of its interval into
    ``stages[0]``; ``u`` receives the held input. Rows are copied in and out rather than
    viewed: a view costs two atomic reference-count updates, more than the copy."""
    for i in range(u.shape[0]):
        u[i] = inputs[j, i]
    _evaluate(model_id, x, u, th, consts, k, scratch)
    for i in range(x.shape[0]):
        stages[0, i] = k[i]
    for i in range(scratch.shape[0]):
        out[j, i] = scratch[i]


@njit(cache=True, inline="always", error_model="numpy")
def _dp_stages(model_id, x, u, th, consts, stages, h, xt, k, scratch):
    """Stages 2-7 of a step of length ``h`` from ``x`` (derivatives only); ``xt`` ends as
    the 5th-order solution."""
    for s in range(1, 7):
        _dp_stage_state(x, stages, s, h, xt)
        _evaluate(model_id, xt, u, th, consts, k, scratch, False)
        for i in range(x.shape[0]):
            stages[s, i] = k[i]


@njit(cache=True, inline="always", error_model="numpy")
def _dp_workspace(x0, n_outputs):
    """Working arrays of one adaptive run: the state (a copy of ``x0``), the state where a
    stage is evaluated, the 7 stage derivatives and an output scratch row."""
    n_x = x0.shape[0]
    return x0.copy(), np.empty(n_x), np.empty((7, n_x)), np.empty(n_outputs)


@njit(cache=True, error_model="numpy")
def _dopri_one(model_id, th, consts, inputs, x0, dt, rtol, scale, props, h_stable, out, steps, counts):
    """Adaptive DP5(4) run of one parameter vector; writes outputs (n_samples, n_outputs) into ``out``.

    ``scale`` (n_states,): absolute error scale of each state (its typical magnitude; the
    absolute tolerance is rtol * scale), 0 to leave a state out of the error norm. Returns the
    numbers of accepted and rejected steps. With propagators ``props`` (n_checks, 2, n, n),
    :func:`_zoh_propagator_sets`, intervals in the linear regime take the exact step
    (integrator "hybrid"; none for n_checks = 0, plain Dormand-Prince), and no step is longer
    than ``h_stable`` (:func:`stable_steps`; infinite for plain Dormand-Prince). A non-empty
    ``steps`` records the accepted step lengths in order and ``counts`` (n_samples - 1,) their
    number per sample interval (0: an exact step), for :func:`_dopri_replay_one`; the accepted
    count is -1 when ``steps`` is too short, DP_DIVERGED when the trajectory left the finite
    numbers (the outputs from the next sample on are NaN, as RK4 gives them).
    """
    x, xt, stages, scratch = _dp_workspace(x0, out.shape[1])
    k = np.empty(x0.shape[0])
    n_checks = props.shape[0]
    delta = dt / max(n_checks, 1)
    n_samples = inputs.shape[0]
    h_open = dt  # the step that opened the previous interval: the transient repeats every sample
    n_accepted = 0
    n_rejected = 0
    recording = steps.shape[0] > 0
    u = np.empty(inputs.shape[1])
    for j in range(n_samples):
        _dp_sample(model_id, x, inputs, j, u, th, consts, stages, k, scratch, out)
        if j == n_samples - 1:
            break
        if n_checks > 0 and _zoh_interval(model_id, x, stages[0], u, th, consts, props, delta, xt, k):
            for i in range(x.shape[0]):
                x[i] = xt[i]
            continue
        t = 0.0
        h = h_open
        opening = True
        while True:
            h = min(h, h_stable)
            rest = dt - t
            final = h >= rest
            if final:
                h = rest
            _dp_stages(model_id, x, u, th, consts, stages, h, xt, k, scratch)
            err = _dp_error(x, xt, stages, h, rtol, scale)
            if err <= 1.0:
                if recording:
                    if n_accepted == steps.shape[0]:
                        return -1, n_rejected
                    steps[n_accepted] = h
                    counts[j] += 1
                _dp_accept(x, stages, xt)
                n_accepted += 1
                fac = _dp_factor(err)
                if opening:
                    h_open = min(dt, h * fac)
                    opening = False
                if final:
                    break
                t += h
                h = h * fac
            else:
                n_rejected += 1
                h = h * _dp_factor(err)
                if _dp_diverged(err, h, dt):
                    _fill_nan(out, j + 1)
                    return DP_DIVERGED, n_rejected
    return n_accepted, n_rejected


@njit(cache=True, parallel=True, error_model="numpy")
def _dopri_batch(model_id, thetas, consts, inputs, x0, dt, rtol, scales, props, h_stable, out):
    """Kernel entry: thetas (n_sets, n_params), scales (n_sets, n_states), props (n_sets,
    n_checks, 2, n, n), h_stable (n_sets,) -> out (n_sets, n_samples, n_outputs)."""
    for s in prange(thetas.shape[0]):
        _dopri_one(model_id, thetas[s], consts, inputs, x0, dt, rtol, scales[s], props[s], h_stable[s], out[s],
                   np.empty(0), np.empty(0, dtype=np.int64))


@njit(cache=True, error_model="numpy")
def _dopri_replay_one(model_id, th, consts, inputs, x0, props, steps, counts, out):
    """The accepted steps recorded by ``_dopri_one``, given (no error control): the same
    arithmetic, so the set that chose the steps is reproduced bit for bit and any other set is
    a smooth function of its parameters along that one step sequence. An interval without
    steps was an exact linear-regime step: it is repeated with this set's own propagator."""
    x, xt, stages, scratch = _dp_workspace(x0, out.shape[1])
    k = np.empty(x0.shape[0])
    n_samples = inputs.shape[0]
    pos = 0
    u = np.empty(inputs.shape[1])
    for j in range(n_samples):
        _dp_sample(model_id, x, inputs, j, u, th, consts, stages, k, scratch, out)
        if j == n_samples - 1:
            break
        if counts[j] == 0 and props.shape[0] > 0:
            _zoh_step(x, stages[0], props, xt)
        for _ in range(counts[j]):
            h = steps[pos]
            pos += 1
            _dp_stages(model_id, x, u, th, consts, stages, h, xt, k, scratch)
            _dp_accept(x, stages, xt)


@njit(cache=True, parallel=True, error_model="numpy")
def _dopri_batch_shared(model_id, thetas, consts, inputs, x0, dt, rtol, scales, props, h_stable, out, steps,
                        counts):
    """``_dopri_batch`` where set 0 chooses the steps and every other set replays them: finite-
    difference sensitivities free of the step-selection noise of independent adaptive runs.
    Returns False (nothing else done) when ``steps`` is too short for set 0's sequence."""
    n_accepted, _ = _dopri_one(model_id, thetas[0], consts, inputs, x0, dt, rtol, scales[0], props[0],
                               h_stable[0], out[0], steps, counts)
    if n_accepted == DP_DIVERGED:  # no step sequence to follow: differences around it are undefined
        for s in range(1, out.shape[0]):
            _fill_nan(out[s], 0)
        return True
    if n_accepted < 0:
        return False
    for s in prange(1, thetas.shape[0]):
        _dopri_replay_one(model_id, thetas[s], consts, inputs, x0, props[s], steps, counts, out[s])
    return True


@njit(cache=True, error_model="numpy")
def _dopri_one_effects(model_id, th, consts, inputs, x0, dt, rtol, scale, out, steps, counts):
    """``_dopri_one`` for an augmented model, the same arithmetic; states with ``scale < 0``
    are frozen (an effect at its ``off`` value whose states feed nothing: the stiff shaft mode
    of ``shaft_compliance`` at period 0 would otherwise be integrated, unresolved, for nothing)."""
    x, xt, stages, scratch = _dp_workspace(x0, out.shape[1])
    n_samples = inputs.shape[0]
    h_open = dt
    n_accepted = 0
    n_rejected = 0
    recording = steps.shape[0] > 0
    for j in range(n_samples):
        u = _dp_sample_effects(model_id, x, inputs, j, th, consts, stages, scale, out)
        if j == n_samples - 1:
            break
        t = 0.0
        h = h_open
        opening = True
        while True:
            rest = dt - t
            final = h >= rest
            if final:
                h = rest
            for s in range(1, 7):
                _dp_stage_state(x, stages, s, h, xt)
                _evaluate_effects(model_id, xt, u, th, consts, stages[s], scratch)
                _freeze(stages[s], scale)
            err = _dp_error(x, xt, stages, h, rtol, scale)
            if err <= 1.0:
                if recording:
                    if n_accepted == steps.shape[0]:
                        return -1, n_rejected
                    steps[n_accepted] = h
                    counts[j] += 1
                _dp_accept(x, stages, xt)
                n_accepted += 1
                fac = _dp_factor(err)
                if opening:
                    h_open = min(dt, h * fac)
                    opening = False
                if final:
                    break
                t += h
                h = h * fac
            else:
                n_rejected += 1
                h = h * _dp_factor(err)
                if _dp_diverged(err, h, dt):
                    _fill_nan(out, j + 1)
                    return DP_DIVERGED, n_rejected
    return n_accepted, n_rejected


@njit(cache=True, inline="always", error_model="numpy")
def _freeze(dx, scale):
    for i in range(dx.shape[0]):
        if scale[i] < 0.0:
            dx[i] = 0.0


@njit(cache=True, inline="always", error_model="numpy")
def _dp_sample_effects(model_id, x, inputs, j, th, consts, stages, scale, out):
    """``_dp_sample`` for an augmented model: outputs of sample j and the first stage, frozen
    states held; returns the held input row."""
    u = inputs[j]
    _evaluate_effects(model_id, x, u, th, consts, stages[0], out[j])
    _freeze(stages[0], scale)
    return u


@njit(cache=True, parallel=True, error_model="numpy")
def _dopri_batch_effects(model_id, thetas, consts, inputs, x0, dt, rtol, scales, out):
    """``_dopri_batch`` for an augmented model."""
    for s in prange(thetas.shape[0]):
        _dopri_one_effects(model_id, thetas[s], consts, inputs, x0, dt, rtol, scales[s], out[s],
                           np.empty(0), np.empty(0, dtype=np.int64))


@njit(cache=True, error_model="numpy")
def _dopri_replay_one_effects(model_id, th, consts, inputs, x0, scale, steps, counts, out):
    """``_dopri_replay_one`` for an augmented model (frozen states as in ``_dopri_one_effects``)."""
    x, xt, stages, scratch = _dp_workspace(x0, out.shape[1])
    n_samples = inputs.shape[0]
    pos = 0
    for j in range(n_samples):
        u = _dp_sample_effects(model_id, x, inputs, j, th, consts, stages, scale, out)
        if j == n_samples - 1:
            break
        for _ in range(counts[j]):
            h = steps[pos]
            pos += 1
            for s in range(1, 7):
                _dp_stage_state(x, stages, s, h, xt)
                _evaluate_effects(model_id, xt, u, th, consts, stages[s], scratch)
                _freeze(stages[s], scale)
            _dp_accept(x, stages, xt)


@njit(cache=True, parallel=True, error_model="numpy")
def _dopri_batch_shared_effects(model_id, thetas, consts, inputs, x0, dt, rtol, scales, out, steps, counts):
    """``_dopri_batch_shared`` for an augmented model."""
    n_accepted, _ = _dopri_one_effects(model_id, thetas[0], consts, inputs, x0, dt, rtol, scales[0], out[0],
                                       steps, counts)
    if n_accepted == DP_DIVERGED:
        for s in range(1, out.shape[0]):
            _fill_nan(out[s], 0)
        return True
    if n_accepted < 0:
        return False
    for s in prange(1, thetas.shape[0]):
        _dopri_replay_one_effects(model_id, thetas[s], consts, inputs, x0, scales[s], steps, counts, out[s])
    return True


# --- exact steps over the linear regime (integrator "hybrid") ------------------------------
# Where a concept is linear (models/htls.py, lths.py: "the linear regime") its held-input
# dynamics dx/dt = A x + b are solved exactly: x(t_k + t) = x_k + Γ(t) f(x_k), f(x_k) being the
# first stage the output evaluation already gives, Γ(t) = ∫_0^t e^{As} ds. Γ and Φ(t) = e^{At}
# (which carries f: f(t) = Φ(t) f(x_k)) are computed once per parameter set at ZOH_CHECKS
# evenly spaced points of the interval; the regime is tested at each, and an interval that
# leaves it anywhere is integrated by Dormand-Prince instead. The transient every held
# reference sample starts (~5 Dormand-Prince steps of 2 ms on HT/LS) costs one
# matrix-vector product per checked point instead.
ZOH_CHECKS = 4
#: Taylor degree of the scaled propagators: with the scaled norm <= 1/2 the truncation
#: error is below 0.5**(ZOH_TAYLOR + 1) / (ZOH_TAYLOR + 2)! ~ 1e-19
ZOH_TAYLOR = 14


@njit(cache=True, inline="always", error_model="numpy")
def _matmul(a, b, out):
    n = a.shape[0]
    for i in range(n):
        for j in range(n):
            acc = 0.0
            for q in range(n):
                acc += a[i, q] * b[q, j]
            out[i, j] = acc


@njit(cache=True, error_model="numpy")
def _balance(a):
    """Diagonal d (powers of 2) with row and column norms of D^-1 A D alike (Parlett-Reinsch,
    as LAPACK's gebal): the raw matrix mixes amperes, rad/s and metres over ten decades, and
    its norm, not its eigenvalues, would set the number of squarings and their rounding."""
    n = a.shape[0]
    b = a.copy()
    d = np.ones(n)
    converged = False
    while not converged:
        converged = True
        for i in range(n):
            col = 0.0
            row = 0.0
            for j in range(n):
                if j != i:
                    col += abs(b[j, i])
                    row += abs(b[i, j])
            if col == 0.0 or row == 0.0:
                continue
            f = 1.0
            total = col + row
            while col < row / 2.0:
                f *= 2.0
                col *= 4.0
            while col > row * 2.0:
                f /= 2.0
                col /= 4.0
            if (col + row) / f < 0.95 * total:
                converged = False
                d[i] *= f
                for j in range(n):
                    b[i, j] /= f
                    b[j, i] *= f
    return d


@njit(cache=True, error_model="numpy")
def _zoh_propagators(a, delta, n_points):
    """(n_points, 2, n, n): Φ(t_i) = e^{A t_i} and Γ(t_i) = ∫_0^{t_i} e^{As} ds at t_i = (i + 1) delta.

    Computed on the balanced matrix (:func:`_balance`) by a Taylor series of the step halved
    until its norm is <= 1/2, then doubled back: Γ(2t) = (I + Φ(t)) Γ(t), Φ(2t) = Φ(t)². The
    rounding of the doublings is what a finite difference between two parameter sets sees.
    """
    n = a.shape[0]
    d = _balance(a)
    bal = np.empty((n, n))
    norm = 0.0
    for j in range(n):
        col = 0.0
        for i in range(n):
            bal[i, j] = a[i, j] * d[j] / d[i]
            col += abs(bal[i, j])
        norm = max(norm, col * delta)
    halvings = 0
    while norm > 0.5:
        norm *= 0.5
        halvings += 1
    h = delta / 2.0 ** halvings
    # Γ(h) = h Σ_k (Ah)^k / (k+1)!, Φ(h) = I + A Γ(h); written as loops, not array expressions,
    # which took numba seconds to compile
    term = np.zeros((n, n))
    gamma = np.zeros((n, n))
    for i in range(n):
        term[i, i] = h
        gamma[i, i] = h
    tmp = np.empty((n, n))
    for k in range(1, ZOH_TAYLOR + 1):
        _matmul(term, bal, tmp)
        for i in range(n):
            for j in range(n):
                term[i, j] = tmp[i, j] * (h / (k + 1))
                gamma[i, j] += term[i, j]
    phi = np.empty((n, n))
    _matmul(bal, gamma, phi)
    for i in range(n):
        phi[i, i] += 1.0
    for _ in range(halvings):
        _matmul(phi, gamma, tmp)
        for i in range(n):
            for j in range(n):
                gamma[i, j] += tmp[i, j]
        _matmul(phi, phi, tmp)
        for i in range(n):
            for j in range(n):
                phi[i, j] = tmp[i, j]
    out = np.empty((n_points, 2, n, n))
    for i in range(n):  # loops, not slice assignments: those add seconds to the compile time
        for j in range(n):
            out[0, 0, i, j] = phi[i, j]
            out[0, 1, i, j] = gamma[i, j]
    for p in range(1, n_points):  # Φ(t + δ) = Φ(t) Φ(δ), Γ(t + δ) = Γ(t) + Φ(t) Γ(δ)
        _matmul(out[p - 1, 0], phi, out[p, 0])
        _matmul(out[p - 1, 0], gamma, tmp)
        for i in range(n):
            for j in range(n):
                out[p, 1, i, j] = out[p - 1, 1, i, j] + tmp[i, j]
    for p in range(n_points):  # undo the balancing: M = D M~ D^-1
        for i in range(n):
            for j in range(n):
                out[p, 0, i, j] *= d[i] / d[j]
                out[p, 1, i, j] *= d[i] / d[j]
    return out


@njit(cache=True, inline="always", error_model="numpy")
def _dp_unstable(z):
    """|R(z)| > 1 for the 5th-order Dormand-Prince solution, R(z) = sum_{k<=5} z^k / k! + z^6 / 600."""
    return abs(1 + z * (1 + z * (1 / 2 + z * (1 / 6 + z * (1 / 24 + z * (1 / 120 + z / 600)))))) > 1.0


@njit(cache=True, error_model="numpy")
def _dp_stability_radius(angle):
    """|z| where the ray z = r e^{i angle} leaves the stability region |R(z)| <= 1 of the 5th-order
    Dormand-Prince solution (3.3 on the negative axis)."""
    direction = complex(math.cos(angle), math.sin(angle))
    lo = 0.0
    hi = 0.0
    for k in range(1, 200):  # scan out to |z| = 10 for the first step outside the region
        hi = 0.05 * k
        if _dp_unstable(hi * direction):
            break
        lo = hi
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        if _dp_unstable(mid * direction):
            hi = mid
        else:
            lo = mid
    return lo


#: fraction of the stability limit a Dormand-Prince step of the hybrid integrator may reach
DP_STABILITY_SAFETY = 0.9


@njit(cache=True, error_model="numpy")
def _dp_stable_steps(eigenvalues):
    """(n_sets,) longest stable Dormand-Prince step for each row of (n_sets, n) eigenvalues."""
    h_max = np.full(eigenvalues.shape[0], np.inf)
    for s in range(eigenvalues.shape[0]):
        for v in eigenvalues[s]:
            if v.real < 0.0:
                radius = _dp_stability_radius(math.atan2(v.imag, v.real))
                h_max[s] = min(h_max[s], DP_STABILITY_SAFETY * radius / abs(v))
    return h_max


@njit(cache=True, error_model="numpy")
def _linear_state_matrices(model_id, thetas, consts, n_x):
    """(n_sets, n_x, n_x) state matrices of the linear regime, one per parameter set."""
    a = np.empty((thetas.shape[0], n_x, n_x))
    for s in range(thetas.shape[0]):
        _linear_state_matrix(model_id, thetas[s], consts, a[s])
    return a


@njit(cache=True, error_model="numpy")
def _zoh_propagator_sets(a, delta, n_points):
    """(n_sets, n_points, 2, n, n) propagators of each state matrix (:func:`_zoh_propagators`),
    computed before the integration kernel, which then compiles without them."""
    n = a.shape[1]
    out = np.empty((a.shape[0], n_points, 2, n, n))
    for s in range(a.shape[0]):
        out[s] = _zoh_propagators(a[s], delta, n_points)
    return out


def _stable_steps_of(a: np.ndarray) -> np.ndarray:
    h_max = np.full(a.shape[0], np.inf)
    finite = np.all(np.isfinite(a), axis=(1, 2))  # a set with overflowing entries diverges on its own
    if np.any(finite):
        h_max[finite] = _dp_stable_steps(np.linalg.eigvals(a[finite]).astype(np.complex128))
    return h_max


def stable_steps(model: Model, thetas: np.ndarray, constants: np.ndarray | None = None) -> np.ndarray:
    """(n_sets,) longest Dormand-Prince step [s] that keeps every decaying mode of each set's
    linear-regime state matrix inside the stability region (infinite when none decays).

    The hybrid integrator holds its Dormand-Prince steps to this. Just outside the linear
    regime (LT/HS below ~76 rad/s motor speed) the trajectory is smooth enough for 10 ms
    steps, beyond the limit of the fast current-speed mode (|lambda| ~ 470 /s: 6.3 ms): the
    error estimate accepts them, but every replay of those steps by another parameter set
    amplifies its difference, and finite differences turn to noise. The eigenvalues are
    taken here, in numpy, rather than inside the parallel kernel, where LAPACK's own threads
    would contend with the kernel's.
    """
    if kernel_family(model) != "nominal":
        raise SimulationError(f"{model.title} declares no linear regime; stable steps cover the nominal concepts")
    consts = model.constants_vector() if constants is None else constants
    return _stable_steps_of(_linear_state_matrices(model.model_id, np.atleast_2d(thetas),
                                                   model.kernel_constants(consts), model.n_states))


def _hybrid_setup(model: Model, thetas: np.ndarray, kernel_consts: np.ndarray, dt: float, hybrid: bool):
    """Propagators (n_sets, n_checks, 2, n, n) and step caps (n_sets,) of the adaptive kernel:
    none and infinite for plain Dormand-Prince."""
    if not hybrid:
        return np.empty((thetas.shape[0], 0, 2, model.n_states, model.n_states)), np.full(thetas.shape[0], np.inf)
    a = _linear_state_matrices(model.model_id, thetas, kernel_consts, model.n_states)
    return _zoh_propagator_sets(a, dt / ZOH_CHECKS, ZOH_CHECKS), _stable_steps_of(a)


@njit(cache=True, error_model="numpy")
def _zoh_interval(model_id, x, dx, u, th, consts, props, delta, xt, dxt):
    """True when the interval from ``x`` (derivative ``dx``) stays in the linear regime at
    every checked point; ``xt`` then holds the exact state at the interval's end."""
    if not _linear_regime(model_id, x, dx, u, th, consts, delta):
        return False
    n = x.shape[0]
    for p in range(props.shape[0]):
        for i in range(n):
            acc_x = 0.0
            acc_f = 0.0
            for q in range(n):
                acc_f += props[p, 0, i, q] * dx[q]
                acc_x += props[p, 1, i, q] * dx[q]
            dxt[i] = acc_f
            xt[i] = x[i] + acc_x
        if not _linear_regime(model_id, xt, dxt, u, th, consts, delta):
            return False
    return True


@njit(cache=True, inline="always", error_model="numpy")
def _zoh_step(x, dx, props, xt):
    """x += Γ(dt) dx, the arithmetic of :func:`_zoh_interval`'s last point: the exact step of a
    linear-regime interval, replayed without the regime tests."""
    n = x.shape[0]
    last = props.shape[0] - 1
    for i in range(n):
        acc = 0.0
        for q in range(n):
            acc += props[last, 1, i, q] * dx[q]
        xt[i] = x[i] + acc
    for i in range(n):
        x[i] = xt[i]


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
    integrator: str | None = None,
    rtol: float | None = None,
    share_steps: bool = False,
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
    effects = kernel_family(model) == "effects"
    x0 = np.zeros(model.n_states) if x0 is None else np.ascontiguousarray(x0, dtype=np.float64)
    out = np.empty((thetas.shape[0], time.size, model.n_outputs))
    if method == "rk4":
        kernel = _integrate_batch_effects if effects else _integrate_batch
        kernel(model.model_id, thetas, model.kernel_constants(consts), inputs, x0, h, n_sub, out)
    elif effects:  # no linear regime is declared for the augmented models: "hybrid" is Dormand-Prince
        args = (model.model_id, thetas, model.kernel_constants(consts), inputs, x0, dt, tol, error_scales(model, thetas))
        if share_steps and thetas.shape[0] > 1:
            _run_shared(_dopri_batch_shared_effects, args, out, time.size)
        else:
            _dopri_batch_effects(*args, out)
    else:
        kernel_consts = model.kernel_constants(consts)
        args = (model.model_id, thetas, kernel_consts, inputs, x0, dt, tol, error_scales(model, thetas),
                *_hybrid_setup(model, thetas, kernel_consts, dt, method == "hybrid"))
        if share_steps and thetas.shape[0] > 1:
            _run_shared(_dopri_batch_shared, args, out, time.size)
        else:
            _dopri_batch(*args, out)
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
        accepted, rejected = _dopri_one(model.model_id, theta, kernel_consts, inputs, np.zeros(model.n_states), dt,
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
