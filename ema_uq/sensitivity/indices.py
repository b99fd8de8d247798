"""Sobol indices with SALib: the seeded design, first, total and second-order indices with
bootstrap intervals (scalar and per time point), the N/2-vs-N convergence check, and the
Ishigami function with its analytic indices as the reference problem."""
from __future__ import annotations

import math
from typing import Any, Mapping, Sequence

import numpy as np

from ..errors import EmaUqError

CONF_LEVEL = 0.95
#: absolute slack of the N vs 2N agreement test: estimates of indices that are zero differ
#: by a few 1e-3 although their bootstrap intervals shrink to nothing
CONVERGENCE_ATOL = 0.01


class SensitivityError(EmaUqError):
    """A sensitivity study that cannot run: bad design size, unknown names, chunks that do not
    belong together or parameter sets the simulator cannot integrate."""


# --------------------------------------------------------------------------------------
# reference problem with analytic indices (SALib style)
# --------------------------------------------------------------------------------------
ISHIGAMI_PROBLEM: dict[str, Any] = {
    "num_vars": 3, "names": ["x1", "x2", "x3"], "bounds": [[-math.pi, math.pi]] * 3,
}


def ishigami(x: np.ndarray, a: float = 7.0, b: float = 0.1) -> np.ndarray:
    """Ishigami-Homma function sin x1 + a sin² x2 + b x3⁴ sin x1 of (n, 3) inputs -> (n,)."""
    x = np.asarray(x, dtype=float)
    return np.sin(x[:, 0]) + a * np.sin(x[:, 1]) ** 2 + b * x[:, 2] ** 4 * np.sin(x[:, 0])


def ishigami_indices(a: float = 7.0, b: float = 0.1) -> dict[str, np.ndarray]:
    """Analytic S1 (3,), ST (3,) and S2 (3, 3, upper triangle) of :func:`ishigami` on [-π, π]³."""
    pi4, pi8 = math.pi ** 4, math.pi ** 8
    v1 = 0.5 * (1.0 + b * pi4 / 5.0) ** 2
    v2 = a ** 2 / 8.0
    v13 = b ** 2 * pi8 * 8.0 / 225.0
    total = v1 + v2 + v13
    s2 = np.zeros((3, 3))
    s2[0, 2] = v13 / total
    return {"S1": np.array([v1, v2, 0.0]) / total, "ST": np.array([v1 + v13, v2, v13]) / total, "S2": s2}


# --------------------------------------------------------------------------------------
# SALib wrapper: sample / analyze
# --------------------------------------------------------------------------------------
def _check_n_base(n_base: int) -> None:
    if n_base < 2 or n_base & (n_base - 1):
        raise SensitivityError(f"n_base = {n_base} is not a power of 2 >= 2; Sobol designs need one (e.g. 512, 1024)")


def sample(problem: Mapping[str, Any], n_base: int, seed: int) -> np.ndarray:
    """Scrambled Sobol/Saltelli design with second-order columns: (n_base (2D + 2), D).

    Rows come in blocks of 2D + 2 per base sample (A, AB_1..AB_D, BA_1..BA_D, B), so the first
    half of the rows is itself the design of n_base / 2 (used by the convergence check).
    """
    from SALib.sample import sobol as sobol_sample

    _check_n_base(n_base)
    return sobol_sample.sample(dict(problem), n_base, calc_second_order=True, scramble=True, seed=int(seed))


def design_size(n_base: int, n_params: int) -> int:
    return n_base * (2 * n_params + 2)


def _degenerate(y: np.ndarray) -> bool:
    """No variance to apportion (constant to rounding)."""
    spread = float(np.ptp(y))
    return not np.isfinite(spread) or spread <= 1e-12 * max(float(np.max(np.abs(y))), 1e-300)


def analyze(problem: Mapping[str, Any], y: np.ndarray, seed: int, *, num_resamples: int = 100,
            conf_level: float = CONF_LEVEL) -> dict[str, np.ndarray]:
    """SALib ``sobol.analyze`` of one scalar output ``y`` (n_base (2D + 2),).

    Returns S1, S1_conf, ST, ST_conf (D,) and S2, S2_conf (D, D; upper triangle, NaN below)
    plus ``degenerate`` (True when ``y`` is constant: every index 0, intervals 0). The
    bootstrap is seeded (SALib treats seed 0 as unseeded, so 0 is shifted to 1).
    """
    from SALib.analyze import sobol as sobol_analyze

    d = int(problem["num_vars"])
    y = np.asarray(y, dtype=float)
    if y.ndim != 1 or y.size % (2 * d + 2):
        raise SensitivityError(f"{y.size} outputs do not fill a second-order Sobol design of {d} parameters "
                               f"(a multiple of {2 * d + 2} is needed)")
    if not np.all(np.isfinite(y)):
        raise SensitivityError(f"{int(np.sum(~np.isfinite(y)))} model outputs are NaN or infinite; "
                               "Sobol indices need every run")
    if _degenerate(y):
        zeros = np.zeros(d)
        s2 = np.full((d, d), np.nan)
        s2[np.triu_indices(d, 1)] = 0.0
        return {"S1": zeros, "S1_conf": zeros.copy(), "ST": zeros.copy(), "ST_conf": zeros.copy(),
                "S2": s2, "S2_conf": s2.copy(), "degenerate": True}
    out = sobol_analyze.analyze(dict(problem), y, calc_second_order=True, num_resamples=num_resamples,
                                conf_level=conf_level, seed=int(seed) or 1)
    res = {k: np.asarray(out[k], dtype=float) for k in ("S1", "S1_conf", "ST", "ST_conf", "S2", "S2_conf")}
    res["degenerate"] = False
    return res


def analyze_time_resolved(problem: Mapping[str, Any], series: np.ndarray, seed: int, *, num_resamples: int = 100,
                          conf_level: float = CONF_LEVEL, block: int = 16) -> dict[str, np.ndarray]:
    """First and total indices at every time point of ``series`` (n_base (2D + 2), n_times).

    Uses SALib's estimators (``first_order``, ``total_order``: Saltelli 2010 / Jansen) on each
    time column after SALib's normalisation, and the same bootstrap over base samples; returns
    S1, S1_conf, ST, ST_conf as (D, n_times) arrays, NaN where the output does not vary (at rest).
    """
    from scipy.stats import norm
    from SALib.analyze.sobol import first_order, total_order

    d = int(problem["num_vars"])
    series = np.asarray(series, dtype=float)
    n_rows, n_times = series.shape
    if n_rows % (2 * d + 2):
        raise SensitivityError(f"{n_rows} rows do not fill a second-order Sobol design of {d} parameters")
    n = n_rows // (2 * d + 2)
    blocks = series.reshape(n, 2 * d + 2, n_times)
    rng = np.random.default_rng(int(seed))
    r = rng.integers(n, size=(n, num_resamples))
    z = norm.ppf(0.5 + conf_level / 2.0)
    out = {k: np.full((d, n_times), np.nan) for k in ("S1", "S1_conf", "ST", "ST_conf")}
    mean = series.mean(axis=0)
    std = series.std(axis=0)
    live = std > 1e-12 * np.maximum(np.abs(mean), 1e-300)
    for t0 in range(0, n_times, block):
        cols = np.arange(t0, min(t0 + block, n_times))
        cols = cols[live[cols]]
        if cols.size == 0:
            continue
        y = (blocks[:, :, cols] - mean[cols]) / std[cols]
        a, b = y[:, 0], y[:, -1]
        ar, br = a[r], b[r]
        for j in range(d):
            ab = y[:, 1 + j]
            abr = ab[r]
            out["S1"][j, cols] = first_order(a, ab, b)
            out["ST"][j, cols] = total_order(a, ab, b)
            out["S1_conf"][j, cols] = z * first_order(ar, abr, br).std(axis=0, ddof=1)
            out["ST_conf"][j, cols] = z * total_order(ar, abr, br).std(axis=0, ddof=1)
    return out


def indices_agree(s_a: np.ndarray, conf_a: np.ndarray, s_b: np.ndarray, conf_b: np.ndarray,
                  atol: float = 0.0) -> np.ndarray:
    """Element-wise: do two estimates agree within their confidence intervals,
    |s_a - s_b| <= max(conf_a, conf_b) + atol? NaN entries (no estimate) agree."""
    s_a, s_b = np.asarray(s_a, float), np.asarray(s_b, float)
    tol = np.maximum(np.asarray(conf_a, float), np.asarray(conf_b, float)) + atol
    diff = np.abs(s_a - s_b)
    return np.where(np.isfinite(diff), diff <= tol, True)


def check_convergence(half: Mapping[str, Mapping[str, np.ndarray]], full: Mapping[str, Mapping[str, np.ndarray]],
                      names: Sequence[str], atol: float = CONVERGENCE_ATOL) -> dict[str, Any]:
    """Compare S1 and ST from N/2 and N base samples for every QoI.

    Returns ``{"converged": bool, "atol": atol, "qoi": {q: {"converged", "worst": {...}}}}``;
    ``worst`` names the index, parameter and difference with the largest excess over its
    tolerance |ΔS| <= max(conf_N/2, conf_N) + atol.
    """
    report: dict[str, Any] = {}
    for q, f in full.items():
        h = half[q]
        worst = None
        ok = True
        for key in ("S1", "ST"):
            diff = np.abs(np.asarray(f[key]) - np.asarray(h[key]))
            tol = np.maximum(f[f"{key}_conf"], h[f"{key}_conf"]) + atol
            agree = indices_agree(f[key], f[f"{key}_conf"], h[key], h[f"{key}_conf"], atol)
            ok &= bool(np.all(agree))
            excess = np.where(np.isfinite(diff), diff - tol, -np.inf)
            j = int(np.argmax(excess))
            if worst is None or excess[j] > worst["excess"]:
                worst = {"index": key, "parameter": names[j], "difference": float(diff[j]),
                         "tolerance": float(tol[j]), "excess": float(excess[j])}
        report[q] = {"converged": ok, "worst": worst}
    return {"converged": all(v["converged"] for v in report.values()), "atol": atol, "qoi": report}
