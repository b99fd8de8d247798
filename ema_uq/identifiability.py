"""Identifiability: which parameters the data of a sensor set can actually determine.

For one sensor set (a choice of measured channels) and data, around the maximum-likelihood
estimate of that set:

1. the Fisher information matrix F of the det R likelihood (output sensitivities by central
   differences, all 2p perturbed sets in one batched simulator call per experiment) in
   relative coordinates s = θ / max(|θ̂|, 0.1 |θ_nominal|): eigenvalues, rank, condition and the null directions,
   named by parameter;
2. Cramér-Rao bounds and the correlation matrix from its (rank-truncated) inverse;
3. Brun et al. (2001) collinearity indices γ_K = 1 / sqrt(λ_min(S̃_Kᵀ S̃_K)) of parameter
   subsets, S̃ the noise-weighted sensitivities with unit-norm columns;
4. profile likelihoods: each friction/damping parameter fixed on a grid (±4 CRB σ, or a
   relative span where that is narrower or the bound is missing), the others re-optimised by
   Gauss-Newton warm-started from the neighbouring point; 95 % interval where the objective
   has risen by χ²₁(0.95)/2;
5. a verdict per parameter — identifiable, practically non-identifiable (profile open on a
   side, or too wide) or structurally non-identifiable (flat profile along an exact null
   direction of F) — and, for every lumped group, the identifiable combination, named from
   the drive train's known structure (reflection of each loss to the motor shaft).

Re-optimising along an exact null direction would make Gauss-Newton singular, so the
reference fit and each profile free only a maximal identifiable subset of the other
parameters (greedy, most informative first); the rest stay at the estimate. Along an exact
null direction one free member of the group compensates any change, so the profile is the
same as with all of them free — until that member reaches a bound; then the group is handed
to another member and the fit continues, so a group can move as far as all its members'
bounds allow.
"""
from __future__ import annotations

import itertools
import math
import time as _time
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np
from scipy.stats import chi2

from . import statistics
from .experiments import Measurement
from .identify import FitProblem, IdentificationError, Settings, covariance, estimate
from .identify.estimators import FD_RELATIVE_STEP
from .models import Model, get_model

#: objective rise of the 95 % profile interval: χ²₁(0.95)/2 on V = (N/2) log det R + prior
PROFILE_THRESHOLD = float(chi2.ppf(0.95, 1) / 2.0)
CRB_Z = float(np.sqrt(chi2.ppf(0.95, 1)))   # 1.96: the Cramér-Rao interval matching the threshold
#: eigenvalues below RANK_RTOL x the largest span the null space (exact collinearity sits at
#: 1e-16 relative, the weakest real direction of either concept above 1e-8)
RANK_RTOL = 1e-10
#: Schur-complement ratio below which a parameter adds nothing to an already chosen set
SELECT_RTOL = 1e-8
#: a parameter belongs to the null space when its squared loading there exceeds this
NULL_LOADING = 1e-4
#: eigenvalues below WEAK_RTOL x the largest are weak directions: a lumped group takes in the
#: parameters that only such a direction separates from it (LT/HS: C_MG from the station
#: Coulomb losses, told apart only by the smoothing of sgn near zero speed)
WEAK_RTOL = 1e-6
#: a profile whose rise stays below this fraction of the threshold over its whole span is flat
FLAT_FRACTION = 0.1
PROFILE_SETTINGS = Settings(tolerance=1e-6, max_iterations=30, cramer_rao=False)  # only V is profiled
GAMMA_CAP = 1e12

VERDICTS = ("identifiable", "practically_non_identifiable", "structurally_non_identifiable")


class IdentifiabilityError(ValueError):
    """Bad input to the identifiability analysis (unknown sensor set or parameter, no free
    parameter, data without the channels of a sensor set)."""


# --------------------------------------------------------------------------------------
# sensor sets
# --------------------------------------------------------------------------------------
def sensor_set(model: Model, item: str | Mapping[str, Any]) -> tuple[str, tuple[str, ...]]:
    """(name, channels) of a sensor set the concept defines (``Model.sensor_sets``: ``"full"``
    = every output, ``"realistic"`` = rig sensors) or of ``{"name": ..., "channels": [...]}``."""
    if isinstance(item, Mapping):
        channels = tuple(item["channels"])
        model.output_index(channels)
        return str(item["name"]), channels
    if item in model.sensor_sets:
        return item, tuple(model.sensor_sets[item])
    if item == "full":
        return "full", tuple(model.outputs)
    if item == "realistic":
        raise IdentifiabilityError(f"no realistic sensor set is defined for concept {model.name}; give channels")
    known = ", ".join(dict.fromkeys(("full", *model.sensor_sets)))
    raise IdentifiabilityError(f"unknown sensor set {item!r}; use {known} or a name with channels")


# --------------------------------------------------------------------------------------
# information matrix
# --------------------------------------------------------------------------------------
@dataclass
class Information:
    """Fisher information of the free parameters ``names`` in relative coordinates s = θ / scale.

    ``matrix`` includes the rig pseudo-measurements, ``data_matrix`` only the data (the
    collinearity indices use it). Eigenvalues ascend; the null space is spanned by the
    eigenvectors whose eigenvalue is below ``rtol`` times the largest.
    """

    names: tuple[str, ...]
    scale: np.ndarray
    matrix: np.ndarray
    data_matrix: np.ndarray
    rtol: float = RANK_RTOL
    eigenvalues: np.ndarray = field(init=False)
    eigenvectors: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        self.matrix = 0.5 * (self.matrix + self.matrix.T)
        self.eigenvalues, self.eigenvectors = np.linalg.eigh(self.matrix)

    @property
    def kept(self) -> np.ndarray:
        return self.eigenvalues > self.rtol * self.eigenvalues[-1]

    @property
    def rank(self) -> int:
        return int(self.kept.sum())

    @property
    def condition(self) -> float:
        """λ_max / λ_min of the whole matrix (inf when singular to rounding)."""
        low = self.eigenvalues[0]
        return float(self.eigenvalues[-1] / low) if low > 0 else float("inf")

    @property
    def condition_identifiable(self) -> float:
        """λ_max / λ_min over the non-null eigenvalues."""
        ev = self.eigenvalues[self.kept]
        return float(ev[-1] / ev[0])

    @property
    def null_basis(self) -> np.ndarray:
        """(p, p - rank) orthonormal null-space basis (relative coordinates)."""
        return self.eigenvectors[:, ~self.kept]

    @property
    def null_projector(self) -> np.ndarray:
        n = self.null_basis
        return n @ n.T

    @property
    def weak_projector(self) -> np.ndarray:
        """Projector onto the null and weak directions (eigenvalue < WEAK_RTOL x largest)."""
        v = self.eigenvectors[:, self.eigenvalues < WEAK_RTOL * self.eigenvalues[-1]]
        return v @ v.T

    @property
    def null_loading(self) -> np.ndarray:
        """(p,) squared length of each coordinate axis inside the null space (0: fully determined)."""
        return np.clip(np.diag(self.null_projector), 0.0, 1.0)

    def in_null_space(self) -> np.ndarray:
        return self.null_loading > NULL_LOADING

    def pseudo_inverse(self) -> np.ndarray:
        """Rank-truncated inverse of ``matrix`` (relative coordinates)."""
        keep = self.kept
        v = self.eigenvectors[:, keep]
        return (v / self.eigenvalues[keep]) @ v.T

    def covariance(self) -> np.ndarray:
        """Cramér-Rao covariance in parameter units; NaN rows/columns for parameters in the null space."""
        cov = self.pseudo_inverse() * np.outer(self.scale, self.scale)
        bad = self.in_null_space()
        cov[bad, :] = np.nan
        cov[:, bad] = np.nan
        return cov

    def std(self) -> np.ndarray:
        return np.sqrt(np.diag(self.covariance()))

    def correlation(self) -> np.ndarray:
        cov = self.covariance()
        sd = np.sqrt(np.diag(cov))
        with np.errstate(invalid="ignore", divide="ignore"):
            return cov / np.outer(sd, sd)

    def combination_std(self, coefficients: np.ndarray) -> float:
        """Cramér-Rao σ of Σ a_j θ_j (``coefficients`` in parameter units, (p,)); valid for a
        combination orthogonal to the null space (an estimable one)."""
        a = np.asarray(coefficients, dtype=float) * self.scale
        return float(np.sqrt(max(a @ self.pseudo_inverse() @ a, 0.0)))

    def null_directions(self, select: Sequence[str] | None = None, cutoff: float = 1e-3) -> list[dict[str, float]]:
        """The null space as named unit directions (relative changes Δθ/θ̂).

        With ``select`` (the parameters kept free, one per lumped group) every direction moves
        exactly one other parameter and compensates with the selected ones — "raise B_TS1 by
        x %, lower B_TS2 by y %"; otherwise the raw eigenvectors.
        """
        basis = self.null_basis
        d = basis.shape[1]
        if d == 0:
            return []
        pivots = [i for i, n in enumerate(self.names) if select is not None and n not in select
                  and self.null_loading[i] > NULL_LOADING]
        if len(pivots) == d:
            sub = basis[pivots, :]
            if np.linalg.cond(sub) < 1e8:
                basis = basis @ np.linalg.inv(sub)
                basis[pivots, :] = np.eye(d)
        out = []
        for k in range(d):
            v = basis[:, k] / np.linalg.norm(basis[:, k])
            v = v * np.sign(v[np.argmax(np.abs(v))])
            out.append({self.names[j]: round(float(v[j]), 4) for j in np.argsort(-np.abs(v)) if abs(v[j]) > cutoff})
        return out

    def collinearity(self, subset: Sequence[str]) -> float:
        """Brun collinearity index γ_K of a parameter subset (data information only)."""
        idx = [self.names.index(n) for n in subset]
        return collinearity_index(self.data_matrix, idx)


def collinearity_index(information: np.ndarray, subset: Sequence[int]) -> float:
    """γ_K = 1/sqrt(λ_min) of the unit-diagonal normalisation of the information submatrix
    (= S̃_Kᵀ S̃_K for unit-norm weighted sensitivity columns); 1 for orthogonal columns,
    → ∞ for linearly dependent ones (capped at 1e12). A parameter without any effect gives the cap."""
    m = np.asarray(information, dtype=float)[np.ix_(subset, subset)]
    d = np.diag(m)
    if np.any(d <= 0):
        return GAMMA_CAP
    norm = m / np.sqrt(np.outer(d, d))
    lam = float(np.linalg.eigvalsh(0.5 * (norm + norm.T))[0])
    return float(min(1.0 / math.sqrt(lam), GAMMA_CAP)) if lam > 0 else GAMMA_CAP


def information_from_sensitivities(weighted: np.ndarray, names: Sequence[str], scale: np.ndarray | None = None,
                                   prior: np.ndarray | None = None, rtol: float = RANK_RTOL) -> Information:
    """Information of noise-whitened sensitivities ``weighted`` (n_rows, p) in relative
    coordinates (columns are dy/ds), plus an optional diagonal ``prior`` information (p,)."""
    weighted = np.asarray(weighted, dtype=float)
    data = weighted.T @ weighted
    full = data + (np.diag(prior) if prior is not None else 0.0)
    scale = np.ones(len(names)) if scale is None else np.asarray(scale, float)
    return Information(tuple(names), scale, full, data, rtol)


def information(problem: FitProblem, theta: np.ndarray, *, rtol: float = RANK_RTOL,
                noise_covariance: np.ndarray | None = None) -> tuple[Information, int]:
    """Fisher information of ``problem``'s free parameters at the full vector ``theta``
    (R estimated from the residuals there, or ``noise_covariance`` (n_channels, n_channels)
    when given: the expected information before any fit); returns it and the number of
    simulated sets."""
    theta = np.asarray(theta, dtype=float)
    idx = problem.free_index
    names = problem.parameters.free_names
    free = theta[idx]
    # a value near zero keeps a step of its nominal magnitude: a step of the value itself would
    # drown the sensitivity in rounding and make an exact collinearity look resolvable
    scale = np.maximum(np.abs(free), 0.1 * np.abs(problem.parameters.nominal[idx]))
    scale = np.where(scale > 0, scale, 1.0)
    p = idx.size
    h = FD_RELATIVE_STEP * scale
    steps = np.concatenate([np.diag(h), -np.diag(h)])
    thetas = problem.full_vectors(np.vstack([free, free + steps]), theta)
    predicted = problem.predict(thetas, share_steps=True)     # row 0 sets the steps of all
    r = covariance(problem.observed - predicted[0]) if noise_covariance is None else noise_covariance
    whiten = np.linalg.cholesky(np.linalg.inv(r))               # R⁻¹ = L Lᵀ
    sens = (predicted[1:p + 1] - predicted[p + 1:]) / (2.0 * h[:, None, None]) * scale[:, None, None]
    weighted = np.einsum("jkc,cd->kdj", sens, whiten).reshape(-1, p)
    pos, _, std = problem.prior_terms()
    prior = np.zeros(p)
    prior[pos] = (scale[pos] / std) ** 2
    return information_from_sensitivities(weighted, names, scale, prior, rtol), thetas.shape[0]


def identifiable_subset(info: Information, exclude: Sequence[str] = (), rtol: float = SELECT_RTOL,
                        avoid: Sequence[str] = ()) -> list[str]:
    """A maximal set of parameters whose information submatrix is regular: greedy, most
    informative (largest diagonal) first; a candidate joins when the part of its information
    not explained by those already chosen (Schur complement) exceeds ``rtol`` of its own.

    Parameters in ``avoid`` (e.g. sitting at a bound, where they cannot compensate in both
    directions) are considered last, so another member represents their group when one can.
    """
    m = info.matrix
    chosen: list[int] = []
    diag = np.diag(m)
    order = sorted(range(len(info.names)), key=lambda j: (info.names[j] in avoid, -diag[j]))
    for j in order:
        if info.names[j] in exclude or m[j, j] <= 0:
            continue
        if chosen:
            k = np.array(chosen)
            rest = m[j, j] - m[j, k] @ np.linalg.solve(m[np.ix_(k, k)], m[k, j])
            if rest <= rtol * m[j, j]:
                continue
        chosen.append(int(j))
    return [info.names[j] for j in sorted(chosen)]


def combination_expression(names: Sequence[str], coefficients: Sequence[float], model: Model,
                           constants: np.ndarray | None = None, digits: int = 6) -> str:
    """Readable ``Σ a_j θ_j``, e.g. ``B_TS1/cos(beta1) + B_U1 + 2*B_TP1``: a screw loss keeps
    the 1/cos β of its U-joint (eq. 10) as a symbol."""
    c = dict(zip(model.constants.names, model.constants_vector() if constants is None else constants))
    terms = []
    for name, a in zip(names, coefficients):
        a = float(a)
        if a == 0.0:
            continue
        symbol, beta = name, f"beta{name[-1]}"
        if name[2:4] == "TS" and beta in c:
            a *= math.cos(c[beta])
            symbol = f"{name}/cos({beta})"
        terms.append(symbol if abs(a - 1.0) < 10.0 ** (-digits) else f"{a:.{digits}g}*{symbol}")
    return " + ".join(terms).replace("+ -", "- ")


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
        stuck = set(free) & set(_near_bounds(model, fit.estimate, free))
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
                v = _objective(problem, start, statistics.log_det(statistics.covariance(res)))
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


# --------------------------------------------------------------------------------------
# lumped groups and identifiable combinations
# --------------------------------------------------------------------------------------
def lumped_groups(info: Information, tol: float = 1e-3) -> list[list[str]]:
    """Parameters coupled through the null and weak directions (connected by |P[i, j]| > tol),
    e.g. every station's B in one group and every C in another; singletons are left out."""
    proj = info.weak_projector
    members = [i for i in range(len(info.names)) if proj[i, i] > NULL_LOADING]
    parent = {i: i for i in members}

    def root(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for a, b in itertools.combinations(members, 2):
        if abs(proj[a, b]) > tol:
            parent[root(a)] = root(b)
    groups: dict[int, list[int]] = {}
    for i in members:
        groups.setdefault(root(i), []).append(i)
    return [[info.names[i] for i in sorted(g)] for g in groups.values() if len(g) > 1]


def combinations(info: Information, theta_hat: Mapping[str, float], model: Model,
                 constants: np.ndarray | None = None, agreement: float = 0.02) -> list[dict[str, Any]]:
    """The identifiable combination(s) of each lumped group.

    Data side: the directions of the group's coordinate space orthogonal to its null and weak
    directions (``weak`` in the entry says whether a weak, not exactly null, direction joined
    the group: then the members are lumped in practice rather than by structure).
    Structure side: the motor-shaft factors ``model.loss_factors``. When the group has
    one combination and both agree within ``agreement`` (relative), the structural expression
    is reported; a group with several combinations (a weak direction joined the viscous and
    the Coulomb losses) reports the structural sum of each kind when each lies in the data's
    directions within ``agreement``; otherwise the data-derived coefficients. ``std`` is its
    Cramér-Rao σ.
    """
    factors = model.loss_factors(constants)
    proj = info.weak_projector
    exact = info.null_projector
    out = []
    for group in lumped_groups(info):
        idx = [info.names.index(n) for n in group]
        q = np.eye(len(idx)) - proj[np.ix_(idx, idx)]
        w, v = np.linalg.eigh(0.5 * (q + q.T))
        directions = v[:, w > 0.5]
        weak = float(np.trace(proj[np.ix_(idx, idx)]) - np.trace(exact[np.ix_(idx, idx)])) > 0.5
        structural = np.array([factors.get(n, np.nan) for n in group])
        parts = _structural_kinds(group, info.scale[idx], directions, structural, agreement)
        if parts is not None:
            for members, deviation in parts:
                sub = [n for n, m in zip(group, members) if m]
                out.append(_structural_entry(info, sub, structural[members], theta_hat, model, constants,
                                             {"parameters": list(sub), "weak": weak,
                                              "structural_deviation": deviation}))
            continue
        for k in range(directions.shape[1]):
            coef = directions[:, k] / info.scale[idx]          # relative -> parameter units
            entry: dict[str, Any] = {"parameters": list(group), "weak": weak}
            use_structure = directions.shape[1] == 1 and np.all(np.isfinite(structural))
            if use_structure:
                ref = _reference_member(group, structural)
                f_norm = structural / structural[ref]
                alpha = float(coef @ f_norm / (f_norm @ f_norm))
                deviation = float(np.max(np.abs(coef / alpha - f_norm)) / np.max(np.abs(f_norm)))
                entry["structural_deviation"] = deviation
                use_structure = deviation < agreement
            if use_structure:
                out.append(_structural_entry(info, group, structural, theta_hat, model, constants, entry))
                continue
            a = coef / coef[int(np.argmax(np.abs(coef)))]
            entry.update(expression=" + ".join(f"{x:.4g}*{n}" for n, x in zip(group, a)).replace("+ -", "- "),
                         structural=False)
            out.append(_with_value(info, group, a, theta_hat, entry))
    return out


def _reference_member(group: Sequence[str], structural: np.ndarray) -> int:
    """The member whose factor scales a structural combination to 1 (the U-joint of station 1)."""
    return next((j for j, n in enumerate(group) if n[2:] in ("U1",)), int(np.argmin(np.abs(structural))))


def _structural_kinds(group: Sequence[str], scale: np.ndarray, directions: np.ndarray, structural: np.ndarray,
                      agreement: float) -> list[tuple[np.ndarray, float]] | None:
    """(members mask, deviation) of the viscous and the Coulomb sums of a group with several
    identifiable directions, when each sum (coefficients in relative coordinates) lies in their
    span within ``agreement``; None otherwise."""
    if directions.shape[1] < 2 or not np.all(np.isfinite(structural)):
        return None
    kinds = [np.array([n.startswith(kind) for n in group]) for kind in ("B_", "C_")]
    kinds = [m for m in kinds if m.any()]
    if len(kinds) != directions.shape[1] or not np.all(np.logical_or.reduce(kinds)):
        return None
    parts = []
    for members in kinds:
        c = np.where(members, structural * scale, 0.0)
        deviation = float(np.linalg.norm(c - directions @ (directions.T @ c)) / np.linalg.norm(c))
        if deviation >= agreement:
            return None
        parts.append((members, deviation))
    return parts


def _structural_entry(info: Information, group: Sequence[str], structural: np.ndarray, theta_hat, model, constants,
                      entry: dict[str, Any]) -> dict[str, Any]:
    ref = _reference_member(group, structural)
    a = structural / structural[ref]
    entry.update(expression=combination_expression(group, a, model, constants), structural=True,
                 motor_shaft_factor=float(structural[ref]),
                 meaning="equivalent loss at the reference member's shaft; x motor_shaft_factor "
                         "gives it at the motor shaft")
    return _with_value(info, group, a, theta_hat, entry)


def _with_value(info: Information, group: Sequence[str], a: np.ndarray, theta_hat, entry: dict[str, Any]):
    """``entry`` with the coefficients, value and Cramér-Rao σ of Σ a_j θ_j over ``group``."""
    full = np.zeros(len(info.names))
    full[[info.names.index(n) for n in group]] = a
    value = float(sum(a[j] * theta_hat[n] for j, n in enumerate(group)))
    std = info.combination_std(full)
    entry.update(coefficients={n: float(x) for n, x in zip(group, a)}, value=value, std=std,
                 relative_std=std / abs(value) if value else float("nan"))
    return entry


# --------------------------------------------------------------------------------------
# one sensor set, and the sensor-set study
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class ProfileSettings:
    """Budgets of the profiles (study section ``identifiability``)."""

    points: int = 9
    sigmas: float = 4.0
    span: float = 0.5
    max_relative_width: float = 1.0
    collinearity_threshold: float = 20.0

    @classmethod
    def from_section(cls, section: Mapping[str, Any]) -> "ProfileSettings":
        return cls(points=int(section["profile_points"]), sigmas=float(section["profile_sigmas"]),
                   span=float(section["profile_span"]), max_relative_width=float(section["max_relative_width"]),
                   collinearity_threshold=float(section["collinearity_threshold"]))


@dataclass
class SensorSetResult:
    """Identifiability of the free parameters with the channels of one sensor set."""

    name: str
    concept: str
    channels: tuple[str, ...]
    names: tuple[str, ...]
    estimate: np.ndarray                 # (p,) free parameters at the reference fit
    objective: float                     # V at the reference fit
    info: Information
    selected: tuple[str, ...]            # the maximal identifiable subset freed in the reference fit
    profiles: dict[str, Profile]
    verdicts: dict[str, tuple[str, str, str]]   # name -> (verdict, method, reason)
    collinearity_pairs: list[dict[str, Any]]
    collinearity_groups: list[dict[str, Any]]
    collinearity_triples: list[dict[str, Any]]
    combinations: list[dict[str, Any]]
    settings: ProfileSettings
    n_simulations: int
    wall_time_s: float
    warnings: list[str] = field(default_factory=list)

    def verdict(self, name: str) -> str:
        return self.verdicts[name][0]

    def max_pair_collinearity(self, name: str) -> tuple[float, str | None]:
        best, other = 1.0, None
        for row in self.collinearity_pairs:
            if name in row["parameters"] and row["index"] > best:
                best = row["index"]
                other = next(p for p in row["parameters"] if p != name)
        return best, other

    def profile_ci(self, name: str) -> tuple[float | None, float | None] | None:
        return self.profiles[name].interval() if name in self.profiles else None

    def crb_ratio(self, name: str) -> tuple[float | None, float | None]:
        """Profile half-widths below/above over the Cramér-Rao half-width 1.96 σ (1 = agreement)."""
        if name not in self.profiles:
            return None, None
        j = self.names.index(name)
        sd = self.info.std()[j]
        lo, hi = self.profiles[name].interval()
        if not np.isfinite(sd) or sd <= 0:
            return None, None
        est = self.estimate[j]
        return (None if lo is None else (est - lo) / (CRB_Z * sd), None if hi is None else (hi - est) / (CRB_Z * sd))

    def parameter_table(self) -> dict[str, dict[str, Any]]:
        std = self.info.std()
        loading = self.info.null_loading
        out = {}
        for j, n in enumerate(self.names):
            verdict, method, reason = self.verdicts[n]
            gamma, partner = self.max_pair_collinearity(n)
            row = {"verdict": verdict, "method": method, "reason": reason, "estimate": float(self.estimate[j]),
                   "crb_std": float(std[j]),
                   "crb_ci": [float(self.estimate[j] - CRB_Z * std[j]), float(self.estimate[j] + CRB_Z * std[j])],
                   "profile_ci": None, "collinearity": gamma, "most_collinear_with": partner,
                   "null_loading": float(loading[j])}
            if n in self.profiles:
                prof = self.profiles[n]
                lo, hi = prof.interval()
                ratio = self.crb_ratio(n)
                row.update(profile_ci=[lo, hi], profile_vs_crb=list(ratio),
                           profile={"grid": prof.grid.tolist(), "delta_objective": prof.delta.tolist(),
                                    "free": list(prof.free), "n_simulations": prof.n_simulations})
            out[n] = row
        return out

    def to_json(self) -> dict[str, Any]:
        info = self.info
        return {
            "name": self.name, "channels": list(self.channels),
            "fim": {"rank": info.rank, "n_parameters": len(self.names), "condition": info.condition,
                    "condition_identifiable": info.condition_identifiable,
                    "eigenvalues_relative": (info.eigenvalues / info.eigenvalues[-1]).tolist(),
                    "null_directions": info.null_directions(self.selected),
                    "coordinates": "relative changes (delta theta / estimate)"},
            "parameters": self.parameter_table(),
            "correlation": {"names": list(self.names), "matrix": info.correlation().tolist()},
            "collinearity": {"threshold": self.settings.collinearity_threshold, "pairs": self.collinearity_pairs,
                             "groups": self.collinearity_groups, "triples": self.collinearity_triples},
            "combinations": self.combinations,
            "reference_fit": {"objective": self.objective, "free": list(self.selected)},
            "profile_threshold": PROFILE_THRESHOLD,
            "n_simulations": self.n_simulations, "wall_time_s": self.wall_time_s, "warnings": self.warnings,
        }

    def summary(self) -> str:
        info = self.info
        lines = [f"[[Sensor set {self.name}: {', '.join(self.channels)}]]",
                 f"    information rank  = {info.rank} of {len(self.names)} (condition {info.condition:.3g}; "
                 f"identifiable part {info.condition_identifiable:.3g})",
                 f"    simulations, time = {self.n_simulations}, {self.wall_time_s:.1f} s"]
        table = self.parameter_table()
        for n, row in table.items():
            ci = row["profile_ci"]
            ci_text = ("[" + ", ".join("open" if x is None else f"{x:.4g}" for x in ci) + "]") if ci else "-"
            lines.append(f"    {n:<8} {row['verdict']:<31} est {row['estimate']:<11.5g} CRB σ {row['crb_std']:<10.3g} "
                         f"profile {ci_text:<22} γ_max {row['collinearity']:.3g}")
        for c in self.combinations:
            lines.append(f"    identifiable combination: {c['expression']} = {c['value']:.5g} +/- {c['std']:.2g}")
        for w in self.warnings:
            lines.append(f"    warning: {w}")
        return "\n".join(lines)


def _collinearity_tables(info: Information, friction: Sequence[str], stations: Mapping[str, Sequence[str]],
                         top_triples: int = 20) -> tuple[list, list, list]:
    pairs = [{"parameters": [a, b], "index": info.collinearity([a, b])}
             for a, b in itertools.combinations(info.names, 2)]
    pairs.sort(key=lambda r: -r["index"])
    groups = [{"name": g, "parameters": list(m), "index": info.collinearity(m)} for g, m in stations.items()
              if len(m) > 1]
    triples = [{"parameters": list(t), "index": info.collinearity(t)} for t in itertools.combinations(friction, 3)]
    triples.sort(key=lambda r: -r["index"])
    return pairs, groups, triples[:top_triples]


def _station_groups(names: Sequence[str]) -> dict[str, list[str]]:
    """Each station's (and the magnetic gear's) losses, all viscous and all Coulomb losses."""
    friction = [n for n in names if n.startswith(("B_", "C_"))]
    groups: dict[str, list[str]] = {}
    for n in friction:
        tail = n[2:]
        key = f"station {tail[-1]}" if tail[-1].isdigit() else tail
        groups.setdefault(key, []).append(n)
    groups["all B"] = [n for n in friction if n.startswith("B_")]
    groups["all C"] = [n for n in friction if n.startswith("C_")]
    return groups


def _near_bounds(model: Model, theta: np.ndarray, names: Sequence[str], fraction: float = 0.01) -> list[str]:
    """Parameters within ``fraction`` of their nominal magnitude from a bound."""
    out = []
    for n in names:
        i = model.parameters.index(n)
        p = model.parameters.parameters[i]
        room = fraction * abs(p.nominal)
        if theta[i] - p.lower <= room or p.upper - theta[i] <= room:
            out.append(n)
    return out


def assess_sensor_set(measurements: Sequence[Measurement], start: np.ndarray, free: Sequence[str],
                      channels: Sequence[str], *, name: str = "custom", settings: ProfileSettings = ProfileSettings(),
                      profile_names: Sequence[str] | None = None, constants: np.ndarray | None = None,
                      progress=None) -> SensorSetResult:
    """Identifiability of ``free`` parameters from ``channels`` of ``measurements``.

    ``start`` is a full parameter vector (e.g. an ML estimate from all channels); the
    reference fit re-estimates the identifiable subset with these channels from there.
    ``profile_names`` default: every free B_*/C_*; the other free parameters are judged from
    the information matrix.
    """
    t0 = _time.perf_counter()
    measurements = list(measurements)
    model = get_model(measurements[0].concept)
    constants = model.constants_vector() if constants is None else np.asarray(constants, dtype=float)
    free = [n for n in model.parameters.names if n in set(free)]
    if not free:
        raise IdentifiabilityError("no free parameter to assess; free at least one")
    unknown = [n for n in (profile_names or []) if n not in free]
    if unknown:
        raise IdentifiabilityError(f"cannot profile {', '.join(unknown)}: not free in the fit; free parameters: "
                                   f"{', '.join(free)}")
    missing = [c for c in channels if any(c not in m.channels for m in measurements)]
    if missing:
        raise IdentifiabilityError(f"sensor set {name}: channel(s) {', '.join(missing)} missing from the data; "
                                   "simulate data with every channel or choose another set")
    if profile_names is None:
        profile_names = [n for n in free if n.startswith(("B_", "C_"))]
    channels = tuple(channels)
    problem = FitProblem(measurements, parameters=model.parameters.freeing_only(free), channels=channels,
                         constants=constants)
    start = np.clip(np.asarray(start, dtype=float), model.parameters.lower, model.parameters.upper)
    info, n_sims = information(problem, start)
    selected = identifiable_subset(info, avoid=_near_bounds(model, start, free))
    say = progress or (lambda _msg: None)
    say(f"{name}: reference fit of {len(selected)} identifiable parameters ({len(free) - len(selected)} lumped)")
    try:
        fit, v_min, _, n = _fit_with_handover(
            measurements, model, channels, constants, selected, start,
            lambda theta: identifiable_subset(info, avoid=_near_bounds(model, theta, free)))
    except IdentificationError as exc:
        raise IdentifiabilityError(f"sensor set {name}: reference fit failed: {exc}") from None
    n_sims += n
    theta_hat = fit.estimate.copy()
    info, n = information(problem, theta_hat)
    n_sims += n
    at_bounds = _near_bounds(model, theta_hat, free)
    selected = identifiable_subset(info, avoid=at_bounds)
    std = info.std()
    in_null = info.in_null_space()
    warnings = [] if fit.converged else [f"reference fit not converged: {fit.message}"]
    if at_bounds:
        warnings.append(f"reference estimate at or near a bound for {', '.join(at_bounds)}: the data push the "
                        "weakly determined direction they belong to towards the edge of the admissible range")

    profiles: dict[str, Profile] = {}
    for pname in profile_names:
        j = info.names.index(pname)
        i = model.parameters.index(pname)
        grid = profile_grid(theta_hat[i], std[j], model.parameters.lower[i], model.parameters.upper[i],
                            points=settings.points, sigmas=settings.sigmas, span=settings.span)
        others = identifiable_subset(info, exclude=[pname], avoid=at_bounds)
        say(f"{name}: profile {pname} on {grid.size} points, re-optimising {len(others)} parameters")
        prof = profile_likelihood(
            measurements, model, channels, constants, theta_hat, v_min, pname, grid, others,
            reselect=lambda theta, pname=pname: identifiable_subset(info, exclude=[pname],
                                                                    avoid=_near_bounds(model, theta, free)))
        profiles[pname] = prof
        n_sims += prof.n_simulations
        warnings += prof.failures
    # a profile point below the reference minimum means the reference fit stopped short
    lowest = min([v_min] + [float(p.objective.min()) for p in profiles.values()])
    if lowest < v_min - 0.05 * PROFILE_THRESHOLD:
        warnings.append(f"a profile found an objective {v_min - lowest:.3g} below the reference fit; "
                        "intervals are measured from the lower value")
    for p in profiles.values():
        p.v_min = min(lowest, v_min)

    verdicts = {}
    for j, pname in enumerate(info.names):
        if pname in profiles:
            v, reason = classify_profile(profiles[pname], bool(in_null[j]),
                                         max_relative_width=settings.max_relative_width)
            verdicts[pname] = (v, "profile", reason)
        else:
            v, reason = classify_information(theta_hat[model.parameters.index(pname)], std[j], bool(in_null[j]),
                                             max_relative_width=settings.max_relative_width)
            verdicts[pname] = (v, "fim", reason)
    friction = [n for n in info.names if n.startswith(("B_", "C_"))]
    pairs, groups, triples = _collinearity_tables(info, friction, _station_groups(info.names))
    combos = combinations(info, {n: theta_hat[model.parameters.index(n)] for n in info.names}, model, constants)
    estimate_free = theta_hat[[model.parameters.index(n) for n in info.names]]
    return SensorSetResult(
        name=name, concept=model.name, channels=channels, names=info.names, estimate=estimate_free,
        objective=v_min, info=info, selected=tuple(selected), profiles=profiles, verdicts=verdicts,
        collinearity_pairs=pairs, collinearity_groups=groups, collinearity_triples=triples, combinations=combos,
        settings=settings, n_simulations=n_sims, wall_time_s=_time.perf_counter() - t0, warnings=warnings,
    )


@dataclass
class IdentifiabilityResult:
    """The sensor-set study: one :class:`SensorSetResult` per set; the first is the primary
    one whose fields fill the top level of IDENT.json (docs/INTERFACES.md)."""

    concept: str
    sets: dict[str, SensorSetResult]
    data: list[str] = field(default_factory=list)
    provenance: dict[str, Any] = field(default_factory=dict)
    #: None: assessed around a fit; else the point assessed without one ("nominal" or a file)
    at: str | None = None
    #: sensor sets asked for but not assessed -> why (their channels are not all in the data)
    skipped: dict[str, str] = field(default_factory=dict)

    @property
    def primary(self) -> SensorSetResult:
        return next(iter(self.sets.values()))

    def comparison(self) -> dict[str, dict[str, str]]:
        """parameter -> {sensor set: verdict}."""
        names = self.primary.names
        return {n: {s: r.verdict(n) for s, r in self.sets.items() if n in r.verdicts} for n in names}

    def summary(self) -> str:
        lines = [f"[[Identifiability: {self.concept}, sensor sets {', '.join(self.sets)}]]"]
        lines += [f"    sensor set {name} skipped: {why}" for name, why in self.skipped.items()]
        for r in self.sets.values():
            lines.append(r.summary())
        lines.append("[[Verdicts per sensor set]]")
        short = {"identifiable": "identifiable", "practically_non_identifiable": "practically NI",
                 "structurally_non_identifiable": "structurally NI"}
        lines.append("    " + f"{'':<8} " + " ".join(f"{s:<16}" for s in self.sets))
        for n, row in self.comparison().items():
            lines.append("    " + f"{n:<8} " + " ".join(f"{short[row.get(s, '')] if s in row else '-':<16}"
                                                        for s in self.sets))
        return "\n".join(lines)

    def to_json(self) -> dict[str, Any]:
        sets = {name: r.to_json() for name, r in self.sets.items()}
        primary = sets[self.primary.name]
        return {
            "concept": self.concept,
            "sensor_set": self.primary.name,
            "channels": primary["channels"],
            "fim": primary["fim"],
            "parameters": primary["parameters"],
            "combinations": primary["combinations"],
            "correlation": primary["correlation"],
            "collinearity": primary["collinearity"],
            "sensor_sets": sets,
            "skipped_sensor_sets": dict(self.skipped),
            "comparison": self.comparison(),
            "profile_threshold": PROFILE_THRESHOLD,
            "n_simulations": int(sum(r.n_simulations for r in self.sets.values())),
            "wall_time_s": float(sum(r.wall_time_s for r in self.sets.values())),
            "data": list(self.data),
            "at": self.at,
            "provenance": self.provenance,
        }


def sensor_set_study(measurements: Sequence[Measurement], start: np.ndarray, free: Sequence[str],
                     sets: Sequence[str | Mapping[str, Any]] = ("full", "realistic"), *,
                     settings: ProfileSettings = ProfileSettings(), profile_names: Sequence[str] | None = None,
                     constants: np.ndarray | None = None, progress=None) -> IdentifiabilityResult:
    """:func:`assess_sensor_set` for each sensor set, from the same start and data.

    A set whose channels are not all in every record is skipped, with the reason in
    ``IdentifiabilityResult.skipped`` (rig data has only the rig's channels, so the default
    "full" set cannot be assessed on it); when no set is left that is an error naming the
    channels the data has."""
    measurements = list(measurements)
    if not measurements:
        raise IdentifiabilityError("no measurement given; pass the estimation (and validation) data")
    model = get_model(measurements[0].concept)
    present = [c for c in model.outputs if all(c in m.channels for m in measurements)]
    results, skipped = {}, {}
    for item in sets:
        name, channels = sensor_set(model, item)
        if name in results or name in skipped:
            raise IdentifiabilityError(f"sensor set {name} given twice; name each set once")
        missing = [c for c in channels if c not in present]
        if missing:
            skipped[name] = f"channel(s) {', '.join(missing)} not in the data"
            continue
        results[name] = assess_sensor_set(measurements, start, free, channels, name=name, settings=settings,
                                          profile_names=profile_names, constants=constants, progress=progress)
    if not results:
        raise IdentifiabilityError(
            "no sensor set can be assessed on this data (" + "; ".join(f"{k}: {v}" for k, v in skipped.items())
            + f"); the data has {', '.join(present) or 'no output channel'}: give --channels with a subset of them")
    if skipped and progress is not None:
        progress("skipped " + "; ".join(f"sensor set {k}: {v}" for k, v in skipped.items()))
    return IdentifiabilityResult(model.name, results, skipped=skipped)


# --------------------------------------------------------------------------------------
# before any fit: the expected information at a point
# --------------------------------------------------------------------------------------
def expected_records(model: Model, experiments: Sequence, theta: np.ndarray,
                     constants: np.ndarray | None = None) -> list[Measurement]:
    """Noise-free records of every output of ``model`` at the full vector ``theta`` on each
    experiment: what the data would be if ``theta`` were the truth."""
    from .experiments import synthesize

    return [synthesize(model, e, theta, noise=0.0, seed=None, constants=constants) for e in experiments]


def assess_at_point(records: Sequence[Measurement], theta: np.ndarray, free: Sequence[str],
                    channels: Sequence[str], *, noise: float, name: str = "custom",
                    settings: ProfileSettings = ProfileSettings(), constants: np.ndarray | None = None
                    ) -> SensorSetResult:
    """Identifiability of ``free`` from ``channels`` at ``theta`` without a fit, to choose sensors.

    ``records`` are the noise-free outputs at ``theta`` (:func:`expected_records`); R is the
    noise the rig would add, diag((``noise`` x each channel's RMS over the records)²), so the
    information matrix is the expected one. Profiles are skipped: they measure the rise of
    the likelihood from its minimum on measured data, which a point without data has not;
    every verdict comes from the information matrix (:func:`classify_information`).
    """
    from .experiments import noise_std

    t0 = _time.perf_counter()
    model = get_model(records[0].concept)
    constants = model.constants_vector() if constants is None else np.asarray(constants, dtype=float)
    free = [n for n in model.parameters.names if n in set(free)]
    if not free:
        raise IdentifiabilityError("no free parameter to assess; free at least one")
    channels = tuple(channels)
    problem = FitProblem(records, parameters=model.parameters.freeing_only(free), channels=channels,
                         constants=constants)
    sigma = noise_std(problem.observed, noise)
    if not np.all(sigma > 0):
        raise IdentifiabilityError(f"sensor set {name}: a channel is identically zero at this point, or the noise "
                                   "level is 0; give a noise fraction > 0 (e.g. --noise 0.02)")
    theta = np.asarray(theta, dtype=float)
    info, n_sims = information(problem, theta, noise_covariance=np.diag(sigma ** 2))
    std, in_null = info.std(), info.in_null_space()
    values = theta[[model.parameters.index(n) for n in info.names]]
    verdicts = {}
    for j, pname in enumerate(info.names):
        v, reason = classify_information(values[j], std[j], bool(in_null[j]),
                                         max_relative_width=settings.max_relative_width)
        verdicts[pname] = (v, "fim", reason)
    friction = [n for n in info.names if n.startswith(("B_", "C_"))]
    pairs, groups, triples = _collinearity_tables(info, friction, _station_groups(info.names))
    combos = combinations(info, dict(zip(info.names, values)), model, constants)
    return SensorSetResult(
        name=name, concept=model.name, channels=channels, names=info.names, estimate=values,
        objective=float("nan"), info=info, selected=tuple(identifiable_subset(info)), profiles={}, verdicts=verdicts,
        collinearity_pairs=pairs, collinearity_groups=groups, collinearity_triples=triples, combinations=combos,
        settings=settings, n_simulations=n_sims, wall_time_s=_time.perf_counter() - t0,
        warnings=[f"no fit: expected information at the given point with noise {noise:g} x each channel's RMS; "
                  "profiles skipped (they need the likelihood minimum of measured data), verdicts from the "
                  "information matrix"],
    )


def sensor_set_study_at(model: Model, experiments: Sequence, theta: np.ndarray, free: Sequence[str],
                        sets: Sequence[str | Mapping[str, Any]] = ("full", "realistic"), *, noise: float,
                        settings: ProfileSettings = ProfileSettings(),
                        constants: np.ndarray | None = None) -> IdentifiabilityResult:
    """:func:`assess_at_point` for each sensor set on the noise-free records of ``experiments``
    at ``theta``: the sensor-set study before any fit."""
    if not experiments:
        raise IdentifiabilityError("no experiment given; pass data files or an experiment name")
    records = expected_records(model, experiments, theta, constants)
    results = {}
    for item in sets:
        name, channels = sensor_set(model, item)
        if name in results:
            raise IdentifiabilityError(f"sensor set {name} given twice; name each set once")
        results[name] = assess_at_point(records, theta, free, channels, noise=noise, name=name, settings=settings,
                                        constants=constants)
    return IdentifiabilityResult(model.name, results)
