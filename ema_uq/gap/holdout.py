"""Step 1 of the gap diagnosis: which data are fitted, which choose the winner and which
score its shrink.

The held-out data are the ``validation`` records when given, else the end of every
estimation record (:func:`split_holdout`). They are cut again in a *selection* part, which
chooses the winning effect, and a *scoring* part, on which its shrink is reported
(:func:`_selection_and_scoring`); :class:`_Split` holds the result for every later step.
Also home of :class:`GapError`, the diagnosis's error for data it cannot use.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Sequence

import numpy as np

from ..errors import EmaUqError
from ..experiments import Measurement
from .localize import ResidualRecord
from .strategy import DiagnosisSettings, DiagnosisStrategy


class GapError(EmaUqError):
    """Data the gap diagnosis cannot use (concept mismatch, no common channel, no catalogue)."""


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
