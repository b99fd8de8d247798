"""The measured rigs: what their records are and what their studies add to the generic
procedures. The command line and the report ask :func:`rig_of` instead of testing concept
names; a concept without a rig (HT/LS, LT/HS) is studied on synthetic data from its own
model, so a truth is known and the Sobol and identifiability stages of the friction terms
apply.

A rig: its module ``rigs/<concept>.py`` with a :class:`Rig` named ``RIG``, and its name in
:data:`RIGS`: the rig's study code lives in its module (:mod:`ema_uq.rigs.emps`,
:mod:`ema_uq.rigs.cranfield` with :mod:`ema_uq.rigs.cranfield_baseline`).
"""
from __future__ import annotations

from dataclasses import dataclass
from importlib import import_module
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

#: concepts with measured records, each the module ``rigs/<concept>.py``
RIGS = ("emps", "cranfield")

#: the gap method version whose switches (:func:`ema_uq.gap.strategy.method_switches`) the measured
#: rigs' strategies carry: the synthetic concepts' default when the rigs' verdicts were last checked
#: against their SOURCE notes, named here so that a new default, decided on simulated records alone,
#: cannot move a verdict on measured data unseen
MEASURED_RIG_METHOD_VERSION = 4


@dataclass(frozen=True)
class Rig:
    """What the command line and the report need to know of one measured rig.

    concept, title : the model's registry name and how the report names the rig.
    data_files : ``study -> [(label, path)]``, the measured files of a study (missing ones
        included), whose hashes the report's provenance lists.
    record_constants : ``measurement -> design constants`` when each record carries its own
        (EMPS: gains and initial state); None: the model's.
    published_comparison : ``(fit, estimation, validation or None) -> JSON`` of the fit beside
        published values, written into FIT.json as ``published_comparison``; None: none.
    gap_figure_data : ``(GapResult, held-out records) -> arrays`` of the rig's own gap figure
        (:data:`ema_uq.report.gap_figures.RIG_GAP_FIGURES`); None: the gap ledger.
    fault_diagnosis : the study is a fault diagnosis of seeded-fault records (one stage: a
        healthy fit and the diagnoses), not the identification pipeline.
    """

    concept: str
    title: str
    data_files: Callable[[Mapping[str, Any]], list[tuple[str, Path]]]
    record_constants: Callable[[Any], np.ndarray] | None = None
    published_comparison: Callable[..., dict[str, Any]] | None = None
    gap_figure_data: Callable[[Any, Sequence[Any]], dict[str, Any]] | None = None
    fault_diagnosis: bool = False


def rig_of(concept: str) -> Rig | None:
    """The rig of ``concept``, None for a concept studied on synthetic data."""
    return import_module(f"{__name__}.{concept}").RIG if concept in RIGS else None


def is_measured(concept: str) -> bool:
    """Whether ``concept``'s records come from a rig (no truth is known) rather than its model."""
    return concept in RIGS


def no_method_version(concept: str) -> str:
    """Why a measured rig takes no gap method version (the command line and the study checker
    refuse one with this reason)."""
    return (f"the method versions are those of the synthetic concepts' diagnosis, and {concept} is a "
            "measured rig with a strategy of its own")
