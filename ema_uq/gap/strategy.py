"""How the one gap diagnosis (:func:`ema_uq.gap.diagnose`) treats a concept.

A :class:`DiagnosisStrategy` holds everything that differs between concepts: the fitted
channels and per-record design constants, the fit settings (:class:`DiagnosisSettings`:
iteration caps, screening, forward-selection rounds), the start grid of effect parameters,
the held-out gap metric, the residual localisation (regime masks), the verdict thresholds
and, for fault diagnosis, a reference fit whose base parameters are held. The diagnosis
itself — hold-out split, nominal fit, candidate refits, scores, verdict — is the same for all.

``strategy_for(concept)`` picks a concept's strategy: the model's ``gap_strategy`` attribute
when it has one (a strategy or a callable returning one), else one registered by
:func:`register_strategy` (EMPS: :data:`ema_uq.rigs.emps.EMPS_STRATEGY`), else
:data:`DEFAULT_STRATEGY` (the synthetic actuator concepts).
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass, replace
from typing import Any, Callable, Mapping, Protocol, Sequence

import numpy as np

from ..experiments import Measurement
from ..statistics import START_MULTIPLES
from .allowance import AllowanceError, ModelFormAllowance, actuator_allowance
from .localize import ResidualRecord, localize, nrmse_of_products, systematic_products
from .structure import StructureSettings
from .verdict import MARGIN_EVIDENCE, Thresholds


#: ``DiagnosisSettings.decision_fits``: the decrease of 2V still to come at which a fit stops, a
#: hundredth of the evidence margin (:data:`ema_uq.gap.verdict.MARGIN_EVIDENCE`) and a 250th of
#: ``Thresholds.bic_min``; a fit stopped there sits within about 0.3 Cramér-Rao σ of its optimum
#: along its least determined direction (2ΔV = δᵀ F δ)
DECISION_TOLERANCE = 0.1


@dataclass(frozen=True)
class DiagnosisSettings:
    """Fit knobs of :func:`~ema_uq.gap.diagnose` (a strategy carries its concept's defaults).

    ``holdout_fraction``: end of each record held out when no validation data are given;
    ``nominal_max_iterations``: Gauss-Newton cap of the nominal fit; ``candidate_max_iterations``:
    cap of a candidate's first refit; ``screen_base_parameters``: base parameters freed beside
    the effect's in that first refit (the most aliased; None: every parameter free, and no
    second refit); ``final_candidates``/``final_max_iterations``: leaders refitted with every
    parameter free, and its cap; ``max_effects``: forward-selection rounds (an effect kept in
    one round joins the model the next round's candidates are added to);
    ``model_form_allowance``: fit the strategy's model-form allowance (kinematic tolerance and
    command lag, :mod:`ema_uq.gap.allowance`) in the nominal model and in every candidate alike
    (from method version 2 on, the default; False with ``converged_step`` False reproduces
    method version 1, which treats the kinematics and the command as exact);
    ``converged_step``: an option, off by default (tried as a method version 3 and not
    adopted, docs/gap-diagnosis.md): every fit and prediction runs RK4 at the model's
    ``converged_step`` (the model contract's step, converged well under the noise: HT/LS 1 ms,
    LT/HS 0.5 ms) instead of its finer ``integration_step``, but for models with an effect of
    faster dynamics (``Model.rk4_step``);
    ``spanning_forms``: offer the catalogue's forms that give a family the freedom its mechanism
    has (:data:`ema_uq.gap.candidates.SPANNING_FORMS`: friction per direction, a sensor delay
    with its filter; method version 4, the default since it passed its evaluation: off with the
    other defaults reproduces method version 2) beside the families' other forms;
    ``operating_point_forms``: offer the forms whose magnitude follows the operating point
    (:data:`ema_uq.gap.candidates.OPERATING_POINT_FORMS`: a ripple share with the motor torque, a
    joint angle along the stroke, a stiffness with the torque carried; method version 5);
    ``nested_forms``: offer a form that another offered form nests (``Effect.nests``; method
    version 5 offers the nesting forms only: the same mechanisms, fewer refits);
    ``decision_fits``: fit at the precision the verdict reads (method version 6): each fit also
    stops once the decrease of 2V still to come (the last two iterations' decreases extrapolated as
    a geometric series) is below :data:`DECISION_TOLERANCE`, in the units of 2 ln L in which ΔBIC,
    the held-out gain and the evidence margin are read, and a fit that holds parameters the data
    cannot determine does not compute the identifiable combinations of the held groups (reported
    by ``identify``, read by no verdict);
    ``decision_stop``: how ``decision_fits`` judges the decrease still to come: "extrapolated"
    (method version 6, the geometric series of the last two decreases) or "predicted" (method
    version 7: the decrease the full Gauss-Newton step promises at the current iterate, checked
    before each step; the history of decreases is no bound, a plateau can come before a large
    decrease);
    ``nested_starts``: a candidate's screening fit that ends with a lower likelihood than a model
    its form contains, the model it is added to (every effect parameter at ``Effect.off``) or,
    for a form that reduces to another form fitted in the same round (``Effect.reduces_to``),
    that form's fit, is refitted from that model's point and the better fit kept (method
    version 8). Why: the form contains those models, so its ML fit can be no worse than theirs;
    the start grid has no point at them, and Gauss-Newton stopped in a dip of a ragged objective
    far below them (plays ending 1400-12 000 in 2V under the nominal they contain, a
    three-harmonic ripple 630 under its fundamental alone). Only such a fit is refitted: a start
    at the nested point itself leaves the parameters that vanish there (a harmonic's phase at
    zero ratio, a torsional mode's damping at zero period) undetermined, and fits from it stayed
    in the nested model where the grid's fit had found the form (development, block 5209);
    ``nested_start_tolerance``: with ``nested_starts``, the shortfall in 2V (2 ln L) below a
    contained model that a fit may end at without a refit: 0 in method version 8 (any shortfall),
    :data:`ema_uq.gap.verdict.MARGIN_EVIDENCE` in method version 9. Why: a refit that only climbs
    to the contained point leaves the form below that model, which is scored already, by the
    penalty of its extra parameters, so it moves no verdict; a shortfall smaller than the
    differences the verdict reads is no sign of a failed descent worth a full refit (version 8
    paid 15-19 % more time for such refits on forms the record does not carry).
    """

    holdout_fraction: float = 0.3
    nominal_max_iterations: int = 30
    candidate_max_iterations: int = 8
    screen_base_parameters: int | None = 6
    final_candidates: int = 2
    final_max_iterations: int = 15
    tolerance: float = 1e-5
    max_effects: int = 1
    model_form_allowance: bool = True
    converged_step: bool = False
    spanning_forms: bool = True
    operating_point_forms: bool = False
    nested_forms: bool = True
    decision_fits: bool = False
    decision_stop: str = "extrapolated"
    nested_starts: bool = False
    nested_start_tolerance: float = 0.0

    def __post_init__(self) -> None:
        if not isinstance(self.model_form_allowance, (bool, np.bool_)):
            raise AllowanceError(f"model_form_allowance must be true or false, got {self.model_form_allowance!r}")
        if not isinstance(self.converged_step, (bool, np.bool_)):
            raise ValueError(f"converged_step must be true or false, got {self.converged_step!r}")
        for option in ("spanning_forms", "operating_point_forms", "nested_forms", "decision_fits", "nested_starts"):
            if not isinstance(getattr(self, option), (bool, np.bool_)):
                raise ValueError(f"{option} must be true or false, got {getattr(self, option)!r}")
        tolerance = self.nested_start_tolerance
        if isinstance(tolerance, (bool, np.bool_)) or not isinstance(tolerance, (int, float, np.number)) \
                or not np.isfinite(tolerance) or tolerance < 0:
            raise ValueError(f"nested_start_tolerance must be a finite number of 2V at or above 0, got {tolerance!r}")
        if self.decision_stop not in ("extrapolated", "predicted"):
            raise ValueError(f"decision_stop {self.decision_stop!r}: choose 'extrapolated' (method version 6) or "
                             "'predicted' (method version 7)")


#: the method versions of the synthetic concepts' diagnosis (docs/gap-diagnosis.md): what each
#: changed; each is a set of :class:`DiagnosisSettings` switches (:func:`method_switches`), and a
#: version is frozen with its evaluation block in a protocol file under ``benchmarks/``
METHOD_VERSIONS = {1: "the nominal model's kinematics and command taken as exact",
                   2: "the model-form allowance (kinematic tolerance, command lag) fitted in every model",
                   3: "2 at the model contract's converged step where no effect brings faster dynamics "
                      "(tried, not adopted)",
                   4: "2 with the spanning forms: friction per direction, a sensor delay with its filter",
                   5: "4 with the operating-point forms (a ripple share with the motor torque, a joint angle along "
                      "the stroke, a stiffness with the torque carried), the nesting forms only, at the model "
                      "contract's converged step where no effect brings faster dynamics",
                   6: "5 with fits at the precision the verdict reads: each stops once the decrease of 2V still to "
                      "come is below 0.1 (a hundredth of the evidence margin), no identifiable combinations of "
                      "held parameters",
                   7: "6 with the decrease still to come judged by what the next full Gauss-Newton step promises "
                      "at the current iterate, not extrapolated from past decreases (version 6 stopped a nominal "
                      "fit on a plateau, 1798 in 2V short of its optimum)",
                   8: "4 with nested starts: a candidate fit that ends below a model its form contains (the "
                      "reference model, or a form it reduces to, as fitted) is refitted from that model's point, "
                      "the better fit kept (a form can fit no worse than the models it contains)",
                   9: "8 refitting only a fit that ends more than the evidence margin (10 in 2V) below a model its "
                      "form contains: a smaller shortfall moves no verdict (version 8 cost 15-19 % more time)",
                   10: "4 at the model contract's converged step where no effect brings faster dynamics (version 3's "
                       "step on the default's forms, judged by a paired non-inferiority rule)"}

#: the version ``DiagnosisSettings()`` gives: 4 since its evaluation block 5205 met its rule (version 2 before)
DEFAULT_METHOD_VERSION = 4


def method_switches(version: int) -> dict[str, Any]:
    """The :class:`DiagnosisSettings` switches of method ``version`` (:data:`METHOD_VERSIONS`), to
    lay over a strategy's settings with :func:`dataclasses.replace`; the other settings (iteration
    caps, hold-out fraction) are the same in every version."""
    if version not in METHOD_VERSIONS:
        raise ValueError(f"no gap method version {version}; choose from {', '.join(map(str, METHOD_VERSIONS))}")
    if version == 8:        # built on version 4, the default, not on the faster versions 5-7
        return {**method_switches(4), "nested_starts": True}
    if version == 9:
        return {**method_switches(8), "nested_start_tolerance": MARGIN_EVIDENCE}
    if version == 10:
        return {**method_switches(4), "converged_step": True}
    return {"model_form_allowance": version >= 2, "converged_step": version in (3, 5, 6, 7),
            "spanning_forms": version >= 4, "operating_point_forms": version >= 5, "nested_forms": version < 5,
            "decision_fits": version >= 6, "decision_stop": "predicted" if version >= 7 else "extrapolated",
            "nested_starts": False, "nested_start_tolerance": 0.0}


def method_version_of(settings: DiagnosisSettings) -> int | None:
    """The method version whose switches ``settings`` carry, None for a combination no version has."""
    for version in METHOD_VERSIONS:
        if all(getattr(settings, key) == value for key, value in method_switches(version).items()):
            return version
    return None


class GapMetric(Protocol):
    """The held-out gap of a fitted model. ``figures`` returns at least ``gap`` (the metric),
    ``z`` (its significance in noise σ, NaN when the metric has none), ``factors`` (common
    error factors), ``per_channel`` ({name: value}), ``significant`` (the gap stands out of
    the noise) and ``terms``: per-sample additive terms (n, k) whose column sums give the gap
    through ``combine`` (the block bootstrap of the shrink resamples their block sums), for
    residual ``records`` of ``model`` on ``measurements`` (same order) in ``channels``, their
    complete residual stretches ``segments`` [(n_i, m)] and channel scales ``spread`` (m,)."""

    description: str

    def figures(self, records: Sequence[ResidualRecord], measurements: Sequence[Measurement], model,
                channels: Sequence[str], segments: Sequence[np.ndarray], spread: np.ndarray) -> dict[str, Any]: ...

    def combine(self, sums: np.ndarray) -> np.ndarray:
        """The gap from column sums of ``terms`` (..., k)."""


@dataclass(frozen=True)
class SystematicNrmse:
    """Gap metric: the systematic NRMSE (:func:`ema_uq.gap.localize.systematic_nrmse`);
    significant when common error factors are found or its z exceeds ``z_significant``."""

    z_significant: float = 5.0
    description: str = "held-out systematic NRMSE: sqrt(channel mean of short-lag residual products / mean square)"

    def figures(self, records, measurements, model, channels, segments, spread) -> dict[str, Any]:
        parts, sigma, found = systematic_products(segments)
        p = np.concatenate(parts)
        gap, per_channel, z, factors = nrmse_of_products(p, sigma, found.n_factors, spread)
        # per sample: its normalised systematic energy (channel mean) and a count
        energy = np.mean(p / spread ** 2, axis=1)
        ok = np.isfinite(energy)
        terms = np.column_stack([np.where(ok, energy, 0.0), ok.astype(float)])[ok]
        return {"gap": gap, "z": z, "factors": factors, "per_channel": dict(zip(channels, map(float, per_channel))),
                "significant": bool(z > self.z_significant or factors > 0), "terms": terms}

    def combine(self, sums: np.ndarray) -> np.ndarray:
        return np.sqrt(np.maximum(sums[..., 0] / sums[..., 1], 0.0))


def localize_residual(records, channels, model, theta, measurements, spread, constants=None):
    """The default localisation: :func:`ema_uq.gap.localize.localize` (actuator regimes)."""
    return localize(records, channels, model, theta, constants=constants, spread=spread)


@dataclass(frozen=True)
class DiagnosisStrategy:
    """What the gap diagnosis does differently for one concept.

    channels : fitted channels (None: every channel the estimation records share).
    constants : design constants (vector) of one record (None: the model's nominal ones), used
        for the fits (those of the first estimation record) and every simulation of a record.
    settings : default :class:`DiagnosisSettings`.
    start_multiples : start grid of an effect's magnitudes, multiples of ``Effect.start``
        (phases always on four points of a turn).
    metric : the held-out gap metric (:class:`GapMetric`).
    localize : ``(records, channels, model, theta, measurements, spread) -> localisation``;
        the result needs ``z``, ``structured``, ``where_regimes``, ``where_channels()``,
        ``signature_match(signature)``, ``summary()`` and ``to_json()``.
    where_source : ``"larger z"`` (the nominal localisation on estimation or held-out data,
        whichever has the larger systematic z, gives ``where``) or ``"held-out"``.
    thresholds : verdict thresholds.
    reference_fit : base parameter values of a fit on healthy data: the nominal fit starts
        there, and with ``hold_base`` no base parameter is fitted at all.
    hold_base : fault diagnosis: base parameters held (at ``reference_fit``, else nominal);
        the nominal model is evaluated, not fitted, and every candidate refit frees only its
        effect's parameters.
    replicate_prediction : for records that repeat one experiment (the same cycle, run after
        run), ``(estimation measurements, their nominal residuals, estimation channels,
        held-out measurements, held-out channels) -> [(n_i, m)] | None``: the held-out residual
        a time-invariant model could predict from the estimation records alone (the replicate
        mean), None where some held-out record repeats none of them. The gap it leaves is the
        ceiling of every candidate's shrink (the part of the gap that changes from run to run,
        which no fixed-parameter effect can explain); None (field or result): no replicates,
        the whole gap counts as explainable. The metric's ``z`` must be the mean
        excess over its standard error (as :class:`ema_uq.rigs.cranfield.ExcessNrmse`'s), so that
        the nominal's z less the ceiling's is the z of the reproducible part.
    structure : thresholds of the cell test of what a candidate leaves
        (:func:`ema_uq.gap.structure.structure_left`).
    healthy_records : fault diagnosis: held-out records of the healthy rig that the reference fit
        did not see. The reference model's residual on them is the *healthy level* of every cell of
        the cell test (per sample): structure the healthy rig leaves too is not the fault's, and no
        candidate is asked to close it. Empty: the healthy level is white noise.
    model_form : ``model -> ModelFormAllowance | None``, the concept's model-form allowance
        (:mod:`ema_uq.gap.allowance`: relative offsets of the kinematic design constants within
        their tolerance, a first-order lag of the position command), fitted in every model when
        ``settings.model_form_allowance`` is on and the base parameters are fitted (not with
        ``hold_base``: a reference fit on healthy data already holds the rig's model form).
        None: the concept has none (EMPS, Cranfield). The default strategy of the actuator
        concepts uses :func:`ema_uq.gap.allowance.actuator_allowance`.
    """

    name: str = "default"
    channels: tuple[str, ...] | None = None
    constants: Callable[[Measurement], np.ndarray] | None = None
    settings: DiagnosisSettings = DiagnosisSettings()
    start_multiples: tuple[float, ...] = START_MULTIPLES
    metric: Any = SystematicNrmse()
    localize: Callable[..., Any] = localize_residual
    where_source: str = "larger z"
    thresholds: Thresholds = Thresholds()
    reference_fit: Mapping[str, float] | None = None
    hold_base: bool = False
    replicate_prediction: Callable[..., list[np.ndarray] | None] | None = None
    structure: StructureSettings = StructureSettings()
    healthy_records: tuple[Measurement, ...] = ()
    model_form: Callable[[Any], ModelFormAllowance | None] | None = None

    def __post_init__(self) -> None:
        if self.where_source not in ("larger z", "held-out"):
            raise ValueError(f"where_source {self.where_source!r}: choose 'larger z' or 'held-out'")
        if self.settings.max_effects < 1:
            raise ValueError(f"max_effects {self.settings.max_effects}: give at least 1 round")

    def with_reference(self, reference_fit: Mapping[str, float], hold_base: bool = True) -> "DiagnosisStrategy":
        """This strategy for fault diagnosis against a fit on healthy data (base parameters held)."""
        return replace(self, reference_fit=dict(reference_fit), hold_base=hold_base)

    def constants_of(self, measurement: Measurement) -> np.ndarray | None:
        return None if self.constants is None else self.constants(measurement)

    def allowance_for(self, model, settings: DiagnosisSettings) -> ModelFormAllowance | None:
        """The model-form allowance a diagnosis of ``model`` with ``settings`` fits (None: none)."""
        if not settings.model_form_allowance or self.model_form is None or self.hold_base:
            return None
        allowance = self.model_form(model)
        if allowance is not None and not isinstance(allowance, ModelFormAllowance):
            raise AllowanceError(f"strategy {self.name}: model_form returned {type(allowance).__name__}, "
                                 "not a ModelFormAllowance")
        return allowance


DEFAULT_STRATEGY = DiagnosisStrategy(model_form=actuator_allowance)

#: concept -> strategy, or "module:attribute" imported on first use
_REGISTRY: dict[str, DiagnosisStrategy | str] = {"emps": "ema_uq.rigs.emps:EMPS_STRATEGY",
                                                 "cranfield": "ema_uq.rigs.cranfield:CRANFIELD_STRATEGY"}


def register_strategy(concept: str, strategy: DiagnosisStrategy | str) -> None:
    """Make ``strategy`` (or a lazily imported ``"module:attribute"``) the concept's default."""
    _REGISTRY[concept] = strategy


def strategy_for(model) -> DiagnosisStrategy:
    """The diagnosis strategy of a concept (a :class:`~ema_uq.models.Model`; see the module docstring)."""
    own = getattr(model, "gap_strategy", None)
    if own is not None:
        return own() if callable(own) else own
    entry = _REGISTRY.get(model.name, DEFAULT_STRATEGY)
    if isinstance(entry, str):
        module, attribute = entry.split(":")
        entry = getattr(importlib.import_module(module), attribute)
        _REGISTRY[model.name] = entry
    return entry
