"""Statistics shared by identification, identifiability and the gap diagnosis, written once.

- the output-error likelihood: residual covariance R, log det R and the objective
  V = (N/2) log det R + ½ Σ_j ((θ_j - θ_j,rig) / σ_j,rig)² (negative log-likelihood
  concentrated over R, with the rig pseudo-measurements of docs/MODEL_SPEC.md);
- residual whiteness: lagged normalised correlations and the Ljung-Box test;
- operating regimes of a speed signal (rest, motion and its direction, acceleration), the
  generic part of every concept's regime masks;
- start grids of effect parameters: magnitudes at multiples of a start value, phases on a
  grid over one turn.

Pure numpy on arrays; no model physics.
"""
from __future__ import annotations

from typing import Sequence

import numpy as np
from scipy import special

#: Ljung-Box lags used by default (residual tests of identify and gap)
LJUNG_BOX_LAGS = 25
#: magnitude multiples and phase points of a start grid (gap diagnosis default)
START_MULTIPLES = (0.3, 1.0, 3.0, 10.0)
PHASE_STARTS = 4
#: above this many combinations a start grid varies one parameter at a time
MAX_GRID = 32


# ----------------------------------------------------------------------------------------
# the output-error likelihood
# ----------------------------------------------------------------------------------------
def covariance(residuals: np.ndarray) -> np.ndarray:
    """R = (1/N) Σ e eᵀ of (N, n_channels) residuals (eq. 49), or of a batch (n_sets, N, n_ch).

    A matrix product eᵀ e (BLAS), not an einsum: with few channels and many samples the
    einsum loop costs more than the simulations of the posterior.

    A trial of a fit whose simulation diverges has residuals so large that their products
    overflow: R gets an infinite entry, :func:`log_det_r` maps it to +inf and the fit refuses
    the trial. That is the intended path, so the overflow is not warned about."""
    residuals = np.asarray(residuals)
    n = residuals.shape[-2]
    with np.errstate(over="ignore", invalid="ignore"):
        return np.matmul(np.swapaxes(residuals, -1, -2), residuals) / n


def information(sens: np.ndarray, r_inv: np.ndarray) -> np.ndarray:
    """Fisher information Σ_k S_k R⁻¹ S_kᵀ (p, p) of sensitivities ``sens`` (p, N, m) under
    residual covariance R (``r_inv`` = R⁻¹, (m, m)): entry (j, l) = Σ_k,c,d S_jkc R⁻¹_cd S_lkd.

    Two matrix products ((S R⁻¹) reshaped to (p, N·m) times Sᵀ) instead of a three-operand
    einsum; the same sum in another order."""
    sens = np.asarray(sens, dtype=float)
    p = sens.shape[0]
    weighted = (sens @ r_inv).reshape(p, -1)
    return weighted @ sens.reshape(p, -1).T


def log_det_r(r: np.ndarray) -> float | np.ndarray:
    """log det R of one (m, m) residual covariance (a float) or of a batch (..., m, m) (an
    array); +inf where R is singular, has det R < 0 or is not finite.

    The one place where log det R is taken: the objective V of identification, the posterior
    (log L = -(N/2) log det R), the cost QoI of the sensitivity analysis and the gap
    diagnosis all read it from here, so all of them treat a degenerate R alike.

    Why +inf for a singular R, although det R -> 0 is log det R -> -inf: a residual
    covariance with a null direction says that some combination of channels is reproduced
    exactly — a constant or duplicated channel, a simulation that diverged to NaN, or fewer
    samples than channels — never that the parameters are good. Read as -inf it would be the
    best point of every fit and the mode of every posterior; read as NaN it compares false
    with everything and silently stalls a line search. +inf is the worst cost: an optimiser
    steps back from it, the posterior gives the point zero likelihood (log L = -inf), and a
    Sobol analysis stops with an error naming the non-finite runs.
    """
    r = np.asarray(r, dtype=float)
    with np.errstate(invalid="ignore"):  # NaN in R: slogdet warns, the point is rejected below
        sign, logdet = np.linalg.slogdet(r)
    value = np.where((sign > 0) & np.isfinite(logdet), logdet, np.inf)
    return float(value) if value.ndim == 0 else value


def rig_penalty(values: np.ndarray, rig_values: np.ndarray, rig_std: np.ndarray) -> float:
    """½ Σ ((θ_j - θ_j,rig) / σ_j,rig)² over the parameters with a rig pseudo-measurement
    (three arrays of equal length; 0 when empty)."""
    values = np.asarray(values, dtype=float)
    if not values.size:
        return 0.0
    return 0.5 * float(np.sum(((values - rig_values) / rig_std) ** 2))


def rig_terms(parameters, index: Sequence[int] | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(positions within ``index``, rig values, rig σ) of the parameters of a ParameterSet that
    carry a rig pseudo-measurement (``prior_std``); ``index``: the parameters considered
    (default: all, e.g. the free ones of a fit)."""
    index = range(len(parameters.parameters)) if index is None else index
    pos, mean, std = [], [], []
    for k, i in enumerate(index):
        p = parameters.parameters[i]
        if p.prior_std is not None:
            pos.append(k)
            mean.append(p.nominal)
            std.append(p.prior_std)
    return np.array(pos, dtype=int), np.array(mean), np.array(std)


def objective(n_samples: int, log_det_r: float, theta: np.ndarray | None = None, parameters=None,
              index: Sequence[int] | None = None) -> float:
    """V = (N/2) log det R + ½ Σ ((θ_j - rig_j) / σ_j)².

    ``theta``: the values of the parameters ``index`` of ``parameters`` (a ParameterSet), in
    that order (default: the full vector over all parameters); without ``parameters`` V has
    no rig term. Counting every parameter with a rig value (not only the free ones) makes V
    comparable between fits with different free sets.
    """
    penalty = 0.0
    if parameters is not None:
        pos, mean, std = rig_terms(parameters, index)
        penalty = rig_penalty(np.asarray(theta, dtype=float)[pos], mean, std)
    return 0.5 * n_samples * log_det_r + penalty


# ----------------------------------------------------------------------------------------
# residual whiteness
# ----------------------------------------------------------------------------------------
def lagged_correlation(a: np.ndarray, b: np.ndarray, lags: np.ndarray) -> np.ndarray:
    """Normalised cross-correlation (1/n) Σ_k a_k b_{k-l} / (σ_a σ_b) of two (n,) signals at the
    given integer lags (only those: O(n · lags))."""
    a = (a - a.mean()) / a.std()
    b = (b - b.mean()) / b.std()
    n = a.size
    return np.array([np.dot(a[l:], b[:n - l]) if l >= 0 else np.dot(a[:n + l], b[-l:]) for l in lags]) / n


def max_cross_correlation(e: np.ndarray, u: np.ndarray, max_lag: int = LJUNG_BOX_LAGS) -> float:
    """Largest |normalised cross-correlation| of ``e`` and ``u`` over lags -max_lag..max_lag."""
    return float(np.max(np.abs(lagged_correlation(e, u, np.arange(-max_lag, max_lag + 1)))))


def ljung_box_statistic(residual: np.ndarray, max_lag: int = LJUNG_BOX_LAGS) -> float:
    """Q = n (n + 2) Σ_{l=1..L} r_l² / (n - l) of one (n,) residual; χ²_L under whiteness."""
    n = residual.size
    lags = np.arange(1, max_lag + 1)
    r = lagged_correlation(residual, residual, lags)
    return float(n * (n + 2) * np.sum(r ** 2 / (n - lags)))


def ljung_box(residual: np.ndarray, max_lag: int = LJUNG_BOX_LAGS) -> float:
    """p-value of the Ljung-Box portmanteau test that the (n,) ``residual`` is white."""
    # χ² survival by scipy.special's chdtrc, the routine behind scipy.stats.chi2.sf: scipy.stats
    # takes ~0.5 s to import, and every verb that validates a fit calls this
    return float(special.chdtrc(max_lag, ljung_box_statistic(residual, max_lag)))


# ----------------------------------------------------------------------------------------
# operating regimes of a speed signal
# ----------------------------------------------------------------------------------------
def speed_regimes(speed: np.ndarray, dt: float, *, low_fraction: float,
                  acceleration_fraction: float) -> dict[str, np.ndarray]:
    """Boolean (n,) masks of a speed signal (any unit) sampled at ``dt`` [s]:
    ``moving`` (|v| > ``low_fraction`` of its maximum) and ``low_speed`` (the rest),
    ``forward``/``backward`` (moving with v > 0 / v < 0) and ``accelerating``
    (|dv/dt| > ``acceleration_fraction`` of its maximum, central differences)."""
    peak = max(float(np.max(np.abs(speed))), 1e-12)
    moving = np.abs(speed) > low_fraction * peak
    accel = np.gradient(speed, dt)
    return {"low_speed": ~moving, "moving": moving, "forward": speed > low_fraction * peak,
            "backward": speed < -low_fraction * peak,
            "accelerating": np.abs(accel) > acceleration_fraction * max(float(np.max(np.abs(accel))), 1e-12)}


# ----------------------------------------------------------------------------------------
# start grids
# ----------------------------------------------------------------------------------------
def start_values(start: float, lower: float, upper: float, *, phase: bool = False,
                 multiples: Sequence[float] = START_MULTIPLES, phase_starts: int = PHASE_STARTS) -> np.ndarray:
    """Start candidates of one parameter, sorted and within [lower, upper]: a phase [rad] at
    ``phase_starts`` points of a turn from ``start``, any other at ``multiples`` of ``start``
    (only ``start`` itself when it is 0)."""
    if phase:
        values = start + np.arange(phase_starts) * (2.0 * np.pi / phase_starts)
        values = np.where(values > upper, values - 2.0 * np.pi, values)
    else:
        values = start * np.array(multiples) if start != 0 else np.array([start])
    return np.unique(np.clip(values, lower, upper))


def start_grid(centre: np.ndarray, positions: Sequence[int], values: Sequence[np.ndarray],
               max_grid: int = MAX_GRID) -> np.ndarray:
    """Start vectors (n_starts, n_params), unique rows in sorted order: ``centre`` (n_params,)
    with the entries ``positions`` set to every combination of their candidate ``values``
    when there are at most ``max_grid``, else varied one at a time around ``centre``."""
    positions = list(positions)
    if int(np.prod([v.size for v in values])) <= max_grid:
        mesh = np.meshgrid(*values, indexing="ij")
        combos = np.column_stack([g.ravel() for g in mesh])
    else:
        middle = centre[positions]
        rows = [middle]
        for j, candidates in enumerate(values):
            for v in candidates:
                row = middle.copy()
                row[j] = v
                rows.append(row)
        combos = np.array(rows)
    thetas = np.repeat(np.asarray(centre, dtype=float)[None], combos.shape[0], axis=0)
    thetas[:, positions] = combos
    return np.unique(thetas, axis=0)
