"""Which unmodelled effect causes the sim-to-real gap, and how much of it does it explain?

One procedure for every concept; what differs between concepts (fitted channels and design
constants, fit settings, start grid, gap metric, localisation, thresholds, a reference fit
held for fault diagnosis) comes from its :class:`~ema_uq.gap.strategy.DiagnosisStrategy`.
The figures below are those of the default strategy (the synthetic actuator concepts); EMPS
(:data:`ema_uq.rigs.emps.EMPS_STRATEGY`) refits every parameter from a three-point start
grid, measures the gap as the benchmark's validation force error, ranks by ΔBIC alone and runs
two forward-selection rounds.

Procedure (``diagnose``):

1. Held-out data: the ``validation`` measurements when given; otherwise the last
   ``holdout_fraction`` (30 %) of every estimation record is held out — the first 70 % is
   fitted, and the held-out part is predicted by simulating the whole record from rest.
   The held-out data are split in a *selection* part, which chooses the winner (held-out
   gain, selection shrink, significance: everything the verdict reads), and a *scoring*
   part, on which the shrink is reported: with two or more held-out records the last one
   scores and the others select; with one, its complete samples are split in time halves
   (the first selects, the second scores).
2. Nominal ML fit (det R, Gauss-Newton) on the estimation data from the nominal values
   (parameters the channels cannot determine — no effect on them, or a singular direction
   of the information matrix, e.g. k_n without a current channel — are held at their nominal
   values here and in every refit), and
   localisation of its residual (:mod:`ema_uq.gap.localize`) on the estimation and on the
   held-out data; ``where`` and the signature matches come from the one with the larger
   systematic z (a gap that only extrapolation reveals shows on held-out data).
3. Every candidate effect of the concept's catalogue: the augmented model
   (``Model.with_effects``) is refitted by ML, warm-started from the nominal estimate for
   the base parameters and from ``Effect.start`` for the effect parameters (the best of a
   small start grid — magnitudes at 0.3, 1, 3 and 10 times ``Effect.start``, phases at four
   points of a turn — evaluated in one batched simulator call, then refined by one pass of
   fine 1-D profiles of each effect parameter but phases between its neighbouring grid points,
   ``PROFILE_POINTS`` (17) each; an effect with a phase is refitted from the grid point too and
   the better fit kept). Screening refit: the effect
   parameters and the ``screen_base_parameters`` (6) base parameters most aliased with them
   (largest |correlation| in the information matrix at the start) are free, Gauss-Newton
   capped at ``candidate_max_iterations`` (Levenberg-Marquardt when a Gauss-Newton step goes
   singular, or finishing a Gauss-Newton fit whose step halving ran out early, as for the
   nominal fit). Final refit of the ``final_candidates`` (2) best-screened candidates: every
   parameter free, from the screening estimate, capped at ``final_max_iterations``; their
   scores and Cramér-Rao std come from it (``CandidateScore.stage``), the others' from the
   screening (a lower bound of what a full refit reaches).
4. Scores per candidate (N = estimation samples, k = effect parameters, V = negative log-likelihood):
   likelihood ratio LR = 2 (V_nominal - V_candidate) = N Δ log det R (+ rig-prior change),
   ΔBIC = LR - k ln N, held-out gain G = N_sel (log det R_sel,nominal - log det R_sel,candidate)
   on the selection part, the selection shrink 1 - after / before of the gap there, the gap
   before/after on the scoring part and the *shrink* = 1 - after / before there (signed, not
   clipped: a candidate that widens the gap has a negative shrink) with its standard error
   (block bootstrap: the scoring part's samples in ``SHRINK_BLOCKS`` (20) contiguous blocks,
   ``SHRINK_REPLICATES`` (400) resamples of the blocks' sums of the metric's per-sample terms,
   before and after on the same resampled samples, seeded by the diagnosis seed, else 0; the
   metric's factor split is held at its fit on the whole part), and the signature match
   m in [0, 1] (:meth:`Localization.signature_match`). Where the records repeat one experiment
   (``DiagnosisStrategy.replicate_prediction``: the Cranfield rig's cycle), the *reproducible
   shrink* (before - after) / (before - ceiling) on the selection part, the ceiling being the
   gap left by the replicate mean of the nominal model's estimation residual: the best any
   time-invariant model learnt from the estimation records could do, so a gap that changes
   from run to run (a drifting rig) is not asked of a fixed-parameter effect (the lack-of-fit
   and pure-error split of regression with replicates); without replicates it is the
   selection shrink. Ranking score::

       score = (ΔBIC + G) · (1 + SIGNATURE_WEIGHT · m)     (when ΔBIC + G > 0, else ΔBIC + G)

5. Forward selection (``DiagnosisSettings.max_effects`` rounds, default 1): when a round's
   best candidate passes the ``effect`` test below, it joins the model, and the remaining
   candidates (less the other forms of its family) are added to that model and scored
   against it in the next round.
6. Verdict (:mod:`ema_uq.gap.verdict`, open-set: the catalogue may not hold the cause):
   ``effect`` only when the best candidate passes the effect test of the aggregate gap
   (ΔBIC > ``BIC_MIN``, G > ``HELD_OUT_GAIN_MIN`` and, if the nominal model's gap on the
   selection part is significant, a reproducible shrink ≥ ``SHRINK_MIN`` of a reproducible
   part that is itself significant), *and* its family beats every other family and the nominal
   model by 2 ln B ≥ ``Thresholds.margin_evidence`` (10) in family probability (evidence ΔBIC + G tempered
   by the effective-sample fraction of the best model's residual), *and* its held-out residual
   leaves no cell — channel, stroke bin, direction, regime, frequency band — that carried a
   material part of the gap and that it did not halve (:mod:`ema_uq.gap.structure`). Its
   confidence is ``high`` when the reproducible shrink is ≥ ``SHRINK_CONFIDENT`` (or the gap
   insignificant) and the augmented model's residual passes every residual test of the
   localisation, on estimation and held-out data; else ``low``. A passing candidate that fails
   the margin gives ``ambiguous`` (the families within the margin, with their probabilities)
   when one of them leaves no structure, else ``unexplained``; one that wins the margin but
   leaves structure gives ``unexplained`` with the cells left (GAP.json ``where_left``).
   Without a passing candidate: ``unexplained`` when the nominal residual is structured
   (Ljung-Box, bias against each record's own noise, input cross-correlation, common error
   factors or systematic energy, family-wise level 0.001) on the estimation data, or on the
   held-out data less the prediction error the fit's own parameter uncertainty explains
   (:meth:`_Diagnosis.without_estimation_error`), or the gap on the selection part is
   significant, or the best candidate has ΔBIC > ``BIC_MIN`` (it fits structure in the
   estimation data that fails on held-out data); else ``none``: the noise explains the residual.
   The winner's figures (``gap.after``, ``effect_parameters``, ``localization_after``) are
   those of the best-ranked candidate whatever the verdict. GAP.json ``gap``: ``before`` and
   ``after`` on all held-out data; ``shrink``, ``shrink_se`` (scored on ``shrink_record``),
   ``selection_shrink`` and ``reproducible_shrink`` only for an ``effect`` verdict (null
   otherwise); with replicates also ``ceiling_gap_selection``/``ceiling_gap_scoring``,
   ``reproducible_share`` (1 - ceiling / before on the selection part), ``reproducible_z`` and
   ``reproducible_significant``. Beside it ``family_probabilities``, ``evidence_tempering``,
   ``margin_evidence``, ``contenders``, ``structure_left``, ``where_left`` and ``verdict_reason``.

Gap metric: the held-out *systematic NRMSE* (:func:`ema_uq.gap.localize.systematic_nrmse`):
per channel the model-error mean square — the part of the residual that channels share
(factor analysis, q by BIC; sensor noise is independent across channels) plus each
channel's own low-frequency part (short-lag products), both unbiased under white
noise — over the channel's mean square (RMS normalisation: every channel's noise of x % of
its RMS weighs alike), averaged over channels, square root: the NRMSE of the model error
with the noise removed, so that a perfect model scores about 0 whatever the noise level.
The held-out gap is *significant* when common factors are found or the lag z exceeds
``Z_HELD_OUT``. The plain held-out NRMSE and log det R are reported beside it.

Frozen thresholds (calibrated on self-check cases with seeds 100-103, never on the
self-check's own seeds): ``BIC_MIN`` = 25, ``HELD_OUT_GAIN_MIN`` = 25, ``SHRINK_MIN`` = 0.5,
``SHRINK_CONFIDENT`` = 0.8, ``MARGIN_EVIDENCE`` = 10, ``Z_HELD_OUT`` = 5, ``SIGNATURE_WEIGHT`` = 0.25.
On the calibration cases the true effect's ΔBIC was 500-25000 and the best wrong
candidate's at most 660 (on an out-of-catalogue case, then without held-out shrink).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from typing import Any, Callable, Sequence

import numpy as np

from .. import statistics
from ..experiments import Measurement
from ..identify import FitProblem, FitResult, IdentificationError, Settings, SingularInformationError, estimate
from ..models import get_model
from ..params import ParameterError
from ..simulate import SimulationError, simulate_batch
from .localize import ResidualRecord, complete_runs, noise_std
from .result import CandidateScore, GapResult
from .strategy import DiagnosisSettings, DiagnosisStrategy, Thresholds, strategy_for
from ..errors import EmaUqError
from .predictable import state_predictable
from .structure import cell_energies, cell_masks, structure_left, where_left
from .verdict import (effective_sample_fraction, family_probabilities, passes as _passes,
                      reproducible_shrink as _reproducible_shrink, verdict as _open_verdict)

_DEFAULT = Thresholds()
BIC_MIN = _DEFAULT.bic_min
HELD_OUT_GAIN_MIN = _DEFAULT.held_out_gain_min
SHRINK_MIN = _DEFAULT.shrink_min
SHRINK_CONFIDENT = _DEFAULT.shrink_confident
MARGIN_EVIDENCE = _DEFAULT.margin_evidence
SIGNATURE_WEIGHT = _DEFAULT.signature_weight
Z_HELD_OUT = 5.0
PHASE_STARTS = statistics.PHASE_STARTS
MAX_GRID = statistics.MAX_GRID
# points of each effect parameter's fine start profile (:func:`_profiled_start`): steps of 1.16x
# between the neighbouring points (x/3.3, x3.3) of the default grid
PROFILE_POINTS = 17
# a held-out prediction this many times the measured RMS (or not finite) has diverged: the
# candidate's fit is unstable away from the estimation profile and cannot be scored
DIVERGED_RELATIVE = 1e6
SINGULAR_RELATIVE = 1e-10
SHRINK_BLOCKS = 20          # contiguous blocks of the scoring part resampled for the shrink's standard error
SHRINK_REPLICATES = 400
SHRINK_SEED = 0             # bootstrap seed when the diagnosis is given none

__all__ = ["CandidateScore", "DiagnosisSettings", "DiagnosisStrategy", "GapError", "GapResult", "diagnose",
           "split_holdout"]


class GapError(EmaUqError):
    """Data the gap diagnosis cannot use (concept mismatch, no common channel, no catalogue)."""


# ----------------------------------------------------------------------------------------
# data preparation
# ----------------------------------------------------------------------------------------
def _check_inputs(measurements: Sequence[Measurement], validation: Sequence[Measurement]) -> str:
    if not measurements:
        raise GapError("no estimation data given; pass at least one measurement file")
    concepts = {m.concept for m in measurements}
    if len(concepts) != 1:
        raise GapError(f"estimation data mix concepts {sorted(concepts)}; diagnose one concept at a time")
    concept = measurements[0].concept
    other = sorted({m.concept for m in validation} - {concept})
    if other:
        raise GapError(f"validation data are of concept {', '.join(other)} but the estimation data are {concept}; "
                       f"give validation data of concept {concept}")
    return concept


def _common_channels(measurements: Sequence[Measurement]) -> list[str]:
    return [c for c in measurements[0].channels if all(c in m.channels for m in measurements)]


def split_holdout(measurements: Sequence[Measurement], fraction: float) -> tuple[list[Measurement], list[Measurement]]:
    """(estimation part, held-out part) of each record: the first ``1 - fraction`` of the
    samples, and the whole record with those samples masked (NaN), so that the held-out part
    is predicted by simulating from rest through the estimation part."""
    if not 0 < fraction < 1:
        raise GapError(f"held-out fraction must be in (0, 1), got {fraction}")
    est, held = [], []
    for m in measurements:
        cut = int(round((1.0 - fraction) * m.experiment.n_samples))
        if cut < 100 or m.experiment.n_samples - cut < 100:
            raise GapError(f"record {m.experiment.name!r} has {m.experiment.n_samples} samples, too few to hold "
                           f"{fraction:.0%} out; give longer records or --validate data")
        est.append(Measurement(m.concept, m.experiment.slice(0, cut), m.channels, m.values[:cut], m.attrs))
        masked = m.values.copy()
        masked[:cut] = np.nan
        held.append(Measurement(m.concept, m.experiment, m.channels, masked, m.attrs))
    return est, held


@dataclass
class _Split:
    """Estimation and held-out records, their channels, record names and channel scales."""

    estimation: list[Measurement]
    held: list[Measurement]
    channels: list[str]
    held_channels: list[str]
    description: str
    est_names: list[str] = field(init=False)
    held_names: list[str] = field(init=False)
    est_spread: np.ndarray = field(init=False)
    held_spread: np.ndarray = field(init=False)

    parts: dict[str, list[np.ndarray]] = field(init=False)
    shrink_record: str = field(init=False)

    def __post_init__(self) -> None:
        self.est_names = [f"estimation {i + 1}: {m.experiment.name}" for i, m in enumerate(self.estimation)]
        self.held_names = [f"held-out {i + 1}: {m.experiment.name}" for i, m in enumerate(self.held)]
        self.est_spread = _spread(self.estimation, self.channels)
        self.held_spread = _spread(self.held, self.held_channels)
        self.parts, self.shrink_record = _selection_and_scoring(self.held, self.held_channels)

    def part(self, records: Sequence[ResidualRecord], part: str):
        """(records, measurements) of the held-out ``part``: "all", "selection" (chooses the
        winner) or "scoring" (scores its shrink); samples outside the part are NaN."""
        if part == "all":
            return list(records), list(self.held)
        kept = [(replace(r, observed=np.where(mask[:, None], r.observed, np.nan)), m)
                for r, m, mask in zip(records, self.held, self.parts[part]) if mask.any()]
        return [r for r, _ in kept], [m for _, m in kept]


def _selection_and_scoring(held: Sequence[Measurement], channels: Sequence[str]):
    """Sample masks of the held-out records that select the winner and that score its shrink,
    and what the scoring part is: with two or more held-out records the last one scores and
    the others select; with one, its complete samples are split in time halves (the first
    selects, the second scores)."""
    valid = [np.all(np.isfinite(m.select(channels).values), axis=1) for m in held]
    if len(held) > 1:
        selection = [v if i < len(held) - 1 else np.zeros_like(v) for i, v in enumerate(valid)]
        scoring = [np.zeros_like(v) if i < len(held) - 1 else v for i, v in enumerate(valid)]
        return {"selection": selection, "scoring": scoring}, f"held-out record {held[-1].experiment.name}"
    rows = np.flatnonzero(valid[0])
    cut = rows[rows.size // 2]
    first = valid[0] & (np.arange(valid[0].size) < cut)
    time = held[0].time
    return ({"selection": [first], "scoring": [valid[0] & ~first]},
            f"second half of held-out record {held[0].experiment.name} (t >= {time[cut] - time[0]:.3g} s)")


def _split(measurements: list[Measurement], validation: list[Measurement], strategy: DiagnosisStrategy,
           settings: DiagnosisSettings) -> _Split:
    """Step 1, the hold-out split: the validation records, else the end of every estimation record."""
    common = _common_channels(measurements)
    channels = [c for c in strategy.channels if c in common] if strategy.channels else common
    if not channels:
        raise GapError("the estimation data share no output channel; give files with at least one common channel"
                       if not strategy.channels else
                       f"the estimation data lack the channels {', '.join(strategy.channels)} the {strategy.name} "
                       "diagnosis fits; give files that measure them")
    if not validation:
        estimation, held = split_holdout(measurements, settings.holdout_fraction)
        return _Split(estimation, held, channels, channels,
                      f"last {settings.holdout_fraction:.0%} of each estimation record")
    held_channels = [c for c in channels if all(c in v.channels for v in validation)]
    if not held_channels:
        raise GapError(f"the validation data have no channel in common with the estimation data "
                       f"({', '.join(channels)}); give validation files that measure at least one of them")
    return _Split(measurements, validation, channels, held_channels,
                  "validation data (" + ", ".join(v.experiment.name for v in validation) + ")")


def _spread(measurements: Sequence[Measurement], channels: Sequence[str]) -> np.ndarray:
    """Per-channel RMS of the measured values (the scale the gap is expressed in)."""
    values = np.concatenate([m.select(channels).values for m in measurements])
    spread = np.sqrt(np.nanmean(values ** 2, axis=0))
    return np.where(spread > 0, spread, 1.0)


# ----------------------------------------------------------------------------------------
# the state of one diagnosis
# ----------------------------------------------------------------------------------------
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
    healthy_cells: dict[str, Any] | None = None         # cells of the reference on the strategy's healthy records
    predictable: Any = None                             # what the state predicts of the nominal's held-out gap
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


# ----------------------------------------------------------------------------------------
# candidates
# ----------------------------------------------------------------------------------------
def _catalogue(model) -> dict[str, Any]:
    """The concept's candidate effects, name -> Effect (``Model.effect_catalogue``), less the
    compounds that carry another family's mechanism (``Effect.combines``): a candidate is one
    mechanism."""
    catalogue = {name: effect for name, effect in (getattr(model, "effect_catalogue", None) or {}).items()
                 if not getattr(effect, "combines", ())}
    if not catalogue or not hasattr(model, "with_effects"):
        raise GapError(f"concept {model.name} has no catalogue of unmodelled effects; the gap diagnosis needs one")
    return catalogue


def _effect_parameter_names(augmented, base) -> list[str]:
    return [n for n in augmented.parameters.names if n not in base.parameters.names]


def _is_phase(name: str, parameter) -> bool:
    """An angle on a turn (its start grid spans the turn, not multiples of the start)."""
    return parameter.unit == "rad" and "phase" in name


def _start_grid(augmented, base_values, effect, names: Sequence[str],
                multiples: Sequence[float] = statistics.START_MULTIPLES) -> np.ndarray:
    """Full start vectors (n_starts, n_params): base parameters at ``base_values`` (the reference
    fit), effect parameters on the grid of :func:`ema_uq.statistics.start_values` around
    ``Effect.start`` (every combination when at most ``MAX_GRID``, else one at a time)."""
    params = augmented.parameters
    start = dict(getattr(effect, "start", {}) or {})
    centre = params.vector({**{k: v for k, v in base_values.items() if k in params},
                            **{n: start[n] for n in names if n in start}})
    values = [statistics.start_values(centre[params.index(n)], params[n].lower, params[n].upper,
                                      phase=_is_phase(n, params[n]), multiples=multiples,
                                      phase_starts=PHASE_STARTS) for n in names]
    return statistics.start_grid(centre, [params.index(n) for n in names], values, MAX_GRID)


def _profiled_start(problem: FitProblem, start: np.ndarray, prediction: np.ndarray, objective: float,
                    params, names: Sequence[str], multiples: Sequence[float]) -> tuple[np.ndarray, np.ndarray, int]:
    """The grid's best start refined by one pass of fine 1-D profiles: each effect parameter in
    turn at ``PROFILE_POINTS`` geometric steps from its value over to its neighbouring grid
    points (÷ and × the grid's widest step), the others held, the best point kept. Why: the
    objective of a play is ragged at finer spacing than the grid's factor of 3 (contact
    switches a step earlier or later), and Gauss-Newton stops in the first dip: an LT/HS nut
    play of the seed-2 self-check has its profile minimum at 2.2x the best grid point, and the
    refit from that point stopped at 1x.
    Phases stay at their grid value (they have their own grid over the turn).
    Returns (start, its prediction, simulations run)."""
    ordered = np.sort(np.asarray(multiples, dtype=float))
    step = float(np.max(ordered[1:] / ordered[:-1])) if ordered.size > 1 else 1.0
    if step <= 1.0:
        return start, prediction, 0
    sims = 0
    for name in names:
        i, parameter = params.index(name), params[name]
        if start[i] <= 0 or _is_phase(name, parameter):
            continue
        values = np.unique(np.clip(start[i] * np.geomspace(1.0 / step, step, PROFILE_POINTS),
                                   parameter.lower, parameter.upper))
        trial = np.repeat(start[None], values.size, axis=0)
        trial[:, i] = values
        k, score, predicted = _best_point(problem, trial)
        sims += values.size
        if score < objective:
            start, prediction, objective = trial[k], predicted[k], score
    return start, prediction, sims


def _best_point(problem: FitProblem, thetas: np.ndarray) -> tuple[int, float, np.ndarray]:
    """(index, V, predictions of all sets) of the set of ``thetas`` with the lowest objective,
    one batched simulator call; sets that simulate to NaN count as infinitely bad."""
    predicted = problem.predict(thetas)
    objectives = [problem.objective(problem.observed - predicted[i], thetas[i, problem.free_index])[0]
                  for i in range(thetas.shape[0])]
    best = _finite_argmin(objectives)
    return best, float(objectives[best]), predicted


def _finite_argmin(values: Sequence[float]) -> int:
    """Index of the smallest value, NaN counting as infinitely large."""
    values = np.asarray(values, dtype=float)
    return int(np.argmin(np.where(np.isfinite(values), values, np.inf)))


def _full_objective(problem: FitProblem, theta: np.ndarray, log_det_r: float) -> float:
    """V of ``problem`` at ``theta`` given log det R there, the rig terms over its free
    parameters, so that fits with different free sets compare."""
    return statistics.objective(problem.n_samples, log_det_r, theta[problem.free_index], problem.parameters,
                                problem.free_index)


def _stepped_sets(theta: np.ndarray, index: np.ndarray, relative: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Parameter sets for relative forward differences: (thetas, h, scale) with thetas row 0 =
    ``theta`` and row 1 + i = ``theta`` with entry ``index[i]`` raised by h_i = ``relative`` x
    scale_i, scale = |value| (1 where the value is 0)."""
    scale = np.where(np.abs(theta[index]) > 0, np.abs(theta[index]), 1.0)
    h = relative * scale
    thetas = np.repeat(theta[None], index.size + 1, axis=0)
    thetas[1 + np.arange(index.size), index] += h
    return thetas, h, scale


def _relevant_base(problem: FitProblem, theta: np.ndarray, predicted: np.ndarray, effect_names: Sequence[str],
                   count: int) -> list[str]:
    """The ``count`` base parameters most aliased with the effect parameters at ``theta``: largest
    |correlation| in the information metric (forward differences, one batched simulator call)."""
    params = problem.parameters
    idx = problem.free_index
    thetas, h, scale = _stepped_sets(theta, idx, 1e-5)    # the base prediction is given: row 0 not run
    sens = (problem.predict(thetas[1:]) - predicted[None]) / (h / scale)[:, None, None]     # (p, N, m)
    residual = problem.observed - predicted
    r_inv = np.linalg.inv(residual.T @ residual / residual.shape[0])
    info = statistics.information(sens, r_inv)
    d = np.sqrt(np.maximum(np.diag(info), 1e-300))
    corr = np.abs(info / np.outer(d, d))
    names = [params.names[i] for i in idx]
    eff = [names.index(n) for n in effect_names]
    relevance = {n: float(np.max(corr[j, eff])) for j, n in enumerate(names) if n not in effect_names}
    return sorted(relevance, key=lambda n: -relevance[n])[:count]


def _unidentifiable_parameters(problem: FitProblem, theta: np.ndarray) -> list[str]:
    """Free parameters the fitted channels cannot determine at ``theta``: those that move no
    channel, then, while the information matrix (relative sensitivities, forward differences
    in one batched call, R of the residual at ``theta``) has a direction with eigenvalue below
    ``SINGULAR_RELATIVE`` of the largest, the parameter weighing most in it (rig-measured
    gains last). E.g. k_n without a current channel, or the friction split without torque channels."""
    names = problem.parameters.names
    idx = problem.free_index
    thetas, h, scale = _stepped_sets(theta, idx, 1e-4)
    predicted = problem.predict(thetas, share_steps=True)     # row 0, the base, sets the steps
    sens = (predicted[1:] - predicted[0][None]) / (h / scale)[:, None, None]
    residual = problem.observed - predicted[0]
    r_inv = np.linalg.inv(residual.T @ residual / residual.shape[0])
    info = statistics.information(sens, r_inv)
    fixed = [names[i] for j, i in enumerate(idx) if not np.any(sens[j])]
    while True:
        keep = [j for j, i in enumerate(idx) if names[i] not in fixed]
        if len(keep) < 2:
            break
        evals, evecs = np.linalg.eigh(info[np.ix_(keep, keep)])
        if evals[0] > SINGULAR_RELATIVE * evals[-1]:
            break
        weight = np.abs(evecs[:, 0]) * [0.5 if problem.parameters.parameters[idx[j]].prior_std else 1.0 for j in keep]
        fixed.append(names[idx[keep[int(np.argmax(weight))]]])
    return fixed


def _robust_estimate(problem: FitProblem, start: np.ndarray, settings: Settings) -> FitResult:
    """Gauss-Newton, retried by Levenberg-Marquardt when a step goes singular: an effect
    parameter at a bound where another loses its effect (an amplitude at its off bound leaves
    its phase free, Stribeck Fs = 0 leaves v_s free) makes the Gauss-Newton matrix singular,
    which the damping survives. When the start itself cannot separate some freed base
    parameter (a reduced sensor set: on the LT/HS rig sensors C_TS2 alone), those parameters are
    held at their start values as ``identify`` does (named in the fit) rather than losing the
    candidate. A Gauss-Newton fit that stops early without converging (its step halving
    exhausted while the model still promised a decrease: on the LT/HS rig sensors a nominal fit
    stopped after 2 of 30 iterations 12 500 short in 2V of its minimum, and every candidate was
    then credited with finishing that descent) is continued by Levenberg-Marquardt for the
    remaining iterations."""
    try:
        fit = estimate(problem, method="gn", start=start, settings=settings)
    except (IdentificationError, np.linalg.LinAlgError):
        return _levenberg_marquardt(problem, start, settings)
    if fit.converged or fit.iterations >= settings.max_iterations:
        return fit
    rest = replace(settings, max_iterations=settings.max_iterations - fit.iterations)
    try:
        more = _levenberg_marquardt(problem, fit.estimate, rest)
    except (IdentificationError, np.linalg.LinAlgError):
        return fit
    if not more.objective < fit.objective:
        return fit
    return replace(more, start=fit.start, iterations=fit.iterations + more.iterations,
                   n_simulations=fit.n_simulations + more.n_simulations,
                   wall_time_s=fit.wall_time_s + more.wall_time_s,
                   message=f"{more.message} (Levenberg-Marquardt after Gauss-Newton stopped: {fit.message})")


def _levenberg_marquardt(problem: FitProblem, start: np.ndarray, settings: Settings) -> FitResult:
    try:
        return estimate(problem, method="lm", start=start, settings=settings)
    except SingularInformationError:
        return estimate(problem, method="lm", start=start, settings=settings, unidentifiable="fix")


def _refit(run: _Diagnosis, reference: _Reference, name: str, effect, start: np.ndarray | None = None,
           screening: bool = True):
    """ML refit of the reference model augmented by one effect.

    Screening (default): start from the best point of the start grid refined by
    :func:`_profiled_start` (for an effect with a phase, from the grid point too, the better fit
    kept), free the effect parameters and the ``screen_base_parameters`` most aliased base
    ones, Gauss-Newton capped at ``candidate_max_iterations`` (every parameter free when
    ``screen_base_parameters`` is None).
    Otherwise (the leaders' final refit): every parameter free from ``start``, capped at
    ``final_max_iterations``. Parameters the channels cannot determine, and with ``hold_base``
    every base parameter, stay held. Returns (augmented model, effect parameter names,
    FitResult, V of the estimate with every free parameter counted).
    """
    settings, base = run.settings, run.root
    augmented = base.with_effects(reference.effects + [name])
    names = _effect_parameter_names(augmented, reference.model)
    fixed = run.fixed
    problem = FitProblem(model=augmented, parameters=augmented.parameters.fixing(fixed), **run.problem_args)
    n_extra = 0
    starts = [(start, None)]
    if start is None:
        grid = _start_grid(augmented, reference.fit.as_dict(), effect, names, run.strategy.start_multiples)
        best, objective, predicted = _best_point(problem, grid)
        profiled, profiled_prediction, sims = _profiled_start(problem, grid[best], predicted[best], objective,
                                                              augmented.parameters, names,
                                                              run.strategy.start_multiples)
        n_extra += grid.shape[0] + sims
        starts = [(profiled, profiled_prediction)]
        if any(_is_phase(n, augmented.parameters[n]) for n in names) and not np.array_equal(profiled, grid[best]):
            # an amplitude profiled at a grid phase settles where that phase is least wrong, and the
            # refit from there can stop in a worse minimum than from the grid point (seed-2 HT/LS
            # ripple with harmonics: ΔBIC 2 549 against 11 333), or a better one (seed-2 LT/HS rig
            # ripple with harmonics: named only from the profile); both are refitted
            starts.append((grid[best], predicted[best]))
    fits = [_screened_fit(run, problem, augmented, names, s, p, screening) for s, p in starts]
    objectives = [_full_objective(problem, f.estimate, f.log_det_r) for f in fits]
    k = _finite_argmin(objectives)
    fit = fits[k]
    fit.n_simulations = sum(f.n_simulations for f in fits) + n_extra
    return augmented, names, fit, objectives[k]


def _screened_fit(run: _Diagnosis, problem: FitProblem, augmented, names: Sequence[str], start: np.ndarray,
                  start_prediction: np.ndarray | None, screening: bool) -> FitResult:
    """One refit of :func:`_refit` from ``start``; ``start_prediction`` (the simulated outputs
    there, known from the start search) picks the base parameters a screening refit frees, and
    is None for the final refit, which frees every parameter."""
    settings, base, fixed = run.settings, run.root, run.fixed
    fit_problem, cap, n_extra = problem, settings.final_max_iterations, 0
    if screening:
        cap = settings.candidate_max_iterations
        count = settings.screen_base_parameters
        if count is not None and count < len(base.parameters) and not run.strategy.hold_base:
            keep = [n for n in _relevant_base(problem, start, start_prediction, names, count + len(fixed))
                    if n not in fixed][:count]
            n_extra += problem.free_index.size
            fit_problem = FitProblem(model=augmented, parameters=augmented.parameters.freeing_only(keep + names),
                                     **run.problem_args)
    fit = _robust_estimate(fit_problem, start, Settings(tolerance=settings.tolerance, max_iterations=cap))
    fit.n_simulations += n_extra
    return fit


def _parameter_table(model, fit: FitResult, names: Sequence[str]) -> dict[str, dict[str, float]]:
    """{name: {"estimate", "std" (Cramér-Rao), "unit"}} of parameters ``names`` of a fit."""
    return {p: {"estimate": fit.value(p), "std": float(fit.std[fit.names.index(p)]),
                "unit": model.parameters[p].unit} for p in names}


# ----------------------------------------------------------------------------------------
# the steps of the diagnosis
# ----------------------------------------------------------------------------------------
def _held_base_fit(run: _Diagnosis, theta: np.ndarray) -> FitResult:
    """The nominal model at the reference fit, evaluated (no parameter fitted): fault diagnosis."""
    problem = FitProblem(model=run.root, **run.problem_args)
    residual = problem.residuals(theta[None])[0]
    r = statistics.covariance(residual)
    logdet = statistics.log_det_r(r)
    p = run.root.parameters
    return FitResult(run.root.name, "held", tuple(p.names), tuple(q.unit for q in p.parameters),
                     np.zeros(len(p), dtype=bool), theta.copy(), theta.copy(), np.zeros(len(p)), np.zeros((0, 0)),
                     tuple(problem.channels), r, logdet, statistics.objective(problem.n_samples, logdet),
                     problem.n_samples, True, "base parameters held at the reference fit", 0, 1, 0.0)


def _fit_nominal(run: _Diagnosis):
    """Step 2: the nominal ML fit on the estimation data (or, holding the base parameters, the
    reference fit evaluated there) and the localisation of its residual on the estimation and
    the held-out data. Returns (reference, localisation on estimation, on held-out data)."""
    d, strategy, settings, base = run.data, run.strategy, run.settings, run.root
    run.problem_args = {"measurements": d.estimation, "channels": d.channels}
    if strategy.constants is not None:
        run.problem_args["constants"] = strategy.constants(d.estimation[0])
    reference = {k: v for k, v in (strategy.reference_fit or {}).items() if k in base.parameters}
    start = base.parameters.vector(reference)
    problem = FitProblem(**run.problem_args)
    run.n_samples = problem.n_samples
    if strategy.hold_base:
        run.fixed = list(base.parameters.names)
        run.say(f"{base.name} held at the reference fit; {problem.n_samples} samples x {len(d.channels)} channels")
        nominal = _held_base_fit(run, start)
    else:
        run.fixed = _unidentifiable_parameters(problem, start)
        run.n_sims += problem.free_index.size + 1
        if run.fixed:
            problem = FitProblem(parameters=base.parameters.fixing(run.fixed), **run.problem_args)
        run.say(f"nominal ML fit of {base.name} on {problem.n_samples} samples x {len(d.channels)} channels"
                + (f" ({', '.join(run.fixed)} held at nominal: these channels cannot determine them)"
                   if run.fixed else ""))
        nominal = _robust_estimate(problem, start, Settings(tolerance=settings.tolerance,
                                                            max_iterations=settings.nominal_max_iterations))
    run.n_sims += nominal.n_simulations
    est_records = run.records(base, nominal.estimate, held=False)
    held_records = run.records(base, nominal.estimate, held=True)
    run.n_sims += len(d.estimation) + len(d.held)
    loc_est = run.localise(base, nominal.estimate, est_records, held=False)
    loc_held = run.localise(base, nominal.estimate, run.without_estimation_error(base, nominal, held_records),
                            held=True)
    before = run.parts(base, held_records, nominal.estimate)
    before["all"] = run.held_out_figures(base, held_records)
    run.ceiling = run.ceiling_of(base, est_records, held_records)
    columns = [d.channels.index(c) for c in d.held_channels]
    run.predictable = state_predictable([replace(r, observed=r.observed[:, columns], predicted=r.predicted[:, columns])
                                         for r in est_records], held_records, d.held_spread)
    if strategy.healthy_records:
        healthy = list(strategy.healthy_records)
        names = [f"healthy {i + 1}: {m.experiment.name}" for i, m in enumerate(healthy)]
        records = _simulate_records(base, nominal.estimate, healthy, d.held_channels, names, strategy)[0]
        run.n_sims += len(healthy)
        constants = strategy.constants_of(healthy[0])
        run.healthy_cells = cell_energies(records, d.held_channels, d.held_spread,
                                          cell_masks(records, base, nominal.estimate,
                                                     base.constants_vector() if constants is None else constants))
    run.say(f"nominal: log det R {nominal.log_det_r:.4g}, held-out gap {before['all']['gap']:.4g} "
            f"(z {before['all']['z']:.1f}); {'structured' if loc_est.structured else 'white'} residual")
    return _Reference(base, nominal, nominal.objective, before, []), loc_est, loc_held


def _score(run: _Diagnosis, reference: _Reference, name: str, effect, refit, seconds: float, stage: str,
           loc) -> tuple[CandidateScore, dict[str, Any]]:
    """Step 5: one refitted candidate's scores against the reference (module docstring, step 4)
    and its held-out figures (selection and scoring part)."""
    augmented, names, fit, objective = refit
    th = run.strategy.thresholds
    before = reference.figures
    lr = 2.0 * (reference.objective - objective)
    delta_bic = lr - len(names) * np.log(run.n_samples)
    held_records = run.records(augmented, fit.estimate, held=True)
    _check_not_diverged(held_records, run.data.held_spread)
    after = run.parts(augmented, held_records)
    chosen, scored = (before["selection"], after["selection"]), (before["scoring"], after["scoring"])
    gain = chosen[1]["n"] * (chosen[0]["log_det_r"] - chosen[1]["log_det_r"])
    selection_shrink, shrink = (1.0 - a["gap"] / b["gap"] if b["gap"] > 0 else 0.0 for b, a in (chosen, scored))
    reproducible = _reproducible_shrink(chosen[0]["gap"], chosen[1]["gap"], run.ceiling_gap("selection"))
    match = loc.signature_match(tuple(getattr(effect, "signature", ()) or ()))
    raw = delta_bic + gain if th.gain_in_score else delta_bic
    score = raw * (1.0 + th.signature_weight * match) if raw > 0 else raw
    of_reproducible = "" if run.ceiling is None else f", {reproducible:.2f} of its reproducible gap"
    run.say(f"  {name} ({stage}): dBIC {delta_bic:.1f}, held-out gain {gain:.1f}, shrink {selection_shrink:.2f} "
            f"(selection{of_reproducible}), {shrink:.2f} (scoring), {seconds:.1f} s")
    row = CandidateScore(
        name, float(score), scored[0]["gap"], scored[1]["gap"], float(shrink), float(lr), float(delta_bic),
        float(gain), float(match), len(names), _parameter_table(augmented, fit, names), fit.log_det_r,
        chosen[1]["log_det_r"], chosen[1]["nrmse"], chosen[1]["z"], bool(fit.converged), fit.iterations,
        fit.n_simulations, seconds, fit.message, fit.as_dict(), stage, list(fit.free_names),
        shrink_se=run.shrink_se(*scored), selection_gap_before=chosen[0]["gap"], selection_gap_after=chosen[1]["gap"],
        selection_shrink=float(selection_shrink), family=_family(name, effect), reproducible_shrink=reproducible)
    return row, after


def _check_not_diverged(records: Sequence[ResidualRecord], spread: np.ndarray) -> None:
    """SimulationError when a held-out prediction is not finite or over ``DIVERGED_RELATIVE``
    times the measured RMS of its channel."""
    for rec in records:
        with np.errstate(invalid="ignore", over="ignore"):
            size = np.max(np.abs(rec.predicted) / np.where(spread > 0, spread, 1.0))
        if not np.isfinite(size) or size > DIVERGED_RELATIVE:
            raise SimulationError(f"its prediction of {rec.name} diverges (peak {size:.3g} times the measured RMS): "
                                  "the fit is unstable away from the estimation profile")


def _candidate(run: _Diagnosis, reference: _Reference, name: str, effect, loc, fits: dict, **kwargs) -> CandidateScore:
    """Refit and score one candidate (a failed refit, or one whose held-out prediction
    diverges, scores -inf); its fit goes into ``fits``."""
    tc = time.perf_counter()
    try:
        # trial points that simulate to NaN have det R = NaN; the optimiser rejects them
        with np.errstate(invalid="ignore", over="ignore"):
            refit = _refit(run, reference, name, effect, **kwargs)
        stage = "screening" if kwargs.get("screening", True) else "final"
        row, after = _score(run, reference, name, effect, refit, time.perf_counter() - tc, stage, loc)
    except (IdentificationError, SimulationError, ParameterError, np.linalg.LinAlgError) as exc:
        # ParameterError: an effect that cannot join the selected ones (the same coupling twice)
        run.say(f"  {name}: refit failed ({exc})")
        return CandidateScore(name, float("-inf"), reference.figures["scoring"]["gap"], float("nan"), float("nan"),
                              float("nan"), float("nan"), float("nan"), 0.0, 0,
                              message=f"refit failed: {exc}", wall_time_s=time.perf_counter() - tc,
                              family=_family(name, effect))
    run.n_sims += refit[2].n_simulations + len(run.data.held)
    fits[name] = (refit, after)
    return row


def _family(name: str, effect) -> str:
    """The family an effect belongs to (``Effect.family``; itself when its catalogue has none)."""
    return getattr(effect, "family", None) or name


def _ranked(rows: list[CandidateScore]) -> list[CandidateScore]:
    return sorted(rows, key=lambda c: -c.score if np.isfinite(c.score) else np.inf)


def _candidate_round(run: _Diagnosis, reference: _Reference, pool: dict[str, Any], loc):
    """Steps 3-4: screening refit of every candidate in ``pool``, then the leaders' final
    refits with every parameter free. Returns (ranking, {name: (refit, held-out figures)})."""
    fits: dict[str, Any] = {}
    ranking = _ranked([_candidate(run, reference, name, effect, loc, fits) for name, effect in pool.items()])
    if run.settings.screen_base_parameters is None:
        return ranking, fits
    leaders = [c for c in ranking[:run.settings.final_candidates] if np.isfinite(c.score)]
    for row in [c for i, c in enumerate(leaders) if i == 0 or c.score > 0]:
        screened = fits[row.effect][0][2]
        final = _candidate(run, reference, row.effect, pool[row.effect], loc, fits, start=screened.estimate,
                           screening=False)
        if not np.isfinite(final.score):
            continue
        final.wall_time_s += row.wall_time_s
        final.n_simulations += row.n_simulations
        ranking[ranking.index(row)] = final
    return _ranked(ranking), fits


def _forward_selection(run: _Diagnosis, nominal: _Reference, loc):
    """Steps 3-5 in rounds: a round's passing winner joins the reference model of the next.
    Returns (rounds of rankings, selected effects, per-round fits, the model after: (reference
    of the last selected effect, or of round 1's best candidate, and its score) or None)."""
    reference, selected, rounds, round_fits = nominal, [], [], []
    for _ in range(run.settings.max_effects):
        # a selected effect's family is done: its other forms are alternatives, not additions
        done = {_family(k, run.catalogue[k]) for k in selected}
        pool = {k: v for k, v in run.catalogue.items() if _family(k, v) not in done}
        if not pool:
            break
        ranking, fits = _candidate_round(run, reference, pool, loc)
        rounds.append(ranking)
        round_fits.append(fits)
        best = ranking[0] if ranking and np.isfinite(ranking[0].score) else None
        chosen = reference.figures["selection"]
        if not _passes(run.strategy.thresholds, best, chosen["significant"], run.reproducible_significant(chosen)):
            break
        selected.append(best.effect)
        (model, _, fit, objective), figures = fits[best.effect]
        reference = _Reference(model, fit, objective, figures, list(selected))
    return rounds, selected, round_fits


def _after_model(run: _Diagnosis, rounds, selected, round_fits):
    """The model the gap is measured after: that of the last selected effect, else round 1's
    best candidate. Returns (its CandidateScore, (model, fit), its held-out figures of the
    selection and scoring part) or Nones."""
    if selected:
        r, name = len(selected) - 1, selected[-1]
    elif rounds and rounds[0] and np.isfinite(rounds[0][0].score):
        r, name = 0, rounds[0][0].effect
    else:
        return None, None, None
    if name not in round_fits[r]:
        return None, None, None
    (model, _, fit, _), figures = round_fits[r][name]
    return next(c for c in rounds[r] if c.effect == name), (model, fit), dict(figures)


def _deterministic(run: _Diagnosis) -> bool | None:
    """Whether the operating state predicts a significant, material part of the nominal's held-out
    gap (:mod:`ema_uq.gap.predictable`); None when it could not be measured."""
    p = run.predictable
    if p is None or not np.isfinite(p.z):
        return None
    th = run.strategy.structure
    return bool(p.z > th.z_cell and p.share >= th.min_share)


def _healthy_level(run: _Diagnosis, nominal_cells: dict) -> dict | None:
    """Per cell the larger of the replicate ceiling's energy and the healthy level (the healthy
    records' energy per sample times the cell's samples); None when neither is there."""
    ceiling = None if run.ceiling is None else run.ceiling["selection"].get("cells")
    healthy = run.healthy_cells
    if ceiling is None and not healthy:
        return None
    out = {}
    for name, cell in nominal_cells.items():
        levels = [ceiling[name].energy] if ceiling and name in ceiling else []
        if healthy and name in healthy and healthy[name].samples > 0:
            levels.append(healthy[name].energy / healthy[name].samples * cell.samples)
        if levels:
            out[name] = replace(cell, energy=float(max(levels)))
    return out


def _cells_left(run: _Diagnosis, ranking: Sequence[CandidateScore], fits: dict, before: dict) -> dict[str, list]:
    """{effect: cells left (:func:`ema_uq.gap.structure.structure_left`)} of the best form of
    every family in ``ranking``, against the nominal's cells and the replicate ceiling's."""
    nominal_cells = before["selection"].get("cells", {})
    floor = _healthy_level(run, nominal_cells)
    out: dict[str, list] = {}
    seen: set[str] = set()
    for c in ranking:
        if c.family in seen or c.effect not in fits or not np.isfinite(c.score):
            continue
        seen.add(c.family)
        cells = fits[c.effect][1]["selection"].get("cells", {})
        out[c.effect] = structure_left(nominal_cells, cells, floor, run.strategy.structure)
    return out


def _verdict(th: Thresholds, ranking: list[CandidateScore], significant: bool, structured: bool,
             loc_after, loc_after_held, reproducible: bool = True, **kwargs) -> tuple[str, str | None, str]:
    """Step 6 as (verdict, effect, confidence) (:func:`ema_uq.gap.verdict.verdict`)."""
    return _open_verdict(th, ranking, significant, structured, loc_after, loc_after_held, reproducible,
                         **kwargs).as_tuple()


def _gap_summary(run: _Diagnosis, before: dict, after: dict | None, verdict: str) -> dict[str, Any]:
    """GAP.json ``gap``. ``before``/``after``: held-out figures ("all", "selection", "scoring")
    of the nominal model and of the model after (None: no candidate). The gap before and after
    is on all held-out data; the shrink is scored on the part that did not select the winner,
    signed and unclipped, with its block-bootstrap standard error, and only for an ``effect``
    verdict (None otherwise)."""
    b, a = before["all"], (after or before)["all"]
    shown = verdict == "effect" and after is not None
    b_score, a_score = before["scoring"], (after or before)["scoring"]
    # no gap on the scoring part: the shrink is undefined, and so is its standard error
    defined = shown and b_score["gap"] > 0
    return {
        "metric": run.strategy.metric.description,
        "before": b["gap"], "after": a["gap"],
        "shrink": (1.0 - a_score["gap"] / b_score["gap"] if defined else float("nan")) if shown else None,
        "shrink_se": (run.shrink_se(b_score, a_score) if defined else float("nan")) if shown else None,
        "shrink_record": run.data.shrink_record,
        "shrink_gap_before": b_score["gap"], "shrink_gap_after": a_score["gap"] if shown else None,
        "selection_shrink": (1.0 - after["selection"]["gap"] / before["selection"]["gap"]
                             if before["selection"]["gap"] > 0 else float("nan")) if shown else None,
        # replicates: the gap a time-invariant model learnt from the estimation records leaves,
        # the share of the nominal gap it closes (and that share's z), and the share of it the winner closes
        **({} if run.ceiling is None else {
            "ceiling_gap_selection": run.ceiling_gap("selection"), "ceiling_gap_scoring": run.ceiling_gap("scoring"),
            "reproducible_share": _reproducible_shrink(before["selection"]["gap"], run.ceiling_gap("selection"), None),
            "reproducible_z": before["selection"]["z"] - run.ceiling["selection"]["z"],
            "reproducible_significant": run.reproducible_significant(before["selection"])}),
        "reproducible_shrink": _reproducible_shrink(before["selection"]["gap"], after["selection"]["gap"],
                                                    run.ceiling_gap("selection")) if shown else None,
        "z_before": b["z"], "common_factors_before": b["factors"], "significant_before": b["significant"],
        "significant_selection": before["selection"]["significant"],
        "z_after": a["z"], "nrmse_before": b["nrmse"], "nrmse_after": a["nrmse"],
        "log_det_R_before": b["log_det_r"], "log_det_R_after": a["log_det_r"],
        "per_channel_before": dict(b["per_channel"]),
    }


def _thresholds_json(strategy: DiagnosisStrategy) -> dict[str, Any]:
    out = strategy.thresholds.to_json()
    z = getattr(strategy.metric, "z_significant", None)
    return {**out, "Z_HELD_OUT": z} if z is not None else out


# ----------------------------------------------------------------------------------------
# the diagnosis
# ----------------------------------------------------------------------------------------
def diagnose(
    measurements: Sequence[Measurement],
    validation: Sequence[Measurement] = (),
    *,
    candidates: Sequence[str] | None = None,
    settings: DiagnosisSettings | None = None,
    strategy: DiagnosisStrategy | None = None,
    seed: int | None = None,
    progress: Callable[[str], None] | None = None,
) -> GapResult:
    """Diagnose the sim-to-real gap of the nominal model on ``measurements``.

    ``validation`` measurements (same concept, at least one channel in common with the
    estimation data) are the held-out data; without them the last ``settings.holdout_fraction``
    of each record is held out. ``candidates`` restricts the catalogue (default: every effect
    available for the concept). ``strategy`` (default: :func:`strategy_for` the concept) says
    how the concept is treated, ``settings`` (default: the strategy's) the fit knobs.
    Returns a :class:`GapResult`.
    """
    t0 = time.perf_counter()
    measurements, validation = list(measurements), list(validation)
    concept = _check_inputs(measurements, validation)
    base = get_model(concept)
    strategy = strategy_for(base) if strategy is None else strategy
    settings = strategy.settings if settings is None else settings
    catalogue = _catalogue(base)
    if candidates is not None:
        compound = [c for c in candidates if getattr(base.effect_catalogue.get(c), "combines", ())]
        if compound:
            raise GapError(f"effect(s) {', '.join(compound)} carry another family's mechanism "
                           f"({', '.join(f for c in compound for f in base.effect_catalogue[c].combines)}) and are no "
                           "candidates; give single mechanisms (forward selection combines them: max_effects)")
        unknown = [c for c in candidates if c not in catalogue]
        if unknown:
            raise GapError(f"unknown candidate effect(s) {', '.join(unknown)} for concept {concept}; "
                           f"choose from {', '.join(catalogue)}")
        catalogue = {c: catalogue[c] for c in candidates}
    run = _Diagnosis(strategy, settings, _split(measurements, validation, strategy, settings), base, catalogue,
                     progress or (lambda _line: None), seed=seed)
    nominal, loc_est, loc_held = _fit_nominal(run)
    # where the gap shows most clearly: a gap in extrapolation shows on held-out data only
    if strategy.where_source == "held-out" or loc_held.z > loc_est.z:
        loc, where_source = loc_held, "held-out"
    else:
        loc, where_source = loc_est, "estimation"
    rounds, selected, round_fits = _forward_selection(run, nominal, loc)
    chosen, after, after_figures = _after_model(run, rounds, selected, round_fits)
    loc_after = loc_after_held = None
    effect_parameters: dict[str, dict[str, float]] = {}
    tempering = 1.0
    if after is not None:
        model, fit = after
        held_records = run.records(model, fit.estimate, held=True)
        est_records_after = run.records(model, fit.estimate, held=False)
        tempering = effective_sample_fraction([r.residual for r in est_records_after])
        loc_after = run.localise(model, fit.estimate, est_records_after, held=False)
        loc_after_held = run.localise(model, fit.estimate, run.without_estimation_error(model, fit, held_records),
                                      held=True)
        run.n_sims += len(run.data.estimation) + len(run.data.held)
        after_figures["all"] = run.held_out_figures(model, held_records)
        effect_parameters = _parameter_table(model, fit, _effect_parameter_names(model, base))
    ranking = rounds[0] if rounds else []
    before = nominal.figures
    probabilities = family_probabilities(ranking, strategy.thresholds, tempering)
    left = _cells_left(run, ranking, round_fits[0] if round_fits else {}, before)
    decided = _open_verdict(strategy.thresholds, ranking, before["selection"]["significant"],
                            loc_est.structured or loc_held.structured, loc_after, loc_after_held,
                            run.reproducible_significant(before["selection"]),
                            probabilities=probabilities, left=left,
                            deterministic=_deterministic(run))
    verdict, effect, confidence = decided.as_tuple()
    best_left = left.get(ranking[0].effect, []) if ranking else []
    open_set = {"family_probabilities": probabilities, "evidence_tempering": tempering,
                "margin_evidence": strategy.thresholds.margin_evidence,
                "contenders": [{"family": f, "probability": probabilities[f]} for f in decided.contenders],
                "structure_left": [c.to_json() for c in best_left], "where_left": where_left(best_left),
                "verdict_reason": decided.reason,
                "state_predictable": (None if run.predictable is None
                                      else {**run.predictable.to_json(), "deterministic": _deterministic(run)})}
    fit = nominal.fit
    nominal_json = {"log_det_R": fit.log_det_r, "objective": fit.objective, "converged": fit.converged,
                    "fixed": run.fixed, "iterations": fit.iterations, "n_samples": fit.n_samples,
                    "estimate": fit.as_dict(), "std": {nm: float(s) for nm, s in zip(fit.names, fit.std)}}
    d = run.data
    return GapResult(
        concept=concept, verdict=verdict, effect=effect,
        family=None if effect is None else _family(effect, catalogue[effect]), confidence=confidence, ranking=ranking,
        where={"channels": loc.where_channels(), "regimes": loc.where_regimes},
        gap={**_gap_summary(run, before, after_figures, verdict), "effect_of_after": chosen.effect if chosen else None},
        localization=loc_est, localization_held_out=loc_held, localization_after=loc_after,
        localization_after_held_out=loc_after_held, where_source=where_source,
        held_out=d.description,
        channels=list(d.channels), held_out_channels=list(d.held_channels), nominal=nominal_json,
        effect_parameters=effect_parameters, thresholds=_thresholds_json(strategy),
        wall_time_s=time.perf_counter() - t0, n_simulations=run.n_sims, seed=seed,
        selected=list(selected), further_rounds=rounds[1:], open_set=open_set,
    )
