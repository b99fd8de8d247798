"""The estimation result: estimates, Cramér-Rao bounds, correlations, flags and history,
with an lmfit-style report and the FIT.json form of docs/INTERFACES.md."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

HIGH_CORRELATION = 0.9


@dataclass
class FitResult:
    """Outcome of one maximum-likelihood fit.

    ``estimate`` holds the full parameter vector (fixed ones at their given value);
    ``covariance`` is the inverse information matrix over the free parameters (Cramér-Rao
    bound), ``std`` its square-root diagonal expanded to the full layout (0 for fixed ones,
    NaN where the information matrix gives no bound and for parameters held because the data
    cannot determine them).

    ``unidentifiable`` is the answer chosen to a singular information matrix at the start
    (``"error"`` or ``"fix"``, :mod:`ema_uq.identify.reduction`); ``fixed`` names the
    parameters it held, {name: {"value", "reason"}}, ``combinations`` the identifiable
    combination of every lumped group (expression, coefficients, value, std, ci95), and
    ``hold_rule`` the rule that chose the held ones (None with ``"error"``).
    """

    concept: str
    method: str
    names: tuple[str, ...]
    units: tuple[str, ...]
    free: np.ndarray
    start: np.ndarray
    estimate: np.ndarray
    std: np.ndarray
    covariance: np.ndarray
    channels: tuple[str, ...]
    residual_covariance: np.ndarray
    log_det_r: float
    objective: float
    n_samples: int
    converged: bool
    message: str
    iterations: int
    n_simulations: int
    wall_time_s: float
    history: list[dict[str, Any]] = field(default_factory=list)
    at_bounds: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    seed: int | None = None
    provenance: dict[str, Any] = field(default_factory=dict)
    unidentifiable: str = "error"
    fixed: dict[str, dict[str, Any]] = field(default_factory=dict)
    combinations: list[dict[str, Any]] = field(default_factory=list)
    hold_rule: str | None = None

    @property
    def free_names(self) -> tuple[str, ...]:
        return tuple(n for n, f in zip(self.names, self.free) if f)

    @property
    def cost(self) -> float:
        """det R at the estimate (eq. 48); may underflow for many channels — see ``log_det_r``."""
        return float(np.exp(self.log_det_r))

    @property
    def correlation(self) -> np.ndarray:
        sd = np.sqrt(np.diag(self.covariance))
        with np.errstate(invalid="ignore", divide="ignore"):
            return self.covariance / np.outer(sd, sd)

    def high_correlations(self, threshold: float = HIGH_CORRELATION) -> list[tuple[str, str, float]]:
        corr, names = self.correlation, self.free_names
        pairs = []
        for i in range(len(names)):
            for j in range(i + 1, len(names)):
                if abs(corr[i, j]) > threshold:
                    pairs.append((names[i], names[j], float(corr[i, j])))
        return pairs

    def value(self, name: str) -> float:
        return float(self.estimate[self.names.index(name)])

    def as_dict(self) -> dict[str, float]:
        return {n: float(v) for n, v in zip(self.names, self.estimate)}

    def summary(self) -> str:
        lines = [
            f"[[Fit: {self.concept} by ML {self.method.upper()}]]",
            f"    converged          = {self.converged} ({self.message})",
            f"    iterations         = {self.iterations}",
            f"    simulations        = {self.n_simulations}",
            f"    wall time          = {self.wall_time_s:.2f} s",
            f"    samples, channels  = {self.n_samples}, {len(self.channels)}",
            f"    log det R          = {self.log_det_r:.6g}",
            f"    unidentifiable     = {self.unidentifiable}"
            + (f" ({len(self.fixed)} held: {', '.join(self.fixed)})" if self.fixed else ""),
            "[[Parameters]] (std = Cramér-Rao bound)",
        ]
        roles = self.roles()
        for i, name in enumerate(self.names):
            role = roles[name]
            tag = {"held": " (held at its start: not estimated)", "fixed": " (fixed)",
                   "kept": f" (carries a lumped group: the group value less the held members; "
                           f"conditional σ {self.std[i]:.3g} given them)"}.get(role, "")
            if name in self.at_bounds:
                tag += " (at bound)"
            rel = abs(self.std[i] / self.estimate[i]) * 100 if self.estimate[i] else np.nan
            bound = {"held": f"{'(no bound)':<23}",
                     "kept": f"{'(bound: its group)':<23}"}.get(role, f"+/- {self.std[i]:<10.3g} ({rel:5.2f}%)")
            lines.append(f"    {name:<8} = {self.estimate[i]:>12.6g} {bound} {self.units[i]}{tag}  "
                         f"(init = {self.start[i]:.6g})")
        lines += self._reduction_lines()
        pairs = self.high_correlations()
        if pairs:
            lines.append(f"[[Correlations]] (|rho| > {HIGH_CORRELATION})")
            lines += [f"    C({a}, {b}) = {r:+.3f}" for a, b, r in pairs]
        for w in self.warnings:
            lines.append(f"    warning: {w}")
        return "\n".join(lines)

    def _reduction_lines(self) -> list[str]:
        if not self.fixed and not self.combinations:
            return []
        lines = [f"[[Held parameters]] (rule: {self.hold_rule})"]
        lines += [f"    {n:<8} = {row['value']:>12.6g}  {row['reason']}" for n, row in self.fixed.items()]
        lines.append("[[Identifiable combinations]] (std = Cramér-Rao bound; what the data determine of a lumped group)")
        for c in self._combinations_with_members():
            lo, hi = c["ci95"]
            lines.append(f"    {c['expression']} = {c['value']:.6g} +/- {c['std']:.3g} "
                         f"({100 * c['relative_std']:.2f}%; 95 % [{lo:.6g}, {hi:.6g}])")
            if c["held"]:
                lines.append(f"        carried by {', '.join(c['kept']) or '-'}; held: {', '.join(c['held'])}")
        return lines

    def roles(self) -> dict[str, str]:
        """What each parameter's value is: ``"estimated"`` (free, with its Cramér-Rao bound),
        ``"fixed"`` (given), ``"held"`` (free, but held at its start because the data cannot
        determine it: no bound) or ``"kept"`` (the free member of a lumped group with held
        members: its value is the group's identifiable combination less the held members at
        their start values, and its std is a bound only given those values; the bound that
        means something is the combination's)."""
        kept = {n for c in self._combinations_with_members() for n in c["kept"] if c["held"]}
        return {n: "held" if n in self.fixed else "kept" if n in kept else "estimated" if f else "fixed"
                for n, f in zip(self.names, self.free)}

    def _combinations_with_members(self) -> list[dict[str, Any]]:
        """The combinations, each with ``kept`` (its free members) and ``held`` (its held ones)."""
        free = set(self.free_names)
        out = []
        for c in self.combinations:
            members = list(c.get("parameters") or c.get("coefficients") or ())
            out.append({**c, "kept": [n for n in members if n in free and n not in self.fixed],
                        "held": [n for n in members if n in self.fixed]})
        return out

    def to_json(self) -> dict[str, Any]:
        corr = self.correlation
        free_names = self.free_names
        roles = self.roles()
        return {
            "concept": self.concept,
            "method": self.method,
            "converged": bool(self.converged),
            "message": self.message,
            "iterations": int(self.iterations),
            "cost": self.cost,
            "log_det_R": self.log_det_r,
            "objective": self.objective,
            "n_samples": self.n_samples,
            "n_simulations": int(self.n_simulations),
            "wall_time_s": float(self.wall_time_s),
            "seed": self.seed,
            "channels": list(self.channels),
            "parameters": {
                n: {"estimate": float(self.estimate[i]), "std": float(self.std[i]), "unit": self.units[i],
                    "start": float(self.start[i]), "free": bool(self.free[i]), "at_bound": n in self.at_bounds,
                    "role": roles[n], "std_conditional": roles[n] == "kept"}
                for i, n in enumerate(self.names)
            },
            "free_parameters": list(free_names),
            "covariance": self.covariance.tolist(),
            "correlation": np.where(np.isfinite(corr), corr, None).tolist(),
            "high_correlations": [{"a": a, "b": b, "rho": r} for a, b, r in self.high_correlations()],
            "at_bounds": list(self.at_bounds),
            "residual_covariance": self.residual_covariance.tolist(),
            "warnings": list(self.warnings),
            "unidentifiable": {"mode": self.unidentifiable, "rule": self.hold_rule},
            "fixed": self.fixed,
            "combinations": self._combinations_with_members(),
            "history": self.history,
            "provenance": self.provenance,
        }

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> "FitResult":
        names = tuple(data["parameters"])
        par = data["parameters"]
        return cls(
            concept=data["concept"], method=data["method"], names=names,
            units=tuple(par[n].get("unit", "") for n in names),
            free=np.array([par[n].get("free", True) for n in names]),
            start=np.array([par[n].get("start", np.nan) for n in names], dtype=float),
            estimate=np.array([par[n]["estimate"] for n in names], dtype=float),
            std=np.array([np.nan if par[n]["std"] is None else par[n]["std"] for n in names], dtype=float),
            covariance=np.array(data.get("covariance", []), dtype=float),
            channels=tuple(data.get("channels", ())),
            residual_covariance=np.array(data.get("residual_covariance", []), dtype=float),
            log_det_r=float(data.get("log_det_R", np.nan)), objective=float(data.get("objective", np.nan)),
            n_samples=int(data.get("n_samples", 0)), converged=bool(data["converged"]),
            message=data.get("message", ""), iterations=int(data["iterations"]),
            n_simulations=int(data.get("n_simulations", 0)), wall_time_s=float(data.get("wall_time_s", 0.0)),
            history=list(data.get("history", [])), at_bounds=list(data.get("at_bounds", [])),
            warnings=list(data.get("warnings", [])), seed=data.get("seed"),
            provenance=dict(data.get("provenance", {})),
            unidentifiable=(data.get("unidentifiable") or {}).get("mode", "error"),
            hold_rule=(data.get("unidentifiable") or {}).get("rule"),
            fixed=dict(data.get("fixed", {})), combinations=list(data.get("combinations", [])),
        )
