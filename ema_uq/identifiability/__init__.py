"""Identifiability: which parameters the data of a sensor set can actually determine.

For one sensor set (a choice of measured channels) and data, around the maximum-likelihood
estimate of that set:

1. the Fisher information matrix F of the det R likelihood (output sensitivities by central
   differences, all 2p perturbed sets in one batched simulator call per experiment) in
   relative coordinates s = θ / max(|θ̂|, 0.1 |θ_nominal|): eigenvalues, rank, condition and the null directions,
   named by parameter;
2. Cramér-Rao bounds and the correlation matrix from its (rank-truncated) inverse;
3. Brun et al. (2001) collinearity indices γ_K = 1 / sqrt(λ_min(S̃_Kᵀ S̃_K)) of parameter
   subsets, S̃ the noise-weighted sensitivities with unit-norm columns;
4. profile likelihoods: each friction/damping parameter fixed on a grid (±4 CRB σ, or a
   relative span where that is narrower or the bound is missing), the others re-optimised by
   Gauss-Newton warm-started from the neighbouring point; 95 % interval where the objective
   has risen by χ²₁(0.95)/2;
5. a verdict per parameter — identifiable, practically non-identifiable (profile open on a
   side, or too wide) or structurally non-identifiable (flat profile along an exact null
   direction of F) — and, for every lumped group, the identifiable combination, named from
   the drive train's known structure (reflection of each loss to the motor shaft).

Re-optimising along an exact null direction would make Gauss-Newton singular, so the
reference fit and each profile free only a maximal identifiable subset of the other
parameters (greedy, most informative first); the rest stay at the estimate. Along an exact
null direction one free member of the group compensates any change, so the profile is the
same as with all of them free — until that member reaches a bound; then the group is handed
to another member and the fit continues, so a group can move as far as all its members'
bounds allow.

The parts: :mod:`ema_uq.identify.information` (1-3 and the combinations),
:mod:`.profiles` (4 and the verdicts of 5), :mod:`.result` (what one sensor set and the
study report) and :mod:`.assess` (a sensor set and the sensor-set study, around a fit or at
a point before any fit).
"""
from ..identify.information import (CRB_Z, GAMMA_CAP, NULL_LOADING, RANK_RTOL, SELECT_RTOL, WEAK_RTOL, Information,
                                    collinearity_index, combination_expression, combinations, identifiable_subset,
                                    information, information_from_sensitivities, lumped_groups)
from .assess import (IdentifiabilityError, assess_at_point, assess_sensor_set, expected_records, sensor_set,
                     sensor_set_study, sensor_set_study_at)
from .profiles import (FLAT_FRACTION, PROFILE_SETTINGS, PROFILE_THRESHOLD, VERDICTS, Profile, classify_information,
                       classify_profile, profile_grid, profile_likelihood)
from .result import IdentifiabilityResult, ProfileSettings, SensorSetResult

__all__ = ["CRB_Z", "GAMMA_CAP", "NULL_LOADING", "RANK_RTOL", "SELECT_RTOL", "WEAK_RTOL", "Information",
           "collinearity_index", "combination_expression", "combinations", "identifiable_subset", "information",
           "information_from_sensitivities", "lumped_groups", "IdentifiabilityError", "assess_at_point",
           "assess_sensor_set", "expected_records", "sensor_set", "sensor_set_study", "sensor_set_study_at",
           "FLAT_FRACTION", "PROFILE_SETTINGS", "PROFILE_THRESHOLD", "VERDICTS", "Profile", "classify_information",
           "classify_profile", "profile_grid", "profile_likelihood", "IdentifiabilityResult", "ProfileSettings",
           "SensorSetResult"]
