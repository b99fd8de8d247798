"""The Fisher information of a fit problem's free parameters, and what it says about them.

At a full parameter vector θ and the data of a :class:`~ema_uq.identify.FitProblem`:

- :func:`information`: F of the det R likelihood from output sensitivities by central
  differences (all 2p perturbed sets in one batched simulator call per experiment), in
  relative coordinates s = θ / max(|θ|, 0.1 |θ_nominal|), plus the rig pseudo-measurements;
  :class:`Information` gives its eigenvalues, rank, condition, null and weak directions
  (named by parameter), Cramér-Rao bounds and correlations from its rank-truncated inverse;
- Brun et al. (2001) collinearity indices γ_K = 1 / sqrt(λ_min(S̃_Kᵀ S̃_K)) of parameter
  subsets, S̃ the noise-weighted sensitivities with unit-norm columns;
- :func:`identifiable_subset`: a maximal set whose information submatrix is regular (greedy,
  most informative first);
- :func:`lumped_groups` and :func:`combinations`: the parameters coupled through null and
  weak directions and the identifiable combination of each group, named from the drive
  train's known structure (reflection of each loss to the motor shaft).

The identification reads it to hold what the data cannot determine
(:mod:`ema_uq.identify.reduction`); the identifiability analysis builds its verdicts on it
(:mod:`ema_uq.identifiability`).
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np
from scipy import special

from ..models import Model
from ..statistics import covariance
from .estimators import FD_RELATIVE_STEP
from .problem import FitProblem

#: z of the 95 % Cramér-Rao interval, 1.96: it matches the profile threshold χ²₁(0.95)/2
#: (scipy.special's inverse χ² survival function, the routine behind scipy.stats.chi2.ppf: the same
#: bits without importing scipy.stats, ~0.5 s, into every fitting verb)
CRB_Z = float(np.sqrt(special.chdtri(1, 1.0 - 0.95)))
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
GAMMA_CAP = 1e12


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
    sets simulated (those the problem's prediction memo held are not run again)."""
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
    runs = problem.predictions.runs
    predicted = problem.predict(thetas, share_steps=True)     # row 0 sets the steps of all
    r = covariance(problem.observed - predicted[0]) if noise_covariance is None else noise_covariance
    whiten = np.linalg.cholesky(np.linalg.inv(r))               # R⁻¹ = L Lᵀ
    sens = (predicted[1:p + 1] - predicted[p + 1:]) / (2.0 * h[:, None, None]) * scale[:, None, None]
    weighted = np.einsum("jkc,cd->kdj", sens, whiten).reshape(-1, p)
    pos, _, std = problem.prior_terms()
    prior = np.zeros(p)
    prior[pos] = (scale[pos] / std) ** 2
    return information_from_sensitivities(weighted, names, scale, prior, rtol), problem.predictions.runs - runs


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
# collinearity tables and bounds
# --------------------------------------------------------------------------------------
def collinearity_tables(info: Information, friction: Sequence[str], stations: Mapping[str, Sequence[str]],
                         top_triples: int = 20) -> tuple[list, list, list]:
    pairs = [{"parameters": [a, b], "index": info.collinearity([a, b])}
             for a, b in itertools.combinations(info.names, 2)]
    pairs.sort(key=lambda r: -r["index"])
    groups = [{"name": g, "parameters": list(m), "index": info.collinearity(m)} for g, m in stations.items()
              if len(m) > 1]
    triples = [{"parameters": list(t), "index": info.collinearity(t)} for t in itertools.combinations(friction, 3)]
    triples.sort(key=lambda r: -r["index"])
    return pairs, groups, triples[:top_triples]


def station_groups(names: Sequence[str]) -> dict[str, list[str]]:
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


def near_bounds(model: Model, theta: np.ndarray, names: Sequence[str], fraction: float = 0.01) -> list[str]:
    """Parameters within ``fraction`` of their nominal magnitude from a bound."""
    out = []
    for n in names:
        i = model.parameters.index(n)
        p = model.parameters.parameters[i]
        room = fraction * abs(p.nominal)
        if theta[i] - p.lower <= room or p.upper - theta[i] <= room:
            out.append(n)
    return out
