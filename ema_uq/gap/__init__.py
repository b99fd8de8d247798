"""Sim-to-real gap diagnosis: where the nominal model departs from measured data
(:mod:`~ema_uq.gap.localize`), which unmodelled effect of the catalogue causes it and how much
of the gap it explains (:mod:`~ema_uq.gap.attribute`, one procedure for every concept, what
differs per concept in :mod:`~ema_uq.gap.strategy`), and a blind self-check on synthetic
cases with hidden causes (:mod:`~ema_uq.gap.selfcheck`)."""
from .attribute import GapError, diagnose, split_holdout
from .localize import Localization, LocalizationError, RegimeRms, ResidualRecord, localize, systematic_nrmse
from .result import CandidateScore, GapResult
from .selfcheck import SelfCheckResult, build_cases, self_check
from .strategy import (DEFAULT_STRATEGY, DiagnosisSettings, DiagnosisStrategy, SystematicNrmse, Thresholds,
                       register_strategy, strategy_for)

__all__ = ["CandidateScore", "DiagnosisSettings", "DiagnosisStrategy", "DEFAULT_STRATEGY", "GapError", "GapResult",
           "SystematicNrmse", "Thresholds", "diagnose", "register_strategy", "split_holdout", "strategy_for",
           "Localization", "LocalizationError", "RegimeRms", "ResidualRecord", "localize", "systematic_nrmse",
           "SelfCheckResult", "build_cases", "self_check"]
