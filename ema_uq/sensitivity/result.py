"""The Sobol result (SOBOL.json of INTERFACES.md) and the analysis that makes it from
evaluated design outputs: in one process (:func:`run`) or from gathered chunks."""
from __future__ import annotations

import time as _time
from dataclasses import dataclass, field
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from .indices import CONF_LEVEL, analyze, analyze_time_resolved, check_convergence, design_size
from .setup import TIME_RESOLVED_OUTPUTS, SensitivitySetup
from .evaluation import SobolChunk, evaluate, gather


# --------------------------------------------------------------------------------------
# result
# --------------------------------------------------------------------------------------
@dataclass
class SobolResult:
    """Sobol indices of one concept's study.

    ``qoi[name]`` holds S1, S1_conf, ST, ST_conf (D,), S2, S2_conf (D, D, upper triangle), the
    QoI's mean, std, unit and a ``degenerate`` flag; ``time_resolved[output]`` holds S1,
    S1_conf, ST, ST_conf as (D, n_times) arrays on ``time`` [s] (``phi_r`` [rad] is the flap
    command there). ``convergence`` compares N/2 with N base samples.
    """

    concept: str
    names: tuple[str, ...]
    bounds: np.ndarray
    nominal: dict[str, float]
    n_base: int
    seed: int
    qoi: dict[str, dict[str, Any]]
    time: np.ndarray
    phi_r: np.ndarray
    time_resolved: dict[str, dict[str, np.ndarray]]
    convergence: dict[str, Any]
    n_evaluations: int
    evaluation_time_s: float
    analysis_time_s: float
    n_chunks: int = 1
    provenance: dict[str, Any] = field(default_factory=dict)

    @property
    def converged(self) -> bool:
        return bool(self.convergence.get("converged", False))

    @property
    def evaluations_per_s(self) -> float:
        return self.n_evaluations / self.evaluation_time_s if self.evaluation_time_s > 0 else float("nan")

    def to_df(self):
        """Long table: one row per (qoi, parameter) with S1, S1_conf, ST, ST_conf."""
        import pandas as pd

        rows = []
        for q, r in self.qoi.items():
            for j, n in enumerate(self.names):
                rows.append({"qoi": q, "parameter": n, "S1": r["S1"][j], "S1_conf": r["S1_conf"][j],
                             "ST": r["ST"][j], "ST_conf": r["ST_conf"][j]})
        return pd.DataFrame(rows).set_index(["qoi", "parameter"])

    def ranking(self, qoi: str) -> list[tuple[str, float]]:
        """Parameters by decreasing total index for one QoI."""
        st = self.qoi[qoi]["ST"]
        return [(self.names[j], float(st[j])) for j in np.argsort(-st)]

    def summary(self, top: int = 4) -> str:
        lines = [f"[[Sobol: {self.concept}, {len(self.names)} parameters, N = {self.n_base}, "
                 f"{self.n_evaluations} runs, seed {self.seed}]]",
                 f"    converged (N/2 vs N) = {self.converged}",
                 f"    evaluation           = {self.evaluation_time_s:.1f} s ({self.evaluations_per_s:.1f} runs/s), "
                 f"analysis {self.analysis_time_s:.1f} s",
                 f"[[Most influential (ST +/- 95 % CI, S1)]]"]
        for q, r in self.qoi.items():
            if r["degenerate"]:
                lines.append(f"    {q:<16} constant over the ranges")
                continue
            order = np.argsort(-r["ST"])[:top]
            parts = [f"{self.names[j]} {r['ST'][j]:.2f}+/-{r['ST_conf'][j]:.2f} ({r['S1'][j]:.2f})" for j in order]
            flag = "" if self.convergence["qoi"].get(q, {}).get("converged", True) else "  [not converged]"
            lines.append(f"    {q:<16} " + ", ".join(parts) + flag)
        if not self.converged:
            for q, c in self.convergence["qoi"].items():
                if not c["converged"]:
                    w = c["worst"]
                    lines.append(f"    warning: {q}: {w['index']}({w['parameter']}) moved {w['difference']:.3f} "
                                 f"from N/2 to N (tolerance {w['tolerance']:.3f}); raise sensitivity.n_base")
        return "\n".join(lines)

    def to_json(self) -> dict[str, Any]:
        def by_name(v):
            return {n: float(x) for n, x in zip(self.names, v)}

        def pairs(m):
            d = len(self.names)
            return {self.names[i]: {self.names[j]: float(m[i, j]) for j in range(i + 1, d)} for i in range(d - 1)}

        qoi = {}
        for q, r in self.qoi.items():
            qoi[q] = {"S1": by_name(r["S1"]), "S1_conf": by_name(r["S1_conf"]), "ST": by_name(r["ST"]),
                      "ST_conf": by_name(r["ST_conf"]), "S2": pairs(r["S2"]), "S2_conf": pairs(r["S2_conf"]),
                      "unit": r["unit"], "mean": float(r["mean"]), "std": float(r["std"]),
                      "degenerate": bool(r["degenerate"])}
        tr = {out: {k: {n: v[j].tolist() for j, n in enumerate(self.names)} for k, v in res.items()}
              for out, res in self.time_resolved.items()}
        return {
            "concept": self.concept, "n_base": int(self.n_base), "converged": self.converged,
            "seed": int(self.seed), "n_evaluations": int(self.n_evaluations), "n_chunks": int(self.n_chunks),
            "evaluation_time_s": float(self.evaluation_time_s), "analysis_time_s": float(self.analysis_time_s),
            "evaluations_per_s": float(self.evaluations_per_s), "conf_level": CONF_LEVEL,
            "parameters": {n: {"lower": float(lo), "upper": float(hi), "nominal": float(self.nominal[n])}
                           for n, (lo, hi) in zip(self.names, self.bounds)},
            "qoi": qoi,
            "convergence": self.convergence,
            "time_resolved": {"time": self.time.tolist(), "phi_r": self.phi_r.tolist(), "outputs": tr},
            "provenance": self.provenance,
        }

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> "SobolResult":
        names = tuple(data["parameters"])
        d = len(names)

        def vec(m):
            return np.array([np.nan if m[n] is None else m[n] for n in names], dtype=float)

        def mat(m):
            out = np.full((d, d), np.nan)
            for i, a in enumerate(names[:-1]):
                for j in range(i + 1, d):
                    v = m[a][names[j]]
                    out[i, j] = np.nan if v is None else v
            return out

        qoi = {}
        for q, r in data["qoi"].items():
            qoi[q] = {k: vec(r[k]) for k in ("S1", "S1_conf", "ST", "ST_conf")}
            qoi[q].update(S2=mat(r["S2"]), S2_conf=mat(r["S2_conf"]), unit=r.get("unit", ""),
                          mean=r.get("mean", np.nan), std=r.get("std", np.nan), degenerate=r.get("degenerate", False))
        tr = data.get("time_resolved", {})
        series = {out: {k: np.array([[np.nan if x is None else x for x in v[n]] for n in names], dtype=float)
                        for k, v in res.items()} for out, res in tr.get("outputs", {}).items()}
        par = data["parameters"]
        return cls(
            concept=data["concept"], names=names, bounds=np.array([[par[n]["lower"], par[n]["upper"]] for n in names]),
            nominal={n: par[n]["nominal"] for n in names}, n_base=int(data["n_base"]), seed=int(data.get("seed", 0)),
            qoi=qoi, time=np.array(tr.get("time", []), dtype=float), phi_r=np.array(tr.get("phi_r", []), dtype=float),
            time_resolved=series, convergence=dict(data.get("convergence", {"converged": data["converged"], "qoi": {}})),
            n_evaluations=int(data.get("n_evaluations", 0)), evaluation_time_s=float(data.get("evaluation_time_s", 0.0)),
            analysis_time_s=float(data.get("analysis_time_s", 0.0)), n_chunks=int(data.get("n_chunks", 1)),
            provenance=dict(data.get("provenance", {})),
        )


def analyze_design(setup: SensitivitySetup, qoi_values: np.ndarray, series: np.ndarray, *,
                   evaluation_time_s: float = float("nan"), n_chunks: int = 1) -> SobolResult:
    """Sobol indices (scalar, time-resolved) and the N/2-vs-N convergence check from evaluated
    design outputs: QoI (n_runs, n_qoi) and series (n_runs, 3, n_times)."""
    t0 = _time.perf_counter()
    problem = setup.problem
    d = len(setup.names)
    analysis_seed = setup.seed + 1
    half_rows = design_size(setup.n_base // 2, d)
    full, half = {}, {}
    for k, q in enumerate(setup.qoi_names):
        y = qoi_values[:, k]
        full[q] = analyze(problem, y, analysis_seed, num_resamples=setup.bootstrap)
        full[q].update(unit=setup.qoi_unit(q), mean=float(np.mean(y)), std=float(np.std(y)))
        half[q] = analyze(problem, y[:half_rows], analysis_seed, num_resamples=setup.bootstrap)
    convergence = check_convergence(half, full, setup.names)
    convergence["n_half"] = setup.n_base // 2
    time_resolved = {out: analyze_time_resolved(problem, series[:, i, :], analysis_seed, num_resamples=setup.bootstrap)
                     for i, out in enumerate(TIME_RESOLVED_OUTPUTS)}
    exp = setup.experiment
    return SobolResult(
        concept=setup.concept, names=setup.names, bounds=setup.bounds,
        nominal={n: float(setup.nominal[setup.model.parameters.index(n)]) for n in setup.names},
        n_base=setup.n_base, seed=setup.seed, qoi=full, time=exp.time[setup.time_index],
        phi_r=exp.inputs["phi_r"][setup.time_index], time_resolved=time_resolved, convergence=convergence,
        n_evaluations=qoi_values.shape[0], evaluation_time_s=evaluation_time_s,
        analysis_time_s=_time.perf_counter() - t0, n_chunks=n_chunks,
    )


def run(setup: SensitivitySetup, progress: Callable[[int], None] | None = None) -> SobolResult:
    """The whole study in one process: design, evaluation, analysis."""
    design = setup.design()
    t0 = _time.perf_counter()
    qoi_values, series = evaluate(setup, design, progress)
    return analyze_design(setup, qoi_values, series, evaluation_time_s=_time.perf_counter() - t0)


def analyze_chunks(setup: SensitivitySetup, chunks: Sequence[SobolChunk]) -> SobolResult:
    """Gather evaluated chunks and analyse; identical to :func:`run` on the same setup."""
    qoi_values, series, wall = gather(setup, chunks)
    return analyze_design(setup, qoi_values, series, evaluation_time_s=wall, n_chunks=len(chunks))
