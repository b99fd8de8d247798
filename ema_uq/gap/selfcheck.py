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
- ``none_per_set`` no-effect cases, every second one stressed (expected ``none``; a
  low-confidence ``unexplained`` is right too);
- every out-of-catalogue variant once (expected a flag: ``unexplained`` or ``ambiguous``);
- every in-catalogue variant once more with its family left out of the catalogue (a flag).

What the figures can and cannot say: the variants were written apart from the catalogue, but
the catalogue later gained forms that mirror some of them (``backlash_compliant``,
``backlash_output``, ``torque_ripple_harmonics``, ``ujoint_stations``) and fit and verdict
rules were changed on named cases of the self-check seeds 1 and 2. Figures on those seeds are
in-sample. The out-of-sample figures are those of the evaluation block of the frozen protocol
of the default method (version 4: ``benchmarks/gap_protocol_v4.yaml``, block 5205; version 2's
``benchmarks/gap_protocol.yaml`` before it; ``benchmarks/gap.py --protocol``), run once on frozen
sources; the left-out cases ask what the diagnosis says of physics it has no form for, which
no added form can answer in advance.

Each case's records (:func:`~ema_uq.gap.variants.make_records`: estimation on deploy-retract,
validation, a scaled second validation; base parameters U(+-10 %) off nominal, rig gains
U(+-1 %), 2 % noise) derive from the case's own seed, and :func:`ema_uq.gap.diagnose` gets
the estimation record and both validation records: it selects the winner on the first and
scores the honest shrink (signed, unclipped, with its standard error) on the second; its
starts are its own (the data carry no label and no true value).

Seeds: the case seed is the first 32-bit word of ``numpy.random.SeedSequence((seed,
concept index, sensor-set index, slot))``, ``slot`` = the variant's index in
:data:`~ema_uq.gap.variants.VARIANTS`, ``100 + k`` for the k-th none case or ``200 + i`` for the
left-out case of the i-th variant; the variant parameters are drawn from ``default_rng((case
seed, 1))``, a stressed case's stress from ``default_rng((case seed, 2))``, the records from ``case seed``
and the diagnosis is seeded with it. A case's outcome therefore depends only on (seed,
concept, sensor set, slot): not on which other cases run, their order or the number of
worker processes. The verdict thresholds of :mod:`ema_uq.gap.attribute` were calibrated on
the seeds 100-103 with catalogue-kernel records; the self-check never uses those seeds
(:func:`build_cases` refuses a derived seed among them).

Left-out families (kind ``left_out``, :func:`build_cases`): every in-catalogue variant once
more, diagnosed with its family's forms removed from the catalogue (``diagnose(candidates=)``
gets every form of the other families, :func:`catalogue_families`). The diagnosis can no
longer name the physics in the records, so the right verdict is a flag: ``unexplained`` or
``ambiguous``. Slot ``200 + i`` for the i-th variant: other records than its ``effect`` case.

Variants written after method version 2 was frozen (:func:`unseen_cases`, slots ``300 + i`` and
``400 + i`` of :data:`~ema_uq.gap.variant_catalogue.UNSEEN_VARIANTS`), for the evaluation of
method version 4 (``variant_set="UNSEEN_VARIANTS_2"``, slots ``500 + i`` and ``600 + i`` of
:data:`~ema_uq.gap.variant_catalogue.UNSEEN_VARIANTS_2`) and for that of method version 5
(``variant_set="UNSEEN_VARIANTS_3"``, slots ``700 + i`` and ``800 + i`` of
:data:`~ema_uq.gap.variant_catalogue.UNSEEN_VARIANTS_3`): never in this list, so that a frozen
method can be run once on mechanisms nobody tuned it on (``benchmarks/gap_unseen.py``).

Model-form stress of no-effect cases: every odd-numbered none case (``none#1``, ``#3``, ...)
is *stressed*: its records differ from the fitted model in ways a rig always does
(:func:`ema_uq.gap.variants.draw_stress`: AR(1) sensor noise, quantised sensors, design
constants a few percent off, unrecorded command shaping), drawn from ``default_rng((case
seed, STRESS_STREAM))``. Right verdict of any none case: ``none``, or ``unexplained`` with low
confidence (a *soft alarm*); a named effect (``effect`` or ``ambiguous``; a diagnosis that
raised counts here too) is a *false alarm*.

Scores (:class:`SelfCheckResult`): top-1 accuracy over in-catalogue cases (right only if the
verdict is ``effect`` and the family named is the variant's); false-alarm rate over none
cases (plain and stressed also apart), the soft-alarm rate, the rate of ``unexplained`` with
high confidence (a *hard alarm*: no effect named, but wrong) and the rate of any verdict but
``none``; flagged rates (``unexplained`` or ``ambiguous``) of the out-of-catalogue and of the
left-out cases; the rate of a wrong family named with high confidence over every case that
carries an effect (in-catalogue, left-out, out-of-catalogue); median and quartiles of the
honest shrink where the right family was named; confusion matrices truth family x verdict
label (in-catalogue, none and out-of-catalogue cases; left-out cases apart); 95 %
Clopper-Pearson intervals. Targets (:data:`TARGETS`): top-1 >= 0.90, left-out and
out-of-catalogue flagged >= 0.85, wrong family named with high confidence <= 0.02, false
alarms <= 0.05 over at least 60 none cases of which at least 40 % stressed. A target's
status (:attr:`SelfCheckResult.status`) is ``met`` only when the one-sided 95 %
Clopper-Pearson bound on the target's side meets it (e.g. 0 false alarms need 59 cases:
0.95^59 < 0.05), ``not met`` only when the bound on the other side fails it, and ``n too
small`` otherwise (never ``met`` on one case). ``kinds`` runs some case kinds only (the same
cases as in the full list): more none cases for the false-alarm rate, without repeating the
others.

Scatter and gather: ``chunk=(i, n)`` runs the cases i, i+n, i+2n, ... of the full list (i in
0..n-1); :func:`gather` joins the n parts into the result of one run (outcomes in list order).
``cache`` (a folder) keeps each case's outcome as a JSON file and reads it back instead of
diagnosing again: an interrupted run resumes where it stopped.
"""
from __future__ import annotations

import json
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, replace
from multiprocessing import get_context
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import numpy as np

from ..models import get_model
from ..threads import single_threaded_worker
from .attribute import diagnose
from .candidates import offered_forms
from .strategy import DiagnosisSettings
from ..errors import EmaUqError
from .selfcheck_scores import Case, CaseOutcome, SelfCheckResult, _num
from .variant_catalogue import UNSEEN_SETS
from .variants import CONCEPTS, VARIANTS, draw_stress, draw_variant_parameters, make_records

# The scores and their targets stay importable from here, where they were defined before they
# had a room of their own (the command line, the benchmark and the tests reach them so).
from .selfcheck_scores import (FALSE_ALARM_MIN_CASES, FALSE_ALARM_MIN_STRESSED, FLAGGED, NAMED,  # noqa: F401
                               OUT_OF_CATALOGUE_ROW, TARGET_FALSE_ALARM, TARGET_LEFT_OUT, TARGET_NAMES,
                               TARGET_OUT_OF_CATALOGUE, TARGET_TOP1, TARGET_WRONG_CONFIDENT, TARGETS,
                               clopper_pearson, target_status)

SENSOR_SETS = ("full", "realistic")
BASE_PERTURBATION = 0.10
DEFAULT_SEED = 2024
NONE_PER_SET = 5                 # x 2 sensor sets x 2 concepts = 20 no-effect cases in the full check
NONE_SLOT = 100                  # slot of the first none case (variants take 0..len(VARIANTS)-1)
LEFT_OUT_SLOT = 200              # slot of the left-out case of variant i: LEFT_OUT_SLOT + i
UNSEEN_SLOT = 300                # unseen variant i (UNSEEN_VARIANTS): slot 300 + i, left out: 400 + i
UNSEEN_LEFT_OUT_SLOT = 400
#: first slots (effect, left out) of each unseen set, apart from each other and the self-check's
UNSEEN_SLOTS = {"UNSEEN_VARIANTS": (UNSEEN_SLOT, UNSEEN_LEFT_OUT_SLOT), "UNSEEN_VARIANTS_2": (500, 600),
                "UNSEEN_VARIANTS_3": (700, 800)}
PARAMETER_STREAM = 1             # variant parameters come from default_rng((case seed, PARAMETER_STREAM))
STRESS_STREAM = 2                # stress of a stressed none case from default_rng((case seed, STRESS_STREAM))
CALIBRATION_SEEDS = frozenset(range(100, 104))
#: case kinds: in-catalogue variants, no-effect records, variants outside the catalogue,
#: in-catalogue variants diagnosed with their family's forms left out of the catalogue
KINDS = ("effect", "none", "out_of_catalogue", "left_out")
#: the quick subset (CI, smoke study): (sensor set, variant or None) on the study's concept
QUICK_CASES = (("realistic", "load_friction_linear"), ("realistic", None), ("realistic", "current_sensor_error"))


class SelfCheckError(EmaUqError):
    """A self-check request that cannot be built (unknown concept, sensor set or size), or parts
    that do not gather into one run."""


# ----------------------------------------------------------------------------------------
# cases
# ----------------------------------------------------------------------------------------
def case_seed(seed: int, concept: str, sensors: str, slot: int) -> int:
    """The case's own seed (see the module docstring)."""
    state = np.random.SeedSequence((int(seed), CONCEPTS.index(concept), SENSOR_SETS.index(sensors), int(slot)))
    return int(state.generate_state(1)[0])


#: the catalogue the cases are defined on, method version 2's: a left-out case's candidates are part
#: of its identity (and of every frozen block's outcome files), so they stay put when the default
#: method changes; :func:`under_catalogue` poses each case to the catalogue of the settings it runs with
CASE_CATALOGUE_SETTINGS = DiagnosisSettings(spanning_forms=False)


def catalogue_families(concept: str, settings: DiagnosisSettings | None = None) -> dict[str, list[str]]:
    """{family: [effect forms]} of the candidate effects ``settings`` offers for the concept
    (:func:`~ema_uq.gap.candidates.offered_forms`; None: the catalogue the cases are defined on,
    :data:`CASE_CATALOGUE_SETTINGS`)."""
    settings = CASE_CATALOGUE_SETTINGS if settings is None else settings
    out: dict[str, list[str]] = {}
    for name, effect in offered_forms(get_model(concept).effect_catalogue, settings).items():
        out.setdefault(getattr(effect, "family", None) or name, []).append(name)
    return out


def catalogue_without(concept: str, family: str, settings: DiagnosisSettings | None = None) -> tuple[str, ...]:
    """Every form ``settings`` offers for the concept but those of ``family``."""
    return tuple(name for fam, forms in catalogue_families(concept, settings).items() if fam != family
                 for name in forms)


def under_catalogue(case: Case, settings: DiagnosisSettings | None) -> Case:
    """The case as the catalogue of ``settings`` (None: the defaults, which the diagnosis then runs
    with) poses it: a left-out case is built with every form of the other families that method
    version 2 offers, and gets instead those ``settings`` offers (method version 4's spanning forms
    beside them, version 5's nesting forms in their place)."""
    settings = DiagnosisSettings() if settings is None else settings
    if case.kind != "left_out":
        return case
    candidates = catalogue_without(case.concept, case.family, settings)
    return case if candidates == tuple(case.candidates) else replace(case, candidates=candidates)


def _case(seed: int, concept: str, sensors: str, variant: str | None, none_index: int = 0,
          left_out: bool = False, unseen: str | None = None) -> Case:
    """A case of the self-check's variants, or of the unseen set named ``unseen`` (:data:`UNSEEN_SLOTS`)."""
    registry = UNSEEN_SETS[unseen] if unseen else VARIANTS
    names = list(registry)
    family = None if variant is None else registry[variant].family
    first, first_left_out = UNSEEN_SLOTS[unseen] if unseen else (0, LEFT_OUT_SLOT)
    stressed, candidates = variant is None and none_index % 2 == 1, None
    if left_out:
        if family is None:
            raise SelfCheckError(f"variant {variant!r} has no catalogue family to leave out")
        slot, kind, label = first_left_out + names.index(variant), "left_out", f"{variant}-left-out"
        candidates = catalogue_without(concept, family)
    elif variant is None:
        slot, kind, label = NONE_SLOT + none_index, "none", f"none#{none_index}" + ("-stressed" if stressed else "")
    else:
        slot = first + names.index(variant)
        kind, label = "effect" if family is not None else "out_of_catalogue", variant
    case = Case(f"{concept}/{sensors}/{label}", concept, sensors, kind, variant, family,
                case_seed(seed, concept, sensors, slot), stressed=stressed, candidates=candidates)
    if case.seed in CALIBRATION_SEEDS:
        raise SelfCheckError(f"case {case.case_id} drew seed {case.seed}, one the thresholds were calibrated on; "
                             "choose another self-check seed")
    return case


def _check_whole_number(name: str, value: Any, minimum: int) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise SelfCheckError(f"{name} must be a whole number >= {minimum}, got {value!r}")


def _check_concepts_and_sensors(concepts: Sequence[str], sensors: Sequence[str]) -> None:
    for concept in concepts:
        if concept not in CONCEPTS:
            raise SelfCheckError(f"no independent variants for concept {concept!r}; choose from {', '.join(CONCEPTS)}")
    for s in sensors:
        if s not in SENSOR_SETS:
            raise SelfCheckError(f"unknown sensor set {s!r}; choose from {', '.join(SENSOR_SETS)}")
    if not concepts or not sensors:
        raise SelfCheckError("the self-check needs at least one concept and one sensor set")


def build_cases(concepts: Sequence[str] = CONCEPTS, *, seed: int = DEFAULT_SEED, quick: bool = False,
                sensors: Sequence[str] = SENSOR_SETS, none_per_set: int = NONE_PER_SET,
                kinds: Sequence[str] = KINDS, none_first: int = 0) -> list[Case]:
    """The labelled cases: per concept x sensor set, every in-catalogue variant, ``none_per_set``
    none cases (numbers ``none_first`` on; the odd-numbered ones stressed), every
    out-of-catalogue variant and every in-catalogue variant with its family left out, of the
    ``kinds`` asked for (``quick``: :data:`QUICK_CASES` on the first concept). A case is the same
    whichever others are built (its seed depends on its slot only): e.g. ``kinds=("none",)``
    with ``none_first`` at an earlier run's ``none_per_set`` adds none cases to its false-alarm
    count without repeating any."""
    concepts, sensors = list(concepts), list(sensors)
    unknown = [k for k in kinds if k not in KINDS]
    if unknown:
        raise SelfCheckError(f"unknown case kind {unknown[0]!r}; choose from {', '.join(KINDS)}")
    if not kinds:
        raise SelfCheckError(f"give at least one case kind of {', '.join(KINDS)}")
    _check_concepts_and_sensors(concepts, sensors)
    _check_whole_number("none_per_set", none_per_set, 0)
    _check_whole_number("none_first", none_first, 0)
    if quick:
        cases = [_case(seed, concepts[0], s, v) for s, v in QUICK_CASES]
    else:
        cases = []
        for concept in concepts:
            for s in sensors:
                inside = [v for v, var in VARIANTS.items() if var.family is not None]
                cases += [_case(seed, concept, s, v) for v in inside]
                cases += [_case(seed, concept, s, None, k) for k in range(none_first, none_first + none_per_set)]
                cases += [_case(seed, concept, s, v) for v, var in VARIANTS.items() if var.family is None]
                if "left_out" in kinds:
                    cases += [_case(seed, concept, s, v, left_out=True) for v in inside]
    return [c for c in cases if c.kind in kinds]


def unseen_cases(seed: int, concepts: Sequence[str] = CONCEPTS, sensors: Sequence[str] = SENSOR_SETS,
                 variant_set: str = "UNSEEN_VARIANTS") -> list[Case]:
    """The cases of an unseen variant set (:data:`~ema_uq.gap.variant_catalogue.UNSEEN_SETS`: the
    variants written after method version 2 was frozen, ``UNSEEN_VARIANTS_2``, written for the
    evaluation of version 4, or ``UNSEEN_VARIANTS_3``, for that of version 5), per concept x
    sensor set: every one once, and every in-catalogue one once more with its family left out.
    Each set has its own slots (:data:`UNSEEN_SLOTS`), none of the self-check's, so no record
    repeats another case's."""
    if variant_set not in UNSEEN_SETS:
        raise SelfCheckError(f"unknown unseen variant set {variant_set!r}; choose from {', '.join(UNSEEN_SETS)}")
    concepts, sensors = list(concepts), list(sensors)
    _check_concepts_and_sensors(concepts, sensors)
    registry = UNSEEN_SETS[variant_set]
    cases = []
    for concept in concepts:
        for s in sensors:
            cases += [_case(seed, concept, s, v, unseen=variant_set) for v in registry]
            cases += [_case(seed, concept, s, v, left_out=True, unseen=variant_set)
                      for v, var in registry.items() if var.family is not None]
    return cases


def case_stress(case: Case) -> dict[str, Any] | None:
    """The model-form stress of a stressed none case (None otherwise), drawn from its seed."""
    if not case.stressed:
        return None
    return draw_stress(case.concept, np.random.default_rng((case.seed, STRESS_STREAM)))


def case_records(case: Case):
    """(estimation, validation, second validation, truth) of a case; the records carry no label."""
    params = None
    if case.variant is not None:
        params = draw_variant_parameters(case.variant, np.random.default_rng((case.seed, PARAMETER_STREAM)),
                                         case.concept)
    return make_records(case.concept, case.variant, params, seed=case.seed, channels=case.sensors,
                        base_perturbation=BASE_PERTURBATION, stress=case_stress(case))


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
    """Simulate a case's records, diagnose them blind (on the case's catalogue) and return the outcome."""
    truth: dict[str, Any] = {"parameters": {}}
    t0 = time.perf_counter()
    candidates = None if case.candidates is None else list(case.candidates)
    try:
        # the records inside the guard too: a variant whose simulation fails is that case's error
        estimation, validation, validation2, truth = case_records(case)
        t0 = time.perf_counter()
        result = diagnose([estimation], [validation, validation2], candidates=candidates, settings=settings,
                          seed=case.seed)
    except Exception as exc:    # noqa: BLE001 - one failing case must not lose a campaign's other outcomes
        return CaseOutcome(case, "error", None, None, "-", float("nan"), float("nan"), None, float("nan"),
                           float("nan"), dict(truth["parameters"]), time.perf_counter() - t0,
                           message=f"{type(exc).__name__}: {exc}", stress=dict(truth.get("stress") or {}))
    stress = dict(truth.get("stress") or {})
    gap = result.gap
    top = [{"effect": c.effect, "score": c.score, "delta_bic": c.delta_bic, "held_out_gain": c.held_out_gain,
            "signature_match": c.signature_match} for c in result.ranking[:3]]
    probabilities = getattr(result, "family_probabilities", None) or {}
    return CaseOutcome(case, result.verdict, result.effect, family_of(result, case.concept), result.confidence,
                       _num(gap.get("shrink")), _num(gap.get("shrink_se")), gap.get("shrink_record"),
                       float(gap["before"]), float(gap["after"]), dict(truth["parameters"]),
                       time.perf_counter() - t0, top,
                       ambiguous_families=list(getattr(result, "ambiguous_families", None) or []),
                       family_probabilities={str(k): float(v) for k, v in dict(probabilities).items()},
                       stress=stress)


def _progress_line(i: int, n: int, o: CaseOutcome) -> str:
    shrink = "" if not np.isfinite(o.shrink) else f", shrink {o.shrink:.2f} +- {o.shrink_se:.2f}"
    return (f"[{i}/{n}] {o.case.case_id}: {o.label} ({o.confidence}){shrink}, "
            f"{'ok' if o.correct else 'WRONG'} (expected {o.case.expected}), {o.wall_time_s:.0f} s"
            + (f" - {o.message}" if o.message else ""))


def parse_chunk(text: str | Sequence[int] | None) -> tuple[int, int] | None:
    """``"I/N"`` (or (I, N)) as (I, N) with 0 <= I < N; None stays None."""
    if text is None:
        return None
    try:
        i, n = (int(v) for v in (text.split("/") if isinstance(text, str) else text))
    except (ValueError, TypeError):
        raise SelfCheckError(f"chunk {text!r}: give I/N, e.g. 2/8 (the third of eight parts, counted from 0)") from None
    if not 0 <= i < n:
        raise SelfCheckError(f"chunk {i}/{n}: I must lie in 0..N-1")
    return i, n


def _cache_file(cache: Path, case: Case) -> Path:
    return cache / (case.case_id.replace("/", "__") + f"__{case.seed}.json")


def _settings_record(settings: DiagnosisSettings | None) -> dict[str, Any]:
    """The settings a cached outcome was diagnosed with (None: the defaults of that code)."""
    return asdict(DiagnosisSettings() if settings is None else settings)


def _cached(cache: Path | None, case: Case, settings: DiagnosisSettings | None = None) -> CaseOutcome | None:
    """The outcome stored for ``case``, or None: none stored, a torn file, a case whose diagnosis
    raised (a crash is no verdict: a resumed run diagnoses it again rather than scoring the old
    exception), or one diagnosed with other settings (e.g. under an earlier default method; files
    written before the settings were recorded carry none and are read back, as the folders of the
    frozen protocols, named by the hash of the sources, need)."""
    if cache is None:
        return None
    path = _cache_file(cache, case)
    if not path.is_file():
        return None
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
        outcome = CaseOutcome.from_json(data)
    except (ValueError, KeyError, TypeError):
        return None                     # a torn file: diagnose again
    if outcome.verdict == "error":
        return None
    stored, current = data.get("diagnosis_settings") or {}, _settings_record(settings)
    # a setting added since the file was written is not in it: what it stored must match
    if any(key not in current or current[key] != value for key, value in stored.items()):
        return None
    return outcome if outcome.case == case else None


def _store(cache: Path | None, outcome: CaseOutcome, settings: DiagnosisSettings | None = None) -> None:
    if cache is None:
        return
    path = _cache_file(cache, outcome.case)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps({**outcome.to_json(), "diagnosis_settings": _settings_record(settings)}, indent=1),
                   encoding="utf-8")
    tmp.replace(path)


def self_check(*, seed: int = DEFAULT_SEED, quick: bool = False, concepts: Sequence[str] = CONCEPTS,
               sensors: Sequence[str] = SENSOR_SETS, none_per_set: int = NONE_PER_SET,
               kinds: Sequence[str] = KINDS, none_first: int = 0, cases: Sequence[Case] | None = None,
               settings: DiagnosisSettings | None = None, jobs: int = 1,
               progress: Callable[[str], None] | None = None, chunk: tuple[int, int] | str | None = None,
               cache: str | Path | None = None) -> SelfCheckResult:
    """Run the blind self-check and score it. ``jobs`` worker processes (spawned: a script
    calling this with ``jobs`` > 1 needs the ``if __name__ == "__main__"`` guard) diagnose cases
    in parallel; every case is seeded on its own, so the outcomes do not depend on ``jobs``.
    ``chunk`` (I, N) or "I/N": only every N-th case from case I, counted from 0 (join the parts with
    :func:`gather`); ``cache``: folder of per-case outcome files, read back instead of diagnosing
    again (resume)."""
    _check_whole_number("jobs", jobs, 1)
    chunk = parse_chunk(chunk)
    every = list(cases) if cases is not None else build_cases(concepts, seed=seed, quick=quick, sensors=sensors,
                                                              none_per_set=none_per_set, kinds=kinds,
                                                              none_first=none_first)
    every = [under_catalogue(case, settings) for case in every]
    indices = list(range(len(every))) if chunk is None else list(range(chunk[0], len(every), chunk[1]))
    todo = [every[i] for i in indices]
    cache = None if cache is None else Path(cache)
    if cache is not None:
        cache.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    found = {i: _cached(cache, every[i], settings) for i in indices}
    missing = [i for i in indices if found[i] is None]
    outcomes: dict[int, CaseOutcome] = {}
    done = 0

    def keep(i: int, outcome: CaseOutcome, fresh: bool) -> None:
        nonlocal done
        outcome.index = i
        outcomes[i] = outcome
        if fresh:
            _store(cache, outcome, settings)
        done += 1
        if progress:
            progress(_progress_line(done, len(indices), outcome) + ("" if fresh else " (cached)"))

    for i in indices:
        if found[i] is not None:
            keep(i, found[i], False)
    cases_missing = [every[i] for i in missing]
    if jobs == 1 or len(missing) <= 1:
        results = map(run_case, cases_missing, [settings] * len(missing))
        pool = None
    else:
        # spawn, not fork: numba's thread pool is not safe to fork; one thread in each worker,
        # as the pool already runs one worker per core
        pool = ProcessPoolExecutor(max_workers=min(jobs, len(missing)), mp_context=get_context("spawn"),
                                   initializer=single_threaded_worker)
        results = pool.map(run_case, cases_missing, [settings] * len(missing))
    try:
        for i, outcome in zip(missing, results):
            keep(i, outcome, True)
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)
    used = {"concepts": sorted({c.concept for c in every}, key=CONCEPTS.index),
            "sensors": sorted({c.sensors for c in every}, key=SENSOR_SETS.index),
            "none_per_set": none_per_set, "none_first": none_first, "quick": quick,
            "base_perturbation": BASE_PERTURBATION,
            "kinds": [k for k in KINDS if any(c.kind == k for c in every)],
            "n_cases_total": len(every)}
    if chunk is not None:
        used["chunk"] = list(chunk)
    return SelfCheckResult([outcomes[i] for i in indices], seed, quick, time.perf_counter() - t0, used)


def gather(parts: Sequence[SelfCheckResult | Mapping[str, Any]]) -> SelfCheckResult:
    """Join the parts of a scattered self-check (``chunk`` 0/N .. N-1/N, in any order) into the
    result of one run: outcomes in case-list order, wall time the parts' sum, provenance the
    first part's. Parts of different runs (seed, settings), a part missing or given twice, or a
    case missing are a SelfCheckError."""
    parts = [p if isinstance(p, SelfCheckResult) else SelfCheckResult.from_json(p) for p in parts]
    if not parts:
        raise SelfCheckError("no self-check parts to gather")
    first = parts[0]
    common = {k: v for k, v in first.settings.items() if k != "chunk"}
    chunks = []
    for p in parts:
        mine = {k: v for k, v in p.settings.items() if k != "chunk"}
        if p.seed != first.seed or p.quick != first.quick or mine != common:
            raise SelfCheckError("self-check parts of different runs (seed or settings differ); gather the parts "
                                 "of one run")
        chunks.append(tuple(p.settings.get("chunk") or (0, 1)))
    n = chunks[0][1]
    if sorted(chunks) != [(i, n) for i in range(n)]:
        raise SelfCheckError(f"self-check parts {', '.join(f'{i}/{m}' for i, m in sorted(chunks))} are not the "
                             f"chunks 0/{n}..{n - 1}/{n} once each")
    outcomes = sorted((o for p in parts for o in p.outcomes), key=lambda o: o.index)
    total = int(common.get("n_cases_total", len(outcomes)))
    if [o.index for o in outcomes] != list(range(total)):
        raise SelfCheckError(f"the parts hold {len(outcomes)} of {total} cases; rerun the missing chunks")
    return SelfCheckResult(outcomes, first.seed, first.quick, float(sum(p.wall_time_s for p in parts)), common,
                           dict(first.provenance))
