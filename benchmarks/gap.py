"""Gap diagnosis: the blind self-check on records of the independent simulator
(``ema_uq.gap.selfcheck`` on ``ema_uq.gap.variants``), scored against its targets, with the
confusion matrix and the per-case table.

Cases per concept and sensor set (full outputs; the rig's sensors): every in-catalogue effect
variant once with log-uniform magnitudes and uniform phases, ``--none-per-set`` no-effect
cases and every out-of-catalogue variant once; base parameters U(+-10 %) off nominal, 2 %
noise, each case from its own seed derived from ``--seed``. Scores: top-1 accuracy (the right
family named), false-alarm rate, out-of-catalogue flagged (only ``unexplained`` counts) with
95 % Clopper-Pearson intervals, and the honest shrink (signed, scored on the second validation
record, with its standard error) where the right family was found.

Peer (``--peer``, off by default: it costs about a quarter of the main run): the former
circular self-check, whose records came from the diagnosis's own catalogue kernels at the
catalogue's nominal magnitudes from nominal base parameters (one case per effect plus one
no-effect case, full outputs), scored by the same rules.

Usage: python benchmarks/gap.py [--concept htls|lths|both] [--sensors full realistic] [--jobs N]
                                [--quick] [--none-per-set N] [--kinds ...] [--none-from K] [--seed N]
                                [--peer] [--out JSON]
"""
from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from ema_uq.experiments import Measurement, add_noise, deploy_retract, validation
from ema_uq.gap import diagnose
from ema_uq.gap.selfcheck import (DEFAULT_SEED, KINDS, NONE_PER_SET, SENSOR_SETS, TARGET_FALSE_ALARM, TARGET_TOP1,
                                  family_of, self_check)
from ema_uq.gap.variants import record_channels, validation_scaled
from ema_uq.models import get_model
from ema_uq.simulate import simulate_batch

PEER_NOISE = 0.02


def circular_records(concept: str, effect: str | None, seed: int) -> list[Measurement]:
    """The former generator: catalogue kernel at its nominal magnitude, nominal base parameters."""
    base = get_model(concept)
    model = base if effect is None else base.with_effects([effect])
    theta = model.parameters.nominal
    channels = record_channels(concept, "full")
    rng = np.random.default_rng(seed)
    records = []
    for experiment in (deploy_retract(), validation(), validation_scaled()):
        clean = simulate_batch(model, theta, experiment.time, experiment.input_matrix(model))
        records.append(Measurement(concept, experiment, channels, add_noise(clean, PEER_NOISE, rng),
                                   {"noise_fraction": PEER_NOISE, "seed": seed, "source": "catalogue kernels"}))
    return records


def circular_peer(concept: str, seed: int) -> dict:
    rows = []
    for i, effect in enumerate((*get_model(concept).available_effects, None)):
        estimation, *held = circular_records(concept, effect, seed + 1000 + i)
        t0 = time.perf_counter()
        result = diagnose([estimation], held, seed=seed + 1000 + i)
        found = family_of(result, concept)
        truth = "none" if effect is None else getattr(get_model(concept).effect_catalogue[effect], "family", None)
        label = found if result.verdict == "effect" else result.verdict
        rows.append({"truth": truth or effect, "label": label, "seconds": time.perf_counter() - t0})
        print(f"    peer {concept}/{effect}: {label} ({time.perf_counter() - t0:.0f} s)", flush=True)
    effects = [r for r in rows if r["truth"] != "none"]
    return {"top1_accuracy": float(np.mean([r["label"] == r["truth"] for r in effects])),
            "false_alarm_rate": float(np.mean([r["label"] != "none" for r in rows if r["truth"] == "none"])),
            "rows": rows}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--concept", choices=("htls", "lths", "both"), default="both")
    parser.add_argument("--sensors", nargs="+", choices=SENSOR_SETS, default=list(SENSOR_SETS))
    parser.add_argument("--jobs", type=int, default=1, help="worker processes (results do not depend on it)")
    parser.add_argument("--quick", action="store_true", help="the 3-case subset on the first concept")
    parser.add_argument("--none-per-set", type=int, default=NONE_PER_SET)
    parser.add_argument("--kinds", nargs="+", choices=KINDS, default=list(KINDS),
                        help="case kinds to run (e.g. --kinds none --none-per-set 15: the false-alarm rate alone)")
    parser.add_argument("--none-from", type=int, default=0, metavar="K",
                        help="number the no-effect cases from K (--kinds none --none-from 6 --none-per-set 9: "
                             "cases #6-#14, adding to a run of 6 without repeating it)")
    parser.add_argument("--seed", type=int, default=DEFAULT_SEED)
    parser.add_argument("--peer", action="store_true", help="also run the former circular self-check")
    parser.add_argument("--out", metavar="JSON", help="write scores and per-case table as JSON")
    args = parser.parse_args()

    concepts = ["htls", "lths"] if args.concept == "both" else [args.concept]
    load = os.getloadavg()[0]
    result = self_check(seed=args.seed, quick=args.quick, concepts=concepts, sensors=args.sensors,
                        none_per_set=args.none_per_set, kinds=args.kinds, none_first=args.none_from, jobs=args.jobs,
                        progress=lambda line: print(line, flush=True))
    print()
    print(result.summary())
    print(f"\nper concept/sensor set: " + "; ".join(
        f"{k}: top-1 {v['top1_accuracy']:.2f}, false alarms {v['false_alarm_rate']:.2f}, out of catalogue "
        f"{v['out_of_catalogue_flagged']:.2f}" for k, v in result.by_set().items()))
    print(f"{len(result.outcomes)} cases in {result.wall_time_s:.0f} s with {args.jobs} job(s) "
          f"(load average {load:.1f} on {os.cpu_count()} cores at the start)")
    peers = {}
    if args.peer:
        print("\n[[Peer: the former circular self-check (catalogue kernels, nominal magnitudes and base)]]")
        peers = {c: circular_peer(c, args.seed) for c in concepts}
        print(f"    {'':<26} {'independent variants':>22} {'circular (peer)':>16}   target")
        for c, p in peers.items():
            print(f"    {c + ' top-1 accuracy':<26} {result.by_set().get(c + '/full', {}).get('top1_accuracy', np.nan):>22.3f} "
                  f"{p['top1_accuracy']:>16.3f}   >= {TARGET_TOP1}")
            print(f"    {c + ' false alarms':<26} {result.by_set().get(c + '/full', {}).get('false_alarm_rate', np.nan):>22.3f} "
                  f"{p['false_alarm_rate']:>16.3f}   <= {TARGET_FALSE_ALARM}")
    if args.out:
        with open(args.out, "w", encoding="utf-8") as fh:
            json.dump({**result.to_json(), "jobs": args.jobs, "load_average": load, "circular_peer": peers}, fh,
                      indent=1)


if __name__ == "__main__":
    main()
