"""Maximum-likelihood identification (output error, det R) with Gauss-Newton and
Levenberg-Marquardt, Cramér-Rao bounds and validation on fresh data."""
from .problem import FitProblem, IdentificationError, covariance
from .estimators import Settings, SingularInformationError, perturbed_start
from .fit import UNIDENTIFIABLE_MODES, estimate
from .result import FitResult

__all__ = ["FitProblem", "IdentificationError", "SingularInformationError", "UNIDENTIFIABLE_MODES", "covariance", "Settings",
           "estimate", "perturbed_start", "FitResult"]
