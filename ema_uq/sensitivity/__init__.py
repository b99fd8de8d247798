"""Global variance-based sensitivity: Sobol indices of the friction/damping parameters,
computed with SALib (Saltelli/Sobol design, ``sobol.analyze``), scalar and time-resolved.

SALib's split is kept: a plain ``problem`` dict, :func:`sample` (seeded, scrambled Sobol
design), evaluation (in independent chunks, each through the one batched simulator call)
and :func:`analyze` (first, total and second-order indices with bootstrap 95 % intervals).
The Ishigami function with its analytic indices lives here as the reference problem the
tests check the wrapper against.

Quantities of interest (QoI) per parameter set, on the study's estimation experiment:

``cost``            log det R of the residuals against reference data (the study's estimation
                    data synthesised at nominal with its noise and seed) [-]; the ML cost on a
                    log scale, because det R spans decades over the ranges and Sobol indices
                    of a heavy-tailed output would only describe its tail
``rms_<channel>``   RMS deviation of the channel from the nominal run [channel unit]
``tracking_error``  RMS of y_r - (y1 + y2)/2 [m]
``peak_torque``     max |k_n I_A|, the motor torque [N m]
``peak_current``    max |I_A| [A]
``energy``          motor shaft energy delivered, ∫ max(k_n I_A Ω, 0) dt [J]

Time-resolved first and total indices of Ω, y1 and I_A are computed per time point on a
decimated grid with SALib's estimators, vectorised over time.

The parts: :mod:`.indices` (SALib and the reference problem), :mod:`.setup` (the study of
one concept), :mod:`.evaluation` (design rows to QoI, in chunks) and :mod:`.result`.
"""
from .evaluation import SobolChunk, chunk_rows, evaluate, evaluate_chunk, gather
from .indices import (CONF_LEVEL, CONVERGENCE_ATOL, ISHIGAMI_PROBLEM, SensitivityError, analyze, analyze_time_resolved,
                      check_convergence, design_size, indices_agree, ishigami, ishigami_indices, sample)
from .result import SobolResult, analyze_chunks, analyze_design, run
from .setup import INTEGRATOR, QOI_KINDS, TIME_RESOLVED_OUTPUTS, SensitivitySetup, friction_names, setup_from_study

__all__ = ["SobolChunk", "chunk_rows", "evaluate", "evaluate_chunk", "gather", "CONF_LEVEL", "CONVERGENCE_ATOL",
           "ISHIGAMI_PROBLEM", "SensitivityError", "analyze", "analyze_time_resolved", "check_convergence",
           "design_size", "indices_agree", "ishigami", "ishigami_indices", "sample", "SobolResult", "analyze_chunks",
           "analyze_design", "run", "INTEGRATOR", "QOI_KINDS", "TIME_RESOLVED_OUTPUTS", "SensitivitySetup",
           "friction_names", "setup_from_study"]
