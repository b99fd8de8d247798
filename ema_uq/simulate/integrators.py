"""The integration loops and their parallel batch entries.

Fixed-step RK4 (``_integrate_batch``) and adaptive Dormand-Prince 5(4) (``_dopri_batch``,
``_dopri_batch_shared``; with propagators, exact steps over the linear regime of ``linear.py``)
for the nominal models, and the same loops for the models with unmodelled effects (``*_effects``).
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit, prange

from .dispatch import _evaluate, _evaluate_effects
from .linear import _zoh_interval, _zoh_step


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
