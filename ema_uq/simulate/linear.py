"""Exact steps over the linear regime (integrator "hybrid").

Where a concept is linear (models/htls.py, lths.py: "the linear regime") its held-input
dynamics dx/dt = A x + b are solved exactly: x(t_k + t) = x_k + Γ(t) f(x_k), f(x_k) being the
first stage the output evaluation already gives, Γ(t) = ∫_0^t e^{As} ds. Γ and Φ(t) = e^{At}
(which carries f: f(t) = Φ(t) f(x_k)) are computed once per parameter set at ZOH_CHECKS
evenly spaced points of the interval; the regime is tested at each, and an interval that
leaves it anywhere is integrated by Dormand-Prince instead. The transient every held
reference sample starts (~5 Dormand-Prince steps of 2 ms on HT/LS) costs one
matrix-vector product per checked point instead.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..models import Model
from .dispatch import SimulationError, _linear_regime, _linear_state_matrix, kernel_family

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
    return _stable_steps_of(linear_state_matrices(model, thetas, constants))


def linear_state_matrices(model: Model, thetas: np.ndarray, constants: np.ndarray | None = None) -> np.ndarray:
    """(n_sets, n_states, n_states) state matrices ∂f/∂x of a nominal concept's linear regime,
    one per parameter set (design ``constants`` default to the model's)."""
    if kernel_family(model) != "nominal":
        raise SimulationError(f"{model.title} declares no linear regime; it is known for the nominal concepts")
    consts = model.constants_vector() if constants is None else constants
    return _linear_state_matrices(model.model_id, np.atleast_2d(np.asarray(thetas, dtype=np.float64)),
                                  model.kernel_constants(consts), model.n_states)


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

