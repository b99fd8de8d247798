"""What the identifiability analysis reports: one sensor set (:class:`SensorSetResult`) and
the sensor-set study (:class:`IdentifiabilityResult`, IDENT.json of INTERFACES.md)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from ..identify.information import CRB_Z, Information
from .profiles import PROFILE_THRESHOLD, Profile


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
