"""Is a gap a model error at all? The part of the held-out residual the operating state predicts.

A model error is a function of the actuator's state and inputs: the same motion under the same
load gives the same error, in any record. Coloured sensor noise, drift and other disturbances
are not: learnt on one record, they predict nothing on another. So a linear black-box model of
the residual — regressors: the nominal model's noise-free outputs, the inputs, their time
derivatives and a smoothed sign of each (friction, play and direction effects switch with the
sign of a speed or force) — is fitted by ridge least squares on the estimation records (the
penalty chosen by a time split of them) and
predicts the held-out residual (:func:`state_predictable`). The *predictable share* is the part
of the held-out systematic energy it removes; its z (the removed energy over the white-noise
standard deviation of that energy) says whether the gap is a model error the state explains.

The verdict reads it for the confidence of ``unexplained``: an unexplained gap is ``high``
confidence only when the state predicts a significant part of it; otherwise (coloured noise, a
slow disturbance, a structure that does not transfer between records) ``low``. Generic reason:
an unmodelled effect is a mechanism, and a mechanism repeats with the state that drives it.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from .localize import LAG_NORM, LocalizationError, ResidualRecord, systematic_products

#: ridge penalties tried, relative to the mean diagonal of the regressors' Gram matrix
PENALTIES = (1e-6, 1e-4, 1e-2, 1.0, 100.0)
#: a smoothed sign reaches ±0.76 at this fraction of the signal's peak magnitude
SIGN_SCALE = 0.05


@dataclass(frozen=True)
class Predictable:
    """``share``: held-out systematic energy the state regression removes (of the nominal's);
    ``z``: that removed energy over its white-noise standard deviation; ``regressors`` used."""

    share: float
    z: float
    regressors: int

    def to_json(self) -> dict[str, float]:
        return {"share": _finite(self.share), "z": _finite(self.z), "regressors": self.regressors}


def _finite(x: float) -> float | None:
    return float(x) if np.isfinite(x) else None


def _ridge(a: np.ndarray, y: np.ndarray, penalty: float) -> np.ndarray:
    gram = a.T @ a
    scale = np.trace(gram) / gram.shape[0]
    return np.linalg.solve(gram + penalty * scale * np.eye(gram.shape[0]), a.T @ y)


def _penalty(a: np.ndarray, y: np.ndarray) -> float:
    """The ridge penalty of ``PENALTIES`` that predicts best across a time split of the estimation
    samples (first half fits, second predicts, and back): the regression must transfer to data it
    did not see, or it would call a disturbance it memorised predictable."""
    half = a.shape[0] // 2
    folds = ((slice(0, half), slice(half, None)), (slice(half, None), slice(0, half)))
    errors = [sum(float(np.sum((y[test] - a[test] @ _ridge(a[train], y[train], p)) ** 2)) for train, test in folds)
              for p in PENALTIES]
    return PENALTIES[int(np.argmin(errors))]


def regressors(record: ResidualRecord, scale: np.ndarray | None = None) -> np.ndarray:
    """(n, k) state regressors of one record: outputs, inputs, their derivatives and smoothed
    signs; ``scale`` (per raw signal) sets the sign's width (default: the record's own peaks)."""
    raw = np.column_stack([record.outputs, record.inputs])
    peak = np.max(np.abs(raw), axis=0) if scale is None else scale
    width = np.where(peak > 0, SIGN_SCALE * peak, 1.0)
    derivative = np.gradient(raw, record.time, axis=0)
    return np.column_stack([raw, derivative, np.tanh(raw / width)])


def state_predictable(estimation: Sequence[ResidualRecord], held: Sequence[ResidualRecord],
                      spread: np.ndarray) -> Predictable:
    """Fit the state regression on the ``estimation`` residual records and measure what it removes
    of the ``held`` records' systematic energy (same channels; NaN samples are left out)."""
    spread = np.asarray(spread, dtype=float)
    scale = np.max(np.abs(np.concatenate([np.column_stack([r.outputs, r.inputs]) for r in estimation])), axis=0)
    x = [regressors(r, scale) for r in estimation]
    rows = [np.all(np.isfinite(r.residual), axis=1) & np.all(np.isfinite(f), axis=1) for r, f in zip(estimation, x)]
    a = np.concatenate([f[ok] for f, ok in zip(x, rows)])
    y = np.concatenate([r.residual[ok] for r, ok in zip(estimation, rows)])
    centre, width = a.mean(axis=0), a.std(axis=0)
    keep = width > 1e-12 * max(float(np.max(width)), 1e-300)
    if not keep.any() or a.shape[0] < 10 * keep.sum():
        return Predictable(float("nan"), float("nan"), int(keep.sum()))
    a = np.column_stack([np.ones(a.shape[0]), (a[:, keep] - centre[keep]) / width[keep]])
    beta = _ridge(a, y / spread, _penalty(a, y / spread)) * spread

    def predicted(r: ResidualRecord) -> np.ndarray:
        f = regressors(r, scale)
        f = np.column_stack([np.ones(f.shape[0]), (f[:, keep] - centre[keep]) / width[keep]])
        return np.where(np.isfinite(f).all(axis=1)[:, None], f @ beta, 0.0)

    residuals = [r.residual for r in held]
    corrected = [e - predicted(r) for e, r in zip(residuals, held)]
    try:
        before, sigma, _ = systematic_products(residuals)
        after, _, _ = systematic_products(corrected)
    except LocalizationError:
        return Predictable(float("nan"), float("nan"), int(keep.sum()))
    unit = 1.0 / spread ** 2
    e_before = sum(float(np.nansum(p * unit)) for p in before)
    e_after = sum(float(np.nansum(p * unit)) for p in after)
    n = sum(int(np.all(np.isfinite(p), axis=1).sum()) for p in before)
    sd = float(np.sqrt(n * LAG_NORM * np.sum((sigma ** 2 * unit) ** 2)))
    share = (e_before - e_after) / e_before if e_before > 0 else float("nan")
    return Predictable(float(share), (e_before - e_after) / sd if sd > 0 else float("nan"), int(keep.sum()))
