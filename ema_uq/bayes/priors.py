"""Priors π_j of the free parameters, each restricted to the parameter's bounds.

Default per free parameter: flat on the parameter's bounds (improper when a bound is
infinite), or the rig pseudo-measurement N(rig, σ_rig) for parameters with ``prior_std``
(p_ACE, p_PCE). A user choice ``lognormal:mu,sigma`` (of ln Θ) / ``uniform:lo,hi`` /
``normal:mean,sd`` replaces it; every prior is restricted to the parameter's bounds.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping

import numpy as np

from ..identify.problem import FitProblem
from .errors import BayesError

LOG_2PI = math.log(2.0 * math.pi)


@dataclass(frozen=True)
class Prior:
    """Prior of one free parameter, restricted to ``[lower, upper]``.

    ``kind``: ``"flat"`` (constant density on the bounds; a, b unused), ``"uniform"``
    (on [a, b]), ``"normal"`` (mean a, sd b), ``"lognormal"`` (ln Θ ~ N(a, b)). Values in
    the parameter's units. ``lower``/``upper`` are the effective support (bounds ∩ prior).
    """

    kind: str
    a: float = 0.0
    b: float = 0.0
    lower: float = -np.inf
    upper: float = np.inf

    def logpdf(self, x: np.ndarray) -> np.ndarray:
        """Log density (n,) of values (n,); -inf outside the support. Normalised except for
        the truncation to the bounds (a constant)."""
        x = np.asarray(x, dtype=float)
        inside = (x >= self.lower) & (x <= self.upper)
        if self.kind == "flat":
            width = self.upper - self.lower
            val = np.full_like(x, -math.log(width) if np.isfinite(width) else 0.0)
        elif self.kind == "uniform":
            val = np.full_like(x, -math.log(self.b - self.a))
        elif self.kind == "normal":
            val = -0.5 * ((x - self.a) / self.b) ** 2 - math.log(self.b) - 0.5 * LOG_2PI
        elif self.kind == "lognormal":
            with np.errstate(divide="ignore", invalid="ignore"):
                lx = np.log(x)
                val = -0.5 * ((lx - self.a) / self.b) ** 2 - lx - math.log(self.b) - 0.5 * LOG_2PI
            inside &= x > 0
        else:  # pragma: no cover - constructor guards
            raise BayesError(f"unknown prior kind {self.kind!r}")
        return np.where(inside, val, -np.inf)

    def describe(self) -> str:
        support = f"on [{self.lower:g}, {self.upper:g}]"
        if self.kind == "flat":
            return f"flat {support}"
        return f"{self.kind}:{self.a:g},{self.b:g} {support}"


def make_prior(name: str, kind: str, a: float, b: float, lower: float, upper: float) -> Prior:
    """A :class:`Prior` for parameter ``name`` with bounds [lower, upper]; one-line errors."""
    if kind not in ("flat", "uniform", "normal", "lognormal"):
        raise BayesError(f"prior of {name}: unknown kind {kind!r}; use lognormal:mu,sigma, uniform:lo,hi or normal:mean,sd")
    if kind != "flat" and not (math.isfinite(a) and math.isfinite(b)):
        raise BayesError(f"prior of {name}: {kind}:{a:g},{b:g} needs two finite numbers")
    if kind == "uniform":
        if not a < b:
            raise BayesError(f"prior of {name}: uniform:{a:g},{b:g} has lower bound not below upper bound; give lo < hi")
        lo, hi = max(lower, a), min(upper, b)
    elif kind in ("normal", "lognormal"):
        if not b > 0:
            raise BayesError(f"prior of {name}: {kind}:{a:g},{b:g} needs a positive spread (second number)")
        lo, hi = (max(lower, 0.0), upper) if kind == "lognormal" else (lower, upper)
    else:
        lo, hi = lower, upper
    if not lo < hi:
        raise BayesError(f"prior of {name}: {kind}:{a:g},{b:g} has no support inside the bounds "
                         f"[{lower:g}, {upper:g}] of {name}; choose a prior that overlaps them")
    return Prior(kind, float(a), float(b), float(lo), float(hi))


def parse_prior(text: str) -> tuple[str, str, float, float]:
    """``NAME=kind:a,b`` (command-line ``--prior``) -> (name, kind, a, b)."""
    name, sep, rest = text.partition("=")
    kind, sep2, values = rest.partition(":")
    parts = [v.strip() for v in values.split(",")]
    try:
        if not (sep and sep2 and name.strip()) or len(parts) != 2:
            raise ValueError
        a, b = float(parts[0]), float(parts[1])
    except ValueError:
        raise BayesError(f"cannot read --prior {text!r}: write NAME=lognormal:mu,sigma, NAME=uniform:lo,hi "
                         "or NAME=normal:mean,sd, e.g. J=uniform:0.01,0.1") from None
    return name.strip(), kind.strip().lower(), a, b


def build_priors(problem: FitProblem, overrides: Mapping[str, tuple[str, float, float]] | None = None) -> list[Prior]:
    """Priors of the free parameters in free-vector order.

    Default: flat on the bounds; N(rig, σ_rig) for parameters with ``prior_std``.
    ``overrides`` maps a free parameter name to (kind, a, b).
    """
    params = problem.parameters
    overrides = dict(overrides or {})
    for name in overrides:
        params.index(name)
        if name not in params.free_names:
            raise BayesError(f"--prior {name}: {name} is fixed in the init fit; give priors for free parameters "
                             f"only ({', '.join(params.free_names)})")
    priors = []
    for i in problem.free_index:
        p = params.parameters[i]
        if p.name in overrides:
            priors.append(make_prior(p.name, *overrides[p.name], p.lower, p.upper))
        elif p.prior_std is not None:
            priors.append(make_prior(p.name, "normal", p.nominal, p.prior_std, p.lower, p.upper))
        else:
            priors.append(make_prior(p.name, "flat", 0.0, 0.0, p.lower, p.upper))
    return priors
