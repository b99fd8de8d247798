"""The one entry of maximum-likelihood identification, :func:`estimate`: a plain fit of every
free parameter (:mod:`.estimators`), or, when the data cannot determine them all, a fit that
holds the undetermined ones and reports the identifiable combinations (:mod:`.reduction`)."""
from __future__ import annotations

from typing import Callable

import numpy as np

from .estimators import METHODS, Settings, maximum_likelihood
from .problem import FitProblem, IdentificationError
from .reduction import estimate_holding_unidentifiable
from .result import FitResult

#: answers to a singular information matrix at the start (see :func:`estimate`)
UNIDENTIFIABLE_MODES = ("error", "fix")


def estimate(
    problem: FitProblem,
    *,
    method: str = "gn",
    start: np.ndarray | None = None,
    settings: Settings = Settings(),
    seed: int | None = None,
    unidentifiable: str = "error",
    progress: Callable[[int, str], None] | None = None,
) -> FitResult:
    """Maximum-likelihood estimate of the free parameters of ``problem``.

    ``start`` is a full parameter vector (default: the set's nominal values) and must lie
    within bounds. Returns a :class:`FitResult` with Cramér-Rao standard deviations
    computed from the information matrix at the estimate.

    ``unidentifiable``: what to do when the data cannot determine every free parameter at
    the start (singular information matrix): ``"error"`` raises
    :class:`~ema_uq.identify.SingularInformationError` naming the direction; ``"fix"`` holds
    the undetermined parameters at their start values, estimates the rest and reports the
    identifiable combinations (:mod:`.reduction`).

    ``progress``: called after every accepted iteration with its number and a one-line state.
    """
    if method not in METHODS:
        raise IdentificationError(f"unknown method {method!r}; choose gn (Gauss-Newton) or lm (Levenberg-Marquardt)")
    if unidentifiable not in UNIDENTIFIABLE_MODES:
        raise IdentificationError(f"unknown unidentifiable mode {unidentifiable!r}; choose "
                                  f"{' or '.join(UNIDENTIFIABLE_MODES)}")
    run = estimate_holding_unidentifiable if unidentifiable == "fix" else maximum_likelihood
    return run(problem, method=method, start=start, settings=settings, seed=seed, progress=progress)
