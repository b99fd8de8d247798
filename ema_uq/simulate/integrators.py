"""The integration loops, one per method, for the nominal and the augmented state vectors.

Between samples the state is advanced by ``n_sub`` classical RK4 steps (``_integrate_one``)
or by adaptive Dormand-Prince 5(4) steps (``_dopri_one``; with propagators, exact steps over
the linear regime: ``linear.py``). Every loop takes the concept's kernel id and the effects'
bit set ``flags`` (``models.effect_kernels.effect_flags``) and passes both down to the
concept's one right-hand side. Each method has one parallel batch entry taking ``flags``
(``*_flags``) and a nominal entry that passes ``NOMINAL`` (None): numba compiles the loops
and the effect hooks once for that type and prunes the effects' branches before typing them,
so the nominal kernel holds the nominal arithmetic only. The entries with effects take
``flags`` as a run-time integer: one compiled kernel per method serves every effect set, each
effect's physics behind a test of its bit.
RK4 has a second entry with effects, ``_integrate_batch_specialised``, compiled for one concept
and one effect set (both literal): LLVM folds every test of a bit and keeps the physics of the
effects that are on only, the same arithmetic at about the nominal cost. ``specialise.py``
decides when an effect set has earned that compilation.
"""
from __future__ import annotations

import math

import numpy as np
from numba import literally, njit, prange

from ..models import effect_kernels as ek
from .dispatch import _evaluate
from .linear import _zoh_interval, _zoh_step


#: the effects' bit set of the nominal models: ``None``, a type of its own, so that numba prunes
#: every ``flags is not None and ...`` branch of the right-hand side before it types the code
NOMINAL = None


# --- fixed-step RK4 -------------------------------------------------------------------------
@njit(cache=True, error_model="numpy")
def _integrate_one(model_id, flags, th, consts, inputs, x0, h, n_sub, out):
    """Integrate one parameter vector; writes outputs (n_samples, n_outputs) into ``out``.

    One call site of the (inlined) right-hand side: inlined at each of the four stages, the
    equations with effects took minutes to compile."""
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
                sample = sub == 0 and stage == 0
                _evaluate(model_id, flags, xt, u, th, consts, stages[stage], out[k] if sample else scratch, sample)
                if last:
                    break
            if last:
                break
            for i in range(n_x):
                x[i] += h / 6.0 * (stages[0, i] + 2.0 * stages[1, i] + 2.0 * stages[2, i] + stages[3, i])


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
def _freeze(flags, dx, scale):
    """Zero the derivatives of the states with ``scale < 0`` (an effect at its ``off`` value
    whose states feed nothing: the stiff shaft mode of ``shaft_compliance`` at period 0 would
    otherwise be integrated, unresolved, for nothing); nothing without effect states."""
    if flags is not None and flags & ek.STATEFUL:
        for i in range(dx.shape[0]):
            if scale[i] < 0.0:
                dx[i] = 0.0


@njit(cache=True, inline="always", error_model="numpy")
def _dp_sample(model_id, flags, x, inputs, j, u, th, consts, scale, stages, k, scratch, out):
    """Outputs at sample j into ``out[j]`` and the first stage of its interval into
    ``stages[0]``; ``u`` receives the held input. Rows are copied in and out rather than
    viewed: a view costs two atomic reference-count updates, more than the copy."""
    for i in range(u.shape[0]):
        u[i] = inputs[j, i]
    _evaluate(model_id, flags, x, u, th, consts, k, scratch)
    _freeze(flags, k, scale)
    for i in range(x.shape[0]):
        stages[0, i] = k[i]
    for i in range(scratch.shape[0]):
        out[j, i] = scratch[i]


@njit(cache=True, inline="always", error_model="numpy")
def _dp_stages(model_id, flags, x, u, th, consts, scale, stages, h, xt, k, scratch):
    """Stages 2-7 of a step of length ``h`` from ``x`` (derivatives only); ``xt`` ends as
    the 5th-order solution."""
    for s in range(1, 7):
        _dp_stage_state(x, stages, s, h, xt)
        _evaluate(model_id, flags, xt, u, th, consts, k, scratch, False)
        _freeze(flags, k, scale)
        for i in range(x.shape[0]):
            stages[s, i] = k[i]


@njit(cache=True, inline="always", error_model="numpy")
def _dp_workspace(x0, n_outputs):
    """Working arrays of one adaptive run: the state (a copy of ``x0``), the state where a
    stage is evaluated, the 7 stage derivatives, a derivative and an output scratch row."""
    n_x = x0.shape[0]
    return x0.copy(), np.empty(n_x), np.empty((7, n_x)), np.empty(n_x), np.empty(n_outputs)


@njit(cache=True, error_model="numpy")
def _dopri_one(model_id, flags, th, consts, inputs, x0, dt, rtol, scale, props, h_stable, out, steps, counts):
    """Adaptive DP5(4) run of one parameter vector; writes outputs (n_samples, n_outputs) into ``out``.

    ``scale`` (n_states,): absolute error scale of each state (its typical magnitude; the
    absolute tolerance is rtol * scale), 0 to leave a state out of the error norm, -1 to freeze
    it (:func:`_freeze`). Returns the
    numbers of accepted and rejected steps. With propagators ``props`` (n_checks, 2, n, n),
    :func:`linear._zoh_propagator_sets`, intervals in the linear regime take the exact step
    (integrator "hybrid"; none for n_checks = 0, plain Dormand-Prince), and no step is longer
    than ``h_stable`` (:func:`linear.stable_steps`; infinite for plain Dormand-Prince). A non-empty
    ``steps`` records the accepted step lengths in order and ``counts`` (n_samples - 1,) their
    number per sample interval (0: an exact step), for :func:`_dopri_replay_one`; the accepted
    count is -1 when ``steps`` is too short, DP_DIVERGED when the trajectory left the finite
    numbers (the outputs from the next sample on are NaN, as RK4 gives them).
    """
    x, xt, stages, k, scratch = _dp_workspace(x0, out.shape[1])
    n_checks = props.shape[0]
    delta = dt / max(n_checks, 1)
    n_samples = inputs.shape[0]
    h_open = dt  # the step that opened the previous interval: the transient repeats every sample
    n_accepted = 0
    n_rejected = 0
    recording = steps.shape[0] > 0
    u = np.empty(inputs.shape[1])
    for j in range(n_samples):
        _dp_sample(model_id, flags, x, inputs, j, u, th, consts, scale, stages, k, scratch, out)
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
            _dp_stages(model_id, flags, x, u, th, consts, scale, stages, h, xt, k, scratch)
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


@njit(cache=True, error_model="numpy")
def _dopri_replay_one(model_id, flags, th, consts, inputs, x0, scale, props, steps, counts, out):
    """The accepted steps recorded by ``_dopri_one``, given (no error control): the same
    arithmetic, so the set that chose the steps is reproduced bit for bit and any other set is
    a smooth function of its parameters along that one step sequence. An interval without
    steps was an exact linear-regime step: it is repeated with this set's own propagator;
    ``scale`` freezes states as in ``_dopri_one``."""
    x, xt, stages, k, scratch = _dp_workspace(x0, out.shape[1])
    n_samples = inputs.shape[0]
    pos = 0
    u = np.empty(inputs.shape[1])
    for j in range(n_samples):
        _dp_sample(model_id, flags, x, inputs, j, u, th, consts, scale, stages, k, scratch, out)
        if j == n_samples - 1:
            break
        if counts[j] == 0 and props.shape[0] > 0:
            _zoh_step(x, stages[0], props, xt)
        for _ in range(counts[j]):
            h = steps[pos]
            pos += 1
            _dp_stages(model_id, flags, x, u, th, consts, scale, stages, h, xt, k, scratch)
            _dp_accept(x, stages, xt)


# --- the batch entries: one per method taking the effects' bit set, and its nominal entry ------
@njit(cache=True, parallel=True, error_model="numpy")
def _integrate_batch_flags(model_id, flags, thetas, consts, inputs, x0, h, n_sub, out):
    """RK4 kernel entry: thetas (n_sets, n_params) -> out (n_sets, n_samples, n_outputs)."""
    for s in prange(thetas.shape[0]):
        _integrate_one(model_id, flags, thetas[s], consts, inputs, x0, h, n_sub, out[s])


@njit(cache=True, parallel=True, error_model="numpy")
def _integrate_batch_specialised(model_id, flags, thetas, consts, inputs, x0, h, n_sub, out):
    """``_integrate_batch_flags`` compiled for the literal ``model_id`` and ``flags``: one
    machine code per concept and effect set, without the branches of the effects that are off."""
    literally(model_id)
    literally(flags)
    for s in prange(thetas.shape[0]):
        _integrate_one(model_id, flags, thetas[s], consts, inputs, x0, h, n_sub, out[s])


@njit(cache=True, parallel=True, error_model="numpy")
def _dopri_batch_flags(model_id, flags, thetas, consts, inputs, x0, dt, rtol, scales, props, h_stable, out):
    """Dormand-Prince kernel entry: thetas (n_sets, n_params), scales (n_sets, n_states), props
    (n_sets, n_checks, 2, n, n), h_stable (n_sets,) -> out (n_sets, n_samples, n_outputs)."""
    for s in prange(thetas.shape[0]):
        _dopri_one(model_id, flags, thetas[s], consts, inputs, x0, dt, rtol, scales[s], props[s], h_stable[s],
                   out[s], np.empty(0), np.empty(0, dtype=np.int64))


@njit(cache=True, inline="always", error_model="numpy")
def _dopri_shared(model_id, flags, thetas, consts, inputs, x0, dt, rtol, scales, props, h_stable, out, steps, counts):
    """The body of ``_dopri_batch_shared_flags`` and of its nominal entry, inlined into both (at
    numba IR level, its prange loop included): set 0 chooses the steps, every other set replays
    them."""
    n_accepted, _ = _dopri_one(model_id, flags, thetas[0], consts, inputs, x0, dt, rtol, scales[0], props[0],
                               h_stable[0], out[0], steps, counts)
    if n_accepted == DP_DIVERGED:  # no step sequence to follow: differences around it are undefined
        for s in range(1, out.shape[0]):
            _fill_nan(out[s], 0)
        return True
    if n_accepted < 0:
        return False
    for s in prange(1, thetas.shape[0]):
        _dopri_replay_one(model_id, flags, thetas[s], consts, inputs, x0, scales[s], props[s], steps, counts,
                          out[s])
    return True


@njit(cache=True, parallel=True, error_model="numpy")
def _dopri_batch_shared_flags(model_id, flags, thetas, consts, inputs, x0, dt, rtol, scales, props, h_stable, out,
                              steps, counts):
    """``_dopri_batch_flags`` where set 0 chooses the steps and every other set replays them:
    finite-difference sensitivities free of the step-selection noise of independent adaptive
    runs. Returns False (nothing else done) when ``steps`` is too short for set 0's sequence."""
    return _dopri_shared(model_id, flags, thetas, consts, inputs, x0, dt, rtol, scales, props, h_stable, out, steps,
                         counts)


# the nominal entries: the same calls with the literal NOMINAL (a nominal entry calling the one
# taking flags would put one more layer of LLVM optimisation over the whole kernel; a body both
# share, such as _dopri_shared, is inlined at numba IR level, which adds no such layer)
@njit(cache=True, parallel=True, error_model="numpy")
def _integrate_batch(model_id, thetas, consts, inputs, x0, h, n_sub, out):
    """``_integrate_batch_flags`` of a nominal model."""
    for s in prange(thetas.shape[0]):
        _integrate_one(model_id, NOMINAL, thetas[s], consts, inputs, x0, h, n_sub, out[s])


@njit(cache=True, parallel=True, error_model="numpy")
def _dopri_batch(model_id, thetas, consts, inputs, x0, dt, rtol, scales, props, h_stable, out):
    """``_dopri_batch_flags`` of a nominal model."""
    for s in prange(thetas.shape[0]):
        _dopri_one(model_id, NOMINAL, thetas[s], consts, inputs, x0, dt, rtol, scales[s], props[s], h_stable[s],
                   out[s], np.empty(0), np.empty(0, dtype=np.int64))


@njit(cache=True, parallel=True, error_model="numpy")
def _dopri_batch_shared(model_id, thetas, consts, inputs, x0, dt, rtol, scales, props, h_stable, out, steps, counts):
    """``_dopri_batch_shared_flags`` of a nominal model."""
    return _dopri_shared(model_id, NOMINAL, thetas, consts, inputs, x0, dt, rtol, scales, props, h_stable, out, steps,
                         counts)


@njit(cache=True, error_model="numpy")
def _dopri_one_nominal(model_id, th, consts, inputs, x0, dt, rtol, scale, props, h_stable, out, steps, counts):
    """``_dopri_one`` of a nominal model (step statistics)."""
    return _dopri_one(model_id, NOMINAL, th, consts, inputs, x0, dt, rtol, scale, props, h_stable, out, steps,
                      counts)
