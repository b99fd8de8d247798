"""Forward-simulation speed: scipy peer vs the numba simulator, side by side.

For each concept, full deploy-retract runs (38 s, 3800 samples) per second of wall time:

  (a) peer   : Python rhs under scipy ``solve_ivp`` (RK45, rtol 1e-6, atol 1e-9), one held
               sample interval at a time (tests/reference_scipy.py, ``peer_simulate``);
  (b) single : ``simulate_batch`` called once per parameter set, in a loop;
  (c) batch  : one ``simulate_batch`` call on 256 sets, on all numba threads;
(b) and (c) for each integrator: "hybrid" (exact zero-order-hold steps over the intervals where
the concept is linear, Dormand-Prince elsewhere; used by the forward-only stages), adaptive
Dormand-Prince 5(4) at the concept's rtol, and fixed-step RK4 at the concept's step (the
default, used by fits). The adaptive rows also give the work of one nominal run: exact
intervals, accepted and rejected steps, right-hand-side evaluations.

Also: accuracy of the peer and of each integrator against the DOP853 rtol 1e-10 reference
(so the peer is compared at equal accuracy), and numba compile time measured in fresh
subprocesses with an empty cache directory (first process compiles, second reuses the cache).

With ``--effects``: the cost of one run of each effect's kernel (each catalogue effect alone,
at its nominal values) relative to the nominal kernel, per concept and integrator, on one
thread; RK4 twice: on the one kernel for every effect set ("rk4") and on the kernel compiled
for each set ("rk4-own", ``ema_uq/simulate/specialise.py``; on an empty cache that compiles
about 13 s per effect); ``--versus DIR`` measures a second package root (e.g. a worktree of an earlier commit)
interleaved with this one and prints the two side by side.

Usage: python benchmarks/simulate.py [--quick] [--effects [--versus DIR]]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time

import numba
import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.join(HERE, os.pardir, "tests"))

from ema_uq import deploy_retract, get_model, simulate_batch  # noqa: E402
from ema_uq.simulate import step_statistics  # noqa: E402
from reference_scipy import PEER_SETTINGS, peer_simulate, reference_simulate  # noqa: E402

TARGET_SINGLE_OVER_PEER = {"htls": 250.0}
TARGET_BATCH_OVER_SINGLE = 1.7
N_BATCH = 256

_FIRST_CALL = r"""
import json, time
t0 = time.perf_counter()
from ema_uq import deploy_retract, get_model, simulate_batch
t1 = time.perf_counter()
ex = deploy_retract()
m = get_model("htls")
simulate_batch(m, m.parameters.nominal, ex.time, ex.input_matrix())
t2 = time.perf_counter()
m = get_model("lths")
simulate_batch(m, m.parameters.nominal, ex.time, ex.input_matrix())
t3 = time.perf_counter()
simulate_batch(m, m.parameters.nominal, ex.time, ex.input_matrix())
t4 = time.perf_counter()
simulate_batch(m, m.parameters.nominal, ex.time, ex.input_matrix(), integrator="hybrid")
t5 = time.perf_counter()
print(json.dumps({"import": t1 - t0, "first_htls": t2 - t1, "first_lths": t3 - t2, "warm_lths": t4 - t3,
                  "first_hybrid": t5 - t4}))
"""


def best_rate(fn, runs_per_call: int, repeats: int) -> float:
    """Best-of-``repeats`` throughput [runs/s] of ``fn`` doing ``runs_per_call`` runs."""
    best = np.inf
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return runs_per_call / best


def parameter_sets(model, n: int, seed: int = 0) -> np.ndarray:
    """(n, n_params) nominal values scaled by U(0.8, 1.2), so each run differs."""
    rng = np.random.default_rng(seed)
    return model.parameters.nominal * rng.uniform(0.8, 1.2, size=(n, len(model.parameters)))


def bench_concept(concept: str, n_peer: int, n_single: int, repeats: int, accuracy: bool,
                  peer_rtol: float = 1e-6) -> list[dict]:
    """Runs per second of the peer, one set and the batch (one row per integrator); ``peer_rtol``
    tightens the peer so it can be compared at the accuracy of the simulator (atol = 1e-3 rtol)."""
    def peer_simulate(concept, theta, consts, time_, inputs):
        return reference_simulate(concept, theta, consts, time_, inputs, method="RK45",
                                  rtol=peer_rtol, atol=1e-3 * peer_rtol)

    model = get_model(concept)
    ex = deploy_retract()
    time_, inputs = ex.time, ex.input_matrix()
    thetas = parameter_sets(model, N_BATCH)
    consts = model.constants.as_dict(model.constants.nominal)
    as_dict = model.parameters.as_dict

    peer = best_rate(lambda: [peer_simulate(concept, as_dict(thetas[i]), consts, time_, inputs)
                              for i in range(n_peer)], n_peer, 1)
    if accuracy:
        theta, const_vec = model.parameters.nominal, model.constants.nominal
        ref = reference_simulate(concept, as_dict(theta), consts, time_, inputs)
        scale = np.abs(ref).max(axis=0)
        err = lambda out: float((np.abs(out - ref).max(axis=0) / scale).max())  # noqa: E731
        err_peer = err(peer_simulate(concept, as_dict(theta), consts, time_, inputs))
    rows = []
    for method, setting in (("hybrid", f"rtol {model.rtol:g}"), ("dopri5", f"rtol {model.rtol:g}"),
                            ("rk4", f"step {model.integration_step * 1e3:g} ms")):
        run = lambda th, m=method: simulate_batch(model, th, time_, inputs, integrator=m)  # noqa: E731
        # load the compiled kernel and let the thread pool and the allocator reach their steady
        # state (the first 256-set call pays for the pages of its 125 MB output) before timing
        run(thetas)
        single = best_rate(lambda: [run(thetas[i]) for i in range(n_single)], n_single, repeats)
        batch = best_rate(lambda: run(thetas), N_BATCH, repeats)
        row = {"concept": concept, "method": method, "setting": setting, "peer": peer, "single": single,
               "batch": batch}
        if method != "rk4":
            row["work"] = step_statistics(model, model.parameters.nominal, time_, inputs, integrator=method).summary()
        if accuracy:
            row["err_peer"] = err_peer
            row["err_numba"] = err(simulate_batch(model, theta, time_, inputs, constants=const_vec, integrator=method))
        rows.append(row)
    return rows


def compile_times() -> list[dict]:
    """Two fresh interpreters sharing one empty NUMBA_CACHE_DIR: compile, then cache reuse."""
    with tempfile.TemporaryDirectory(prefix="numba-cache-") as cache:
        env = dict(os.environ, NUMBA_CACHE_DIR=cache)
        rows = []
        for label in ("fresh cache (compiles)", "second process (cache)"):
            t = time.perf_counter()
            res = subprocess.run([sys.executable, "-c", _FIRST_CALL], env=env, check=True,
                                 capture_output=True, text=True)
            row = json.loads(res.stdout.strip().splitlines()[-1])
            row["process"] = time.perf_counter() - t
            row["label"] = label
            rows.append(row)
    return rows



# --- cost of the effect kernels relative to the nominal one ---------------------------------
_EFFECT_COSTS = r"""
import json, sys, time
import numpy as np
from ema_uq import deploy_retract, get_model, simulate_batch
from ema_uq.models.effects import CATALOGUE
concepts, methods, repeats = sys.argv[1].split(","), sys.argv[2].split(","), int(sys.argv[3])
ex = deploy_retract()
rows = {}
try:
    from ema_uq.simulate import specialise
    own_kernel_cached = specialise._cached
except ImportError:  # a package root from before the kernels compiled per effect set
    specialise = None
for concept in concepts:
    base = get_model(concept)
    models = {"nominal": base, **{name: base.with_effects([name]) for name in CATALOGUE}}
    for method in methods:
        if specialise is not None:  # "rk4": the one kernel for every set; "rk4-own": each set's own
            own = method == "rk4-own"
            specialise.SPECIALISE_AFTER_S = 0.0 if own else float("inf")
            specialise._cached = own_kernel_cached if own else (lambda signature: False)
            specialise._PROBED.clear()
            if not own:
                specialise._ENTRIES.clear()
        elif method == "rk4-own":
            continue
        integrator = method.split("-")[0]
        for label, model in models.items():  # compile and warm up first
            for _ in range(2):
                simulate_batch(model, model.parameters.nominal, ex.time, ex.input_matrix(model), integrator=integrator)
        best = {label: np.inf for label in models}
        for _ in range(repeats):  # interleaved: every kernel once per round, best of the rounds
            for label, model in models.items():
                theta, inputs = model.parameters.nominal, ex.input_matrix(model)
                t = time.perf_counter()
                simulate_batch(model, theta, ex.time, inputs, integrator=integrator)
                best[label] = min(best[label], time.perf_counter() - t)
        for label, seconds in best.items():
            rows[f"{concept}|{method}|{label}"] = seconds
print(json.dumps(rows))
"""


def effect_costs(concepts, methods, repeats: int, rounds: int, roots: dict[str, str]) -> dict[str, dict[str, float]]:
    """Best time [s] of one deploy-retract run of each concept, method and model (nominal and
    each catalogue effect at its nominal values, alone), for each package root of ``roots``
    (label -> directory put first on PYTHONPATH; "" for the installed one). Single-threaded;
    the roots take turns ``rounds`` times (interleaved), each best of ``repeats`` runs."""
    best: dict[str, dict[str, float]] = {label: {} for label in roots}
    for _ in range(rounds):
        for label, root in roots.items():
            env = dict(os.environ, NUMBA_NUM_THREADS="1")
            if root:
                env["PYTHONPATH"] = os.pathsep.join(filter(None, (root, env.get("PYTHONPATH", ""))))
            # run outside the repository: ``python -c`` puts the working directory first on the
            # path, before PYTHONPATH, so from the checkout every root would import the checkout
            res = subprocess.run([sys.executable, "-c", _EFFECT_COSTS, ",".join(concepts), ",".join(methods),
                                  str(repeats)], env=env, check=True, capture_output=True, text=True,
                                 cwd=tempfile.gettempdir())
            for key, seconds in json.loads(res.stdout.strip().splitlines()[-1]).items():
                best[label][key] = min(best[label].get(key, np.inf), seconds)
    return best


def print_effect_costs(best: dict[str, dict[str, float]]) -> None:
    """Each effect's run time over the nominal run's, per concept and method, the roots side by side."""
    labels = list(best)
    keys = list(next(iter(best.values())))
    print("\neffect kernel cost per run relative to the nominal kernel (one set, one thread, best of "
          "interleaved runs; nominal: ms per run):")
    print(f"{'concept':<8}{'method':<8}{'model':<26}" + "".join(f"{label:>14}" for label in labels))
    for key in keys:
        concept, method, model = key.split("|")
        cells = []
        for label in labels:
            seconds = best[label].get(key)
            nominal = best[label].get(f"{concept}|{method}|nominal")
            if seconds is None:
                cells.append(f"{'-':>14}")
            elif model == "nominal":
                cells.append(f"{1e3 * seconds:>11.2f} ms")
            else:
                cells.append(f"{seconds / nominal:>13.2f}x")
        print(f"{concept:<8}{method:<8}{model:<26}" + "".join(cells))


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer repeats, no accuracy check")
    ap.add_argument("--peer-rtol", type=float, default=1e-6,
                    help="peer tolerance; 1e-8 matches the fixed-step simulator's accuracy (default 1e-6)")
    ap.add_argument("--effects", action="store_true",
                    help="only the effect kernels' cost per run relative to the nominal kernel")
    ap.add_argument("--versus", metavar="DIR",
                    help="with --effects: a second package root (e.g. a worktree of an earlier commit), "
                         "measured interleaved with this one and printed beside it")
    args = ap.parse_args(argv)
    if args.effects:
        roots = {"this": ""}
        if args.versus:
            roots = {"versus": os.path.abspath(args.versus), "this": os.path.abspath(os.path.join(HERE, os.pardir))}
        repeats, rounds = (2, 1) if args.quick else (3, 3)
        print("load average at start (1, 5, 15 min): %.2f %.2f %.2f" % os.getloadavg())
        print_effect_costs(effect_costs(("htls", "lths"), ("rk4", "rk4-own", "dopri5"), repeats, rounds, roots))
        print("load average at end (1, 5, 15 min): %.2f %.2f %.2f" % os.getloadavg())
        return
    n_peer, n_single, repeats = (1, 5, 1) if args.quick else (3, 20, 5)
    threads = numba.get_num_threads()

    print(f"ema_uq forward simulation, deploy-retract (3800 samples, 38 s); numba {numba.__version__}, "
          f"{threads} numba threads, {os.cpu_count()} CPUs")
    print(f"peer: scipy solve_ivp RK45 rtol {args.peer_rtol:g} atol {1e-3 * args.peer_rtol:g}, Python rhs, "
          "per held sample interval")
    # other work on the machine distorts every figure below; the load average shows it
    print("load average at start (1, 5, 15 min): %.2f %.2f %.2f\n" % os.getloadavg())
    rows = [r for c in ("htls", "lths") for r in bench_concept(c, n_peer, n_single, repeats, not args.quick,
                                                                 args.peer_rtol)]

    head = (f"{'concept':<8}{'method':<8}{'peer run/s':>12}{'single run/s':>14}{f'batch{N_BATCH} run/s':>16}"
            f"{'single/peer':>13}{'target':>9}{'batch/single':>14}{'target':>9}")
    print(head)
    print("-" * len(head))
    for r in rows:
        s_p = r["single"] / r["peer"]
        b_s = r["batch"] / r["single"]
        t_sp = TARGET_SINGLE_OVER_PEER.get(r["concept"])
        t_sp_txt = f">={t_sp:g}" if t_sp else "-"
        mark_sp = "" if t_sp is None else (" ok" if s_p >= t_sp else " MISS")
        mark_bs = " ok" if b_s >= TARGET_BATCH_OVER_SINGLE else " MISS"
        print(f"{r['concept']:<8}{r['method']:<8}{r['peer']:>12.3g}{r['single']:>14.4g}{r['batch']:>16.4g}"
              f"{s_p:>10.1f}x{mark_sp:<3}{t_sp_txt:>8}{b_s:>11.2f}x{mark_bs:<3}{'>=' + str(TARGET_BATCH_OVER_SINGLE):>8}")
    print("\nper run [ms]:")
    for r in rows:
        t_sp = TARGET_SINGLE_OVER_PEER.get(r["concept"])
        of_target = f", {r['single'] / r['peer'] / t_sp:.2f} of the single/peer target" if t_sp else ""
        print(f"  {r['concept']} {r['method']:<6} ({r['setting']}): peer {1e3 / r['peer']:.0f}, "
              f"single {1e3 / r['single']:.2f}, batch {1e3 / r['batch']:.2f}{of_target}")
    print("work of one nominal run:")
    for r in rows:
        if "work" in r:
            print(f"  {r['concept']} {r['work']}")
    if not args.quick:
        print("accuracy vs DOP853 rtol 1e-10 reference (max over channels of max|err|/max|ref|):")
        for r in rows:
            print(f"  {r['concept']} {r['method']:<6} numba {r['err_numba']:.1e} (peer {r['err_peer']:.1e})")

    print("\nnumba compile time (fresh interpreters, empty NUMBA_CACHE_DIR) [s]:")
    for c in compile_times():
        print(f"  {c['label']:<24} import {c['import']:.2f}  first htls call {c['first_htls']:.2f}  "
              f"first lths call {c['first_lths']:.3f}  warm lths call {c['warm_lths']:.3f}  "
              f"first hybrid call {c['first_hybrid']:.2f}  "
              f"whole process {c['process']:.2f}")
    print("load average at end (1, 5, 15 min): %.2f %.2f %.2f" % os.getloadavg())


if __name__ == "__main__":
    main()
