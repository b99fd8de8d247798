"""Gap diagnosis: two frozen method versions on the same evaluation block, read against a rule
fixed before either ran.

A comparison of two versions on blocks of different seeds mixes the method with the draw of
the records (one binomial standard error at the rates seen is about 2.5 of 48 cases). Here the
incumbent (the default method) and the challenger run the very same cases: two protocol files
frozen with the same evaluation seeds, each run with ``benchmarks/gap.py --protocol P --block
evaluation --results R``. This script reads their per-case outcomes, checks that they cover the
same cases, prints both versions' figures side by side with every case whose verdict differs,
and reads the rule:

* the challenger's in-catalogue top-1 count is at least the incumbent's;
* its left-out and out-of-catalogue flag counts are each at least the incumbent's (no slack);
* it names a wrong family with high confidence, and names a family on a no-effect record, no
  more often than the incumbent;
* its own left-out and out-of-catalogue flag rates are each at least 0.85, its wrong family with
  high confidence at most 0.02 of the records that carry an effect, and at most 0.05 of the
  no-effect records name a family.

``--slack 1`` (the non-inferiority rule of method version 10, a change of numerical accuracy far
under the noise, which moves only verdicts at a threshold's edge, either way) gives each paired
count one record of slack: at least the incumbent's less one, at most the incumbent's plus one;
the challenger's own bounds stay as they are.

The rule is read only when both versions have run every case of the block. Before that the
script prints only how many cases each version has run: a look at partial figures invites
stopping a run early on a good or a bad look. ``--partial-figures`` prints the shared cases'
figures anyway, marked partial (for a check of the script, not of the methods).

Usage: python benchmarks/gap_paired.py --incumbent PROTOCOL RESULTS --challenger PROTOCOL RESULTS
                                       [--slack 1] [--partial-figures]
"""
from __future__ import annotations

import argparse
import json
from dataclasses import dataclass, replace
from pathlib import Path

from ema_uq.gap.selfcheck import build_cases
from ema_uq.gap.selfcheck_scores import TARGETS, Case, CaseOutcome, SelfCheckResult
from gap import cases_by_environment, load_protocol
from gap_development import differing_lines

#: the self-check targets the challenger must also meet on its own, as point values (conditions
#: (b) and (c) of the rules before): flags >= 0.85, wrong family high <= 0.02, no-effect naming <= 0.05
OWN_TARGETS = {"left_out_flagged": "left out flagged", "out_of_catalogue_flagged": "out of catalogue flagged",
               "wrong_family_confident": "wrong family, high", "false_alarm_rate": "no-effect naming"}

#: (label, SelfCheckResult property, the challenger must be at least / at most the incumbent)
PAIRED_CONDITIONS = (("in-catalogue top-1", "top1", ">="),
                     ("left out flagged", "left_out_flagged", ">="),
                     ("out of catalogue flagged", "out_of_catalogue_flagged", ">="),
                     ("wrong family, high confidence", "wrong_family_confident", "<="),
                     ("no-effect records naming a family", "false_alarms", "<="))


@dataclass
class PairedReading:
    """Both versions' outcomes on the cases of one block that both have run: ``complete`` when
    each has every case the block's protocol lists; ``conditions`` (label, incumbent count,
    challenger count, held); ``runs`` how many cases each version has run on its own;
    ``environments`` per version, the library versions its cases were diagnosed with and how many
    cases each (None: stored before runs recorded them)."""

    incumbent: SelfCheckResult
    challenger: SelfCheckResult
    complete: bool
    n_block: int
    conditions: list[tuple[str, str, str, bool]]
    runs: tuple[int, int] = (0, 0)
    environments: tuple[list, list] = ([], [])

    @property
    def switch(self) -> bool:
        """The challenger replaces the incumbent: the block is complete and every condition holds."""
        return self.complete and all(held for *_, held in self.conditions)

    def differing(self) -> list[str]:
        """The cases whose verdict, family or confidence differ between the versions."""
        return differing_lines(self.incumbent.outcomes, self.challenger.outcomes)

    def environment_lines(self) -> list[str]:
        """Which library versions diagnosed how many cases of each version; a warning when the
        block spans more than one (a fit's last digits move with them)."""
        lines, distinct = [], []
        for name, groups in zip(("incumbent", "challenger"), self.environments):
            for libraries, n in groups:
                where = ("stored before runs recorded their libraries" if libraries is None
                         else ", ".join(f"{k} {v}" for k, v in libraries.items()))
                lines.append(f"    {name}: {n} cases, {where}")
                if libraries is not None and libraries not in distinct:
                    distinct.append(libraries)
        if len(distinct) > 1:
            lines.append(f"    the block spans {len(distinct)} library environments: a verdict that rests on "
                         "the last digits of a fit could differ between them")
        return lines

    def summary(self, partial_figures: bool = False) -> str:
        if not self.complete and not partial_figures:
            return "\n".join([f"[[Paired block]] incomplete: the incumbent has run {self.runs[0]} and the challenger "
                              f"{self.runs[1]} of its {self.n_block} cases; the rule is read when both have run every "
                              "case", *self.environment_lines()])
        n = len(self.incumbent.outcomes)
        state = "complete" if self.complete else f"PARTIAL ({n} of {self.n_block} cases): decides nothing"
        lines = [f"[[Paired block]] {state}",
                 f"    {'':<36}{'incumbent':>14}{'challenger':>14}  condition"]
        for label, mine, theirs, held in self.conditions:
            lines.append(f"    {label:<36}{mine:>14}{theirs:>14}  {'holds' if held else 'FAILS'}")
        differing = self.differing()
        lines.append(f"    cases with another verdict, family or confidence: {len(differing)}")
        lines += differing
        lines.append("    the challenger becomes the default: "
                     + ("yes" if self.switch else "no" if self.complete else "not decided (block incomplete)"))
        return "\n".join(lines + self.environment_lines())


def _count(result: SelfCheckResult, prop: str) -> tuple[int, int, float]:
    rate = getattr(result, prop)
    return int(rate["count"]), int(rate["n"]), float(rate["value"])


def read_rule(incumbent: SelfCheckResult, challenger: SelfCheckResult, n_block: int,
              runs: tuple[int, int] | None = None, slack: int = 0) -> PairedReading:
    """The rule of the module docstring on two versions' outcomes of the same cases; ``slack``
    records allowed on each paired count (0: none)."""
    conditions = []
    for label, prop, side in PAIRED_CONDITIONS:
        (a, n, _), (b, m, _) = _count(incumbent, prop), _count(challenger, prop)
        conditions.append((label, f"{a}/{n}", f"{b}/{m}", b >= a - slack if side == ">=" else b <= a + slack))
    for key, label in OWN_TARGETS.items():
        prop, bound, side = TARGETS[key]
        count, n, value = _count(challenger, prop)
        conditions.append((f"challenger's {label}", f"{side} {bound:g}", f"{count}/{n}",
                           value >= bound if side == ">=" else value <= bound))
    complete = len(incumbent.outcomes) == len(challenger.outcomes) == n_block
    return PairedReading(incumbent, challenger, complete, n_block, conditions,
                         runs or (len(incumbent.outcomes), len(challenger.outcomes)))


def _outcomes(results: Path) -> dict[str, CaseOutcome]:
    """The per-case outcomes of an evaluation block under ``results`` (one sources folder)."""
    folders = sorted(p for p in (Path(results) / "evaluation").glob("*") if p.is_dir())
    if len(folders) > 1:
        raise SystemExit(f"{results}/evaluation holds outcomes of {len(folders)} sources hashes "
                         f"({', '.join(f.name for f in folders)}); keep one per results folder")
    files = sorted(folders[0].glob("seed*/*.json")) if folders else []
    out = {}
    for file in files:
        outcome = CaseOutcome.from_json(json.loads(file.read_text(encoding="utf-8")))
        if outcome.case.case_id in out:
            raise SystemExit(f"two outcomes of case {outcome.case.case_id} under {folders[0]}; keep one results "
                             "folder per version and block")
        out[outcome.case.case_id] = outcome
    return out


def environments(results: Path) -> list[tuple[dict | None, int]]:
    """(library versions, number of cases) over the seed folders of one results folder's block,
    in the order each environment first appears."""
    counts: dict[str, list] = {}
    for folder in sorted((Path(results) / "evaluation").glob("*/seed*")):
        for libraries, files in cases_by_environment(folder):
            counts.setdefault(json.dumps(libraries, sort_keys=True), [libraries, 0])[1] += len(files)
    return [(libraries, n) for libraries, n in counts.values()]


def block_cases(protocol: dict) -> dict[str, Case]:
    """Every case of the protocol's evaluation block, by case id (an id names a slot, the same in
    every block; the case itself carries its block's record seed)."""
    settings = protocol["selfcheck"]
    return {c.case_id: c for seed in protocol["blocks"]["evaluation"]["seeds"]
            for c in build_cases(settings["concepts"], seed=int(seed), sensors=settings["sensors"],
                                 none_per_set=int(settings["none_per_set"]), kinds=settings["kinds"])}


def _record(case: Case) -> Case:
    """What makes a case the same record in both versions: everything but the candidate list,
    which is the method's own (a version with other forms offers other candidates)."""
    return replace(case, candidates=None)


def compare(incumbent: tuple[str, str], challenger: tuple[str, str], slack: int = 0) -> PairedReading:
    """Read the rule on the outcomes of two (protocol, results folder) pairs of the same block."""
    protocols = [load_protocol(p) for p, _ in (incumbent, challenger)]
    blocks = [p["blocks"]["evaluation"]["seeds"] for p in protocols]
    if blocks[0] != blocks[1]:
        raise SystemExit(f"the protocols name different evaluation blocks ({blocks[0]} and {blocks[1]}); a paired "
                         "reading needs the same seeds: freeze both with the same --evaluation-seeds")
    if protocols[0]["selfcheck"] != protocols[1]["selfcheck"]:
        raise SystemExit("the protocols build different cases from the same seeds (their self-check settings "
                         "differ); freeze both with the same case list")
    cases = block_cases(protocols[0])
    ids = list(cases)
    mine, theirs = _outcomes(Path(incumbent[1])), _outcomes(Path(challenger[1]))
    foreign = sorted({o.case.case_id for o in [*mine.values(), *theirs.values()]
                      if o.case.case_id not in cases or _record(cases[o.case.case_id]) != _record(o.case)})
    if foreign:
        raise SystemExit(f"{len(foreign)} outcome(s) are not cases of the block (e.g. {foreign[0]}); "
                         "point each version at its own results folder of this block")
    shared = [i for i in ids if i in mine and i in theirs]
    reading = read_rule(SelfCheckResult([mine[i] for i in shared], int(blocks[0][0]), False, 0.0),
                        SelfCheckResult([theirs[i] for i in shared], int(blocks[0][0]), False, 0.0), len(ids),
                        runs=(len(mine), len(theirs)), slack=slack)
    return replace(reading, environments=(environments(Path(incumbent[1])), environments(Path(challenger[1]))))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--incumbent", nargs=2, required=True, metavar=("PROTOCOL", "RESULTS"))
    parser.add_argument("--challenger", nargs=2, required=True, metavar=("PROTOCOL", "RESULTS"))
    parser.add_argument("--partial-figures", action="store_true",
                        help="print the shared cases' figures before the block is complete (they decide nothing)")
    parser.add_argument("--slack", type=int, choices=(0, 1), default=0,
                        help="records of slack on each paired count: 0 (versions 7 and 9), 1 (version 10)")
    args = parser.parse_args()
    print(compare(tuple(args.incumbent), tuple(args.challenger), args.slack).summary(args.partial_figures))


if __name__ == "__main__":
    main()
