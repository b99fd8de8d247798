"""Cranfield linear actuator: simulator speed, the healthy fit and the fault diagnosis of every
record set, timed, with the verdict table (the study of ``studies/cranfield.yaml``).

Timings: one 1620-sample block (64.8 s at 25 Hz) simulated for 1 and for 64 parameter sets
(the batched kernel, after its first compile), nominal and with every effect switched on; the
healthy fit (Gauss-Newton on runs 1-5 of normal.csv, 15 blocks); one diagnosis per record set.

Usage: python benchmarks/cranfield.py [--quick | --splits all] [--out JSON]
    --quick: a reduced study (fit on runs 1-3, faults judged on runs 3-4 after fitting runs 1-2)
    --splits all: the study under every split of the family :func:`ema_uq.rigs.cranfield.run_splits`
        (12 halvings of the ten runs, fitted | held out: the ten arcs and the two interleaved
        ones), one verdict line each, then the verdict counts per record set: how much the
        verdicts depend on which runs are held out, the rig drifting within each test session
        (~25 s per split)

Needs the record sets ($EMA_UQ_CRANFIELD_DIR or ../shared/data/real/cranfield_linear_actuator).
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np

from ema_uq import io
from ema_uq.rigs.cranfield import CHANNELS, EXPECTED, run_split_study, run_study
from ema_uq.models import get_model
from ema_uq.models.cranfield import EFFECTS
from ema_uq.simulate import simulate_batch


def _best_of(fn, repeats: int = 5) -> float:
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def simulator_timings() -> dict[str, float]:
    """Seconds per call on one healthy block: 1 and 64 sets, nominal and with every effect."""
    block = io.read_cranfield(io.cranfield_file("normal"), loads=[20], runs=[1], channels=CHANNELS)[0]
    out = {}
    for label, model in (("nominal", get_model("cranfield")),
                         ("all effects", get_model("cranfield").with_effects(tuple(EFFECTS)))):
        inputs = block.experiment.input_matrix(model)
        theta = model.parameters.nominal
        t0 = time.perf_counter()
        simulate_batch(model, theta, block.time, inputs)
        out[f"{label}: first call (compile or cache load)"] = time.perf_counter() - t0
        out[f"{label}: 1 set"] = _best_of(lambda: simulate_batch(model, theta, block.time, inputs))
        many = np.repeat(theta[None], 64, axis=0)
        out[f"{label}: 64 sets"] = _best_of(lambda: simulate_batch(model, many, block.time, inputs))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="reduced study (about 40 s instead of 60 s)")
    parser.add_argument("--splits", choices=("all",), help="the study under every split of the run-split family "
                                                          "(ema_uq.rigs.cranfield.run_splits)")
    parser.add_argument("--out", help="also write the timings and the study as JSON")
    args = parser.parse_args()
    if args.quick and args.splits:
        parser.error("--quick and --splits choose different runs; give one of them")

    timings = simulator_timings()
    print("[[Simulator]] one block of 1620 samples")
    for label, seconds in timings.items():
        print(f"    {label:<48} {seconds * 1e3:9.2f} ms")

    records = io.CranfieldRecords(channels=CHANNELS)
    read = records.read

    if args.splits:
        result = run_split_study(read, record_sets=io.cranfield_record_sets(), runs_of=records.runs_of)
        print(result.summary())
        if args.out:
            with open(args.out, "w", encoding="utf-8") as fh:
                json.dump({"simulator_s": timings, **result.to_json()}, fh, indent=2, default=float)
        return
    splits = (dict(fit_runs=(1, 2, 3), healthy_held_out_runs=(6, 7, 8, 9), estimation_runs=(1, 2), held_out_runs=(3, 4))
              if args.quick else {})
    t0 = time.perf_counter()
    study = run_study(read, **splits)
    wall = time.perf_counter() - t0
    print(study.summary())
    right = sum(study.verdict_of(name) == expected for name, expected in EXPECTED.items())
    print(f"[[Verdicts]] {right} of {len(EXPECTED)} as expected; healthy fit {study.reference.wall_time_s:.1f} s, "
          f"study {wall:.1f} s")
    if args.out:
        with open(args.out, "w", encoding="utf-8") as fh:
            json.dump({"simulator_s": timings, "study": study.to_json(), "study_wall_time_s": wall}, fh, indent=2,
                      default=float)


if __name__ == "__main__":
    main()
