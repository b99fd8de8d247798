"""Sim-to-real gap diagnosis: where the nominal model departs from measured data
(:mod:`~ema_uq.gap.localize`), which unmodelled effect of the catalogue causes it and how much
of the gap it explains (:mod:`~ema_uq.gap.attribute`), and a blind self-check on synthetic
cases with hidden causes (:mod:`~ema_uq.gap.selfcheck`)."""
from .attribute import CandidateScore, DiagnosisSettings, GapError, GapResult, diagnose, split_holdout
from .localize import Localization, LocalizationError, ResidualRecord, localize, systematic_nrmse
from .selfcheck import SelfCheckResult, build_cases, self_check

__all__ = ["CandidateScore", "DiagnosisSettings", "GapError", "GapResult", "diagnose", "split_holdout",
           "Localization", "LocalizationError", "ResidualRecord", "localize", "systematic_nrmse",
           "SelfCheckResult", "build_cases", "self_check"]
