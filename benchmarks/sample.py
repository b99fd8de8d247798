"""Posterior sampling speed: effective samples per second (minimum over parameters) of
``ema_uq.bayes.sample`` for each emcee move kind, side by side with the same run driven one
walker at a time (``vectorize=False``: one simulator call per walker).

Problem (the default HT/LS study): deploy-retract (3800 samples), every output channel, 2 %
noise (seed 1), all 16 parameters free, ML Gauss-Newton fit as the start, default priors
(flat on the bounds, rig normal for p_ACE/p_PCE), default settings of each move kind
(independence: 4 ensembles x 16 walkers; de/stretch: 4 ensembles x 32 walkers; started
overdispersed from N(ML, 9 x Cramér-Rao covariance)).

Per move kind: a run under the stopping rule, capped at the step count a timed warm-up says
fits ``--budget`` seconds (the target is >= 1000 bulk ESS for every parameter within 300 s).
Figures: ESS = ArviZ bulk/tail ESS over the kept draws (one chain per ensemble, its walkers'
draws concatenated) and the emcee figure walkers x (n_steps - burn-in) / τ (τ averaged over
the ensembles); R-hat across the ensembles; ESS/s divides by the sampling wall time, ESS per
1000 simulations does not depend on the machine's load; sd/CRB = posterior sd over the
Cramér-Rao σ (range over parameters).

Peer column: the first move kind with ``vectorize=False`` for ``--peer-steps`` steps, same
seed. The walkers see the same log-probabilities, so its stored chain is the batched chain
step for step (checked and printed); its ESS/s is the batched ESS per step times its steps
per second. The independence run adapts its proposal after a 100-step pilot and its stopping
rule and ESS count only the steps after it.

Integrator of the likelihood's simulations (``--integrator``): by default the one the default
HT/LS study samples with (``sample.integrator`` of ``studies/htls.yaml``, "hybrid"), so the figure
is the workflow's posterior stage; ``--integrator rk4`` gives the command line's own default (the
concept's RK4), the configuration the issue's first figures were measured on.

Usage: python benchmarks/sample.py [--moves independence de stretch] [--budget S]
       [--peer-steps N] [--seed N] [--integrator rk4|dopri5|hybrid]

Before/after: ``--compare BASE_TREE`` runs the first move kind for a fixed ``--steps`` (same
seed, so both sides sample nearly the same chain and the ESS agree) alternately with the
package of BASE_TREE (another checkout, e.g. the base commit) and with this one, ``--rounds``
times each, in fresh processes; it prints per-parameter bulk ESS/s side by side (best wall
time of the rounds: the machine may be shared; per CPU-second too, which the load disturbs less)
and, per batch of walkers, the seconds spent
simulating and in the likelihood's linear algebra (covariance and log det R).

       python benchmarks/sample.py --compare /path/to/base/checkout [--steps 400] [--rounds 2]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numba
import numpy as np

from ema_uq import bayes, deploy_retract, get_model, synthesize
from ema_uq.bayes.sampler import _with_integrator as with_integrator   # the sampler's own switch
from ema_uq.identify import FitProblem, estimate
from ema_uq.study import load_study, section

DEFAULT_STUDY = Path(__file__).resolve().parents[1] / "studies" / "htls.yaml"

TARGET_ESS = 1000
TARGET_SECONDS = 300.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--moves", nargs="+", choices=bayes.MOVE_KINDS, default=list(bayes.MOVE_KINDS),
                    help="move kinds to compare, the first one also against the peer (default: all)")
    ap.add_argument("--budget", type=float, default=270.0, help="seconds per move kind (default 270)")
    ap.add_argument("--peer-steps", type=int, default=50, help="steps of the one-at-a-time run (default 50)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--integrator", choices=("rk4", "dopri5", "hybrid"), default=None,
                    help="integrator of the likelihood's simulations (default: the default HT/LS study's)")
    ap.add_argument("--compare", metavar="BASE_TREE", help="before/after against the package in BASE_TREE")
    ap.add_argument("--steps", type=int, default=400, help="with --compare: steps per run (default 400)")
    ap.add_argument("--rounds", type=int, default=2, help="with --compare: runs per side, interleaved (default 2)")
    ap.add_argument("--json", help=argparse.SUPPRESS)          # one fixed-step run, figures to this file
    args = ap.parse_args()
    if args.integrator is None:
        args.integrator = section(load_study(DEFAULT_STUDY), "sample").get("integrator") or "rk4"
    if args.compare:
        return _compare(args)
    if args.json:
        return _fixed_run(args)

    model = get_model("htls")
    data = synthesize("htls", deploy_retract(), noise=0.02, seed=1)
    problem = FitProblem([data])
    fit = estimate(problem, start=model.parameters.nominal)
    n_free = len(fit.free_names)
    print(f"HT/LS, {n_free} free parameters, {problem.n_samples} samples x {len(problem.channels)} channels; "
          f"{numba.get_num_threads()} numba threads; likelihood simulated with {args.integrator}")

    store = tempfile.TemporaryDirectory()
    rows, results = {}, {}
    for kind in args.moves:
        settings = bayes.SamplerSettings(moves=kind, n_predictive=0, integrator=args.integrator)
        per_set = _time_per_set(problem, fit, settings)
        n_chains = settings.walkers_for(n_free) * settings.n_ensembles
        steps = int(args.budget / (per_set * n_chains) * 0.95) // settings.check_every * settings.check_every
        steps = max(steps, 2 * settings.check_every)
        print(f"{kind}: {settings.n_ensembles} ensembles x {settings.walkers_for(n_free)} walkers; warm-up "
              f"{per_set * 1e3:.2f} ms per parameter set -> at most {steps} steps for {args.budget:.0f} s", flush=True)
        res = bayes.sample(problem, fit, settings=bayes.SamplerSettings(**{**settings.__dict__, "max_steps": steps}),
                           seed=args.seed, predictive=False, backend=Path(store.name) / f"{kind}.h5",
                           progress=lambda line, k=kind: print(f"  {k} {line}", flush=True))
        results[kind] = res
        rows[kind] = _figures(res)

    first = args.moves[0]
    peer_settings = bayes.SamplerSettings(moves=first, max_steps=args.peer_steps, check_every=args.peer_steps,
                                          n_predictive=0, vectorize=False, integrator=args.integrator)
    peer = bayes.sample(problem, fit, settings=peer_settings, seed=args.seed, predictive=False,
                        backend=Path(store.name) / "peer.h5")
    batched = results[first]
    peer_steps_per_s = peer.n_steps / peer.wall_time_s
    rows["peer"] = {
        "steps run": peer.n_steps, "simulations": peer.n_simulations, "wall time [s]": peer.wall_time_s,
        "simulations per second": peer.n_simulations / peer.wall_time_s,
        "min bulk ESS per second": rows[first]["min bulk ESS"] / batched.n_steps * peer_steps_per_s,
    }

    print()
    names = [*args.moves, "peer"]
    print(f"{'':<32}" + "".join(f"{n if n != 'peer' else first + ', 1 walker/call':>24}" for n in names))
    for key, fmt in [("steps run", "d"), ("stopping rule met", "s"), ("simulations", "d"), ("wall time [s]", ".1f"),
                     ("simulations per second", ".1f"), ("acceptance", ".2f"), ("max tau [steps]", ".1f"),
                     ("min bulk ESS", ".0f"), ("min tail ESS", ".0f"), ("min emcee ESS (walkers*L/tau)", ".0f"),
                     ("min bulk ESS per second", ".2f"), ("min bulk ESS per 1000 sims", ".1f"),
                     ("max R-hat", ".4f"), ("sd/CRB min", ".3f"), ("sd/CRB max", ".3f")]:
        cells = []
        for n in names:
            v = rows[n].get(key)
            cells.append(f"{'':>24}" if v is None else f"{format(v, fmt):>24}")
        print(f"{key:<32}" + "".join(cells))
    same = _same_prefix(Path(store.name) / f"{first}.h5", Path(store.name) / "peer.h5", peer.n_steps,
                        batched.attrs["n_ensembles"])
    print(f"peer chain identical to the batched {first} chain's first {peer.n_steps} steps: {same}")
    print(f"batched speed-up over one walker per call: "
          f"{batched.n_simulations / batched.wall_time_s / rows['peer']['simulations per second']:.2f}x simulations/s")
    ess = rows[first]["min bulk ESS"]
    ok = ess >= TARGET_ESS and batched.wall_time_s <= TARGET_SECONDS
    print(f"target >= {TARGET_ESS} ESS for every parameter in <= {TARGET_SECONDS:.0f} s ({first} moves): "
          f"{'MET' if ok else 'NOT MET'} (min bulk ESS {ess:.0f} in {batched.wall_time_s:.0f} s)")
    print()
    table = batched.summary()
    table["sd/crb"] = table["sd"] / table["crb_sd"]
    print(table[["mean", "sd", "crb_sd", "sd/crb", "ess_bulk", "ess_tail", "r_hat"]].to_string(
        float_format=lambda v: f"{v:.4g}"))


def _problem():
    model = get_model("htls")
    data = synthesize("htls", deploy_retract(), noise=0.02, seed=1)
    problem = FitProblem([data])
    return problem, estimate(problem, start=model.parameters.nominal)


def _fixed_run(args) -> None:
    """One run of ``args.steps`` steps of the first move kind (stopping rule off); figures to
    ``args.json``: per-parameter bulk ESS, sampling wall time, and the split of one batched
    posterior evaluation into simulation and likelihood linear algebra (best of 5)."""
    problem, fit = _problem()
    settings = bayes.SamplerSettings(moves=args.moves[0], n_predictive=0, integrator=args.integrator)
    n_free = len(fit.free_names)
    batch = settings.walkers_for(n_free)
    _time_per_set(problem, fit, settings)                  # compiles every kernel the run uses
    problem = with_integrator(problem, args.integrator)
    posterior = bayes.LogPosterior(problem, bayes.build_priors(problem), fit.estimate)
    # distinct vectors, as a batch of walkers is: identical ones are simulated once
    free = fit.estimate[problem.free_index][None] * (1.0 + 1e-9 * np.arange(batch)[:, None])
    thetas = problem.full_vectors(free, fit.estimate)
    sim, lin = [], []
    for _ in range(5):
        t0 = time.perf_counter()
        e = problem.residuals(thetas)
        t1 = time.perf_counter()
        posterior.log_likelihood_of_residuals(e)
        t2 = time.perf_counter()
        sim.append(t1 - t0)
        lin.append(t2 - t1)
    fixed = bayes.SamplerSettings(**{**settings.__dict__, "max_steps": args.steps, "check_every": args.steps})
    cpu0 = time.process_time()
    res = bayes.sample(problem, fit, settings=fixed, seed=args.seed, predictive=False)
    cpu = time.process_time() - cpu0
    table = res.summary()
    Path(args.json).write_text(json.dumps({
        "names": list(table.index), "ess_bulk": table["ess_bulk"].tolist(), "wall": res.wall_time_s, "cpu": cpu,
        "steps": res.n_steps, "batch": batch, "simulate_s": min(sim), "likelihood_s": min(lin),
        "simulations": res.n_simulations}))


def _compare(args) -> None:
    here = Path(__file__).resolve().parents[1]
    trees = {"before": Path(args.compare).resolve(), "after": here}
    runs = {k: [] for k in trees}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.rounds):
            for label, tree in trees.items():
                out = Path(tmp) / f"{label}_{r}.json"
                env = {**os.environ, "PYTHONPATH": str(tree)}
                subprocess.run([sys.executable, __file__, "--moves", args.moves[0], "--steps", str(args.steps),
                                "--seed", str(args.seed), "--integrator", args.integrator, "--json", str(out)],
                               env=env, check=True)
                runs[label].append(json.loads(out.read_text()))
                print(f"round {r + 1} {label}: {runs[label][-1]['wall']:.1f} s for {args.steps} steps", flush=True)
    best = {k: min(v, key=lambda d: d["wall"]) for k, v in runs.items()}
    b, a = best["before"], best["after"]
    print(f"\nHT/LS default posterior, {args.moves[0]} moves, {args.steps} steps, seed {args.seed}; best of "
          f"{args.rounds} interleaved runs per side (shared machine: wall times carry its load)")
    print(f"{'':<14}{'before':>12}{'after':>12}")
    print(f"{'wall [s]':<14}{b['wall']:>12.1f}{a['wall']:>12.1f}")
    print(f"{'CPU [s]':<14}{b['cpu']:>12.1f}{a['cpu']:>12.1f}")
    print(f"{'sims/s':<14}{b['simulations'] / b['wall']:>12.0f}{a['simulations'] / a['wall']:>12.0f}")
    print(f"per batch of {a['batch']} walkers: simulation {b['simulate_s'] * 1e3:.1f} -> {a['simulate_s'] * 1e3:.1f} ms, "
          f"likelihood linear algebra {b['likelihood_s'] * 1e3:.2f} -> {a['likelihood_s'] * 1e3:.2f} ms "
          f"({b['likelihood_s'] / a['likelihood_s']:.1f}x)")
    print(f"\n{'parameter':<10}{'bulk ESS':>10}{'':>10}{'bulk ESS/s (wall)':>20}{'':>10}"
          f"{'bulk ESS/CPU-s':>18}{'':>10}")
    print(f"{'':<10}{'before':>10}{'after':>10}{'before':>20}{'after':>10}{'before':>18}{'after':>10}")

    def line(name, eb, ea):
        return (f"{name:<10}{eb:>10.0f}{ea:>10.0f}{eb / b['wall']:>20.2f}{ea / a['wall']:>10.2f}"
                f"{eb / b['cpu']:>18.2f}{ea / a['cpu']:>10.2f}")

    for j, name in enumerate(a["names"]):
        print(line(name, b["ess_bulk"][j], a["ess_bulk"][j]))
    print(line("min", min(b["ess_bulk"]), min(a["ess_bulk"])))


def _time_per_set(problem, fit, settings) -> float:
    """Seconds per parameter set of the log posterior in batches of one ensemble's walkers,
    simulated with the settings' integrator (a warm-up call compiles first)."""
    batch = settings.walkers_for(len(fit.free_names))
    problem = with_integrator(problem, settings.integrator)
    posterior = bayes.LogPosterior(problem, bayes.build_priors(problem), fit.estimate)
    rng = np.random.default_rng(0)
    free = fit.estimate[problem.free_index] + 0.1 * rng.standard_normal((batch, len(fit.free_names))) * np.sqrt(
        np.diag(fit.covariance))
    posterior(free)
    t0 = time.perf_counter()
    for _ in range(3):
        posterior(free)
    return (time.perf_counter() - t0) / (3 * batch)


def _figures(res) -> dict:
    table = res.summary()
    wall = res.wall_time_s
    ratio = (table["sd"] / table["crb_sd"]).values
    ess = float(table["ess_bulk"].min())
    return {
        "steps run": res.n_steps, "stopping rule met": str(res.converged), "simulations": res.n_simulations,
        "wall time [s]": wall, "simulations per second": res.n_simulations / wall,
        "acceptance": float(res.idata.sample_stats["acceptance_rate"].mean()),
        "max tau [steps]": float(res.tau.max()),
        "min bulk ESS": ess, "min tail ESS": float(table["ess_tail"].min()),
        "min emcee ESS (walkers*L/tau)": float(res.ess_tau.min()),
        "min bulk ESS per second": ess / wall, "min bulk ESS per 1000 sims": 1000 * ess / res.n_simulations,
        "max R-hat": float(table["r_hat"].max()), "sd/CRB min": float(ratio.min()), "sd/CRB max": float(ratio.max()),
    }


def _same_prefix(batched: Path, peer: Path, n_steps: int, n_ensembles: int) -> bool:
    """The peer's stored chains equal the batched run's first ``n_steps`` steps."""
    import emcee

    def chain(path, k):
        return emcee.backends.HDFBackend(str(path), name=f"ensemble_{k}", read_only=True).get_chain()

    return all(np.array_equal(chain(batched, k)[:n_steps], chain(peer, k)) for k in range(n_ensembles))


if __name__ == "__main__":
    main()
