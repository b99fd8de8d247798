"""When an effect set gets an RK4 kernel of its own.

The RK4 entry that takes an effect set as a run-time bit set (``_integrate_batch_flags``) is
compiled once for every set, and pays for it on every run: each effect's physics sits behind a
test of its bit, in one function large enough that LLVM optimises it poorly. An HT/LS model with
one effect ran at 2.3x the nominal cost (32 against 14 ms a run), and each effect added to the
catalogue slowed all of them. The entry compiled for one concept and effect set
(``_integrate_batch_specialised``) computes the same numbers bit for bit at about the nominal
cost, but each set compiles for about 13 s (into the numba cache: once per machine).

So an effect set runs specialised when its kernel is already compiled (in this process or in
the cache), or once this process has spent :data:`SPECIALISE_AFTER_S` seconds running it on
the generic entry: a set used that much is being fitted, and a fit runs it many times more (a
candidate of the gap diagnosis: hundreds of runs), in this process or the next. A test that
simulates an effect a few times never compiles one. Which entry ran is invisible in the
results: both compute the same numbers.
"""
from __future__ import annotations

import time
from collections import defaultdict

import numba
from numba import types

from .integrators import _integrate_batch_flags, _integrate_batch_specialised

#: seconds of generic runs of one effect set in a process after which its own kernel is compiled
SPECIALISE_AFTER_S = 4.0

_ENTRIES: dict = {}                         # compiled specialisations: (kernel id, flags) -> entry point
_PROBED: set = set()                        # effect sets whose cache entry was looked for
_GENERIC_SECONDS: defaultdict = defaultdict(float)   # seconds run on the generic entry, per set


def _signature(model_id: int, flags: int, args) -> tuple:
    return (types.literal(model_id), types.literal(flags), *(numba.typeof(a) for a in args))


def _cached(signature) -> bool:
    """Whether the numba cache holds this specialisation (loading it is cheap, compiling is not)."""
    cache = getattr(_integrate_batch_specialised, "_cache", None)
    try:
        return cache is not None and cache.load_overload(signature, _integrate_batch_specialised.targetctx) is not None
    except Exception:       # an unreadable or foreign cache entry: numba recompiles it when asked
        return False


def _compile(key: tuple, signature):
    entry = _integrate_batch_specialised.compile(signature)
    _ENTRIES[key] = entry
    return entry


def _entry(model_id: int, flags: int, args):
    """The specialised entry of the set when it is compiled, cached, or has earned it; else None."""
    key = (model_id, flags)
    entry = _ENTRIES.get(key)
    if entry is not None or not hasattr(_integrate_batch_specialised, "compile"):   # NUMBA_DISABLE_JIT
        return entry
    if key not in _PROBED:
        _PROBED.add(key)
        signature = _signature(model_id, flags, args)
        if _cached(signature):
            return _compile(key, signature)
    if _GENERIC_SECONDS[key] >= SPECIALISE_AFTER_S:
        return _compile(key, _signature(model_id, flags, args))
    return None


def run_rk4_effects(model_id: int, flags: int, *args) -> None:
    """``_integrate_batch_flags(model_id, flags, *args)``, on the set's own kernel when it has one
    or has earned it (module docstring). ``args`` as ``simulate_batch`` passes them (C-contiguous
    float64 arrays, a float step, an int count): the compiled entry point is called directly and
    takes exactly the types it was compiled for."""
    entry = _entry(model_id, flags, args)
    if entry is not None:
        entry(model_id, flags, *args)
        return
    start = time.perf_counter()
    _integrate_batch_flags(model_id, flags, *args)
    _GENERIC_SECONDS[(model_id, flags)] += time.perf_counter() - start


def specialise(model_id: int, flags: int, *args):
    """The specialised entry of one concept and effect set, compiled (or loaded) now."""
    key = (model_id, flags)
    return _ENTRIES.get(key) or _compile(key, _signature(model_id, flags, args))
