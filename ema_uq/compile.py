"""Fill the numba cache of every simulation kernel ahead of the work that uses it.

Every kernel is declared ``cache=True``: its machine code is written next to its module (or
under ``NUMBA_CACHE_DIR``) on first use and loaded by later processes. Without this step the
first stage of a workflow that touches a kernel pays its compilation (tens of seconds per
kernel family), and parallel jobs pay it at once. :func:`compile_kernels` calls every entry
point on a few samples: each concept with each integrator (``rk4``, ``dopri5``, ``hybrid``;
with and without shared step sequences), the concept augmented with each of its catalogue
effects, and the gap self-check's independent simulator. numba compiles a kernel with its
whole call tree on its first call, so a short run reaches every branch. The RK4 kernels
compiled for one effect set (``simulate/specialise.py``) are not made here: there is one per
set a diagnosis tries, pairs included, and the first process that runs a set often compiles
its kernel into the same cache.
"""
from __future__ import annotations

import time
from typing import Callable

import numpy as np

#: samples simulated per call: enough for every kernel to run a step, few enough to be instant
N_SAMPLES = 20
INTEGRATORS = ("rk4", "dopri5", "hybrid")


def _paths(concept: str):
    """(label, thunk) of every simulation entry point of one concept."""
    from .models import get_model
    from .simulate import simulate_batch

    model = get_model(concept)
    dt = 0.01
    t = dt * np.arange(N_SAMPLES)
    u = np.zeros((N_SAMPLES, len(model.inputs)))
    thetas = np.repeat(model.parameters.nominal[None], 2, axis=0)

    def run(m, th, integrator, share):
        return lambda: simulate_batch(m, th, t, u, integrator=integrator, share_steps=share)

    for integrator in INTEGRATORS:
        for share in ((False,) if integrator == "rk4" else (False, True)):
            yield f"{concept} {integrator}{' shared steps' if share else ''}", run(model, thetas, integrator, share)
    for effect in model.available_effects:
        augmented = model.with_effects([effect])
        th = np.repeat(augmented.parameters.nominal[None], 2, axis=0)
        for share in (False, True):
            yield (f"{concept} + {effect}{' shared steps' if share else ''}",
                   run(augmented, th, augmented.integrator, share))


def _variant_paths(concepts):
    from .experiments import deploy_retract
    from .gap.variants import CONCEPTS, simulate_variant

    experiment = deploy_retract().slice(0, N_SAMPLES)
    for concept in (c for c in CONCEPTS if c in concepts):
        yield f"{concept} self-check simulator", (lambda c=concept: simulate_variant(c, experiment))


def compile_kernels(concepts=None, progress: Callable[[str], None] | None = None) -> list[dict]:
    """Call every kernel entry point once (see the module doc); returns one row per path:
    ``{"path", "seconds", "status"}`` with status ``"ok"`` or the one-line reason the path does
    not apply to the concept (e.g. an integrator the concept does not offer)."""
    from .models import concepts as all_concepts

    names = all_concepts() if concepts is None else tuple(concepts)
    unknown = [c for c in names if c not in all_concepts()]
    if unknown:
        raise ValueError(f"unknown concept(s) {', '.join(unknown)}; choose from {', '.join(all_concepts())}")
    rows = []

    def paths():
        for concept in names:
            yield from _paths(concept)
        yield from _variant_paths(names)

    for label, thunk in paths():
        t0 = time.perf_counter()
        try:
            thunk()
            status = "ok"
        except ValueError as exc:       # a path the concept does not have: named, not fatal
            status = " ".join(str(exc).split())
        rows.append({"path": label, "seconds": time.perf_counter() - t0, "status": status})
        if progress is not None:
            progress(f"{label}: {rows[-1]['seconds']:.1f} s{'' if status == 'ok' else ' (' + status + ')'}")
    return rows
