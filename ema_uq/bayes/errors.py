"""The one exception of :mod:`ema_uq.bayes`."""
from __future__ import annotations

from ..errors import EmaUqError


class BayesError(EmaUqError):
    """Bad sampling input: init of another concept, impossible prior, walkers that cannot be
    placed, a backend of another run."""
