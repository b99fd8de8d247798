"""The set-point cycle of the Cranfield rig's records, and what a time-invariant model could
predict from it.

Every record repeats one set-point cycle under a constant load. :func:`set_point_period` finds
that cycle; :func:`cycle_replicate_prediction` averages a residual over every cycle of the
estimation records at each phase and lays that mean over held-out records: the replicate
ceiling of the fault diagnosis's shrink test (:mod:`ema_uq.rigs.cranfield`). The data-driven
baseline (:mod:`ema_uq.rigs.cranfield_baseline`) cuts its records into cycles with it too.
"""
from __future__ import annotations

from typing import Any, Sequence

import numpy as np

from ..experiments import Measurement


def set_point_period(x_sp: np.ndarray, tolerance: float = 1e-9) -> int | None:
    """The smallest number of samples P after which the set point repeats (x_sp[k + P] =
    x_sp[k] within ``tolerance`` [m] for every k), with at least two whole cycles in the
    record; None when it does not repeat."""
    x = np.asarray(x_sp, dtype=float)
    return next((p for p in range(2, x.size // 2 + 1) if np.allclose(x[p:], x[:-p], rtol=0.0, atol=tolerance)), None)


def _phase_offset(x_sp: np.ndarray, cycle: np.ndarray, tolerance: float = 1e-9) -> int | None:
    """o such that x_sp[k] = cycle[(k + o) mod P] (the record's phase in the cycle), or None."""
    period = cycle.size
    return next((o for o in range(period) if np.allclose(x_sp[:period], np.roll(cycle, -o), rtol=0.0,
                                                         atol=tolerance)), None)


def _fill_circular(mean: np.ndarray) -> np.ndarray:
    """Phases with no sample (NaN rows of a cycle mean (P, m)) linearly interpolated from their
    neighbours, around the cycle."""
    out = mean.copy()
    phase = np.arange(mean.shape[0])
    for c in range(mean.shape[1]):
        known = np.isfinite(mean[:, c])
        if known.any() and not known.all():
            out[~known, c] = np.interp(phase[~known], phase[known], mean[known, c], period=mean.shape[0])
    return np.where(np.isfinite(out), out, 0.0)


def cycle_replicate_prediction(estimation: Sequence[Measurement], residuals_: Sequence[np.ndarray],
                               channels: Sequence[str], held_out: Sequence[Measurement],
                               held_channels: Sequence[str]) -> list[np.ndarray] | None:
    """The held-out residual a time-invariant model could predict from the estimation records
    (``DiagnosisStrategy.replicate_prediction`` of the rig): the records repeat one set-point
    cycle under a constant load, so per load and cycle the mean of the estimation residual at
    each phase of the cycle (over every cycle of every estimation record; phases the thinned
    records skip filled from their neighbours), laid over each held-out record at its own
    phase. A fault whose effect does not change from run to run leaves only noise beside it; the
    gap that remains is the part that changes between runs (the rig drifts within a test
    session), which no fixed-parameter effect can explain. Returns (n_i, len(held_channels))
    per held-out record (zeros for a channel the estimation records lack), or None when a
    held-out record repeats no cycle that an estimation record at its load repeats: no ceiling
    can then be learnt for it, and the diagnosis judges the whole gap."""
    groups: dict[tuple[float, int], dict[str, Any]] = {}
    for m, residual in zip(estimation, residuals_):
        x_sp = m["x_sp"]
        period = set_point_period(x_sp)
        if period is None:
            continue
        group = groups.setdefault((float(m["F_load"][0]), period), {"cycle": x_sp[:period].copy(),
                                                                   "sum": np.zeros((period, len(channels))),
                                                                   "count": np.zeros((period, len(channels)))})
        offset = _phase_offset(x_sp, group["cycle"])
        if offset is None:
            continue
        phase = (np.arange(x_sp.size) + offset) % period
        finite = np.isfinite(residual)
        for c in range(len(channels)):
            np.add.at(group["sum"][:, c], phase[finite[:, c]], residual[finite[:, c], c])
            np.add.at(group["count"][:, c], phase[finite[:, c]], 1.0)
    out = []
    for m in held_out:
        prediction = np.zeros((m.experiment.n_samples, len(held_channels)))
        period = set_point_period(m["x_sp"])
        group = groups.get((float(m["F_load"][0]), period)) if period is not None else None
        offset = None if group is None else _phase_offset(m["x_sp"], group["cycle"])
        if offset is None:
            return None
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = _fill_circular(group["sum"] / np.where(group["count"] > 0, group["count"], np.nan))
        phase = (np.arange(m.experiment.n_samples) + offset) % period
        for j, name in enumerate(held_channels):
            if name in channels:
                prediction[:, j] = mean[phase, list(channels).index(name)]
        out.append(prediction)
    return out
