"""Bit-identity check of the compiled simulator across a change of its kernels.

``save DIR`` writes the outputs of every case below to DIR (one .npz per concept); ``compare
DIR`` recomputes them with the installed package and reports every case whose outputs differ
in any bit. Run ``save`` with the package before the change and ``compare`` after it.

Cases, for HT/LS and LT/HS on deploy-retract: the nominal model and each effect of the
catalogue at its nominal values (plus two combinations of every effect, one of each exclusive
pair), for each integrator ("rk4", "dopri5", "hybrid") and, for the adaptive ones, with and
without ``share_steps``; two parameter sets per case (nominal and every parameter x 1.02).

Usage: python benchmarks/kernel_identity.py save|compare DIR [--concept htls|lths] [--case NAME] [--method NAME]
"""
from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

from ema_uq import deploy_retract, get_model, simulate_batch
from ema_uq.models.effects import CATALOGUE

COMBOS = {"all_a": [n for n in CATALOGUE if n not in ("backlash_compliant", "ujoint_stations")],
          "all_b": [n for n in CATALOGUE if n not in ("shaft_compliance", "ujoint_kinematics")]}
METHODS = (("rk4", False), ("dopri5", False), ("dopri5", True), ("hybrid", False), ("hybrid", True))


def cases(concept: str, only=None):
    """(label, model) of every case, or of the labels in ``only``."""
    base = get_model(concept)
    everything = [("nominal", base)] + [(name, base.with_effects([name])) for name in CATALOGUE]
    everything += [(label, base.with_effects(names)) for label, names in COMBOS.items()]
    return [(label, model) for label, model in everything if not only or label in only]


def run_all(concept: str, only=None, methods=None) -> dict[str, np.ndarray]:
    ex = deploy_retract()
    out = {}
    for label, model in cases(concept, only):
        nominal = model.parameters.nominal
        thetas = np.stack([nominal, np.clip(nominal * 1.02, model.parameters.lower, model.parameters.upper)])
        for method, shared in METHODS:
            if methods and method not in methods:
                continue
            t = time.perf_counter()
            key = f"{label}|{method}|{'shared' if shared else 'own'}"
            out[key] = simulate_batch(model, thetas, ex.time, ex.input_matrix(model), integrator=method,
                                      share_steps=shared)
            print(f"  {concept} {key}: {time.perf_counter() - t:.1f} s", flush=True)
    return out


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mode", choices=("save", "compare"))
    ap.add_argument("directory")
    ap.add_argument("--concept", choices=("htls", "lths"), action="append")
    ap.add_argument("--case", action="append", help="compare only this case (nominal, an effect, all_a, all_b)")
    ap.add_argument("--method", action="append", choices=("rk4", "dopri5", "hybrid"), help="compare only this integrator")
    args = ap.parse_args(argv)
    failures = 0
    for concept in args.concept or ("htls", "lths"):
        path = os.path.join(args.directory, f"{concept}.npz")
        results = run_all(concept, args.case, args.method)
        if args.mode == "save":
            if args.case or args.method:
                raise SystemExit("save writes every case: leave out --case")
            np.savez(path, **results)
            continue
        reference = np.load(path)
        for key, value in results.items():
            ref = reference[key]
            same = ref.shape == value.shape and np.array_equal(ref.view(np.uint64), value.view(np.uint64))
            if not same:
                failures += 1
                diff = np.nanmax(np.abs(ref - value)) if ref.shape == value.shape else float("nan")
                print(f"DIFFERS {concept} {key}: max |diff| {diff:.3g}")
        print(f"{concept}: {len(results)} cases compared, {failures} differ so far")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
