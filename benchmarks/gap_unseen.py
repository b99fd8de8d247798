"""Gap diagnosis: the frozen method run once on mechanisms it was never run on.

The self-check's variants shaped method versions 1 and 2 (the catalogue once gained forms that
mirror some of them), and its evaluation blocks draw new records of the same variants. This
script runs the frozen method on the variants written after version 2 was frozen
(:data:`ema_uq.gap.variant_catalogue.UNSEEN_VARIANTS`): three other forms of catalogue families
(direction-dependent ball-screw efficiency, direction-asymmetric Stribeck friction,
sample-and-hold sensors) and three mechanisms outside the catalogue (friction warm-up during a
record, a periodic linearity error of the position sensors, a force offset of the load rig),
each per concept and sensor set, the in-catalogue ones also with their family left out. A protocol
that names ``variant_set: UNSEEN_VARIANTS_2`` (``benchmarks/gap_unseen2.yaml``) runs instead the
second set, written for the evaluation of method version 4 (a torque ripple proportional to the
motor torque, a U-joint angle growing with the stroke, window-averaging sensors; outside the
catalogue a saturating torque constant, a PI speed loop and a speed feed-forward), and one that
names ``variant_set: UNSEEN_VARIANTS_3`` (``benchmarks/gap_unseen3.yaml``) the third, written for
the evaluation of method version 5 and run on the frozen version 7 (the play of a worn screw, a
progressive coupling, breakaway friction that builds up at rest; outside the catalogue a binding screw, an eccentric motor angle
sensor and a position-loop dead band); without the key the set is the first.

The protocol (``benchmarks/gap_unseen.yaml``, committed before the run) fixes the seeds, the
cases and the scoring; the run refuses unless the diagnosis sources hash to a value the method
protocol (``benchmarks/gap_protocol.yaml``) accepts, and it uses that protocol's settings. Each
case's outcome is kept under ``results/<sources hash>/seed<S>/`` (a rerun resumes and diagnoses
nothing twice); the scores go to ``<results>.json`` and are printed beside those of the method's
evaluation block.

Usage: python benchmarks/gap_unseen.py [--protocol benchmarks/gap_unseen.yaml|gap_unseen2.yaml|...]
                                      [--jobs N]
       python benchmarks/gap_unseen.py --development VERSION --results DIR [--jobs N]   (a method not frozen)
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import yaml

from ema_uq.gap.selfcheck import SelfCheckResult, self_check, unseen_cases
from ema_uq.gap.variant_catalogue import UNSEEN_SETS
from gap import (METHOD_VERSIONS, ROOT, check_sources, load_protocol, method_settings, outcome_hash, protocol_settings,
                 record_environment, side_by_side)


#: the variant set of a protocol that names none (the first protocol, written before there were two)
DEFAULT_VARIANT_SET = "UNSEEN_VARIANTS"


def load_unseen_protocol(path: Path) -> dict:
    """The protocol, checked against the variants it names (a variant renamed or moved to
    another family since it was written stops the run); ``variant_set`` (default
    :data:`DEFAULT_VARIANT_SET`) names the set of :data:`~ema_uq.gap.variant_catalogue.UNSEEN_SETS`.
    ``cases_from: OTHER.yaml`` (a paired reference run) takes every key but the method and the
    results folder from that protocol, so both runs diagnose the same cases by construction."""
    with open(path, encoding="utf-8") as fh:
        protocol = yaml.safe_load(fh)
    if isinstance(protocol, dict) and "cases_from" in protocol:
        cases = load_unseen_protocol(ROOT / protocol["cases_from"])
        own = {k: v for k, v in protocol.items() if k != "cases_from"}
        extra, missing = set(own) - {"method_protocol", "results"}, {"method_protocol", "results"} - set(own)
        if extra or missing:
            raise SystemExit(f"{path}: a protocol with cases_from sets only method_protocol and results, "
                             + (f"not {sorted(extra)}" if extra else f"and both; {sorted(missing)} is missing"))
        protocol = {**cases, **own}
    if not isinstance(protocol, dict) or "variants" not in protocol or not protocol.get("seeds"):
        raise SystemExit(f"{path}: not an unseen-variant protocol (needs seeds and variants)")
    variant_set = protocol.get("variant_set", DEFAULT_VARIANT_SET)
    if variant_set not in UNSEEN_SETS:
        raise SystemExit(f"{path} names the variant set {variant_set!r}; give one of {', '.join(UNSEEN_SETS)}")
    named = {k: v.get("family") for k, v in protocol["variants"].items()}
    written = {k: v.family for k, v in UNSEEN_SETS[variant_set].items()}
    if named != written:
        raise SystemExit(f"{path} names the variants {named}, the code has {written}: the protocol no longer "
                         "describes the cases; write a new protocol with a new seed")
    return protocol


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--protocol", default=str(ROOT / "benchmarks" / "gap_unseen.yaml"), metavar="YAML")
    parser.add_argument("--jobs", type=int, default=1, help="worker processes (results do not depend on it)")
    parser.add_argument("--development", type=int, metavar="VERSION", choices=tuple(METHOD_VERSIONS),
                        help="run the protocol's cases as development cases of method VERSION (not frozen: no "
                             "source check), outcomes under --results, scored beside the protocol's own run")
    parser.add_argument("--results", metavar="DIR", help="outcome folder of a --development run")
    args = parser.parse_args()
    protocol = load_unseen_protocol(Path(args.protocol))
    method = load_protocol(ROOT / protocol["method_protocol"])
    if args.development is not None:
        if not args.results:
            raise SystemExit("a --development run needs --results DIR: its outcomes must not mix with the protocol's")
        development(protocol, args.development, Path(args.results), args.jobs)
        return
    problem = check_sources(method)
    if problem:
        raise SystemExit(problem)
    current = outcome_hash(method)
    results = ROOT / protocol["results"]
    seeds = [int(seed) for seed in protocol["seeds"]]
    parts = {}
    for seed in seeds:
        cases = unseen_cases(seed, protocol["concepts"], protocol["sensors"],
                             protocol.get("variant_set", DEFAULT_VARIANT_SET))
        if len(cases) != int(protocol["n_cases_per_seed"]):
            raise SystemExit(f"{len(cases)} cases built, the protocol states {protocol['n_cases_per_seed']}")
        note = record_environment(results / current[:12] / f"seed{seed}")
        if note:
            print(note, flush=True)
        parts[seed] = self_check(cases=cases, seed=seed, settings=protocol_settings(method), jobs=args.jobs,
                                 cache=results / current[:12] / f"seed{seed}",
                                 progress=lambda line, s=seed: print(f"seed {s} {line}", flush=True))
    first = parts[seeds[0]]
    result = SelfCheckResult([o for part in parts.values() for o in part.outcomes], seeds[0], False,
                             sum(part.wall_time_s for part in parts.values()),
                             {**first.settings, "seeds": seeds, "protocol": protocol, "sources_sha256": current},
                             first.provenance)
    with open(results.with_suffix(".json"), "w", encoding="utf-8") as fh:
        json.dump(result.to_json(), fh, indent=1)
    print()
    print(result.summary())
    columns = {}
    evaluation = results.parent / "evaluation.json"
    if evaluation.is_file():
        with open(evaluation, encoding="utf-8") as fh:
            block = json.load(fh)
            columns[f"evaluation {block['seed']}"] = SelfCheckResult.from_json(block)
    if len(seeds) > 1:
        columns.update({f"unseen {seed}": part for seed, part in parts.items()})
    columns["unseen " + "+".join(map(str, seeds))] = result
    print("\n[[Frozen method: self-check variants vs variants written after the freeze]]")
    print(side_by_side(columns))


def development(protocol: dict, version: int, results: Path, jobs: int) -> None:
    """The protocol's cases diagnosed by method ``version`` as it stands (development data: the
    cases are those the protocol's run has already shown), scored beside that run."""
    seeds = [int(seed) for seed in protocol["seeds"]]
    settings = method_settings(version)
    outcomes, wall = [], 0.0
    for seed in seeds:
        cases = unseen_cases(seed, protocol["concepts"], protocol["sensors"],
                             protocol.get("variant_set", DEFAULT_VARIANT_SET))
        part = self_check(cases=cases, seed=seed, settings=settings, jobs=jobs, cache=results / f"seed{seed}",
                          progress=lambda line, s=seed: print(f"seed {s} {line}", flush=True))
        outcomes += part.outcomes
        wall += part.wall_time_s
    result = SelfCheckResult(outcomes, seeds[0], False, wall,
                             {**part.settings, "seeds": seeds, "development_of_method": version}, part.provenance)
    with open(results.with_suffix(".json"), "w", encoding="utf-8") as fh:
        json.dump(result.to_json(), fh, indent=1)
    columns = {}
    frozen = (ROOT / protocol["results"]).with_suffix(".json")
    if frozen.is_file():
        with open(frozen, encoding="utf-8") as fh:
            columns["the protocol's run"] = SelfCheckResult.from_json(json.load(fh))
    columns[f"method {version}, development"] = result
    print(result.summary())
    print(f"\n[[Unseen variants: the protocol's run vs method version {version} (development)]]")
    print(side_by_side(columns))


if __name__ == "__main__":
    main()
