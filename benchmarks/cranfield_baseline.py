"""Cranfield linear actuator: the data-driven baseline (:mod:`ema_uq.rigs.cranfield_baseline`) beside
the model-based fault diagnosis (:mod:`ema_uq.rigs.cranfield`).

The baseline, a random forest on per-cycle features, is trained on the labelled record sets
(normal -> none, backlash1/2 -> backlash, lackLubrication1/2 -> lubrication_loss) and
cross-validated by run (GroupKFold over the run number: a test run is never in training, in
any set); printed: its accuracy overall and per class, and the labels it gives each record
set's cycles. Then each fault class is left out of training and the baseline names its cycles:
it has no "none of mine" and puts them in a class it knows. Beside it, the diagnosis's verdict
of each record set (fitted on runs 1-5, judged on runs 6-10, from healthy records only), or
the verdict counts of a split benchmark's JSON (``--splits-json``, written by
``benchmarks/cranfield.py --splits all --out``).

Usage: python benchmarks/cranfield_baseline.py [--splits-json JSON] [--out JSON]

Needs the record sets ($EMA_UQ_CRANFIELD_DIR or ../shared/data/real/cranfield_linear_actuator)
and scikit-learn (the ``baseline`` extra).
"""
from __future__ import annotations

import argparse
import json
import time

from ema_uq import io
from ema_uq.rigs.cranfield import CHANNELS, EXPECTED, run_study
from ema_uq.rigs.cranfield_baseline import CycleTable, cross_validate, leave_one_class_out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--splits-json", help="verdict counts of the diagnosis from a split benchmark's JSON")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", help="also write the figures as JSON")
    args = parser.parse_args()

    def read(name, runs):
        return io.read_cranfield(io.cranfield_file(name), runs=runs, channels=CHANNELS)

    t0 = time.perf_counter()
    blocks = {name: read(name, range(1, 11)) for name in EXPECTED}
    table = CycleTable.of(blocks, EXPECTED)
    cv = cross_validate(table, seed=args.seed)
    print(f"[[Baseline]] random forest on {table.x.shape[1]} per-cycle features, {table.label.size} cycles; "
          f"cross-validated by run (folds hold out runs {cv.folds})")
    print(f"    accuracy {cv.accuracy:.3f}; per class " + ", ".join(f"{c} {a:.3f}" for c, a in cv.per_class.items()))
    left_out = {}
    for fault in sorted(set(EXPECTED.values()) - {"none"}):
        left_out[fault] = leave_one_class_out(table, fault, seed=args.seed)

    if args.splits_json:
        with open(args.splits_json, encoding="utf-8") as fh:
            split_counts = json.load(fh)["counts"]
        diagnosis = {name: ", ".join(f"{n} {v}" for v, n in sorted(c.items(), key=lambda kv: -kv[1]))
                     for name, c in split_counts.items()}
        diagnosis_label = "diagnosis (verdicts over the splits)"
    else:
        study = run_study(read)
        diagnosis = {name: study.verdict_of(name) for name in EXPECTED}
        diagnosis_label = "diagnosis (runs 1-5 | 6-10)"
    print(f"    {'record set':<18} {'expected':<18} {'baseline (cycles named, out of fold)':<46} {diagnosis_label}")
    for name in EXPECTED:
        named = ", ".join(f"{n} {v}" for v, n in sorted(cv.per_record_set[name].items(), key=lambda kv: -kv[1]))
        print(f"    {name:<18} {EXPECTED[name]:<18} {named:<46} {diagnosis[name]}")
    print("[[Baseline, one fault class left out of training]] what it calls the cycles of the kind it never saw")
    for fault, per_set in left_out.items():
        for name, named in per_set.items():
            print(f"    {fault:<18} {name:<18} " + ", ".join(f"{n} {v}" for v, n in
                                                           sorted(named.items(), key=lambda kv: -kv[1])))
    print(f"    wall time {time.perf_counter() - t0:.0f} s")
    if args.out:
        with open(args.out, "w", encoding="utf-8") as fh:
            json.dump({"baseline": cv.to_json(), "left_out": left_out, "diagnosis": diagnosis}, fh, indent=2,
                      default=float)


if __name__ == "__main__":
    main()
