"""Global variance-based sensitivity: Sobol indices of the friction/damping parameters,
computed with SALib (Saltelli/Sobol design, ``sobol.analyze``), scalar and time-resolved.

SALib's split is kept: a plain ``problem`` dict, :func:`sample` (seeded, scrambled Sobol
design), evaluation (in independent chunks, each through the one batched simulator call)
and :func:`analyze` (first, total and second-order indices with bootstrap 95 % intervals).
The Ishigami function with its analytic indices lives here as the reference problem the
tests check the wrapper against.

Quantities of interest (QoI) per parameter set, on the study's estimation experiment:

``cost``            log det R of the residuals against reference data (the study's estimation
                    data synthesised at nominal with its noise and seed) [-]; the ML cost on a
                    log scale, because det R spans decades over the ranges and Sobol indices
                    of a heavy-tailed output would only describe its tail
``rms_<channel>``   RMS deviation of the channel from the nominal run [channel unit]
``tracking_error``  RMS of y_r - (y1 + y2)/2 [m]
``peak_torque``     max |k_n I_A|, the motor torque [N m]
``peak_current``    max |I_A| [A]
``energy``          motor shaft energy delivered, ∫ max(k_n I_A Ω, 0) dt [J]

Time-resolved first and total indices of Ω, y1 and I_A are computed per time point on a
decimated grid with SALib's estimators, vectorised over time.
"""
from __future__ import annotations

import hashlib
import json
import math
import os
import time as _time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from .experiments import Experiment, get_experiment, synthesize
from .models import Model, get_model
from .simulate import simulate_batch

#: scalar QoI kinds of the study schema, in report order
QOI_KINDS = ("cost", "rms", "tracking_error", "peak_torque", "peak_current", "energy")
#: outputs with time-resolved indices
TIME_RESOLVED_OUTPUTS = ("Omega", "y1", "I_A")
CONF_LEVEL = 0.95
#: absolute slack of the N vs 2N agreement test: estimates of indices that are zero differ
#: by a few 1e-3 although their bootstrap intervals shrink to nothing
CONVERGENCE_ATOL = 0.01
#: Sobol runs are forward simulations only (no finite differences), where an adaptive
#: integrator's step choice per parameter set costs nothing: the hybrid one (exact steps over
#: the intervals where the model is linear) takes 2.5x (HT/LS) to 10x (LT/HS) less time than
#: plain Dormand-Prince on the deploy-retract run, at its accuracy
INTEGRATOR = "hybrid"
_QOI_UNITS = {"cost": "1", "tracking_error": "m", "peak_torque": "N m", "peak_current": "A", "energy": "J"}


class SensitivityError(ValueError):
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


# --------------------------------------------------------------------------------------
# the actuator study: parameters, ranges, reference data, QoI
# --------------------------------------------------------------------------------------
def friction_names(model: Model) -> tuple[str, ...]:
    """The friction/damping parameters (B_*, C_*) of a concept, in layout order."""
    return tuple(n for n in model.parameters.names if n.startswith(("B_", "C_")))


_MOTOR_CONSTANTS = ("k_n", "R_A", "L_A", "k_s")


@dataclass(frozen=True)
class SensitivitySetup:
    """Everything one concept's Sobol study needs, resolved from a study file.

    ``nominal`` is the full parameter vector around which ranges are set and at which every
    parameter outside ``names`` is held; ``bounds`` (D, 2) are the uniform ranges of ``names``.
    ``reference`` (n_samples, n_channels) is the noisy estimation data the cost QoI compares
    with; ``time_index`` the samples kept for the time-resolved indices.
    """

    concept: str
    names: tuple[str, ...]
    bounds: np.ndarray
    nominal: np.ndarray
    constants: np.ndarray
    experiment: Experiment
    reference_channels: tuple[str, ...]
    reference: np.ndarray
    rms_channels: tuple[str, ...]
    qoi_kinds: tuple[str, ...]
    time_index: np.ndarray
    n_base: int
    seed: int
    chunks: int = 1
    batch_size: int = 128
    bootstrap: int = 100

    @property
    def model(self) -> Model:
        return get_model(self.concept)

    @property
    def problem(self) -> dict[str, Any]:
        """The plain SALib problem description."""
        return {"num_vars": len(self.names), "names": list(self.names), "bounds": self.bounds.tolist()}

    @property
    def qoi_names(self) -> tuple[str, ...]:
        names: list[str] = []
        for kind in self.qoi_kinds:
            names += [f"rms_{c}" for c in self.rms_channels] if kind == "rms" else [kind]
        return tuple(names)

    def qoi_unit(self, name: str) -> str:
        if name.startswith("rms_"):
            return self.model.unit_of(name[4:])
        return _QOI_UNITS[name]

    @property
    def n_evaluations(self) -> int:
        return design_size(self.n_base, len(self.names))

    def digest(self) -> str:
        """Fingerprint of everything that determines the evaluated numbers (chunks must share it)."""
        h = hashlib.sha256()
        h.update(json.dumps([self.concept, self.names, self.reference_channels, self.rms_channels, self.qoi_kinds,
                             self.n_base, self.seed, self.experiment.name, INTEGRATOR]).encode())
        for arr in (self.bounds, self.nominal, self.constants, self.reference, self.time_index):
            h.update(np.ascontiguousarray(arr).tobytes())
        return h.hexdigest()[:16]

    def design(self) -> np.ndarray:
        return sample(self.problem, self.n_base, self.seed)

    def thetas(self, rows: np.ndarray) -> np.ndarray:
        """Full parameter vectors (n, n_params) for design rows (n, D)."""
        full = np.repeat(self.nominal[None, :], rows.shape[0], axis=0)
        full[:, [self.model.parameters.index(n) for n in self.names]] = rows
        return full


def setup_from_study(study: Mapping[str, Any], *, n_base: int | None = None) -> SensitivitySetup:
    """Resolve a (validated) study's ``sensitivity`` section into a :class:`SensitivitySetup`."""
    from .study import section

    model = get_model(study["concept"])
    if not friction_names(model) or "I_A" not in model.outputs or "k_y" not in model.constants:
        raise SensitivityError(f"concept {model.name} has no EMA friction parameters and outputs; "
                               "the Sobol study covers htls and lths")
    sens = section(study, "sensitivity")
    data = section(study, "data")
    n_base = int(sens["n_base"] if n_base is None else n_base)
    _check_n_base(n_base)
    params, consts = model.split_assignments(dict(data.get("set") or {}))
    nominal = model.parameters.vector(params)
    constants = model.constants_vector(consts)

    names = list(friction_names(model))
    if sens["include_inertia"]:
        names.insert(0, "J")
    if sens["include_motor"]:
        names += [n for n in _MOTOR_CONSTANTS if n in model.parameters]
    fraction = float(sens["range_fraction"])
    if not 0 < fraction < 1:
        raise SensitivityError(f"sensitivity.range_fraction = {fraction} must lie in (0, 1)")
    ranges = {n: (nominal[model.parameters.index(n)] * (1 - fraction),
                  nominal[model.parameters.index(n)] * (1 + fraction)) for n in names}
    for name, (lo, hi) in dict(sens["parameters"]).items():
        if name not in model.parameters:
            raise SensitivityError(f"sensitivity.parameters: unknown parameter {name!r} for {model.name}")
        if not lo < hi:
            raise SensitivityError(f"sensitivity.parameters.{name}: lower {lo} must be below upper {hi}")
        ranges[name] = (float(lo), float(hi))
        if name not in names:
            names.append(name)
    for name in names:
        p = model.parameters[name]
        lo, hi = ranges[name]
        if lo < p.lower or hi > p.upper or not lo < hi:
            raise SensitivityError(f"range of {name} [{lo:g}, {hi:g}] leaves its bounds [{p.lower:g}, {p.upper:g}] "
                                   "or is empty; narrow range_fraction or give sensitivity.parameters")
    bounds = np.array([ranges[n] for n in names], dtype=float)

    experiment = get_experiment(data["estimation"])
    ref_channels = tuple(data.get("channels") or model.outputs)
    seed = int(study.get("seed", 1))
    reference = synthesize(model, experiment, nominal, noise=float(data["noise"]), seed=seed,
                           channels=ref_channels, constants=constants).values
    if not np.all(np.isfinite(reference)):
        raise SensitivityError("the reference data have missing samples; the cost QoI needs complete data")
    if sens["rms_channels"]:
        rms_channels = tuple(sens["rms_channels"])
        model.output_index(rms_channels)
    else:
        # channels set by the inputs alone (M_ER) do not move with any parameter
        moving = _moving_channels(model, experiment, nominal, bounds, names, constants)
        rms_channels = tuple(c for c in model.outputs if c in moving)
    n = experiment.n_samples
    time_index = np.unique(np.round(np.linspace(0, n - 1, min(int(sens["time_points"]), n))).astype(np.int64))
    return SensitivitySetup(
        concept=model.name, names=tuple(names), bounds=bounds, nominal=nominal, constants=constants,
        experiment=experiment, reference_channels=ref_channels, reference=reference, rms_channels=rms_channels,
        qoi_kinds=tuple(sens["qoi"]), time_index=time_index, n_base=n_base,
        seed=seed + int(sens["seed_offset"]), chunks=int(sens["chunks"]), batch_size=int(sens["batch_size"]),
        bootstrap=int(sens["bootstrap"]),
    )


def _moving_channels(model, experiment, nominal, bounds, names, constants) -> set[str]:
    """Channels that differ between the nominal run and the two range corners."""
    idx = [model.parameters.index(n) for n in names]
    thetas = np.repeat(nominal[None], 3, axis=0)
    thetas[1, idx] = bounds[:, 0]
    thetas[2, idx] = bounds[:, 1]
    out = simulate_batch(model, thetas, experiment.time, experiment.input_matrix(model), constants=constants,
                         integrator=INTEGRATOR)
    spread = np.max(np.abs(out[1:] - out[:1]), axis=(0, 1))
    scale = np.max(np.abs(out[0]), axis=0)
    return {c for c, s, m in zip(model.outputs, spread, scale) if s > 1e-9 * max(m, 1e-300)}


# --------------------------------------------------------------------------------------
# evaluation (pure: design rows -> QoI and decimated series)
# --------------------------------------------------------------------------------------
def _qoi_batch(setup: SensitivitySetup, thetas: np.ndarray, out: np.ndarray, nominal_out: np.ndarray,
               k_y: float, phi_r: np.ndarray, dt: float) -> np.ndarray:
    """QoI (n_sets, n_qoi) from simulated outputs (n_sets, n_samples, n_outputs)."""
    model = setup.model
    oi = {c: i for i, c in enumerate(model.outputs)}
    k_n = thetas[:, model.parameters.index("k_n")][:, None]
    i_a = out[:, :, oi["I_A"]]
    torque = k_n * i_a
    cols = []
    for kind in setup.qoi_kinds:
        if kind == "cost":
            e = setup.reference[None] - out[:, :, model.output_index(setup.reference_channels)]
            r = np.matmul(e.transpose(0, 2, 1), e) / e.shape[1]
            sign, logdet = np.linalg.slogdet(r)
            cols.append(np.where(sign > 0, logdet, np.nan))
        elif kind == "rms":
            idx = model.output_index(setup.rms_channels)
            rms = np.sqrt(np.mean((out[:, :, idx] - nominal_out[None, :, idx]) ** 2, axis=1))
            cols += list(rms.T)
        elif kind == "tracking_error":
            y_s = 0.5 * (out[:, :, oi["y1"]] + out[:, :, oi["y2"]])
            cols.append(np.sqrt(np.mean((k_y * phi_r - y_s) ** 2, axis=1)))
        elif kind == "peak_torque":
            cols.append(np.max(np.abs(torque), axis=1))
        elif kind == "peak_current":
            cols.append(np.max(np.abs(i_a), axis=1))
        elif kind == "energy":
            cols.append(np.sum(np.maximum(torque * out[:, :, oi["Omega"]], 0.0), axis=1) * dt)
        else:  # pragma: no cover - the schema enumerates the kinds
            raise SensitivityError(f"unknown QoI {kind!r}; choose from {', '.join(QOI_KINDS)}")
    return np.column_stack(cols)


def evaluate(setup: SensitivitySetup, rows: np.ndarray,
             progress: Callable[[int], None] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Evaluate design rows (n, D): returns QoI (n, n_qoi) and the time-resolved series
    (n, len(TIME_RESOLVED_OUTPUTS), n_times), in batches of ``setup.batch_size`` sets per
    simulator call. Deterministic per row: any split into chunks gives the same numbers.
    ``progress`` is called with the number of rows of every finished batch."""
    model = setup.model
    exp = setup.experiment
    inputs = exp.input_matrix(model)
    nominal_out = simulate_batch(model, setup.nominal, exp.time, inputs, constants=setup.constants,
                                 integrator=INTEGRATOR)
    k_y = float(setup.constants[model.constants.index("k_y")])
    phi_r = exp.inputs["phi_r"]
    series_idx = model.output_index(TIME_RESOLVED_OUTPUTS)
    rows = np.atleast_2d(np.asarray(rows, dtype=float))
    n = rows.shape[0]
    qoi = np.empty((n, len(setup.qoi_names)))
    series = np.empty((n, len(TIME_RESOLVED_OUTPUTS), setup.time_index.size))
    for start in range(0, n, setup.batch_size):
        stop = min(start + setup.batch_size, n)
        thetas = setup.thetas(rows[start:stop])
        out = simulate_batch(model, thetas, exp.time, inputs, constants=setup.constants, integrator=INTEGRATOR)
        bad = ~np.all(np.isfinite(out), axis=(1, 2))
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            values = ", ".join(f"{nm}={v:.4g}" for nm, v in zip(setup.names, rows[start + k]))
            raise SensitivityError(f"{int(bad.sum())} parameter set(s) give a non-finite trajectory, e.g. {values}; "
                                   "narrow the ranges (sensitivity.range_fraction or sensitivity.parameters)")
        qoi[start:stop] = _qoi_batch(setup, thetas, out, nominal_out, k_y, phi_r, exp.dt)
        series[start:stop] = out[:, setup.time_index][:, :, series_idx].transpose(0, 2, 1)
        if progress is not None:
            progress(stop - start)
    return qoi, series


def chunk_rows(n_rows: int, chunk_index: int, n_chunks: int) -> tuple[int, int]:
    """Row range [start, stop) of chunk ``chunk_index`` (0-based) of ``n_chunks`` near-equal parts."""
    if n_chunks < 1 or not 0 <= chunk_index < n_chunks:
        raise SensitivityError(f"chunk {chunk_index}/{n_chunks}: give 0 <= I < N with N >= 1 (chunks are numbered from 0)")
    if n_chunks > n_rows:
        raise SensitivityError(f"{n_chunks} chunks for {n_rows} runs; use at most {n_rows} chunks")
    edges = np.linspace(0, n_rows, n_chunks + 1).round().astype(int)
    return int(edges[chunk_index]), int(edges[chunk_index + 1])


@dataclass
class SobolChunk:
    """The evaluated rows [start, stop) of a design: QoI (n, n_qoi) and series (n, 3, n_times)."""

    concept: str
    digest: str
    chunk_index: int
    n_chunks: int
    start: int
    stop: int
    qoi_names: tuple[str, ...]
    qoi: np.ndarray
    series: np.ndarray
    wall_time_s: float

    def save(self, path: str | os.PathLike) -> Path:
        """Write as .npz (atomically: a killed job never leaves a chunk that looks finished)."""
        from . import io

        path = io.prepare_output(path)
        meta = {"concept": self.concept, "digest": self.digest, "chunk_index": self.chunk_index,
                "n_chunks": self.n_chunks, "start": self.start, "stop": self.stop,
                "qoi_names": list(self.qoi_names), "wall_time_s": self.wall_time_s}
        tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}.npz")
        np.savez(tmp, meta=np.array(json.dumps(meta)), qoi=self.qoi, series=self.series)
        os.replace(tmp, path)
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> "SobolChunk":
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as f:
                meta = json.loads(str(f["meta"]))
                return cls(meta["concept"], meta["digest"], int(meta["chunk_index"]), int(meta["n_chunks"]),
                           int(meta["start"]), int(meta["stop"]), tuple(meta["qoi_names"]), f["qoi"], f["series"],
                           float(meta["wall_time_s"]))
        except FileNotFoundError:
            raise SensitivityError(f"{path}: no such chunk file; run 'ema-uq sensitivity --chunk I/N' first") from None
        except (OSError, ValueError, KeyError) as exc:
            raise SensitivityError(f"{path}: not a chunk written by 'ema-uq sensitivity --chunk' ({exc})") from None


def evaluate_chunk(setup: SensitivitySetup, design: np.ndarray, chunk_index: int, n_chunks: int,
                   progress: Callable[[int], None] | None = None) -> SobolChunk:
    """Evaluate one of ``n_chunks`` independent parts of ``design`` (a job of its own in a
    workflow); ``progress`` as in :func:`evaluate`."""
    start, stop = chunk_rows(design.shape[0], chunk_index, n_chunks)
    t0 = _time.perf_counter()
    qoi, series = evaluate(setup, design[start:stop], progress)
    return SobolChunk(setup.concept, setup.digest(), chunk_index, n_chunks, start, stop, setup.qoi_names,
                      qoi, series, _time.perf_counter() - t0)


def gather(setup: SensitivitySetup, chunks: Sequence[SobolChunk]) -> tuple[np.ndarray, np.ndarray, float]:
    """Join chunks into the full (QoI, series) arrays; every chunk of one design exactly once."""
    if not chunks:
        raise SensitivityError("no chunk given to gather; pass every chunk file of the design")
    digest = setup.digest()
    n_chunks = {c.n_chunks for c in chunks}
    if len(n_chunks) != 1:
        raise SensitivityError(f"chunks of different splits {sorted(n_chunks)} given; gather the chunks of one split")
    n_chunks = n_chunks.pop()
    for c in chunks:
        if c.digest != digest or c.qoi_names != setup.qoi_names:
            raise SensitivityError(f"chunk {c.chunk_index}/{c.n_chunks} was evaluated for another study or design "
                                   f"({c.concept}, fingerprint {c.digest} != {digest}); re-run it with this study")
    seen = sorted(c.chunk_index for c in chunks)
    if seen != list(range(n_chunks)):
        missing = sorted(set(range(n_chunks)) - set(seen))
        dup = sorted({i for i in seen if seen.count(i) > 1})
        raise SensitivityError(f"chunks of {n_chunks}: missing {missing or 'none'}, repeated {dup or 'none'}; "
                               "give each chunk file exactly once")
    ordered = sorted(chunks, key=lambda c: c.chunk_index)
    qoi = np.concatenate([c.qoi for c in ordered])
    series = np.concatenate([c.series for c in ordered])
    if qoi.shape[0] != setup.n_evaluations or ordered[-1].stop != setup.n_evaluations:
        raise SensitivityError(f"chunks hold {qoi.shape[0]} runs, the design has {setup.n_evaluations}")
    return qoi, series, float(sum(c.wall_time_s for c in ordered))


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
    """The whole study in one process: design, evaluation, analysis; ``progress`` as in :func:`evaluate`."""
    design = setup.design()
    t0 = _time.perf_counter()
    qoi_values, series = evaluate(setup, design, progress)
    return analyze_design(setup, qoi_values, series, evaluation_time_s=_time.perf_counter() - t0)


def analyze_chunks(setup: SensitivitySetup, chunks: Sequence[SobolChunk]) -> SobolResult:
    """Gather evaluated chunks and analyse; identical to :func:`run` on the same setup."""
    qoi_values, series, wall = gather(setup, chunks)
    return analyze_design(setup, qoi_values, series, evaluation_time_s=wall, n_chunks=len(chunks))
