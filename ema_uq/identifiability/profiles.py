"""Profile likelihoods and the verdict per parameter.

Each friction/damping parameter is fixed on a grid (±4 CRB σ, or a relative span where that is
narrower or the bound is missing) and the others re-optimised by Gauss-Newton, warm-started
from the neighbouring point; the 95 % interval is where the objective has risen by
χ²₁(0.95)/2. Re-optimising along an exact null direction would make Gauss-Newton singular, so
each profile frees only a maximal identifiable subset of the other parameters; when a freed
member of a lumped group reaches a bound, the group is handed to another member.

A verdict is identifiable, practically non-identifiable (profile open on a side, or too
wide) or structurally non-identifiable (flat profile along an exact null direction of F);
parameters not profiled are judged from the information matrix alone.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from scipy.stats import chi2

from .. import statistics
from ..experiments import Measurement
from ..identify import FitProblem, IdentificationError, Settings, estimate
from ..identify.information import CRB_Z, near_bounds
from ..models import Model

#: objective rise of the 95 % profile interval: χ²₁(0.95)/2 on V = (N/2) log det R + prior
PROFILE_THRESHOLD = float(chi2.ppf(0.95, 1) / 2.0)
#: a profile whose rise stays below this fraction of the threshold over its whole span is flat
FLAT_FRACTION = 0.1
PROFILE_SETTINGS = Settings(tolerance=1e-6, max_iterations=30, cramer_rao=False)  # only V is profiled

VERDICTS = ("identifiable", "practically_non_identifiable", "structurally_non_identifiable")


# --------------------------------------------------------------------------------------
# profile likelihood
# --------------------------------------------------------------------------------------
@dataclass
class Profile:
    """Profile of one parameter: ``grid`` values, re-optimised objective ``objective`` (V),
    and the 95 % interval where V - V_min crosses :data:`PROFILE_THRESHOLD` (None: open side)."""

    name: str
    estimate: float
    grid: np.ndarray
    objective: np.ndarray
    free: tuple[str, ...]
    n_simulations: int
    v_min: float = float("nan")
    failures: list[str] = field(default_factory=list)

    @property
    def delta(self) -> np.ndarray:
        return self.objective - self.v_min

    def interval(self, threshold: float = PROFILE_THRESHOLD) -> tuple[float | None, float | None]:
        """Crossings of the threshold, interpolated linearly in the signed root sqrt(2 ΔV)
        (exact for a quadratic profile)."""
        order = np.argsort(self.grid)
        g, dv = self.grid[order], np.maximum(self.delta[order], 0.0)
        c = int(np.argmin(np.abs(g - self.estimate)))
        root = math.sqrt(2.0 * threshold)

        def crossing(indices):
            prev = c
            for i in indices:
                if dv[i] >= threshold:
                    r0, r1 = math.sqrt(2.0 * dv[prev]), math.sqrt(2.0 * dv[i])
                    w = (root - r0) / (r1 - r0) if r1 > r0 else 1.0
                    return float(g[prev] + w * (g[i] - g[prev]))
                prev = i
            return None

        return crossing(range(c - 1, -1, -1)), crossing(range(c + 1, g.size))

    def rise(self) -> tuple[float, float]:
        """Largest ΔV below and above the estimate."""
        below = self.delta[self.grid < self.estimate]
        above = self.delta[self.grid > self.estimate]
        return (float(below.max()) if below.size else 0.0, float(above.max()) if above.size else 0.0)


def _objective(problem: FitProblem, theta: np.ndarray, log_det_r: float) -> float:
    """V at the full vector ``theta``, the rig term over every parameter with a rig value, free
    or fixed, so that profiles with different free sets share one objective."""
    return statistics.objective(problem.n_samples, log_det_r, theta, problem.parameters)


def _fit(measurements, model, channels, constants, free: Sequence[str], start: np.ndarray):
    parameters = model.parameters.freeing_only(free)
    problem = FitProblem(measurements, parameters=parameters, channels=channels, constants=constants)
    fit = estimate(problem, method="gn", start=start, settings=PROFILE_SETTINGS)
    return fit, _objective(problem, fit.estimate, fit.log_det_r)


def _fit_with_handover(measurements, model, channels, constants, free: Sequence[str], start: np.ndarray,
                       reselect, max_handovers: int = 8):
    """GN fit of ``free``; while a freed representative of a lumped group ends at a bound, hand
    its group to another member (``reselect(theta)`` -> new free list) and continue from there,
    so that the group as a whole can move as far as its members' bounds allow.

    Returns (fit, V, free list used last, simulations)."""
    free = list(free)
    n_sims = 0
    for _ in range(max_handovers + 1):
        fit, v = _fit(measurements, model, channels, constants, free, start)
        n_sims += fit.n_simulations
        stuck = set(free) & set(near_bounds(model, fit.estimate, free))
        if not stuck or reselect is None:
            break
        new = reselect(fit.estimate)
        if new == free:
            break
        free, start = new, fit.estimate.copy()
    return fit, v, free, n_sims


def profile_grid(estimate_value: float, crb_std: float, lower: float, upper: float, *, points: int,
                 sigmas: float, span: float) -> np.ndarray:
    """Grid centred on the estimate: half-width ``sigmas`` CRB σ, or ``span`` × |estimate| when
    that is narrower or σ is missing; clipped to the parameter bounds."""
    half = span * abs(estimate_value)
    if np.isfinite(crb_std) and crb_std > 0:
        half = min(half, sigmas * crb_std)
    n_side = max(1, (points - 1) // 2)
    steps = np.arange(-n_side, n_side + 1) / n_side * half
    grid = estimate_value + steps
    return grid[(grid >= lower) & (grid <= upper)]


def profile_likelihood(measurements: Sequence[Measurement], model: Model, channels: Sequence[str],
                       constants: np.ndarray, theta_hat: np.ndarray, v_min: float, name: str, grid: np.ndarray,
                       free: Sequence[str], stop_above: float = 2.0 * PROFILE_THRESHOLD,
                       reselect=None) -> Profile:
    """Fix ``name`` at each grid value and re-optimise ``free`` (GN), walking outward from the
    estimate and warm-starting from the neighbour; a side stops once ΔV exceeds ``stop_above``.
    ``reselect(theta)`` hands a lumped group to another member when its representative ends at
    a bound (see :func:`_fit_with_handover`)."""
    i = model.parameters.index(name)
    centre = theta_hat[i]
    values, objectives, n_sims = [centre], [v_min], 0
    failures: list[str] = []
    for side in (-1, 1):
        start = theta_hat.copy()
        side_free = list(free)
        points = sorted((g for g in grid if (g - centre) * side > 0), key=lambda g: abs(g - centre))
        for g in points:
            start[i] = g
            if side_free:
                try:
                    fit, v, side_free, n = _fit_with_handover(measurements, model, channels, constants, side_free,
                                                              start, reselect)
                except IdentificationError as exc:
                    failures.append(f"profile of {name} stopped at {g:.6g}: {exc}")
                    break
                n_sims += n
                start = fit.estimate.copy()
            else:
                problem = FitProblem(measurements, parameters=model.parameters, channels=channels, constants=constants)
                res = problem.residuals(start)[0]
                v = _objective(problem, start, statistics.log_det_r(statistics.covariance(res)))
                n_sims += 1
            values.append(g)
            objectives.append(v)
            if v - v_min > stop_above:
                break
    order = np.argsort(values)
    return Profile(name, float(centre), np.array(values)[order], np.array(objectives)[order], tuple(free),
                   n_sims, v_min, failures)


# --------------------------------------------------------------------------------------
# verdicts
# --------------------------------------------------------------------------------------
def classify_profile(profile: Profile, in_null_space: bool, *, max_relative_width: float,
                     threshold: float = PROFILE_THRESHOLD) -> tuple[str, str]:
    """(verdict, reason) from a profile and whether the parameter lies in the null space of F."""
    rise = max(profile.rise())
    if rise < FLAT_FRACTION * threshold:
        if in_null_space:
            return "structurally_non_identifiable", (f"flat profile (rise {rise:.2g} over the span) along an exact "
                                                     "null direction of the information matrix")
        return "practically_non_identifiable", f"profile nearly flat (rise {rise:.2g} < threshold {threshold:.2f})"
    lo, hi = profile.interval(threshold)
    if lo is None or hi is None:
        side = "both sides" if lo is None and hi is None else ("below" if lo is None else "above")
        return "practically_non_identifiable", f"95 % profile interval open {side} within the profiled span"
    width = (hi - lo) / abs(profile.estimate) if profile.estimate else np.inf
    if width > max_relative_width:
        return "practically_non_identifiable", f"95 % profile interval {width:.0%} of the estimate wide"
    return "identifiable", f"closed 95 % profile interval, {width:.2%} of the estimate wide"


def classify_information(estimate_value: float, crb_std: float, in_null_space: bool, *,
                         max_relative_width: float) -> tuple[str, str]:
    """(verdict, reason) from the information matrix alone (parameters not profiled)."""
    if in_null_space or not np.isfinite(crb_std):
        return "structurally_non_identifiable", "in the null space of the information matrix"
    width = 2 * CRB_Z * crb_std / abs(estimate_value) if estimate_value else np.inf
    if width > max_relative_width:
        return "practically_non_identifiable", f"Cramér-Rao 95 % interval {width:.0%} of the estimate wide"
    return "identifiable", f"Cramér-Rao 95 % interval {width:.2%} of the estimate wide"
