"""Validation of a fitted model on data not used for estimation: per-channel fit (NRMSE)
and residual tests (whiteness, cross-correlation with the inputs)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np
from scipy import special

from ..experiments import Measurement
from ..simulate import simulate_batch
from ..statistics import LJUNG_BOX_LAGS, ljung_box, max_cross_correlation

MAX_LAG = LJUNG_BOX_LAGS
ALPHA = 0.01


@dataclass
class ChannelValidation:
    """Per-channel figures: ``fit_percent`` = 100 (1 - ||z - y|| / ||z - mean z||) (MATLAB ``compare``),
    ``nrmse`` = ||z - y|| / ||z - mean z||, whiteness by Ljung-Box over ``MAX_LAG`` lags, and the
    largest normalised cross-correlation with each input over ±``MAX_LAG`` lags, tested against a
    Bonferroni bound over all lags and inputs at level ``ALPHA``."""

    channel: str
    fit_percent: float
    nrmse: float
    ljung_box_p: float
    white: bool
    max_input_xcorr: dict[str, float]
    independent_of_inputs: bool


@dataclass
class ValidationReport:
    experiment: str
    channels: list[ChannelValidation] = field(default_factory=list)
    confidence_bound: float = 0.0

    def summary(self) -> str:
        rows = [f"Validation on {self.experiment!r} (residual tests at {ALPHA:.0%}, "
                f"cross-correlation bound {self.confidence_bound:.3g})",
                f"  {'channel':<10} {'fit %':>8} {'NRMSE':>9} {'LB p':>8} white  max|xcorr|  indep."]
        for c in self.channels:
            rows.append(f"  {c.channel:<10} {c.fit_percent:>8.2f} {c.nrmse:>9.4f} {c.ljung_box_p:>8.3f} "
                        f"{'yes' if c.white else 'no ':<5}  {max(c.max_input_xcorr.values()):>9.3f}  "
                        f"{'yes' if c.independent_of_inputs else 'no'}")
        return "\n".join(rows)

    def to_json(self) -> dict:
        return {"experiment": self.experiment, "confidence_bound": self.confidence_bound,
                "channels": {c.channel: {"fit_percent": c.fit_percent, "nrmse": c.nrmse,
                                         "ljung_box_p": c.ljung_box_p, "white": c.white,
                                         "max_input_xcorr": c.max_input_xcorr,
                                         "independent_of_inputs": c.independent_of_inputs}
                             for c in self.channels}}


def validate(fit_values: np.ndarray, measurement: Measurement, *, channels: Sequence[str] | None = None,
             constants: np.ndarray | None = None) -> ValidationReport:
    """Simulate the full parameter vector ``fit_values`` on ``measurement`` and test the residuals.

    Samples with NaN are left out of every figure (residual tests use the longest complete stretch).
    """
    model = measurement.model
    channels = tuple(measurement.channels if channels is None else channels)
    predicted = simulate_batch(model, fit_values, measurement.time, measurement.experiment.input_matrix(model),
                               constants=constants)[:, model.output_index(channels)]
    observed = measurement.select(channels).values
    n = observed.shape[0]
    inputs = {k: v for k, v in measurement.experiment.inputs.items() if np.std(v) > 0}
    # the maximum over all lags and inputs is tested, hence the Bonferroni level
    n_tests = (2 * MAX_LAG + 1) * max(len(inputs), 1)
    bound = special.ndtri(1 - ALPHA / (2 * n_tests)) / np.sqrt(n)     # the normal quantile
    report = ValidationReport(measurement.experiment.name, confidence_bound=float(bound))
    for j, ch in enumerate(channels):
        z, y = observed[:, j], predicted[:, j]
        ok = np.isfinite(z)
        err = np.linalg.norm(z[ok] - y[ok])
        spread = np.linalg.norm(z[ok] - z[ok].mean())
        nrmse = float(err / spread) if spread > 0 else float("inf")
        e = np.where(ok, z - y, 0.0)
        if ok.all() and np.std(e) > 0:
            p = ljung_box(e, MAX_LAG)
            xc = {k: max_cross_correlation(e, u, MAX_LAG) for k, u in inputs.items()}
        else:
            p, xc = float("nan"), {k: float("nan") for k in inputs}
        report.channels.append(ChannelValidation(
            channel=ch, fit_percent=100.0 * (1.0 - nrmse), nrmse=nrmse, ljung_box_p=p,
            white=bool(p > ALPHA), max_input_xcorr=xc,
            independent_of_inputs=bool(all(v <= bound for v in xc.values())),
        ))
    return report
