"""Gap diagnosis: a method version's development run read against the incumbent's outcomes of
the same records, by the development rule that decides whether it goes on to a freeze.

A development run (``benchmarks/gap.py --seed S --method-version N --cache DIR``) keeps one
outcome file per case. This script reads two such folders (or an evaluation block's seed folder
for the incumbent), keeps the cases both have run, prints both versions' counts side by side,
every case whose verdict, family or confidence differs, and how many records had a form of the
top three move, and reads one of the development rules of docs/gap-diagnosis.md.

``--rule nested-starts`` (the default; method versions 8 and 9):
(a) in-catalogue family top-1 does not fall;
(b) left-out records are flagged at least as often, less one case;
(c) no more out-of-catalogue records are named a family;
(d) no no-effect record names a family;
(e) no wrong family is named with high confidence.

``--rule non-inferiority`` (method version 10, a change of numerical accuracy far under the noise,
which moves only verdicts at a threshold's edge, either way): one record of slack on every count,
(a) and (b) at least the incumbent's less one, (c), (d) and (e) at most the incumbent's plus one.

Rule (f), the time per case, is measured side by side on one record (``benchmarks/gap_speed.py``):
stored wall times of runs on a busy machine say nothing about it, so they are shown, not read.
The rule is read only when the candidate has run every case the incumbent has; before that the
figures are marked partial and decide nothing.

Usage: python benchmarks/gap_development.py --incumbent DIR --candidate DIR [--rule nested-starts|non-inferiority]
"""
from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Sequence

from ema_uq.gap.selfcheck_scores import CaseOutcome, SelfCheckResult

#: (label, how a version's count is taken, how the candidate's count must compare with the incumbent's)
CONDITIONS = (("(a) in-catalogue family top-1", "top1", "at least"),
              ("(b) left out flagged", "left_out_flagged", "at least, less one"),
              ("(c) out of catalogue named a family", "out_of_catalogue_named", "at most"),
              ("(d) no-effect records naming a family", "false_alarms", "none"),
              ("(e) wrong family named with high confidence", "wrong_family_confident", "none"))
#: the rule of method version 10: one record of slack on each count, either way (module docstring)
NON_INFERIORITY = tuple((label, what, "at least, less one" if side.startswith("at least") else "at most, plus one")
                        for label, what, side in CONDITIONS)
RULES = {"nested-starts": CONDITIONS, "non-inferiority": NON_INFERIORITY}


def read_outcomes(folder: Path) -> dict[str, CaseOutcome]:
    """The per-case outcomes of one folder, by case id; a second outcome of one case stops."""
    folder = Path(folder)
    if not folder.is_dir():
        raise SystemExit(f"{folder}: no such folder of case outcomes; give the --cache folder of a run")
    out: dict[str, CaseOutcome] = {}
    for file in sorted(folder.glob("*.json")):
        data = json.loads(file.read_text(encoding="utf-8"))
        if "case_id" not in data:        # a folder's environment record, not a case
            continue
        outcome = CaseOutcome.from_json(data)
        if outcome.case.case_id in out:
            raise SystemExit(f"two outcomes of case {outcome.case.case_id} in {folder}; keep one folder per "
                             "version and block")
        out[outcome.case.case_id] = outcome
    return out


def differing_lines(incumbent: Sequence[CaseOutcome], other: Sequence[CaseOutcome]) -> list[str]:
    """One line per case whose verdict, family or confidence differ between two versions'
    outcomes of the same cases (``other`` holds every case of ``incumbent``)."""
    theirs = {o.case.case_id: o for o in other}
    lines = []
    for mine in incumbent:
        their = theirs[mine.case.case_id]
        if (mine.verdict, mine.family, mine.confidence) != (their.verdict, their.family, their.confidence):
            lines.append(f"    {mine.case.case_id}: {mine.label} ({mine.confidence}, "
                         f"{'ok' if mine.correct else 'wrong'}) -> {their.label} ({their.confidence}, "
                         f"{'ok' if their.correct else 'wrong'})")
    return lines


def _count(result: SelfCheckResult, what: str) -> tuple[int, int]:
    if what == "out_of_catalogue_named":
        cases = result.of("out_of_catalogue")
        return sum(o.verdict == "effect" for o in cases), len(cases)
    rate = getattr(result, what)
    return int(rate["count"]), int(rate["n"])


@dataclass
class DevelopmentReading:
    """Both versions' outcomes on the cases both have run: ``rows`` (label, incumbent count,
    candidate count, held), ``complete`` when the candidate has run every case the incumbent has."""

    incumbent: SelfCheckResult
    candidate: SelfCheckResult
    rows: list[tuple[str, str, str, bool]]
    complete: bool
    n_incumbent: int

    @property
    def passes(self) -> bool:
        return self.complete and all(held for *_, held in self.rows)

    def differing(self) -> list[str]:
        return differing_lines(self.incumbent.outcomes, self.candidate.outcomes)

    def moved(self) -> int:
        """Records where the top three forms or their ΔBIC (to 0.1) differ."""
        theirs = {o.case.case_id: o for o in self.candidate.outcomes}

        def top(o: CaseOutcome) -> list:
            return [(c.get("effect"), round(float(c.get("delta_bic", float("nan"))), 1)) for c in o.top]
        return sum(top(o) != top(theirs[o.case.case_id]) for o in self.incumbent.outcomes)

    def summary(self) -> str:
        n = len(self.candidate.outcomes)
        state = "complete" if self.complete else f"PARTIAL ({n} of the incumbent's {self.n_incumbent} cases): decides nothing"
        lines = [f"[[Development rule]] {state}", f"    {'':<46}{'incumbent':>11}{'candidate':>11}  condition"]
        for label, mine, theirs, held in self.rows:
            lines.append(f"    {label:<46}{mine:>11}{theirs:>11}  {'holds' if held else 'FAILS'}")
        wall = [sum(o.wall_time_s for o in r.outcomes) / max(len(r.outcomes), 1) for r in (self.incumbent, self.candidate)]
        lines.append(f"    {'stored wall time per case [s] (not read)':<46}{wall[0]:>11.0f}{wall[1]:>11.0f}")
        differing = self.differing()
        lines.append(f"    records with a top-three form moved: {self.moved()} of {n}")
        lines.append(f"    cases with another verdict, family or confidence: {len(differing)}")
        lines += differing
        lines.append("    goes on to a freeze (rule (f) read apart): "
                     + ("yes" if self.passes else "no" if self.complete else "not decided (run incomplete)"))
        return "\n".join(lines)


def read_rule(incumbent: dict[str, CaseOutcome], candidate: dict[str, CaseOutcome],
              rule: str = "nested-starts") -> DevelopmentReading:
    """The development rule ``rule`` (:data:`RULES`) on the cases both folders hold."""
    foreign = sorted(set(candidate) - set(incumbent))
    if foreign:
        raise SystemExit(f"{len(foreign)} case(s) of the candidate are not in the incumbent's folder (e.g. "
                         f"{foreign[0]}); point both at runs of the same block")
    shared = [i for i in incumbent if i in candidate]
    for i in shared:
        if incumbent[i].case.seed != candidate[i].case.seed:
            raise SystemExit(f"case {i} has record seed {incumbent[i].case.seed} in the incumbent's folder and "
                             f"{candidate[i].case.seed} in the candidate's; point both at runs of the same block")
    seed = incumbent[shared[0]].case.seed if shared else 0
    mine = SelfCheckResult([incumbent[i] for i in shared], seed, False, 0.0)
    theirs = SelfCheckResult([candidate[i] for i in shared], seed, False, 0.0)
    rows = []
    for label, what, side in RULES[rule]:
        (a, n), (b, m) = _count(mine, what), _count(theirs, what)
        held = {"at least": b >= a, "at least, less one": b >= a - 1, "at most": b <= a,
                "at most, plus one": b <= a + 1, "none": b == 0}[side]
        rows.append((label, f"{a}/{n}", f"{b}/{m}", held))
    return DevelopmentReading(mine, theirs, rows, len(shared) == len(incumbent), len(incumbent))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--incumbent", required=True, metavar="DIR", help="the incumbent's outcomes of the block")
    parser.add_argument("--candidate", required=True, metavar="DIR", help="the development run's --cache folder")
    parser.add_argument("--rule", choices=tuple(RULES), default="nested-starts",
                        help="nested-starts: versions 8 and 9; non-inferiority: version 10 (module docstring)")
    args = parser.parse_args()
    print(read_rule(read_outcomes(Path(args.incumbent)), read_outcomes(Path(args.candidate)), args.rule).summary())


if __name__ == "__main__":
    main()
