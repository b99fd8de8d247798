"""The gap verdict: name a family only when the evidence singles it out and it leaves nothing.

The verdict is open-set: the catalogue may not hold the cause. A family is named (``effect``)
only when both hold:

1. **It beats every other family by a stated margin.** Each candidate's evidence is its ranking
   evidence ΔBIC + G (G, the held-out gain, when the strategy puts it in the score): twice the
   log of the estimation data's marginal likelihood (BIC) times the selection part's predictive
   likelihood, relative to the nominal model. The likelihood assumes white residuals; where the
   residual of the best model is autocorrelated, each sample carries less information than one
   and every log-likelihood ratio is inflated by about the integrated autocorrelation time, so
   the evidence is tempered by the effective-sample fraction τ = 1 / (1 + 2 Σ ρ_k)
   (:func:`effective_sample_fraction`; the magnitude adjustment of a misspecified likelihood).
   Family probabilities: the families (and the nominal model, ``none``) share a uniform prior,
   the forms of a family share its part; p(f) ∝ mean over its forms of exp(τ · evidence / 2).
   The family *wins* when 2 ln(p_best / p_f) ≥ ``MARGIN_EVIDENCE`` for every other family f,
   ``none`` included: 10, "very strong" on the scale of Kass and Raftery (1995).
2. **It leaves no structure.** After adding it, the held-out residual has no cell (channel,
   stroke position, direction, regime, frequency band) with more structure than the healthy
   level (:func:`ema_uq.gap.structure.structure_left`).

Otherwise, when the best candidate passes the effect test of the aggregate gap
(:func:`passes`): ``ambiguous`` when at least one family within the margin leaves no structure
(the families within the margin are reported with their probabilities); ``unexplained`` when
every family within the margin leaves structure (the best partial candidate, what it closes
and the cells left are reported), or when the nominal model is within the margin of the best.
Without a passing candidate the verdict is ``unexplained`` or ``none`` as before
(:func:`verdict`); an ``unexplained`` verdict has ``high`` confidence only when no candidate
closes a quarter of the gap and the operating state predicts it (:mod:`ema_uq.gap.predictable`:
coloured noise and disturbances are not a mechanism).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np

from .result import CandidateScore

#: 2 ln of the least Bayes factor between the named family and any other ("very strong")
MARGIN_EVIDENCE = 10.0
#: the nominal model's entry in the family probabilities
NONE_FAMILY = "none"
#: autocorrelation lags read at most for the effective-sample fraction
MAX_AUTOCORRELATION_LAG = 200


@dataclass(frozen=True)
class Thresholds:
    """Verdict thresholds (see :mod:`ema_uq.gap.attribute` and this module). ``held_out_gain_min``
    None: the held-out gain is not required; ``gain_in_score`` False: the ranking score and the
    evidence are ΔBIC alone (the score times the signature factor); ``margin_evidence``: 2 ln of
    the least Bayes factor by which a named family beats every other family and the nominal model."""

    bic_min: float = 25.0
    held_out_gain_min: float | None = 25.0
    shrink_min: float = 0.5
    shrink_confident: float = 0.8
    margin_evidence: float = MARGIN_EVIDENCE
    signature_weight: float = 0.25
    gain_in_score: bool = True

    def to_json(self) -> dict[str, Any]:
        return {"BIC_MIN": self.bic_min, "HELD_OUT_GAIN_MIN": self.held_out_gain_min, "SHRINK_MIN": self.shrink_min,
                "SHRINK_CONFIDENT": self.shrink_confident, "MARGIN_EVIDENCE": self.margin_evidence,
                "SIGNATURE_WEIGHT": self.signature_weight}


def passes(th: Thresholds, best: CandidateScore | None, significant: bool, reproducible: bool = True) -> bool:
    """The ``effect`` test on the selection part: ΔBIC, held-out gain and, where the reference's
    held-out gap is significant (an insignificant gap is noise, and its shrink no evidence), the
    shrink of its reproducible part, which must itself be significant (``reproducible``: with
    replicates, a gap that only changes from run to run is no fixed effect's)."""
    return (best is not None and best.delta_bic > th.bic_min
            and (th.held_out_gain_min is None or best.held_out_gain > th.held_out_gain_min)
            and ((reproducible and best.reproducible_shrink >= th.shrink_min) or not significant))


def reproducible_shrink(before: float, after: float, ceiling: float | None) -> float:
    """The share of the reproducible gap, before - ``ceiling``, that a candidate closes:
    (before - after) / (before - ceiling). Without replicates (``ceiling`` None) the plain shrink
    1 - after / before (0 where there is no gap); NaN where the ceiling leaves nothing
    reproducible (the whole gap changes from run to run: no fixed effect can explain it)."""
    if ceiling is None:
        return float(1.0 - after / before) if before > 0 else 0.0
    reproducible = before - ceiling
    return float((before - after) / reproducible) if reproducible > 0 else float("nan")


def effective_sample_fraction(residuals: Sequence[np.ndarray]) -> float:
    """τ = N_eff / N of residual records [(n_i, m)] (NaN rows allowed): per record and channel
    1 / (1 + 2 Σ ρ_k), the autocorrelations summed over the initial positive sequence (up to the
    first lag with ρ_k ≤ 0, at most ``MAX_AUTOCORRELATION_LAG``), averaged with the samples as
    weights; 1 for white noise, about (1 - φ) / (1 + φ) for an AR(1) residual."""
    total, weight = 0.0, 0
    for e in residuals:
        e = np.asarray(e, dtype=float)
        rows = e[np.all(np.isfinite(e), axis=1)]
        n = rows.shape[0]
        if n < 20:
            continue
        rows = rows - rows.mean(axis=0)
        size = 1 << int(np.ceil(np.log2(2 * n)))
        spectrum = np.abs(np.fft.rfft(rows, n=size, axis=0)) ** 2
        acov = np.fft.irfft(spectrum, n=size, axis=0)[:min(n, MAX_AUTOCORRELATION_LAG + 1)]
        for c in range(rows.shape[1]):
            if acov[0, c] <= 0:
                continue
            rho = acov[1:, c] / acov[0, c]
            stop = np.flatnonzero(rho <= 0.0)
            positive = rho[:stop[0]] if stop.size else rho
            total += n / (1.0 + 2.0 * float(np.sum(positive)))
            weight += n
    return float(total / weight) if weight else 1.0


def _evidence(c: CandidateScore, th: Thresholds) -> float:
    return c.delta_bic + (c.held_out_gain if th.gain_in_score and np.isfinite(c.held_out_gain) else 0.0)


def family_probabilities(ranking: Sequence[CandidateScore], th: Thresholds, tempering: float = 1.0) -> dict[str, float]:
    """Posterior probability of each family and of the nominal model (``none``) from the
    tempered evidence of its forms (module docstring), largest first."""
    log_w: dict[str, list[float]] = {NONE_FAMILY: [0.0]}
    for c in ranking:
        evidence = _evidence(c, th)
        if np.isfinite(c.score) and np.isfinite(evidence):
            log_w.setdefault(c.family, []).append(0.5 * tempering * evidence)
    family_log = {f: float(np.logaddexp.reduce(v) - np.log(len(v))) for f, v in log_w.items()}
    top = max(family_log.values())
    weights = {f: np.exp(v - top) for f, v in family_log.items()}
    norm = sum(weights.values())
    return dict(sorted(((f, float(w / norm)) for f, w in weights.items()), key=lambda kv: -kv[1]))


def within_margin(probabilities: Mapping[str, float], margin: float = MARGIN_EVIDENCE) -> list[str]:
    """Families (``none`` included) whose 2 ln probability ratio to the most probable is below ``margin``."""
    best = max(probabilities.values())
    out = []
    for family, p in probabilities.items():
        ratio = np.inf if p <= 0 else 2.0 * np.log(best / p)
        if ratio < margin:
            out.append(family)
    return out


@dataclass
class Verdict:
    """What :func:`verdict` decides: ``verdict`` (effect, ambiguous, unexplained, none), the named
    ``effect`` (form) or None, ``confidence`` and, for ``ambiguous``, the ``contenders``
    (families within the margin that leave no structure), for ``unexplained`` after a passing
    candidate the ``reason``."""

    verdict: str
    effect: str | None
    confidence: str
    contenders: list[str] = field(default_factory=list)
    reason: str = ""

    def as_tuple(self) -> tuple[str, str | None, str]:
        return self.verdict, self.effect, self.confidence


def verdict(th: Thresholds, ranking: list[CandidateScore], significant: bool, structured: bool,
            loc_after, loc_after_held, reproducible: bool = True, *,
            probabilities: Mapping[str, float] | None = None,
            left: Mapping[str, Sequence[Any]] | None = None,
            margin: float | None = None, deterministic: bool | None = None) -> Verdict:
    """The verdict from round 1's ``ranking`` (module docstring). ``probabilities``: family
    probabilities (None: from the untempered evidence); ``left``: {effect: cells left} of the
    best form of each family (None: no cell test); ``deterministic``: whether the operating state
    predicts the gap (:mod:`ema_uq.gap.predictable`; None: not measured), which an
    ``unexplained`` verdict needs for ``high`` confidence."""
    best = ranking[0] if ranking and np.isfinite(ranking[0].score) else None
    if passes(th, best, significant, reproducible):
        probabilities = family_probabilities(ranking, th) if probabilities is None else probabilities
        close = within_margin(probabilities, th.margin_evidence if margin is None else margin)
        left = {} if left is None else left
        if NONE_FAMILY in close:
            return Verdict("unexplained", None, "low",
                           reason="the best candidate's evidence is within the margin of the nominal model's")
        best_form = {}
        for c in ranking:
            best_form.setdefault(c.family, c)
        clean = [f for f in close if f in best_form and not left.get(best_form[f].effect)]
        if len(close) > 1:
            if clean:
                return Verdict("ambiguous", None, "low", contenders=list(close))
            return Verdict("unexplained", None, "low",
                           reason="no family within the margin explains the gap in every cell")
        if left.get(best.effect):
            return Verdict("unexplained", None, "low", reason=f"{best.family} leaves structure")
        confident = ((best.reproducible_shrink >= th.shrink_confident or not significant)
                     and loc_after is not None and not loc_after.structured and not loc_after_held.structured)
        return Verdict("effect", best.effect, "high" if confident else "low")
    # a candidate that fits the estimation data far beyond noise (ΔBIC > BIC_MIN) but fails on
    # held-out data says the residual is not noise even where the localisation tests pass
    fits_beyond_noise = best is not None and best.delta_bic > th.bic_min
    if structured or significant or fits_beyond_noise:
        # NaN: nothing reproducible, so surely no fixed effect's
        closes_some = best is not None and best.reproducible_shrink >= th.shrink_min / 2
        reason = ("no candidate fits" if best is None else
                  f"the best candidate, {best.family}, fails the effect test (dBIC {best.delta_bic:.0f}, held-out gain "
                  f"{best.held_out_gain:.0f}, closes {best.reproducible_shrink:.0%} of the reproducible gap)")
        # a gap the state does not predict may be coloured noise or a disturbance, not a mechanism
        return Verdict("unexplained", None, "low" if closes_some or deterministic is False else "high", reason=reason)
    return Verdict("none", None, "high")
