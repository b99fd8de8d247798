"""Blind self-check of the gap diagnosis on records it did not write: seeded rig-like data
from the independent simulator of :mod:`ema_uq.gap.variants`, diagnosed without their
labels and scored against them.

Why not the catalogue's own kernels: records made by the equations the diagnosis fits (at
magnitudes on its start grid, from nominal base parameters) only show that it recovers its
own equations. Here every record comes from an independently written simulator and effect
variant, so a right answer means the diagnosis named the right *family* of physics.

Cases (:func:`build_cases`), for each concept and each sensor set (``full``: every output;
``realistic``: the rig's sensors, :data:`ema_uq.gap.variants.REALISTIC_CHANNELS`):

- every in-catalogue variant once (expected label: its family), its parameters drawn by
  :func:`~ema_uq.gap.variants.draw_variant_parameters` (magnitudes log-uniform from "just
  visible at 2 % noise" to "strong", phases uniform in [0, 2 pi));
- ``none_per_set`` no-effect cases (expected ``none``);
- every out-of-catalogue variant once (expected ``unexplained``).

Each case's records (:func:`~ema_uq.gap.variants.make_records`: estimation on deploy-retract,
validation, a scaled second validation; base parameters U(+-10 %) off nominal, rig gains
U(+-1 %), 2 % noise) derive from the case's own seed, and :func:`ema_uq.gap.diagnose` gets
the estimation record and both validation records: it selects the winner on the first and
scores the honest shrink (signed, unclipped, with its standard error) on the second; its
starts are its own (the data carry no label and no true value).

Seeds: the case seed is the first 32-bit word of ``numpy.random.SeedSequence((seed,
concept index, sensor-set index, slot))``, ``slot`` = the variant's index in
:data:`~ema_uq.gap.variants.VARIANTS` or ``100 + k`` for the k-th none case; the variant
parameters are drawn from ``default_rng((case seed, 1))``, the records from ``case seed``
and the diagnosis is seeded with it. A case's outcome therefore depends only on (seed,
concept, sensor set, slot): not on which other cases run, their order or the number of
worker processes. The verdict thresholds of :mod:`ema_uq.gap.attribute` were calibrated on
the seeds 100-103 with catalogue-kernel records; the self-check never uses those seeds
(:func:`build_cases` refuses a derived seed among them).

Scores (:class:`SelfCheckResult`): top-1 accuracy over in-catalogue cases (right only if the
verdict is ``effect`` and the family named is the variant's); false-alarm rate over none
cases (any verdict but ``none``); out-of-catalogue flagged rate, STRICT: only ``unexplained``
counts (a low-confidence attribution is a miss); median and quartiles of the honest shrink
where the right family was named; confusion matrix truth family x verdict label; 95 %
Clopper-Pearson intervals for the three rates. Targets: top-1 >= 0.90, false alarms <= 0.05,
out-of-catalogue flagged >= 0.80, each reported met or NOT met on its point estimate, and
"shown at 95 %" when its one-sided 95 % Clopper-Pearson bound meets it too
(:attr:`SelfCheckResult.demonstrated`). ``kinds`` runs some case kinds only (the same cases as
in the full list): more none cases for the false-alarm rate, without repeating the others.
"""
from __future__ import annotations

import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from multiprocessing import get_context
from typing import Any, Callable, Mapping, Sequence

import numpy as np
from scipy import stats

from ..models import get_model
from .attribute import diagnose
from .strategy import DiagnosisSettings
from .variants import CONCEPTS, VARIANTS, draw_variant_parameters, make_records
from ..errors import EmaUqError

SENSOR_SETS = ("full", "realistic")
BASE_PERTURBATION = 0.10
DEFAULT_SEED = 2024
NONE_PER_SET = 5                 # x 2 sensor sets x 2 concepts = 20 no-effect cases in the full check
NONE_SLOT = 100                  # slot of the first none case (variants take 0..len(VARIANTS)-1)
PARAMETER_STREAM = 1             # variant parameters come from default_rng((case seed, PARAMETER_STREAM))
CALIBRATION_SEEDS = frozenset(range(100, 104))
TARGET_TOP1, TARGET_FALSE_ALARM, TARGET_OUT_OF_CATALOGUE = 0.90, 0.05, 0.80
OUT_OF_CATALOGUE_ROW = "outside catalogue"
#: case kinds: in-catalogue variants, no-effect records, variants outside the catalogue
KINDS = ("effect", "none", "out_of_catalogue")
#: the quick subset (CI, smoke study): (sensor set, variant or None) on the study's concept
QUICK_CASES = (("realistic", "load_friction_linear"), ("realistic", None), ("realistic", "current_sensor_error"))


class SelfCheckError(EmaUqError):
    """A self-check request that cannot be built (unknown concept, sensor set or size)."""


@dataclass(frozen=True)
class Case:
    """One labelled case. ``kind``: ``effect`` (in-catalogue variant), ``none`` or
    ``out_of_catalogue``; ``variant`` None for none cases; ``family`` the catalogue family
    the diagnosis should name (None unless ``effect``)."""

    case_id: str
    concept: str
    sensors: str
    kind: str
    variant: str | None
    family: str | None
    seed: int

    @property
    def expected(self) -> str:
        """The right verdict label: the family, ``none`` or ``unexplained``."""
        return {"effect": self.family, "none": "none"}.get(self.kind, "unexplained")

    @property
    def truth_row(self) -> str:
        """Row of the confusion matrix: the family, ``none`` or ``outside catalogue``."""
        return {"effect": self.family, "none": "none"}.get(self.kind, OUT_OF_CATALOGUE_ROW)


@dataclass
class CaseOutcome:
    """The diagnosis of one case: verdict, effect form and family named, confidence, the
    honest shrink (signed, unclipped; None/NaN unless ``effect``) with its standard error
    and the record it was scored on, the held-out gap before/after, the drawn variant
    parameters (hidden from the diagnosis) and the wall time [s]. A case whose diagnosis raised
    has verdict ``error`` and the exception in ``message``: it counts as wrong, and the other
    cases' outcomes are kept."""

    case: Case
    verdict: str
    effect: str | None
    family: str | None
    confidence: str
    shrink: float
    shrink_se: float
    shrink_record: str | None
    gap_before: float
    gap_after: float
    parameters: dict[str, float]
    wall_time_s: float
    top: list[dict[str, Any]] = field(default_factory=list)
    message: str = ""

    @property
    def label(self) -> str:
        """The verdict as a confusion-matrix column: the family named, ``none`` or ``unexplained``."""
        return str(self.family) if self.verdict == "effect" else self.verdict

    @property
    def correct(self) -> bool:
        """Right family named (effect), ``none`` (none), ``unexplained`` (out of catalogue; strict)."""
        return self.label == self.case.expected and (self.case.kind != "effect" or self.verdict == "effect")

    def to_json(self) -> dict[str, Any]:
        out = {k: v for k, v in vars(self).items() if k != "case"}
        case = dict(vars(self.case))
        case["truth_family"] = case.pop("family")
        out.update(case)
        out.update(label=self.label, expected=self.case.expected, correct=self.correct)
        return _clean(out)

    @classmethod
    def from_json(cls, c: Mapping[str, Any]) -> "CaseOutcome":
        case = Case(c["case_id"], c["concept"], c["sensors"], c["kind"], c["variant"], c["truth_family"],
                    int(c["seed"]))
        return cls(case, c["verdict"], c["effect"], c["family"], c["confidence"], _num(c["shrink"]),
                   _num(c["shrink_se"]), c.get("shrink_record"), _num(c["gap_before"]), _num(c["gap_after"]),
                   dict(c.get("parameters") or {}), float(c["wall_time_s"]), list(c.get("top") or []),
                   str(c.get("message") or ""))


def _num(value) -> float:
    return float("nan") if value is None else float(value)


def _clean(value):
    if isinstance(value, (float, np.floating)):
        return float(value) if np.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    if isinstance(value, np.bool_):
        return bool(value)
    if isinstance(value, np.integer):
        return int(value)
    return value


def clopper_pearson(k: int, n: int, level: float = 0.95) -> tuple[float, float]:
    """Exact binomial interval of a rate k/n (NaN, NaN for n = 0)."""
    if n == 0:
        return float("nan"), float("nan")
    alpha = 1.0 - level
    low = 0.0 if k == 0 else float(stats.beta.ppf(alpha / 2, k, n - k + 1))
    high = 1.0 if k == n else float(stats.beta.ppf(1 - alpha / 2, k + 1, n - k))
    return low, high


@dataclass
class SelfCheckResult:
    """Scores of a self-check run (see the module docstring); ``settings`` holds what built
    the case list (concepts, sensor sets, none_per_set, quick)."""

    outcomes: list[CaseOutcome]
    seed: int
    quick: bool
    wall_time_s: float
    settings: dict[str, Any] = field(default_factory=dict)
    provenance: dict[str, Any] = field(default_factory=dict)

    # --- scores ----------------------------------------------------------------------------
    def of(self, kind: str) -> list[CaseOutcome]:
        return [o for o in self.outcomes if o.case.kind == kind]

    def _rate(self, kind: str, hit: Callable[[CaseOutcome], bool]) -> dict[str, Any]:
        cases = self.of(kind)
        k = sum(bool(hit(o)) for o in cases)
        low, high = clopper_pearson(k, len(cases))
        return {"value": k / len(cases) if cases else float("nan"), "count": k, "n": len(cases),
                "interval95": [low, high]}

    @property
    def top1(self) -> dict[str, Any]:
        """In-catalogue cases where the verdict is ``effect`` and names the variant's family."""
        return self._rate("effect", lambda o: o.correct)

    @property
    def false_alarms(self) -> dict[str, Any]:
        """No-effect cases with any verdict but ``none``."""
        return self._rate("none", lambda o: o.verdict != "none")

    @property
    def out_of_catalogue_flagged(self) -> dict[str, Any]:
        """Out-of-catalogue cases diagnosed ``unexplained`` (nothing else counts)."""
        return self._rate("out_of_catalogue", lambda o: o.verdict == "unexplained")

    @property
    def top1_accuracy(self) -> float:
        return self.top1["value"]

    @property
    def false_alarm_rate(self) -> float:
        return self.false_alarms["value"]

    @property
    def out_of_catalogue_rate(self) -> float:
        return self.out_of_catalogue_flagged["value"]

    @property
    def shrink(self) -> dict[str, Any]:
        """Honest shrink where the right family was named: median, quartiles, range, median se."""
        found = [o for o in self.of("effect") if o.correct and np.isfinite(o.shrink)]
        values = np.array([o.shrink for o in found])
        if not found:
            return {"n": 0, "median": float("nan"), "q25": float("nan"), "q75": float("nan"),
                    "min": float("nan"), "max": float("nan"), "median_se": float("nan")}
        q25, median, q75 = np.percentile(values, [25, 50, 75])
        return {"n": len(found), "median": float(median), "q25": float(q25), "q75": float(q75),
                "min": float(values.min()), "max": float(values.max()),
                "median_se": float(np.nanmedian([o.shrink_se for o in found]))}

    @property
    def met(self) -> dict[str, bool]:
        """Each target met on its point estimate (a rate over no cases is not met)."""
        return {"top1_accuracy": bool(self.top1_accuracy >= TARGET_TOP1),
                "false_alarm_rate": bool(self.false_alarm_rate <= TARGET_FALSE_ALARM),
                "out_of_catalogue_flagged": bool(self.out_of_catalogue_rate >= TARGET_OUT_OF_CATALOGUE)}

    @property
    def demonstrated(self) -> dict[str, bool]:
        """Each target shown at 95 % confidence, not only met by the point estimate: the one-sided
        95 % Clopper-Pearson bound (the two-sided 90 % interval's end) on the target's side of the
        rate meets it. E.g. 0 false alarms need 59 none cases to show <= 0.05 (0.95^59 < 0.05)."""
        def bound(rate: dict[str, Any], upper: bool) -> float:
            low, high = clopper_pearson(rate["count"], rate["n"], level=0.90)
            return high if upper else low

        top1, alarms, flagged = self.top1, self.false_alarms, self.out_of_catalogue_flagged
        return {"top1_accuracy": bool(top1["n"] and bound(top1, False) >= TARGET_TOP1),
                "false_alarm_rate": bool(alarms["n"] and bound(alarms, True) <= TARGET_FALSE_ALARM),
                "out_of_catalogue_flagged": bool(flagged["n"] and bound(flagged, False) >= TARGET_OUT_OF_CATALOGUE)}

    def confusion(self) -> dict[str, dict[str, int]]:
        """{truth family (``none``, ``outside catalogue``): {verdict label: count}} over every case."""
        matrix: dict[str, dict[str, int]] = {}
        for o in self.outcomes:
            row = matrix.setdefault(o.case.truth_row, {})
            row[o.label] = row.get(o.label, 0) + 1
        return matrix

    def by_set(self) -> dict[str, dict[str, float]]:
        """The three rates per concept/sensor set."""
        out = {}
        for key in dict.fromkeys(f"{o.case.concept}/{o.case.sensors}" for o in self.outcomes):
            part = SelfCheckResult([o for o in self.outcomes if f"{o.case.concept}/{o.case.sensors}" == key],
                                   self.seed, self.quick, 0.0)
            out[key] = {"top1_accuracy": part.top1_accuracy, "false_alarm_rate": part.false_alarm_rate,
                        "out_of_catalogue_flagged": part.out_of_catalogue_rate}
        return out

    # --- text ------------------------------------------------------------------------------
    def score_lines(self) -> list[str]:
        def line(name, rate, target, key, cmp):
            low, high = rate["interval95"]
            return (f"    {name:<28} {rate['value']:6.3f} ({rate['count']}/{rate['n']}, 95 % CI "
                    f"{low:.2f}-{high:.2f})  target {cmp} {target:.2f}: {'met' if self.met[key] else 'NOT met'}"
                    f"{', shown at 95 %' if self.demonstrated[key] else ''}")

        s = self.shrink
        return [line("top-1 accuracy (family)", self.top1, TARGET_TOP1, "top1_accuracy", ">="),
                line("false-alarm rate", self.false_alarms, TARGET_FALSE_ALARM, "false_alarm_rate", "<="),
                line("out of catalogue flagged", self.out_of_catalogue_flagged, TARGET_OUT_OF_CATALOGUE,
                     "out_of_catalogue_flagged", ">="),
                f"    {'honest shrink (right family)':<28} median {s['median']:.3f}, quartiles {s['q25']:.3f}-"
                f"{s['q75']:.3f}, range {s['min']:.3f}-{s['max']:.3f}, median se {s['median_se']:.3f} "
                f"(n = {s['n']})"]

    def confusion_lines(self) -> list[str]:
        matrix = self.confusion()
        columns = sorted({lab for row in matrix.values() for lab in row}, key=_label_order)
        width = max([len(r) for r in matrix] + [18])
        cells = [max(len(c), 4) for c in columns]
        lines = ["    " + " " * width + " " + " ".join(f"{c:>{w}}" for c, w in zip(columns, cells))]
        for truth in sorted(matrix, key=_label_order):
            lines.append(f"    {truth:<{width}} "
                         + " ".join(f"{matrix[truth].get(c, 0) or '.':>{w}}" for c, w in zip(columns, cells)))
        return lines

    def case_lines(self) -> list[str]:
        lines = [f"    {'case':<44} {'family':<24} {'verdict':<11} {'family found':<24} {'conf':<6} "
                 f"{'shrink +- se':>15} {'time':>6}  ok"]
        for o in self.outcomes:
            shrink = "" if not np.isfinite(o.shrink) else f"{o.shrink:.3f} +- {o.shrink_se:.3f}"
            lines.append(f"    {o.case.case_id:<44} {o.case.truth_row:<24} {o.verdict:<11} "
                         f"{(o.family if o.verdict == 'effect' else '-'):<24} {o.confidence:<6} {shrink:>15} "
                         f"{o.wall_time_s:>5.0f}s  {'yes' if o.correct else 'NO'}")
        return lines

    def summary(self) -> str:
        concepts = ", ".join(self.settings.get("concepts", []))
        return "\n".join([f"[[Gap self-check]] {len(self.outcomes)} cases on independent variant records "
                          f"({concepts}; seed {self.seed}{', quick subset' if self.quick else ''}), "
                          f"{self.wall_time_s:.0f} s", *self.score_lines(),
                          "[[Confusion]] (rows: truth family, columns: verdict label)", *self.confusion_lines(),
                          "[[Cases]]", *self.case_lines()])

    # --- serialised form -------------------------------------------------------------------
    def to_json(self) -> dict[str, Any]:
        return _clean({
            "n_cases": len(self.outcomes), "seed": self.seed, "quick": self.quick, "settings": self.settings,
            "generator": "ema_uq.gap.variants (independent simulator and effect variants)",
            "top1": self.top1, "false_alarms": self.false_alarms, "demonstrated": self.demonstrated,
            "out_of_catalogue_flagged": self.out_of_catalogue_flagged, "shrink": self.shrink,
            "top1_accuracy": self.top1_accuracy, "false_alarm_rate": self.false_alarm_rate,
            "out_of_catalogue_rate": self.out_of_catalogue_rate, "met": self.met,
            "targets": {"top1_accuracy": TARGET_TOP1, "false_alarm_rate": TARGET_FALSE_ALARM,
                        "out_of_catalogue_flagged": TARGET_OUT_OF_CATALOGUE},
            "by_set": self.by_set(), "confusion": self.confusion(), "cases": [o.to_json() for o in self.outcomes],
            "wall_time_s": self.wall_time_s, "provenance": self.provenance,
        })

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> "SelfCheckResult":
        return cls([CaseOutcome.from_json(c) for c in data["cases"]], int(data["seed"]), bool(data["quick"]),
                   float(data["wall_time_s"]), dict(data.get("settings") or {}), dict(data.get("provenance") or {}))


def _label_order(label: str) -> tuple[int, str]:
    return ({"none": 1, "unexplained": 2, OUT_OF_CATALOGUE_ROW: 2}.get(label, 0), label)


# ----------------------------------------------------------------------------------------
# cases
# ----------------------------------------------------------------------------------------
def case_seed(seed: int, concept: str, sensors: str, slot: int) -> int:
    """The case's own seed (see the module docstring)."""
    state = np.random.SeedSequence((int(seed), CONCEPTS.index(concept), SENSOR_SETS.index(sensors), int(slot)))
    return int(state.generate_state(1)[0])


def _case(seed: int, concept: str, sensors: str, variant: str | None, none_index: int = 0) -> Case:
    names = list(VARIANTS)
    slot = NONE_SLOT + none_index if variant is None else names.index(variant)
    family = None if variant is None else VARIANTS[variant].family
    kind = "none" if variant is None else ("effect" if family is not None else "out_of_catalogue")
    label = f"none#{none_index}" if variant is None else variant
    case = Case(f"{concept}/{sensors}/{label}", concept, sensors, kind, variant, family,
                case_seed(seed, concept, sensors, slot))
    if case.seed in CALIBRATION_SEEDS:
        raise SelfCheckError(f"case {case.case_id} drew seed {case.seed}, one the thresholds were calibrated on; "
                             "choose another self-check seed")
    return case


def _check_whole_number(name: str, value: Any, minimum: int) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise SelfCheckError(f"{name} must be a whole number >= {minimum}, got {value!r}")


def build_cases(concepts: Sequence[str] = CONCEPTS, *, seed: int = DEFAULT_SEED, quick: bool = False,
                sensors: Sequence[str] = SENSOR_SETS, none_per_set: int = NONE_PER_SET,
                kinds: Sequence[str] = KINDS, none_first: int = 0) -> list[Case]:
    """The labelled cases: per concept x sensor set, every in-catalogue variant, ``none_per_set``
    none cases (numbers ``none_first`` on) and every out-of-catalogue variant, of the ``kinds``
    asked for (``quick``: :data:`QUICK_CASES` on the first concept). A case is the same whichever
    others are built (its seed depends on its slot only): e.g. ``kinds=("none",)`` with
    ``none_first`` at an earlier run's ``none_per_set`` adds none cases to its false-alarm count
    without repeating any."""
    concepts, sensors = list(concepts), list(sensors)
    unknown = [k for k in kinds if k not in KINDS]
    if unknown:
        raise SelfCheckError(f"unknown case kind {unknown[0]!r}; choose from {', '.join(KINDS)}")
    if not kinds:
        raise SelfCheckError(f"give at least one case kind of {', '.join(KINDS)}")
    for concept in concepts:
        if concept not in CONCEPTS:
            raise SelfCheckError(f"no independent variants for concept {concept!r}; choose from {', '.join(CONCEPTS)}")
    for s in sensors:
        if s not in SENSOR_SETS:
            raise SelfCheckError(f"unknown sensor set {s!r}; choose from {', '.join(SENSOR_SETS)}")
    if not concepts or not sensors:
        raise SelfCheckError("the self-check needs at least one concept and one sensor set")
    _check_whole_number("none_per_set", none_per_set, 0)
    _check_whole_number("none_first", none_first, 0)
    if quick:
        cases = [_case(seed, concepts[0], s, v) for s, v in QUICK_CASES]
    else:
        cases = []
        for concept in concepts:
            for s in sensors:
                cases += [_case(seed, concept, s, v) for v, var in VARIANTS.items() if var.family is not None]
                cases += [_case(seed, concept, s, None, k) for k in range(none_first, none_first + none_per_set)]
                cases += [_case(seed, concept, s, v) for v, var in VARIANTS.items() if var.family is None]
    return [c for c in cases if c.kind in kinds]


def case_records(case: Case):
    """(estimation, validation, second validation, truth) of a case; the records carry no label."""
    params = None
    if case.variant is not None:
        params = draw_variant_parameters(case.variant, np.random.default_rng((case.seed, PARAMETER_STREAM)),
                                         case.concept)
    return make_records(case.concept, case.variant, params, seed=case.seed, channels=case.sensors,
                        base_perturbation=BASE_PERTURBATION)


def family_of(result, concept: str) -> str | None:
    """The family the diagnosis named: ``GapResult.family``, else the catalogue entry's
    ``family``, else the effect name (a catalogue without families)."""
    if result.verdict != "effect" or result.effect is None:
        return None
    family = getattr(result, "family", None)
    if family:
        return family
    effect = get_model(concept).effect_catalogue.get(result.effect)
    return getattr(effect, "family", None) or result.effect


def run_case(case: Case, settings: DiagnosisSettings | None = None) -> CaseOutcome:
    """Simulate a case's records, diagnose them blind and return the outcome."""
    estimation, validation, validation2, truth = case_records(case)
    t0 = time.perf_counter()
    try:
        result = diagnose([estimation], [validation, validation2], settings=settings, seed=case.seed)
    except Exception as exc:    # noqa: BLE001 - one failing case must not lose a campaign's other outcomes
        return CaseOutcome(case, "error", None, None, "-", float("nan"), float("nan"), None, float("nan"),
                           float("nan"), dict(truth["parameters"]), time.perf_counter() - t0,
                           message=f"{type(exc).__name__}: {exc}")
    gap = result.gap
    top = [{"effect": c.effect, "score": c.score, "delta_bic": c.delta_bic, "held_out_gain": c.held_out_gain,
            "signature_match": c.signature_match} for c in result.ranking[:3]]
    return CaseOutcome(case, result.verdict, result.effect, family_of(result, case.concept), result.confidence,
                       _num(gap.get("shrink")), _num(gap.get("shrink_se")), gap.get("shrink_record"),
                       float(gap["before"]), float(gap["after"]), dict(truth["parameters"]),
                       time.perf_counter() - t0, top)


def _progress_line(i: int, n: int, o: CaseOutcome) -> str:
    shrink = "" if not np.isfinite(o.shrink) else f", shrink {o.shrink:.2f} +- {o.shrink_se:.2f}"
    return (f"[{i}/{n}] {o.case.case_id}: {o.label} ({o.confidence}){shrink}, "
            f"{'ok' if o.correct else 'WRONG'} (expected {o.case.expected}), {o.wall_time_s:.0f} s"
            + (f" - {o.message}" if o.message else ""))


def self_check(*, seed: int = DEFAULT_SEED, quick: bool = False, concepts: Sequence[str] = CONCEPTS,
               sensors: Sequence[str] = SENSOR_SETS, none_per_set: int = NONE_PER_SET,
               kinds: Sequence[str] = KINDS, none_first: int = 0, cases: Sequence[Case] | None = None,
               settings: DiagnosisSettings | None = None, jobs: int = 1,
               progress: Callable[[str], None] | None = None) -> SelfCheckResult:
    """Run the blind self-check and score it. ``jobs`` worker processes (spawned: a script
    calling this with ``jobs`` > 1 needs the ``if __name__ == "__main__"`` guard) diagnose cases
    in parallel; every case is seeded on its own, so the outcomes do not depend on ``jobs``."""
    _check_whole_number("jobs", jobs, 1)
    cases = list(cases) if cases is not None else build_cases(concepts, seed=seed, quick=quick, sensors=sensors,
                                                              none_per_set=none_per_set, kinds=kinds,
                                                              none_first=none_first)
    t0 = time.perf_counter()
    outcomes: list[CaseOutcome] = []
    if jobs == 1 or len(cases) == 1:
        results = map(run_case, cases, [settings] * len(cases))
        pool = None
    else:
        # spawn, not fork: numba's thread pool is not safe to fork
        pool = ProcessPoolExecutor(max_workers=min(jobs, len(cases)), mp_context=get_context("spawn"))
        results = pool.map(run_case, cases, [settings] * len(cases))
    try:
        for outcome in results:
            outcomes.append(outcome)
            if progress:
                progress(_progress_line(len(outcomes), len(cases), outcome))
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)
    used = {"concepts": sorted({c.concept for c in cases}, key=CONCEPTS.index),
            "sensors": sorted({c.sensors for c in cases}, key=SENSOR_SETS.index),
            "none_per_set": none_per_set, "none_first": none_first, "quick": quick,
            "base_perturbation": BASE_PERTURBATION,
            "kinds": [k for k in KINDS if any(c.kind == k for c in cases)]}
    return SelfCheckResult(outcomes, seed, quick, time.perf_counter() - t0, used)
