"""What a self-check run is scored with: the labelled :class:`Case`, the
:class:`CaseOutcome` of its blind diagnosis (right or wrong by the case's kind), and the
:class:`SelfCheckResult` of a run: rates with 95 % Clopper-Pearson intervals, each target's
status, the confusion matrices, the printed summary and the JSON form.

What the cases are and how they are drawn and diagnosed is :mod:`ema_uq.gap.selfcheck`; the
meaning of every score is described there too.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Callable, Iterable, Mapping, Sequence

import numpy as np
from scipy import stats

from .result import SHRINK_RESOLVED_SE, shrink_resolved

TARGET_TOP1, TARGET_FALSE_ALARM, TARGET_OUT_OF_CATALOGUE = 0.90, 0.05, 0.85
TARGET_LEFT_OUT, TARGET_WRONG_CONFIDENT = 0.85, 0.02
FALSE_ALARM_MIN_CASES, FALSE_ALARM_MIN_STRESSED = 60, 0.4
OUT_OF_CATALOGUE_ROW = "outside catalogue"
#: verdicts that flag a gap the catalogue does not explain
FLAGGED = ("unexplained", "ambiguous")
#: verdicts that name an effect (a false alarm on a none case; "error": no clean verdict either)
NAMED = ("effect", "ambiguous", "error")
#: targets: score key -> (rate property, target, side the rate must lie on)
TARGETS = {"top1_accuracy": ("top1", TARGET_TOP1, ">="),
           "left_out_flagged": ("left_out_flagged", TARGET_LEFT_OUT, ">="),
           "out_of_catalogue_flagged": ("out_of_catalogue_flagged", TARGET_OUT_OF_CATALOGUE, ">="),
           "wrong_family_confident": ("wrong_family_confident", TARGET_WRONG_CONFIDENT, "<="),
           "false_alarm_rate": ("false_alarms", TARGET_FALSE_ALARM, "<=")}
TARGET_NAMES = {"top1_accuracy": "top-1 accuracy (family)", "left_out_flagged": "left-out family flagged",
                "out_of_catalogue_flagged": "out of catalogue flagged",
                "wrong_family_confident": "wrong family, high confidence", "false_alarm_rate": "false-alarm rate"}


@dataclass(frozen=True)
class Case:
    """One labelled case. ``kind``: ``effect`` (in-catalogue variant), ``none``,
    ``out_of_catalogue`` or ``left_out``; ``variant`` None for none cases; ``family`` the
    variant's catalogue family (None for none and out-of-catalogue cases); ``stressed``: a none
    case with model-form stress; ``candidates``: the catalogue the diagnosis gets (None: all of
    it; a left-out case: every form but its family's)."""

    case_id: str
    concept: str
    sensors: str
    kind: str
    variant: str | None
    family: str | None
    seed: int
    stressed: bool = False
    candidates: tuple[str, ...] | None = None

    @property
    def expected(self) -> str:
        """The right verdict label: the family, ``none`` or ``unexplained`` (``ambiguous`` counts
        as a flag too)."""
        return {"effect": self.family, "none": "none"}.get(self.kind, "unexplained")

    @property
    def truth_row(self) -> str:
        """Row of the confusion matrix: the family (left-out cases: the family left out), ``none``
        or ``outside catalogue``."""
        return {"none": "none", "out_of_catalogue": OUT_OF_CATALOGUE_ROW}.get(self.kind, self.family)


@dataclass
class CaseOutcome:
    """The diagnosis of one case: verdict, effect form and family named, confidence, the
    honest shrink (signed, unclipped; None/NaN unless ``effect``) with its standard error
    and the record it was scored on, the held-out gap before/after, the drawn variant
    parameters and stress (hidden from the diagnosis), the wall time [s], the families an
    ``ambiguous`` verdict names and the family probabilities (when the diagnosis gives them),
    and ``index``, the case's place in the full case list. A case whose diagnosis raised has
    verdict ``error`` and the exception in ``message``: it counts as wrong, and the other
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
    ambiguous_families: list[str] = field(default_factory=list)
    family_probabilities: dict[str, float] = field(default_factory=dict)
    stress: dict[str, Any] = field(default_factory=dict)
    index: int = -1

    @property
    def label(self) -> str:
        """The verdict as a confusion-matrix column: the family named, ``none``, ``unexplained``,
        ``ambiguous`` or ``error``."""
        return str(self.family) if self.verdict == "effect" else self.verdict

    @property
    def named_wrong_confidently(self) -> bool:
        """An effect named with high confidence whose family is not the truth's (every family is
        wrong for out-of-catalogue and left-out cases)."""
        if self.verdict != "effect" or self.confidence != "high":
            return False
        return self.case.kind != "effect" or self.family != self.case.family

    @property
    def correct(self) -> bool:
        """Right family named (effect); ``none`` or a low-confidence ``unexplained`` (none); a
        flag, ``unexplained`` or ``ambiguous`` (out of catalogue, left out)."""
        kind = self.case.kind
        if kind == "effect":
            return self.verdict == "effect" and self.family == self.case.family
        if kind == "none":
            return self.verdict == "none" or (self.verdict == "unexplained" and self.confidence == "low")
        return self.verdict in FLAGGED

    def to_json(self) -> dict[str, Any]:
        out = {k: v for k, v in vars(self).items() if k != "case"}
        case = dict(vars(self.case))
        case["truth_family"] = case.pop("family")
        case["candidates"] = None if self.case.candidates is None else list(self.case.candidates)
        out.update(case)
        out.update(label=self.label, expected=self.case.expected, correct=self.correct)
        return _clean(out)

    @classmethod
    def from_json(cls, c: Mapping[str, Any]) -> "CaseOutcome":
        candidates = c.get("candidates")
        case = Case(c["case_id"], c["concept"], c["sensors"], c["kind"], c["variant"], c["truth_family"],
                    int(c["seed"]), bool(c.get("stressed", False)), None if candidates is None else tuple(candidates))
        return cls(case, c["verdict"], c["effect"], c["family"], c["confidence"], _num(c["shrink"]),
                   _num(c["shrink_se"]), c.get("shrink_record"), _num(c["gap_before"]), _num(c["gap_after"]),
                   dict(c.get("parameters") or {}), float(c["wall_time_s"]), list(c.get("top") or []),
                   str(c.get("message") or ""), list(c.get("ambiguous_families") or []),
                   dict(c.get("family_probabilities") or {}), dict(c.get("stress") or {}), int(c.get("index", -1)))


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


def target_status(count: int, n: int, target: float, side: str, minimum_n: int = 1) -> str:
    """``met`` when the one-sided 95 % Clopper-Pearson bound of count/n on the target's side meets
    the target (``>=``: the lower bound >= target; ``<=``: the upper bound <= target) and n >=
    ``minimum_n``; ``not met`` when the bound on the other side fails it (the rate is shown to miss
    it); else ``n too small``."""
    if n == 0:
        return "n too small"
    low, high = clopper_pearson(count, n, level=0.90)       # its ends: the one-sided 95 % bounds
    if side == ">=":
        met, missed = low >= target, high < target
    else:
        met, missed = high <= target, low > target
    if met and n >= minimum_n:
        return "met"
    return "not met" if missed else "n too small"


@dataclass
class SelfCheckResult:
    """Scores of a self-check run (see the module docstring); ``settings`` holds what built
    the case list (concepts, sensor sets, none_per_set, quick, kinds; a part of a scattered run
    also its ``chunk`` [i, n] and ``n_cases_total``)."""

    outcomes: list[CaseOutcome]
    seed: int
    quick: bool
    wall_time_s: float
    settings: dict[str, Any] = field(default_factory=dict)
    provenance: dict[str, Any] = field(default_factory=dict)

    # --- scores ----------------------------------------------------------------------------
    def of(self, *kinds: str) -> list[CaseOutcome]:
        return [o for o in self.outcomes if o.case.kind in kinds]

    @staticmethod
    def _rate_of(cases: Sequence[CaseOutcome], hit: Callable[[CaseOutcome], bool]) -> dict[str, Any]:
        k = sum(bool(hit(o)) for o in cases)
        low, high = clopper_pearson(k, len(cases))
        return {"value": k / len(cases) if cases else float("nan"), "count": k, "n": len(cases),
                "interval95": [low, high]}

    def _rate(self, kind: str, hit: Callable[[CaseOutcome], bool]) -> dict[str, Any]:
        return self._rate_of(self.of(kind), hit)

    @property
    def top1(self) -> dict[str, Any]:
        """In-catalogue cases where the verdict is ``effect`` and names the variant's family."""
        return self._rate("effect", lambda o: o.correct)

    @property
    def false_alarms(self) -> dict[str, Any]:
        """No-effect cases with a named effect (``effect``, ``ambiguous``; or an ``error``)."""
        return self._rate("none", lambda o: o.verdict in NAMED)

    @property
    def soft_alarms(self) -> dict[str, Any]:
        """No-effect cases diagnosed ``unexplained`` with low confidence (right, but counted)."""
        return self._rate("none", lambda o: o.verdict == "unexplained" and o.confidence == "low")

    @property
    def hard_alarms(self) -> dict[str, Any]:
        """No-effect cases diagnosed ``unexplained`` with high confidence: no effect named, but
        not right either (the residual judged structured beyond what any candidate closes)."""
        return self._rate("none", lambda o: o.verdict == "unexplained" and o.confidence != "low")

    @property
    def any_alarm(self) -> dict[str, Any]:
        """No-effect cases with any verdict but ``none`` (the strict rate of earlier self-checks)."""
        return self._rate("none", lambda o: o.verdict != "none")

    @property
    def false_alarms_by_stress(self) -> dict[str, dict[str, Any]]:
        """False, soft, hard and any alarms of the plain and of the stressed none cases apart."""
        out = {}
        for key, stressed in (("plain", False), ("stressed", True)):
            cases = [o for o in self.of("none") if o.case.stressed is stressed]
            out[key] = {"false": self._rate_of(cases, lambda o: o.verdict in NAMED),
                        "soft": self._rate_of(cases, lambda o: o.verdict == "unexplained" and o.confidence == "low"),
                        "hard": self._rate_of(cases, lambda o: o.verdict == "unexplained" and o.confidence != "low"),
                        "any": self._rate_of(cases, lambda o: o.verdict != "none")}
        return out

    @property
    def out_of_catalogue_flagged(self) -> dict[str, Any]:
        """Out-of-catalogue cases flagged: ``unexplained`` or ``ambiguous``."""
        return self._rate("out_of_catalogue", lambda o: o.verdict in FLAGGED)

    @property
    def left_out_flagged(self) -> dict[str, Any]:
        """Left-out-family cases flagged: ``unexplained`` or ``ambiguous``."""
        return self._rate("left_out", lambda o: o.verdict in FLAGGED)

    @property
    def wrong_family_confident(self) -> dict[str, Any]:
        """Cases carrying an effect (in-catalogue, left out, out of catalogue) where a wrong
        family was named with high confidence."""
        return self._rate_of(self.of("effect", "left_out", "out_of_catalogue"), lambda o: o.named_wrong_confidently)

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
    def left_out_rate(self) -> float:
        return self.left_out_flagged["value"]

    @property
    def shrink(self) -> dict[str, Any]:
        """Honest shrink where the right family was named: median, quartiles, range, median se,
        and how many of these shrinks are not resolved (:func:`ema_uq.gap.result.shrink_resolved`)."""
        found = [o for o in self.of("effect") if o.correct and np.isfinite(o.shrink)]
        values = np.array([o.shrink for o in found])
        if not found:
            return {"n": 0, "median": float("nan"), "q25": float("nan"), "q75": float("nan"),
                    "min": float("nan"), "max": float("nan"), "median_se": float("nan"), "not_resolved": 0}
        q25, median, q75 = np.percentile(values, [25, 50, 75])
        return {"n": len(found), "median": float(median), "q25": float(q25), "q75": float(q75),
                "min": float(values.min()), "max": float(values.max()),
                "median_se": float(np.nanmedian([o.shrink_se for o in found])),
                "not_resolved": sum(not shrink_resolved(o.shrink, o.shrink_se) for o in found)}

    def rates(self) -> dict[str, dict[str, Any]]:
        """The rate of every target, by target key."""
        return {key: getattr(self, prop) for key, (prop, _, _) in TARGETS.items()}

    @property
    def status(self) -> dict[str, str]:
        """Each target's status, ``met``/``not met``/``n too small`` (:func:`target_status`); the
        false-alarm target also needs ``FALSE_ALARM_MIN_CASES`` none cases, at least
        ``FALSE_ALARM_MIN_STRESSED`` of them stressed, to be ``met``."""
        out = {}
        stressed = sum(o.case.stressed for o in self.of("none"))
        for key, (prop, target, side) in TARGETS.items():
            rate = getattr(self, prop)
            minimum = 1
            if key == "false_alarm_rate":
                enough = rate["n"] >= FALSE_ALARM_MIN_CASES and stressed >= FALSE_ALARM_MIN_STRESSED * rate["n"]
                minimum = rate["n"] if enough else rate["n"] + 1
            out[key] = target_status(rate["count"], rate["n"], target, side, minimum)
        return out

    @property
    def met(self) -> dict[str, bool]:
        """Each target shown met at 95 % (status ``met``)."""
        return {k: v == "met" for k, v in self.status.items()}

    def confusion(self) -> dict[str, dict[str, int]]:
        """{truth family (``none``, ``outside catalogue``): {verdict label: count}} over the
        in-catalogue, none and out-of-catalogue cases."""
        return _matrix(self.of("effect", "none", "out_of_catalogue"))

    def confusion_left_out(self) -> dict[str, dict[str, int]]:
        """{family left out: {verdict label: count}} over the left-out cases."""
        return _matrix(self.of("left_out"))

    def by_set(self) -> dict[str, dict[str, float]]:
        """The rates per concept/sensor set."""
        out = {}
        for key in dict.fromkeys(f"{o.case.concept}/{o.case.sensors}" for o in self.outcomes):
            part = SelfCheckResult([o for o in self.outcomes if f"{o.case.concept}/{o.case.sensors}" == key],
                                   self.seed, self.quick, 0.0)
            out[key] = {"top1_accuracy": part.top1_accuracy, "false_alarm_rate": part.false_alarm_rate,
                        "out_of_catalogue_flagged": part.out_of_catalogue_rate,
                        "left_out_flagged": part.left_out_rate,
                        "wrong_family_confident": part.wrong_family_confident["value"]}
        return out

    # --- text ------------------------------------------------------------------------------
    def score_lines(self) -> list[str]:
        status = self.status

        def line(name, rate, tail=""):
            low, high = rate["interval95"]
            return (f"    {name:<36} {rate['value']:6.3f} ({rate['count']}/{rate['n']}, 95 % CI "
                    f"{low:.2f}-{high:.2f}){tail}")

        lines = []
        for key, (prop, target, side) in TARGETS.items():
            lines.append(line(TARGET_NAMES[key], getattr(self, prop), f"  target {side} {target:.2f}: {status[key]}"))
        lines += [line("  soft alarms (unexplained, low)", self.soft_alarms),
                  line("  hard alarms (unexplained, high)", self.hard_alarms),
                  line("  any verdict but none", self.any_alarm)]
        for key, parts in self.false_alarms_by_stress.items():
            if parts["false"]["n"]:
                lines.append(line(f"  false alarms, {key} none", parts["false"],
                                  f"; soft {parts['soft']['count']}, hard {parts['hard']['count']}"))
        s = self.shrink
        lines.append(f"    {'honest shrink (right family)':<36} median {s['median']:.3f}, quartiles {s['q25']:.3f}-"
                     f"{s['q75']:.3f}, range {s['min']:.3f}-{s['max']:.3f}, median se {s['median_se']:.3f} "
                     f"(n = {s['n']}; {s.get('not_resolved', 0)} less than {SHRINK_RESOLVED_SE:g} se above zero)")
        return lines

    def confusion_lines(self, matrix: Mapping[str, Mapping[str, int]] | None = None) -> list[str]:
        matrix = self.confusion() if matrix is None else matrix
        if not matrix:
            return ["    (no cases)"]
        columns = sorted({lab for row in matrix.values() for lab in row}, key=_label_order)
        width = max([len(r) for r in matrix] + [18])
        cells = [max(len(c), 4) for c in columns]
        lines = ["    " + " " * width + " " + " ".join(f"{c:>{w}}" for c, w in zip(columns, cells))]
        for truth in sorted(matrix, key=_label_order):
            lines.append(f"    {truth:<{width}} "
                         + " ".join(f"{matrix[truth].get(c, 0) or '.':>{w}}" for c, w in zip(columns, cells)))
        return lines

    def case_lines(self) -> list[str]:
        lines = [f"    {'case':<52} {'family':<24} {'verdict':<11} {'family found':<24} {'conf':<6} "
                 f"{'shrink +- se':>15} {'time':>6}  ok"]
        for o in self.outcomes:
            shrink = "" if not np.isfinite(o.shrink) else f"{o.shrink:.3f} +- {o.shrink_se:.3f}"
            found = o.family if o.verdict == "effect" else ("|".join(o.ambiguous_families) or "-")
            lines.append(f"    {o.case.case_id:<52} {o.case.truth_row:<24} {o.verdict:<11} "
                         f"{found:<24} {o.confidence:<6} {shrink:>15} "
                         f"{o.wall_time_s:>5.0f}s  {'yes' if o.correct else 'NO'}")
        return lines

    def summary(self) -> str:
        concepts = ", ".join(self.settings.get("concepts", []))
        lines = [f"[[Gap self-check]] {len(self.outcomes)} cases on independent variant records "
                 f"({concepts}; seed {self.seed}{', quick subset' if self.quick else ''}), "
                 f"{self.wall_time_s:.0f} s", *self.score_lines(),
                 "[[Confusion]] (rows: truth family, columns: verdict label)", *self.confusion_lines()]
        if self.of("left_out"):
            lines += ["[[Confusion, left-out families]] (rows: family left out of the catalogue, columns: verdict "
                      "label)", *self.confusion_lines(self.confusion_left_out())]
        return "\n".join([*lines, "[[Cases]]", *self.case_lines()])

    # --- serialised form -------------------------------------------------------------------
    def to_json(self) -> dict[str, Any]:
        return _clean({
            "n_cases": len(self.outcomes), "seed": self.seed, "quick": self.quick, "settings": self.settings,
            "generator": "ema_uq.gap.variants (independent simulator and effect variants)",
            "top1": self.top1, "false_alarms": self.false_alarms, "soft_alarms": self.soft_alarms,
            "hard_alarms": self.hard_alarms,
            "any_alarm": self.any_alarm, "false_alarms_by_stress": self.false_alarms_by_stress,
            "out_of_catalogue_flagged": self.out_of_catalogue_flagged, "left_out_flagged": self.left_out_flagged,
            "wrong_family_confident": self.wrong_family_confident, "shrink": self.shrink,
            "top1_accuracy": self.top1_accuracy, "false_alarm_rate": self.false_alarm_rate,
            "out_of_catalogue_rate": self.out_of_catalogue_rate, "left_out_rate": self.left_out_rate,
            "status": self.status, "met": self.met,
            "targets": {k: t for k, (_, t, _) in TARGETS.items()},
            "target_sides": {k: side for k, (_, _, side) in TARGETS.items()},
            "by_set": self.by_set(), "confusion": self.confusion(), "confusion_left_out": self.confusion_left_out(),
            "cases": [o.to_json() for o in self.outcomes],
            "wall_time_s": self.wall_time_s, "provenance": self.provenance,
        })

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> "SelfCheckResult":
        return cls([CaseOutcome.from_json(c) for c in data["cases"]], int(data["seed"]), bool(data["quick"]),
                   float(data["wall_time_s"]), dict(data.get("settings") or {}), dict(data.get("provenance") or {}))


def _matrix(outcomes: Iterable[CaseOutcome]) -> dict[str, dict[str, int]]:
    matrix: dict[str, dict[str, int]] = {}
    for o in outcomes:
        row = matrix.setdefault(o.case.truth_row, {})
        row[o.label] = row.get(o.label, 0) + 1
    return matrix


def _label_order(label: str) -> tuple[int, str]:
    return ({"none": 1, "ambiguous": 2, "unexplained": 2, "error": 3, OUT_OF_CATALOGUE_ROW: 2}.get(label, 0), label)
