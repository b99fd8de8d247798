"""Cost of one gap diagnosis: wall time on one core, simulations in total and per candidate.

Record: the independent simulator's Stribeck variant (``stribeck_rational``, breakaway ratio 1.0,
Stribeck speed 1.5 rad/s) on a base perturbed U(+-10 %) off nominal, 2 % noise, every output
channel; estimation on deploy-retract, held out on both validation runs (as the self-check).
Four candidates: stribeck, sensor_delay, shaft_compliance, load_dependent_friction.

Columns, measured in this run on this machine, one numba and one BLAS thread (the share of one
self-check worker): the method without the model-form allowance (version 1), with it
(version 2, the default until version 4 passed its evaluation) and with it at the model contract's
converged RK4 step where no effect brings faster dynamics (version 3: the ``converged_step``
option, tried and not adopted), and version 4 (the default: version 2 with the spanning forms of
the same families beside them, seven candidates)
and version 5 (each family by its nesting form only, the compliance's a stiffness that grows with
the torque carried, at the converged step: four candidates) and version 6 (version 5 with each fit
stopped once the decrease of 2V still to come is below 0.1) and version 7 (version 6 with that
decrease judged by what the next full Gauss-Newton step promises, not extrapolated).
Beside them the figures the performance issue recorded before the
work (HT/LS: 92 s, 636 simulations, on the code of that time) and its targets (HT/LS <= 20 s,
LT/HS <= 45 s on one core). A warm-up diagnosis runs first so the generic kernels' compilation
and cache loading are excluded; the RK4 kernels compiled per effect set
(``ema_uq/simulate/specialise.py``) compile in the first run that uses each set for long enough
(about 13 s each) and load from the cache after that, so the figures to quote are a second run's.

Usage: python benchmarks/gap_speed.py [--concept htls|lths|both] [--seed N] [--versions 5,6]
"""
from __future__ import annotations

import argparse
import os
import time

os.environ.setdefault("NUMBA_NUM_THREADS", "1")      # before numba is imported: one core
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

from ema_uq.gap.attribute import diagnose  # noqa: E402 - after the thread settings
from ema_uq.gap.candidates import offered_forms  # noqa: E402
from ema_uq.gap.strategy import METHOD_VERSIONS  # noqa: E402
from ema_uq.models import get_model  # noqa: E402
from ema_uq.gap.variants import make_records  # noqa: E402
from gap import method_settings  # noqa: E402 - benchmarks/gap.py

CANDIDATES = ("stribeck", "sensor_delay", "shaft_compliance", "load_dependent_friction")
FAMILIES = set(CANDIDATES)
VERSIONS = tuple(METHOD_VERSIONS)
VARIANT, PARAMS = "stribeck_rational", {"ratio": 1.0, "speed": 1.5}
BEFORE = {"htls": (92.0, 636)}            # the figures before the work (s, simulations)
TARGET_S = {"htls": 20.0, "lths": 45.0}


def one(concept: str, seed: int, version: int) -> dict:
    estimation, validation, validation2, _ = make_records(concept, VARIANT, PARAMS, seed=seed)
    settings = method_settings(version)
    # the forms of the four families that the version offers
    candidates = [name for name, effect in offered_forms(get_model(concept).effect_catalogue, settings).items()
                  if effect.family in FAMILIES]
    t0 = time.perf_counter()
    result = diagnose([estimation], [validation, validation2], candidates=candidates, settings=settings, seed=seed)
    wall = time.perf_counter() - t0
    rows = {c.effect: c for c in result.ranking}
    return {"wall": wall, "sims": result.n_simulations, "verdict": result.verdict, "effect": result.effect,
            "per_candidate": {name: (rows[name].n_simulations, rows[name].wall_time_s) for name in rows}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--concept", choices=("htls", "lths", "both"), default="both")
    parser.add_argument("--seed", type=int, default=7)
    parser.add_argument("--versions", default=",".join(map(str, VERSIONS)),
                        help="comma-separated method versions to measure (default: all)")
    args = parser.parse_args()
    concepts = ("htls", "lths") if args.concept == "both" else (args.concept,)
    versions = tuple(int(v) for v in args.versions.split(","))
    unknown = sorted(set(versions) - set(VERSIONS))
    if unknown:
        raise SystemExit(f"--versions: no method version {unknown[0]}; choose from {', '.join(map(str, VERSIONS))}")
    for concept in concepts:
        one(concept, args.seed, 2)                            # warm-up: compile or load every kernel used
        runs = {v: one(concept, args.seed, v) for v in versions}
        before = BEFORE.get(concept)
        print(f"\n{concept}: one gap diagnosis, the forms of {len(CANDIDATES)} families, one core")
        print(f"  {'':40s}{'before (issue)':>16s}" + "".join(f"{f'version {v}':>16s}" for v in versions)
              + f"{'target':>10s}")
        print(f"  {'wall time [s]':40s}{(f'{before[0]:.0f}' if before else '-'):>16s}"
              + "".join(f"{runs[v]['wall']:16.1f}" for v in versions) + f"{TARGET_S[concept]:10.0f}")
        print(f"  {'simulations':40s}{(str(before[1]) if before else '-'):>16s}"
              + "".join(f"{runs[v]['sims']:16d}" for v in versions))
        for name in dict.fromkeys(n for v in versions for n in runs[v]["per_candidate"]):
            cells = [runs[v]["per_candidate"].get(name) for v in versions]
            text = "".join(f"{f'{c[0]} / {c[1]:.1f} s' if c else '-':>16s}" for c in cells)
            print(f"  {'  ' + name + ' (sims / s)':40s}{'-':>16s}{text}")
        print("  verdict: " + ", ".join(f"v{v} {runs[v]['verdict']} {runs[v]['effect'] or ''}".rstrip()
                                        for v in versions))

if __name__ == "__main__":
    main()
