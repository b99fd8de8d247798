"""The state one gap diagnosis shares between its steps: :class:`_Diagnosis` (data split,
strategy, settings, simulation count, and the held-out figures every model is judged by: gap
metric per part, cell energies, replicate ceiling, bootstrap standard error of a shrink) and
:class:`_Reference`, the fitted model candidates are compared with.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Callable, Sequence

import numpy as np

from .. import statistics
from ..experiments import Measurement
from ..identify import FitResult
from ..simulate import simulate_batch
from .fitting import _stepped_sets
from .holdout import _Split
from .localize import ResidualRecord, complete_runs, noise_std
from .strategy import DiagnosisSettings, DiagnosisStrategy
from .structure import cell_energies, cell_masks, stroke_bins

Z_HELD_OUT = 5.0
SHRINK_BLOCKS = 20          # contiguous blocks of the scoring part resampled for the shrink's standard error
SHRINK_REPLICATES = 400
SHRINK_SEED = 0             # bootstrap seed when the diagnosis is given none


@dataclass
class _Reference:
    """A fitted model candidates are compared with: the nominal fit, or the model with the
    effects selected so far. ``figures``: its held-out figures of the selection and the scoring
    part (:meth:`_Diagnosis.parts`)."""

    model: Any
    fit: FitResult
    objective: float
    figures: dict[str, Any]
    effects: list[str]


@dataclass
class _Diagnosis:
    """What every step of one diagnosis shares; counts the simulations."""

    strategy: DiagnosisStrategy
    settings: DiagnosisSettings
    data: _Split
    root: Any
    catalogue: dict[str, Any]
    say: Callable[[str], None]
    problem_args: dict[str, Any] = field(default_factory=dict)
    fixed: list[str] = field(default_factory=list)
    n_samples: int = 0
    n_sims: int = 0
    seed: int | None = None
    ceiling: dict[str, dict[str, Any]] | None = None   # held-out figures of the replicate prediction
    masks: dict[str, list[np.ndarray]] | None = None   # cell masks of the selection part (nominal outputs)
    stroke_bins: Any = None                             # (stroke output, bin edges) of those masks
    healthy_cells: dict[str, Any] | None = None         # cells of the reference on the strategy's healthy records
    predictable: Any = None                             # what the state predicts of the nominal's held-out gap
    allowance: Any = None                               # the model-form allowance fitted in every model (or None)
    resamples: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        rng = np.random.default_rng(SHRINK_SEED if self.seed is None else self.seed)
        self.resamples = rng.integers(0, SHRINK_BLOCKS, size=(SHRINK_REPLICATES, SHRINK_BLOCKS))

    def records(self, model, theta: np.ndarray, held: bool) -> list[ResidualRecord]:
        """Residual records of one full parameter vector on the held-out or the estimation records."""
        d = self.data
        measurements, channels, names = ((d.held, d.held_channels, d.held_names) if held
                                         else (d.estimation, d.channels, d.est_names))
        return _simulate_records(model, theta, measurements, channels, names, self.strategy)[0]

    def localise(self, model, theta: np.ndarray, records: Sequence[ResidualRecord], held: bool):
        d = self.data
        measurements, channels, spread = ((d.held, d.held_channels, d.held_spread) if held
                                          else (d.estimation, d.channels, d.est_spread))
        return self.strategy.localize(records, channels, model, theta, measurements, spread,
                                      constants=self.strategy.constants_of(measurements[0]))

    def held_out_figures(self, model, records: Sequence[ResidualRecord], part: str = "all") -> dict[str, Any]:
        """Gap metric and companions on a part of the held-out records (:meth:`_Split.part`): the
        strategy's metric (gap, z, factors, per_channel, significant, terms), plain NRMSE
        (channel mean), log det R and sample count."""
        d = self.data
        records, measurements = d.part(records, part)
        segments = [seg for r in records for seg in complete_runs(r.residual)]
        out = dict(self.strategy.metric.figures(records, measurements, model, d.held_channels, segments,
                                                d.held_spread))
        e = np.concatenate(segments)
        out.update(nrmse=float(np.mean(np.sqrt(np.mean(e ** 2, axis=0)) / d.held_spread)),
                   log_det_r=statistics.log_det_r(e.T @ e / e.shape[0]), n=int(e.shape[0]))
        return out

    def without_estimation_error(self, model, fit: FitResult, records: Sequence[ResidualRecord]) -> list[ResidualRecord]:
        """Held-out records whose prediction is moved by the parameter error the estimation
        data leave open: the posterior mean of δ ~ N(0, Cramér-Rao covariance of ``fit``) given
        the held-out residual, linearised (relative forward differences on shared steps, one
        batched call per record), each record and channel weighted by its own noise.

        Why: held-out residuals carry the fit's own estimation error, J δ, on top of the noise;
        on thousands of samples a δ well inside its bound already shows as a bias or a slow
        drift, and the structure tests, built for white noise, would call a correct model
        structured (LT/HS rig sensors: a current bias). With C = J Σ Jᵀ + σ² I the predictive
        covariance, the adjusted residual is σ² C⁻¹ y: under a correct model its covariance
        σ⁴ C⁻¹ is at most σ² I, so the tests keep their level; a missing effect loses only its
        part along the sensitivities, and of that the share G / (1 + G), G the held-out over
        the estimation information (about half for records alike).
        Records are returned unchanged when nothing is free or the covariance is not finite."""
        free = np.flatnonzero(fit.free)
        cov = np.asarray(fit.covariance, dtype=float)
        if free.size == 0 or cov.shape != (free.size, free.size) or not np.all(np.isfinite(cov)):
            return list(records)
        thetas, h, _ = _stepped_sets(fit.estimate, free, 1e-4)
        d = self.data
        per_set = _simulate_records(model, thetas, d.held, d.held_channels, d.held_names, self.strategy,
                                    share_steps=True)
        self.n_sims += thetas.shape[0] * len(d.held)
        evals, evecs = np.linalg.eigh(0.5 * (cov + cov.T))
        root = evecs * np.sqrt(np.clip(evals, 0.0, None))            # cov = root rootᵀ, δ = root u
        a, b, unit_sens = np.eye(free.size), np.zeros(free.size), []
        for r, rec in enumerate(records):
            base_pred = per_set[0][r].predicted
            sens = np.stack([(per_set[1 + i][r].predicted - base_pred) / h[i] for i in range(free.size)])
            sens_u = np.einsum("kl,knm->lnm", root, sens)           # response to unit u
            unit_sens.append(sens_u)
            valid = rec.valid
            e = rec.residual
            sigma = noise_std(e)
            w = np.where(valid[:, None] & (sigma > 0), 1.0 / np.where(sigma > 0, sigma, 1.0) ** 2, 0.0)
            su = np.where(valid[None, :, None], sens_u, 0.0)
            a += np.einsum("lnm,nm,knm->lk", su, w, su)
            b += np.einsum("lnm,nm,nm->l", su, w, np.where(valid[:, None], e, 0.0))
        u = np.linalg.solve(a, b)
        return [replace(rec, predicted=rec.predicted + np.einsum("l,lnm->nm", u, su))
                for rec, su in zip(records, unit_sens)]

    def parts(self, model, records: Sequence[ResidualRecord], theta: np.ndarray | None = None) -> dict[str, dict[str, Any]]:
        """Held-out figures of the selection and the scoring part; the selection part's also
        carry ``cells``, the excess energy per cell (:mod:`ema_uq.gap.structure`), whose masks
        come from the first model asked (the nominal one, ``theta`` its estimate)."""
        out = {part: self.held_out_figures(model, records, part) for part in ("selection", "scoring")}
        selection, _ = self.data.part(records, "selection")
        if self.masks is None:
            constants = self.strategy.constants_of(self.data.held[0])
            self.masks = cell_masks(selection, model, theta,
                                    model.constants_vector() if constants is None else constants)
            self.stroke_bins = stroke_bins(selection, model)
        out["selection"]["cells"] = cell_energies(selection, self.data.held_channels, self.data.held_spread,
                                                  self.masks)
        return out

    def ceiling_of(self, model, est_records: Sequence[ResidualRecord],
                   held_records: Sequence[ResidualRecord]) -> dict[str, dict[str, Any]] | None:
        """Held-out figures (selection and scoring part) of the strategy's replicate prediction,
        a time-invariant model learnt from the estimation residual of ``model``: the gap it
        leaves is what no fixed-parameter effect can close. None without replicates (no
        prediction, or one that cannot predict every held-out record)."""
        predict = self.strategy.replicate_prediction
        if predict is None:
            return None
        d = self.data
        predicted = predict(d.estimation, [r.residual for r in est_records], d.channels, d.held, d.held_channels)
        if predicted is None:
            self.say("no replicate ceiling: the held-out records do not repeat the estimation records' experiment")
            return None
        records = [replace(r, predicted=r.predicted + p) for r, p in zip(held_records, predicted)]
        return self.parts(model, records)

    def ceiling_gap(self, part: str) -> float | None:
        return None if self.ceiling is None else self.ceiling[part]["gap"]

    def reproducible_significant(self, before: dict[str, Any]) -> bool:
        """Whether the part of a reference's gap on the selection part (its figures there,
        ``before``) that the replicate prediction closes stands out of the noise: its z, the
        reference's z less the ceiling's (the same standard error over the same blocks), passes
        the metric's threshold. True without replicates (the whole gap is reproducible)."""
        if self.ceiling is None:
            return True
        threshold = getattr(self.strategy.metric, "z_significant", Z_HELD_OUT)
        return bool(before["z"] - self.ceiling["selection"]["z"] > threshold)

    def shrink_se(self, before: dict[str, Any], after: dict[str, Any]) -> float:
        """Standard error of the shrink 1 - gap_after / gap_before on the scoring part: block
        bootstrap (``SHRINK_BLOCKS`` contiguous blocks of its samples, the same ``SHRINK_REPLICATES``
        seeded resamples for every candidate) of the metric's per-sample terms, before and after
        on the same samples; NaN when the two models' complete samples differ."""
        a, b = after["terms"], before["terms"]
        if a.shape != b.shape or a.shape[0] < SHRINK_BLOCKS:
            return float("nan")
        blocks = np.array_split(np.arange(a.shape[0]), SHRINK_BLOCKS)
        sums_a = np.array([a[i].sum(axis=0) for i in blocks])
        sums_b = np.array([b[i].sum(axis=0) for i in blocks])
        metric = self.strategy.metric
        with np.errstate(invalid="ignore", divide="ignore"):
            shrinks = 1.0 - metric.combine(sums_a[self.resamples].sum(axis=1)) / metric.combine(
                sums_b[self.resamples].sum(axis=1))
        shrinks = shrinks[np.isfinite(shrinks)]
        return float(np.std(shrinks, ddof=1)) if shrinks.size > 1 else float("nan")


def _simulate_records(model, thetas: np.ndarray, measurements: Sequence[Measurement], channels: Sequence[str],
                      names: Sequence[str], strategy: DiagnosisStrategy | None = None,
                      share_steps: bool = False) -> list[list[ResidualRecord]]:
    """Records per parameter set: [set][measurement] ResidualRecord; one batched call per
    measurement, with the record's own design constants when the strategy gives them
    (``share_steps``: one step sequence for the whole batch, for finite differences)."""
    thetas = np.atleast_2d(thetas)
    idx = model.output_index(channels)
    per_set: list[list[ResidualRecord]] = [[] for _ in range(thetas.shape[0])]
    for name, m in zip(names, measurements):
        inputs = m.experiment.input_matrix(model)
        constants = None if strategy is None else strategy.constants_of(m)
        out = simulate_batch(model, thetas, m.time, inputs, constants=constants, share_steps=share_steps)
        observed = m.select(channels).values
        for s in range(thetas.shape[0]):
            per_set[s].append(ResidualRecord(name, m.time, inputs, observed, out[s][:, idx], out[s]))
    return per_set
