"""The Cranfield linear actuator study: a fit of the rig model (``ema_uq.models.cranfield``) on
the healthy records and the fault diagnosis of the seeded-fault record sets against it, through
the one gap diagnosis (:func:`ema_uq.gap.diagnose`) with this rig's strategy
(:func:`cranfield_strategy`): the base parameters held at the healthy fit and only the candidate
effect's parameters fitted, since a refit of the base would absorb a friction change.

The candidates are the rig's catalogue (:data:`ema_uq.models.cranfield.EFFECTS`): one
mechanism each, each its own family, so a verdict names a mechanism only on that mechanism's
own evidence: ``backlash`` is play and nothing else, and it can win only where the position
error (and the force the drive stops delivering while the play is crossed) shows lost motion;
a friction change of the ball contact (``contact_friction``, signed, scaling with preload +
|load|), more friction from lost lubrication (``lubrication_loss``, >= 0, Coulomb and viscous)
and a load-independent seal drag (``seal_drag``) compete as separate candidates.
:data:`EXPECTED` holds the seeded fault of each record set (the backlash sets: ``backlash``,
whether or not the records show play; the lubrication sets: ``lubrication_loss``).

Three choices make the diagnosis's statistics fit real records:

- *Thinning.* The healthy fit's residual is coloured (integrated autocorrelation time ~6
  samples on the current): the det R likelihood, which counts every sample as independent,
  would overstate every likelihood ratio by that factor. The effect parameters are therefore
  fitted on every ``stride``-th sample only (:func:`thinning_stride`: the integrated
  autocorrelation time of the healthy residual, rounded up), the others marked missing, so
  ΔBIC compares like with like. (The held-out gain, read on every sample, stays inflated by
  that factor; it is a second condition, not the first.)
- *Gap relative to the healthy rig.* The gap metric (:class:`ExcessNrmse`) is the excess of
  the held-out residual's systematic mean square (short-lag products: no white noise) over the
  healthy fit's own on healthy records (the model's own error), on every fitted channel (the
  position error, where play shows, and the current, where friction shows), weighed as the
  det R likelihood weighs them: the residual whitened by the healthy fit's residual covariance,
  so the selection and the shrink test read the channels in the units the fit used; it is
  significant when it exceeds three standard errors of the block-to-block spread of healthy
  records. So healthy held-out records have no gap, and a fault's gap shrinks to zero when its
  effect explains it.
- *Reproducible gap.* Every block repeats one set-point cycle, and the rig drifts within a
  test session (the healthy fit's mean residual of the moving current on backlash1 is +0.004 A
  in run 1 and -0.046 A in run 7 under +20 kgf, but -0.078 A in run 1 and -0.036 A in run 9
  under +40 kgf), so part of a held-out gap changes from run to run and no fixed-parameter
  effect can close it. The replicate mean of the estimation residual
  (:func:`cycle_replicate_prediction`, per load and phase of the cycle, from every sample of
  the estimation runs) is the best any time-invariant model learnt from them could do; the
  verdict's shrink test is read on the part of the gap it closes (the *reproducible shrink* of
  :mod:`ema_uq.gap.attribute`), and that part must itself stand out of the healthy spread.

Everything here is numerics on :class:`~ema_uq.experiments.Measurement` blocks (read by
:func:`ema_uq.io.read_cranfield`); results are documented objects with ``summary()`` and
``to_json()``.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from . import Rig
from ..errors import EmaUqError
from ..experiments import Measurement
from ..gap.localize import RegimeRms, lag_products
from ..gap.strategy import DiagnosisSettings, DiagnosisStrategy, Thresholds, method_switches
from ..identify import FitProblem, FitResult, Settings, estimate
from ..models import get_model
from ..simulate import simulate_batch
from . import MEASURED_RIG_METHOD_VERSION
from .cranfield_cycles import cycle_replicate_prediction
from .cranfield_cycles import set_point_period  # noqa: F401 - still importable from here

#: fitted channels: the potentiometer error (its residual equals the position's, but its RMS is
#: the loop's lag, not the 120 mm stroke, so the gap is expressed on the scale that matters) and
#: the drive current
CHANNELS = ("position_error", "current")
START_S = 0.8          # a stroke start or stop and the loop's settling after it [s]
SIGNIFICANT_Z = 3.0    # the normal quantile of the error rate at which an excess is a gap (see ExcessNrmse)
MAX_LAG = 60           # samples of the autocorrelation used for the thinning stride


# --------------------------------------------------------------------------------------
# healthy fit and the statistics taken from it
# --------------------------------------------------------------------------------------
def fit_healthy(measurements: Sequence[Measurement], *, max_iterations: int = 30) -> FitResult:
    """ML fit (det R, Gauss-Newton from the nominal values) of every base parameter on healthy blocks."""
    problem = FitProblem(measurements, channels=CHANNELS)
    return estimate(problem, method="gn", settings=Settings(max_iterations=max_iterations))


def residuals(theta: np.ndarray, measurements: Sequence[Measurement], model=None) -> list[np.ndarray]:
    """Measured minus simulated ``CHANNELS`` (n, 2) of each block at full parameter vector ``theta``."""
    model = get_model("cranfield") if model is None else model
    index = model.output_index(CHANNELS)
    out = []
    for m in measurements:
        simulated = simulate_batch(model, theta, m.time, m.experiment.input_matrix(model))
        out.append(m.select(CHANNELS).values - simulated[:, index])
    return out


def student_threshold(z_normal: float, dof: int) -> float:
    """The Student-t quantile, ``dof`` degrees of freedom, of the upper normal tail beyond
    ``z_normal``: the threshold of a z whose standard error was estimated with ``dof`` degrees
    of freedom, at the error rate the normal threshold means."""
    from scipy import stats

    return float(stats.t.isf(stats.norm.sf(z_normal), dof))


def thinning_stride(residual_blocks: Sequence[np.ndarray], max_lag: int = MAX_LAG) -> int:
    """Integrated autocorrelation time of the residual (channel maximum, autocorrelation averaged
    over blocks, Sokal's window: the first lag M >= 5 tau(M)), rounded up: the sample spacing at
    which the residual is about independent."""
    taus = []
    for c in range(residual_blocks[0].shape[1]):
        acs = []
        for r in residual_blocks:
            e = r[:, c] - np.nanmean(r[:, c])
            e = np.where(np.isfinite(e), e, 0.0)
            acs.append([np.dot(e[: e.size - lag], e[lag:]) / np.dot(e, e) for lag in range(max_lag)])
        tau = 1.0 + 2.0 * np.cumsum(np.mean(acs, axis=0)[1:])
        window = next((m for m in range(1, max_lag) if m >= 5.0 * tau[m - 1]), max_lag - 1)
        taus.append(tau[window - 1])
    return max(1, int(math.ceil(max(taus))))


def thinned(measurements: Sequence[Measurement], stride: int) -> list[Measurement]:
    """Copies of the blocks in which only every ``stride``-th sample is kept (the others NaN:
    missing for the fits and figures; the simulation still runs over every sample)."""
    out = []
    for m in measurements:
        values = np.full_like(m.values, np.nan)
        values[::stride] = m.values[::stride]
        out.append(Measurement(m.concept, m.experiment, m.channels, values, {**m.attrs, "thinning_stride": stride}))
    return out


def whitening(residual_blocks: Sequence[np.ndarray]) -> np.ndarray:
    """The likelihood's channel weighting: W = L⁻¹ with R = L Lᵀ the residual covariance (second
    moments about zero, NaN rows left out) of the healthy fit on the blocks it was fitted to.
    The det R criterion at its optimum weighs a residual e as eᵀ R⁻¹ e = |W e|², so W e is the
    residual in the units the fit itself used: each channel per its own residual scale, the part
    of the second channel that the first predicts removed. No weight is set by hand."""
    e = np.concatenate(residual_blocks)
    e = e[np.all(np.isfinite(e), axis=1)]
    return np.linalg.inv(np.linalg.cholesky(e.T @ e / e.shape[0]))


@dataclass(frozen=True)
class ExcessNrmse:
    """Gap metric of the fault diagnosis, on every fitted channel, weighed as the likelihood
    weighs them: the residual is whitened by the healthy fit's residual covariance
    (:func:`whitening`, ``weights`` W), and the gap is sqrt(mean over the whitened channels of
    max(0, S_c - base_c)), where S_c is the systematic mean square of the held-out whitened
    residual's channel c (the mean of its short-lag products,
    :func:`ema_uq.gap.localize.lag_products`, which white noise leaves at zero, so a change of
    the sensor noise between test sessions is no gap) and ``base_c`` the same figure of the
    healthy fit on healthy blocks it did not see (the model's own error). So a gap in the
    position error (play at a reversal) counts as much as one in the current, each in units of
    the healthy fit's own residual. ``z`` is the mean excess over its standard error, and that
    error counts both means it compares: sd sqrt(1 / blocks + 1 / healthy_blocks), sd the
    block-to-block spread of the channel-mean excess on the ``healthy_blocks`` healthy blocks
    (``mean_spread_sd``; ``spread_sd`` per channel), since the healthy level ``base`` is itself
    a mean of a few blocks. Significant when ``z`` passes ``z_significant``: the Student-t
    quantile, with healthy_blocks - 1 degrees of freedom, of the normal tail beyond
    ``SIGNIFICANT_Z`` (taking the level and its sd from six blocks as known, white-noise record
    sets passed for a gap in 6.5 % of 3000 simulated draws against the 0.13 % meant; 0.2 % now).
    ``per_channel`` reports the excess of every whitened channel under the name of the measured
    one it leads with (the first is that channel alone, the second the part of the second channel
    the first does not predict); ``channels``, ``base``, ``spread_sd``: (m,); ``weights``: W (m, m)."""

    channels: tuple[str, ...]
    weights: tuple[tuple[float, ...], ...]
    base: tuple[float, ...]
    spread_sd: tuple[float, ...]
    mean_spread_sd: float
    description: str = ("held-out excess systematic NRMSE of the position error and the drive current, whitened by "
                        "the healthy fit's residual covariance, over the healthy fit on healthy records")
    z_significant: float = SIGNIFICANT_Z
    healthy_blocks: int | None = None     # None: the healthy level taken as known (no error of its own)

    @classmethod
    def from_healthy(cls, residual_blocks: Sequence[np.ndarray], weights: np.ndarray,
                     channels: Sequence[str] = CHANNELS) -> "ExcessNrmse":
        """From the healthy fit's residuals (each (n, m)) on healthy blocks it did not see (at
        least two: the spread needs one degree of freedom) and its whitening ``weights``
        (:func:`whitening` of its residual on the blocks it was fitted to)."""
        if len(residual_blocks) < 2:
            raise EmaUqError(f"the gap metric's healthy level needs at least two healthy blocks, got "
                             f"{len(residual_blocks)}; hold out more healthy runs")
        w = np.asarray(weights, dtype=float)
        per_block = np.array([np.nanmean(lag_products(r @ w.T), axis=0) for r in residual_blocks])
        n = len(residual_blocks)
        return cls(tuple(channels), tuple(map(tuple, w)), tuple(per_block.mean(axis=0)),
                   tuple(per_block.std(axis=0, ddof=1)), float(per_block.mean(axis=1).std(ddof=1)),
                   z_significant=student_threshold(SIGNIFICANT_Z, n - 1), healthy_blocks=n)

    def figures(self, records, measurements, model, channels, segments, spread) -> dict[str, Any]:
        if tuple(channels) != self.channels:
            raise ValueError(f"the gap metric weighs channels {self.channels}, the diagnosis fits {tuple(channels)}")
        w = np.asarray(self.weights)
        p = np.concatenate([lag_products(np.asarray(seg) @ w.T) for seg in segments])
        p = p[np.all(np.isfinite(p), axis=1)]
        terms = np.column_stack([p, np.ones(p.shape[0])])
        excess = self._excess(terms.sum(axis=0))
        n_blocks = max(1, sum(1 for r in records if np.any(np.isfinite(r.residual))))
        level = 0.0 if self.healthy_blocks is None else 1.0 / self.healthy_blocks
        se = self.mean_spread_sd * math.sqrt(1.0 / n_blocks + level)
        mean_excess = float(np.mean(terms[:, :-1].mean(axis=0) - np.asarray(self.base)))
        return {"gap": float(np.sqrt(np.mean(excess))), "z": mean_excess / se if se > 0 else float("nan"),
                "factors": 0, "per_channel": dict(zip(self.channels, map(float, np.sqrt(excess)))),
                "significant": bool(mean_excess > self.z_significant * se), "terms": terms}

    def _excess(self, sums: np.ndarray) -> np.ndarray:
        return np.maximum(sums[..., :-1] / sums[..., -1:] - np.asarray(self.base), 0.0)

    def combine(self, sums: np.ndarray) -> np.ndarray:
        return np.sqrt(np.mean(self._excess(sums), axis=-1))

    def to_json(self) -> dict[str, Any]:
        return {"channels": list(self.channels), "weights": [list(r) for r in self.weights], "base": list(self.base),
                "spread_sd": list(self.spread_sd), "mean_spread_sd": self.mean_spread_sd,
                "significant_z": self.z_significant, "healthy_blocks": self.healthy_blocks,
                "significant_z_normal": SIGNIFICANT_Z}


# --------------------------------------------------------------------------------------
# regimes and localisation
# --------------------------------------------------------------------------------------
def regime_masks(measurement: Measurement) -> dict[str, np.ndarray]:
    """Sample masks from the set point and load of one block: ``reversal`` (0.8 s from every
    change of the set-point speed: stroke starts, the reversal at the bottom, the stop at the
    top), ``low_speed`` (set point at rest, after that window), ``constant_speed`` (moving,
    after that window), ``up``/``down`` (set point rising/falling), ``high_load`` (moving under
    40 kgf, the largest load) and ``negative_load``."""
    dt = measurement.experiment.dt
    x_sp = measurement["x_sp"]
    direction = np.sign(np.round(np.append(np.diff(x_sp), 0.0) / dt, 9))
    near = np.zeros(x_sp.size, dtype=bool)
    reach = int(round(START_S / dt))
    for k in np.concatenate([[0], np.flatnonzero(np.diff(direction) != 0) + 1]):
        near[k: k + reach] = True
    moving = direction != 0
    load = measurement["F_load"]
    return {"reversal": near, "low_speed": ~moving & ~near, "constant_speed": moving & ~near,
            "up": direction > 0, "down": direction < 0, "high_load": moving & (np.abs(load) >= 0.99 * 40 * 9.80665),
            "negative_load": load < 0}


def residual_by_regime(records, channels, model, theta, measurements, spread, constants=None) -> RegimeRms:
    """Localisation: RMS by regime (:func:`regime_masks`) of the channel-normalised residual
    sqrt(Σ_c (e_c / spread_c)² / m) (position error and current weigh alike)."""
    residual_parts, masks = [], []
    for record, m in zip(records, measurements):
        e = record.residual / np.asarray(spread)[None, :]
        ok = np.all(np.isfinite(e), axis=1)
        residual_parts.append(np.sqrt(np.mean(e[ok] ** 2, axis=1)))
        masks.append({k: v[ok] for k, v in regime_masks(m).items()})
    joined = {k: np.concatenate([mk[k] for mk in masks]) for k in masks[0]}
    return RegimeRms.of("+".join(channels), np.concatenate(residual_parts), joined)


# --------------------------------------------------------------------------------------
# the strategy
# --------------------------------------------------------------------------------------
#: Verdict thresholds: the package's frozen ones (ΔBIC > 25, held-out gain > 25, shrink >= 0.5
#: where the gap is significant), applied to thinned records; the signature is reported, not
#: scored (weight 0: the regimes are this rig's, not the catalogue's calibration).
THRESHOLDS = Thresholds(signature_weight=0.0)


def cranfield_strategy(reference_fit: Mapping[str, float] | None = None, metric: ExcessNrmse | None = None,
                       replicates: bool = True) -> DiagnosisStrategy:
    """How :func:`ema_uq.gap.diagnose` treats the rig. With ``reference_fit`` (base parameter
    values of the healthy fit) a fault diagnosis: base held there, only effect parameters fitted
    (Gauss-Newton, 30 iterations, from the start grid at 0.3, 1, 3, 10 x ``Effect.start``);
    ``metric`` the gap relative to the healthy rig (default: the systematic NRMSE);
    ``replicates`` False judges the shrink on the whole gap, not on its reproducible part
    (:func:`cycle_replicate_prediction`), for comparison."""
    from ..gap.strategy import SystematicNrmse

    strategy = DiagnosisStrategy(
        name="cranfield", channels=CHANNELS,
        settings=DiagnosisSettings(**method_switches(MEASURED_RIG_METHOD_VERSION), candidate_max_iterations=30,
                                   screen_base_parameters=None, final_max_iterations=30),
        start_multiples=(0.3, 1.0, 3.0, 10.0), metric=metric or SystematicNrmse(), localize=residual_by_regime,
        where_source="held-out", thresholds=THRESHOLDS,
        replicate_prediction=cycle_replicate_prediction if replicates else None)
    return strategy if reference_fit is None else strategy.with_reference(reference_fit)


#: The rig's strategy without a healthy reference (every base parameter refitted); the
#: registry of ``ema_uq.gap.strategy`` names it for concept cranfield.
CRANFIELD_STRATEGY = cranfield_strategy()


# --------------------------------------------------------------------------------------
# the study: healthy fit, then one diagnosis per record set
# --------------------------------------------------------------------------------------
@dataclass
class HealthyReference:
    """The healthy fit and what the fault diagnosis takes from it: the thinning ``stride`` and
    the gap ``metric``; ``nrmse_held_out`` per channel on healthy blocks the fit did not see."""

    fit: FitResult
    stride: int
    metric: ExcessNrmse
    nrmse_held_out: dict[str, float]
    fit_blocks: list[str]
    held_out_blocks: list[str]
    wall_time_s: float
    replicates: bool = True
    healthy_blocks: tuple[Measurement, ...] = ()

    @property
    def values(self) -> dict[str, float]:
        return self.fit.as_dict()

    def strategy(self) -> DiagnosisStrategy:
        # the healthy held-out blocks give the cell test its healthy level: what the healthy rig
        # leaves in the position loop and the current is not a fault's
        return replace(cranfield_strategy(self.values, self.metric, self.replicates),
                       healthy_records=tuple(self.healthy_blocks))

    def to_json(self) -> dict[str, Any]:
        return {"estimate": self.values, "std": dict(zip(self.fit.names, map(float, self.fit.std))),
                "converged": bool(self.fit.converged), "iterations": int(self.fit.iterations),
                "thinning_stride": self.stride, "metric": self.metric.to_json(),
                "nrmse_held_out": self.nrmse_held_out, "fit_blocks": self.fit_blocks,
                "held_out_blocks": self.held_out_blocks, "wall_time_s": self.wall_time_s,
                "replicate_ceiling": self.replicates}


def healthy_reference(fit_blocks: Sequence[Measurement], baseline_blocks: Sequence[Measurement],
                      held_out_blocks: Sequence[Measurement] = ()) -> HealthyReference:
    """Fit on healthy ``fit_blocks``; the thinning stride from that fit's residual there; the gap
    metric's healthy baseline from its residual on healthy ``baseline_blocks`` the fit did not
    see (a fitted record's residual is smaller than a new one's); NRMSE (RMS residual / RMS
    measured, per channel) on ``baseline_blocks`` and ``held_out_blocks``, all unseen by the fit."""
    t0 = time.perf_counter()
    fit = fit_healthy(fit_blocks)
    fitted = residuals(fit.estimate, fit_blocks)
    stride = thinning_stride(fitted)
    baseline = residuals(fit.estimate, baseline_blocks)
    metric = ExcessNrmse.from_healthy(baseline, whitening(fitted))
    unseen = list(baseline_blocks) + list(held_out_blocks)
    held = np.concatenate(baseline + residuals(fit.estimate, held_out_blocks))
    measured = np.concatenate([m.select(CHANNELS).values for m in unseen])
    nrmse = np.sqrt(np.mean(held ** 2, axis=0) / np.mean(measured ** 2, axis=0))
    return HealthyReference(fit, stride, metric, dict(zip(CHANNELS, map(float, nrmse))),
                            [m.experiment.name for m in fit_blocks], [m.experiment.name for m in unseen],
                            time.perf_counter() - t0, healthy_blocks=tuple(held_out_blocks))


@dataclass
class RecordSetDiagnosis:
    """The gap diagnosis of one record set against the healthy fit: ``result`` (a
    :class:`~ema_uq.gap.GapResult`), the blocks whose effect parameters were fitted and those
    held out (the last of them scores the shrink)."""

    record_set: str
    result: Any
    estimation_blocks: list[str]
    held_out_blocks: list[str]

    def row(self) -> dict[str, Any]:
        r = self.result
        runner_up = r.ranking[1].effect if len(r.ranking) > 1 else None
        return {"record_set": self.record_set, "verdict": r.verdict, "effect": r.effect, "confidence": r.confidence,
                "best": r.ranking[0].effect if r.ranking else None, "runner_up": runner_up,
                "score_margin": (r.ranking[0].score - r.ranking[1].score) if len(r.ranking) > 1 else float("nan"),
                "gap_before": r.gap.get("before"), "gap_after": r.gap.get("after"), "shrink": r.gap.get("shrink"),
                "shrink_se": r.gap.get("shrink_se"), "significant_before": r.gap.get("significant_before"),
                "significant_selection": r.gap.get("significant_selection"),
                "selection_shrink": r.ranking[0].selection_shrink if r.ranking else None,
                "reproducible_share": r.gap.get("reproducible_share"),
                "reproducible_shrink": r.ranking[0].reproducible_shrink if r.ranking else None,
                "effect_parameters": r.effect_parameters, "wall_time_s": r.wall_time_s,
                "where_stroke": list(r.where.get("stroke", [])),
                **open_set_row(getattr(r, "open_set", {}) or {})}


def open_set_row(open_set: Mapping[str, Any], top: int = 3) -> dict[str, Any]:
    """Why a record set is or is not named, in a row: the ``top`` family probabilities, the
    contenders of an ``ambiguous`` verdict, the reason no family was named and, per group of
    cells (channel, stroke, direction, regime, band), the first cell the best candidate leaves."""
    probabilities = dict(list((open_set.get("family_probabilities") or {}).items())[:top])
    return {"family_probabilities": {f: float(p) for f, p in probabilities.items()},
            "contenders": [c["family"] for c in open_set.get("contenders") or []],
            "verdict_reason": open_set.get("verdict_reason"),
            "where_left": {group: cells[0] for group, cells in (open_set.get("where_left") or {}).items() if cells}}


@dataclass
class CranfieldStudy:
    """The healthy fit and the verdict of every record set (``diagnoses``), with ``expected``
    verdicts (record set -> effect name or "none") when known."""

    reference: HealthyReference
    diagnoses: list[RecordSetDiagnosis]
    expected: dict[str, str] = field(default_factory=dict)
    wall_time_s: float = 0.0

    def verdict_of(self, record_set: str) -> str:
        r = next(d.result for d in self.diagnoses if d.record_set == record_set)
        return r.effect if r.verdict == "effect" else r.verdict

    def summary(self) -> str:
        ref = self.reference
        lines = [f"[[Cranfield linear actuator]] healthy fit on {len(ref.fit_blocks)} blocks "
                 f"({'converged' if ref.fit.converged else 'NOT converged'}, {ref.fit.iterations} iterations); "
                 f"held-out NRMSE " + ", ".join(f"{c} {v:.3f}" for c, v in ref.nrmse_held_out.items())
                 + f"; thinning stride {ref.stride}",
                 f"    {'record set':<18} {'verdict':<18} {'expected':<18} {'runner-up':<18} {'gap before':>10} "
                 f"{'after':>7} {'reproducible':>12} {'closed':>7} {'shrink':>13} {'s':>6}"]
        for d in self.diagnoses:
            row = d.row()
            verdict = row["effect"] if row["verdict"] == "effect" else row["verdict"]
            shrink = row["shrink"]
            shrink_text = "-" if shrink is None else (f"{shrink:.2f}" + ("" if row["shrink_se"] is None
                                                                           else f" +/- {row['shrink_se']:.2f}"))
            lines.append(f"    {d.record_set:<18} {verdict:<18} {self.expected.get(d.record_set, '?'):<18} "
                         f"{row['runner_up'] or '-':<18} {row['gap_before']:>10.4f} {row['gap_after']:>7.4f} "
                         f"{_share(row['reproducible_share']) if row['significant_selection'] else 'no gap':>12} "
                         f"{_share(row['reproducible_shrink']) if row['significant_selection'] else '-':>7} "
                         f"{shrink_text:>13} {row['wall_time_s']:>6.1f}")
            for name, p in (row["effect_parameters"] if row["verdict"] == "effect" else {}).items():
                lines.append(f"        {name:<30} = {p['estimate']:.4g} +/- {p['std']:.2g} {p.get('unit', '')}")
            lines.extend(f"        {line}" for line in _why_lines(row))
        lines.append("    reproducible: share of the selection blocks' gap a replicate mean of the estimation runs "
                     "closes; closed: share of that the best candidate closes (the verdict's shrink test); "
                     "expected ?: no known seeded fault")
        lines.append(f"    wall time {self.wall_time_s:.0f} s")
        return "\n".join(lines)

    def to_json(self) -> dict[str, Any]:
        return {"reference": self.reference.to_json(), "expected": self.expected,
                "diagnoses": [{**d.row(), "estimation_blocks": d.estimation_blocks,
                               "held_out_blocks": d.held_out_blocks, "gap": d.result.to_json()} for d in self.diagnoses],
                "wall_time_s": self.wall_time_s}


def _why_lines(row: Mapping[str, Any]) -> list[str]:
    """The open-set figures of a summary row: family probabilities, contenders, the reason no
    family was named and the first cell left per group."""
    lines = []
    if row.get("family_probabilities"):
        lines.append("family probability " + ", ".join(f"{f} {p:.3g}" for f, p in row["family_probabilities"].items())
                     + (f"; contenders {' / '.join(row['contenders'])}" if row.get("contenders") else ""))
    if row.get("verdict_reason"):
        lines.append(f"why not named: {row['verdict_reason']}")
    lines.extend(f"the gap lies along the stroke in {cell}" for cell in row.get("where_stroke") or [])
    lines.extend(f"left ({group}): {cell}" for group, cell in (row.get("where_left") or {}).items())
    return lines


def _share(value: float | None) -> str:
    return "-" if value is None or not np.isfinite(value) else f"{value:.2f}"


#: Loads in the order the held-out blocks are given: the last held-out block scores the shrink,
#: and it is the 40 kgf one, the largest load pushing the carriage up the stroke.
HELD_OUT_LOAD_ORDER = (20.0, -40.0, 40.0)


def _ordered(blocks: Sequence[Measurement]) -> list[Measurement]:
    return sorted(blocks, key=lambda m: (m.attrs["run"], HELD_OUT_LOAD_ORDER.index(m.attrs["load_kgf"])
                                         if m.attrs["load_kgf"] in HELD_OUT_LOAD_ORDER else -1))


def diagnose_record_set(reference: HealthyReference, name: str, estimation: Sequence[Measurement],
                        held_out: Sequence[Measurement], *, seed: int = 0,
                        progress: Callable[[str], None] | None = None) -> RecordSetDiagnosis:
    """The gap diagnosis of one record set against ``reference`` (base parameters held): effect
    parameters fitted on the thinned ``estimation`` blocks, verdict and shrink on ``held_out``
    (every sample: the gap metric reads short-lag products); the held-out blocks go in
    :data:`HELD_OUT_LOAD_ORDER`, so the last, which scores the shrink, is at 40 kgf. The
    replicate ceiling of the shrink test is the cycle mean of the healthy fit's residual on
    every sample of ``estimation`` (the thinned copies keep one sample per phase and block)."""
    from ..gap import diagnose

    held_out = _ordered(held_out)
    strategy = reference.strategy()
    if strategy.replicate_prediction is not None:
        strategy = replace(strategy, replicate_prediction=_replicates_of(
            estimation, residuals(reference.fit.estimate, estimation)))
    result = diagnose(thinned(estimation, reference.stride), held_out, strategy=strategy, seed=seed,
                      progress=progress)
    return RecordSetDiagnosis(name, result, [m.experiment.name for m in estimation],
                              [m.experiment.name for m in held_out])


def _replicates_of(blocks: Sequence[Measurement], residual_blocks: Sequence[np.ndarray]):
    """A ``replicate_prediction`` learnt from every sample of ``blocks`` (their ``CHANNELS``
    residual ``residual_blocks``), whatever thinned copies the diagnosis fits."""
    def predict(_estimation, _residuals, _channels, held_out, held_channels):
        return cycle_replicate_prediction(blocks, residual_blocks, CHANNELS, held_out, held_channels)
    return predict


#: The verdict each record set of the rig should get.
EXPECTED = {"normal": "none", "backlash1": "backlash", "backlash2": "backlash",
            "lackLubrication1": "lubrication_loss", "lackLubrication2": "lubrication_loss"}


def run_study(read: Callable[[str, Sequence[int]], list[Measurement]], *, fit_runs: Sequence[int] = (1, 2, 3, 4, 5),
              healthy_held_out_runs: Sequence[int] = (6, 7, 8, 9, 10), estimation_runs: Sequence[int] = (1, 2, 3, 4, 5),
              held_out_runs: Sequence[int] = (6, 7, 8, 9, 10), record_sets: Sequence[str] = tuple(EXPECTED),
              seed: int = 0, replicates: bool = True, progress: Callable[[str], None] | None = None,
              runs_of: Callable[[str], Sequence[int]] | None = None) -> CranfieldStudy:
    """Fit on the healthy runs ``fit_runs`` of ``normal``, then diagnose each record set.

    ``read(record_set, runs)`` returns the blocks of those runs (every load). The first two
    ``healthy_held_out_runs`` give the gap metric's healthy baseline and, for the ``normal``
    diagnosis, fit the effect parameters; the others are the held-out healthy records of that
    diagnosis. The faulted sets fit effect parameters on ``estimation_runs`` and are judged on
    ``held_out_runs``; with ``runs_of(record_set)`` (the runs a set holds) a set that lacks some
    of those runs is split in its own runs instead (:func:`own_runs_split`). A set with no
    known seeded fault (not in :data:`EXPECTED`) is diagnosed alike and left out of
    ``expected``. ``replicates`` False: the shrink test reads the whole gap, not its
    reproducible part (:func:`cranfield_strategy`).
    """
    t0 = time.perf_counter()
    say = progress or (lambda _line: None)
    # every set's runs are split before any fit, so a set that cannot be split stops the study at once
    splits = {name: own_runs_split(name, runs_of(name) if runs_of else None, estimation_runs, held_out_runs)
              for name in record_sets if name != "normal"}
    healthy_held = list(healthy_held_out_runs)
    baseline, healthy_rest = read("normal", healthy_held[:2]), read("normal", healthy_held[2:])
    reference = replace(healthy_reference(read("normal", fit_runs), baseline, healthy_rest), replicates=replicates)
    say(f"healthy fit: NRMSE {reference.nrmse_held_out}, stride {reference.stride}, {reference.wall_time_s:.1f} s")
    diagnoses = []
    for name in record_sets:
        if name == "normal":
            estimation, held = baseline, healthy_rest
        else:
            fitted, judged = splits[name]
            estimation, held = read(name, fitted), read(name, judged)
        d = diagnose_record_set(reference, name, estimation, held, seed=seed)
        say(f"{name}: {d.row()['verdict']} {d.row()['effect'] or ''} ({d.result.wall_time_s:.1f} s)")
        diagnoses.append(d)
    return CranfieldStudy(reference, diagnoses, {k: EXPECTED[k] for k in record_sets if k in EXPECTED},
                          time.perf_counter() - t0)


def own_runs_split(name: str, held: Sequence[int] | None, estimation_runs: Sequence[int],
                   held_out_runs: Sequence[int]) -> tuple[tuple[int, ...], tuple[int, ...]]:
    """(estimation runs, held-out runs) of record set ``name`` holding the runs ``held`` (None:
    not known, the runs asked for are used): the runs asked for when it holds them all, else
    its own runs in halves, the earlier half fitted (a set recorded with fewer or other runs).
    A set of one run cannot be split into runs that choose an effect and runs that judge it."""
    asked = tuple(int(r) for r in estimation_runs), tuple(int(r) for r in held_out_runs)
    if held is None or set(asked[0] + asked[1]) <= set(held):
        return asked
    runs = sorted({int(r) for r in held})
    if len(runs) < 2:
        raise EmaUqError(f"record set {name} holds {len(runs)} run(s); the diagnosis needs at least two, one to fit "
                         "the effect and one to judge it on: add a run to it, or leave it out with the study's "
                         "data.record_sets")
    half = (len(runs) + 1) // 2
    return tuple(runs[:half]), tuple(runs[half:])


def run_splits(n_runs: int = 10) -> dict[str, tuple[tuple[int, ...], ...]]:
    """Every leave-half-the-runs-out split of the family the split benchmark reads: label ->
    (healthy fit runs, healthy held-out runs, fault estimation runs, fault held-out runs), the
    two halves A | B the same for the healthy and the faulted sets (A fitted, B held out; the
    first two runs of B, in the order given, the healthy baseline).

    The family: the ``n_runs`` splits whose halves are two arcs of the runs laid on a circle
    (A = n_runs/2 consecutive runs, wrapping round, B the rest, in order after A), and the two
    interleaved ones (odd | even, even | odd). Why these: the runs of a set were recorded one
    after the other and the rig drifts within a session, so how far in time the held-out runs
    lie from the fitted ones matters most; the arcs hold out every run equally often (half of
    them) at every distance from the fitted block, from extrapolation (1-5 | 6-10) to
    interpolation (a block fitted on both ends), and the interleaved pair is the nearest
    neighbour case. All C(10, 5) = 252 halvings would cost 21 times as much for splits that
    mostly repeat these distances. Count: n_runs + 2 (12 for the rig's ten runs)."""
    if n_runs % 2 or n_runs < 4:
        raise ValueError(f"the split family needs an even number of runs >= 4, not {n_runs}")
    half = n_runs // 2
    splits: dict[str, tuple[tuple[int, ...], ...]] = {}
    for r in range(n_runs):
        a = tuple((r + i) % n_runs + 1 for i in range(half))
        b = tuple((r + half + i) % n_runs + 1 for i in range(half))
        splits[f"{_runs_label(a)} | {_runs_label(b)}"] = (a, b, a, b)
    odd, even = tuple(range(1, n_runs + 1, 2)), tuple(range(2, n_runs + 1, 2))
    splits["odd | even"] = (odd, even, odd, even)
    splits["even | odd"] = (even, odd, even, odd)
    return splits


def _runs_label(runs: Sequence[int]) -> str:
    """'3-7' for consecutive runs, '9,10,1,2,3' otherwise."""
    runs = list(runs)
    if all(b == a + 1 for a, b in zip(runs, runs[1:])):
        return f"{runs[0]}-{runs[-1]}"
    return ",".join(map(str, runs))


@dataclass
class SplitStudy:
    """The study under every split of a split family (:func:`run_splits`): ``rows`` one per
    split (its fitted and held-out runs, how many sets of known fault came out as expected, and
    per record set the verdict, the best candidate, the shrink figures, the backlash candidate's
    fitted play and the open-set reasons), ``counts`` the verdicts per record set over the
    splits, ``expected`` the known seeded faults, ``not_split`` the record sets that lack some
    of the runs the splits halve."""

    rows: list[dict[str, Any]]
    counts: dict[str, dict[str, int]]
    expected: dict[str, str]
    not_split: list[str] = field(default_factory=list)
    wall_time_s: float = 0.0

    def summary(self) -> str:
        lines = [f"[[Run splits]] verdicts under {len(self.rows)} splits (fitted runs | held-out runs)"
                 + (f"; not split (they lack some of the runs): {', '.join(self.not_split)}" if self.not_split else "")]
        labelled = sum(name in self.expected for name in self.counts)
        for row in self.rows:
            lines.append(f"    {row['split']:<22} {row['right']}/{labelled}  "
                         + "  ".join(f"{name}: {v['verdict']}" for name, v in row["sets"].items()))
        lines.append("[[Verdict counts]] per record set over the splits")
        for name, c in self.counts.items():
            lines.append(f"    {name:<18} expected {self.expected.get(name, '?'):<18} "
                         + ", ".join(f"{v} {n}" for v, n in sorted(c.items(), key=lambda kv: -kv[1])))
        lines.append(f"    wall time {self.wall_time_s:.0f} s")
        return "\n".join(lines)

    def to_json(self) -> dict[str, Any]:
        return {"family": "ema_uq.rigs.cranfield.run_splits", "n_splits": len(self.rows), "expected": self.expected,
                "counts": self.counts, "not_split": self.not_split, "splits": self.rows,
                "wall_time_s": self.wall_time_s}


def run_split_study(read: Callable[[str, Sequence[int]], list[Measurement]], *,
                    record_sets: Sequence[str] = tuple(EXPECTED), splits: Mapping[str, Any] | None = None,
                    runs_of: Callable[[str], Sequence[int]] | None = None, seed: int = 0,
                    progress: Callable[[str], None] | None = None) -> SplitStudy:
    """:func:`run_study` under every split of ``splits`` (default :func:`run_splits` of ten runs):
    how much each record set's verdict depends on which runs are held out. With ``runs_of``,
    the record sets that lack some of the split runs are left out (named in ``not_split``)."""
    t0 = time.perf_counter()
    splits = dict(splits or run_splits())
    needed = {int(r) for parts in splits.values() for half in parts for r in half}
    sets = [n for n in record_sets if runs_of is None or needed <= {int(r) for r in runs_of(n)}]
    rows: list[dict[str, Any]] = []
    counts: dict[str, dict[str, int]] = {name: {} for name in sets}
    for label, (fit, healthy, estimation, held) in splits.items():
        study = run_study(read, fit_runs=fit, healthy_held_out_runs=healthy, estimation_runs=estimation,
                          held_out_runs=held, record_sets=sets, seed=seed)
        row: dict[str, Any] = {"split": label, "fit_runs": list(fit), "held_out_runs": list(held), "right": 0,
                               "sets": {}}
        for d in study.diagnoses:
            r, verdict = d.row(), study.verdict_of(d.record_set)
            play = next((c for c in d.result.ranking if c.effect == "backlash"), None)
            row["right"] += verdict == EXPECTED.get(d.record_set)
            counts[d.record_set][verdict] = counts[d.record_set].get(verdict, 0) + 1
            row["sets"][d.record_set] = {
                "verdict": verdict, "best": r["best"], "runner_up": r["runner_up"],
                "selection_shrink": r["selection_shrink"], "reproducible_shrink": r["reproducible_shrink"],
                "reproducible_share": r["reproducible_share"],
                "play_m": None if play is None else play.parameters["backlash_play"]["estimate"],
                "play_std_m": None if play is None else play.parameters["backlash_play"]["std"],
                "play_delta_bic": None if play is None else play.delta_bic,
                "family_probabilities": r["family_probabilities"], "contenders": r["contenders"],
                "verdict_reason": r["verdict_reason"], "where_left": r["where_left"]}
        rows.append(row)
        if progress:
            progress(f"split {label}: " + ", ".join(f"{n} {v['verdict']}" for n, v in row["sets"].items()))
    return SplitStudy(rows, counts, {k: EXPECTED[k] for k in sets if k in EXPECTED},
                      [n for n in record_sets if n not in sets], time.perf_counter() - t0)


# --------------------------------------------------------------------------------------
# the rig as the command line and the report see it
# --------------------------------------------------------------------------------------
def _data_files(study: Mapping[str, Any]) -> list[tuple[str, Path]]:
    from .. import io

    files = [io.cranfield_file(name, study, must_exist=False) for name in io.cranfield_record_sets(study)]
    return [(f"{f.name} (measured)", f) for f in files]


RIG = Rig(concept="cranfield", title="Cranfield linear actuator", data_files=_data_files, fault_diagnosis=True)
