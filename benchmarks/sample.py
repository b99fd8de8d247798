"""Posterior sampling speed: effective samples per second (minimum over parameters) of
``ema_uq.bayes.sample`` driven by the batched simulator, side by side with the same emcee
run driven one walker at a time (``vectorize=False``: one simulator call per walker).

Problem: HT/LS, all 16 parameters free, deploy-retract (3800 samples), every output channel,
2 % noise (seed 1), ML Gauss-Newton fit as the start, default priors (flat on the bounds,
rig normal for p_ACE/p_PCE), 4 ensembles x 32 walkers, DE moves.

Batched column: a run whose step count is chosen from a timed warm-up to fit ``--budget``
seconds (default 270 s, the target is >= 1000 ESS for every parameter within 300 s).
ESS = ArviZ bulk and tail ESS over the kept draws (walkers as chains), and the emcee figure
n_walkers x (n_steps - burn-in) / τ for comparison; ESS/s divides by the sampling wall time.

Peer column: the same seed and settings with ``vectorize=False`` for ``--peer-steps`` steps.
The walkers see the same log-probabilities, so its chain is the batched chain step for step
(checked and printed); its ESS per step is therefore the batched run's, and its ESS/s is
that times its measured steps per second.

Usage: python benchmarks/sample.py [--budget S] [--peer-steps N] [--seed N]
"""
from __future__ import annotations

import argparse
import time

import numba
import numpy as np

from ema_uq import bayes, deploy_retract, get_model, synthesize
from ema_uq.identify import FitProblem, estimate

TARGET_ESS = 1000
TARGET_SECONDS = 300.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--budget", type=float, default=270.0, help="seconds for the batched run (default 270)")
    ap.add_argument("--peer-steps", type=int, default=100, help="steps of the one-at-a-time run (default 100)")
    ap.add_argument("--seed", type=int, default=1)
    args = ap.parse_args()

    model = get_model("htls")
    data = synthesize("htls", deploy_retract(), noise=0.02, seed=1)
    problem = FitProblem([data])
    fit = estimate(problem, start=model.parameters.nominal)
    settings = bayes.SamplerSettings(check_every=50, n_predictive=0)
    n_walkers = settings.walkers_for(len(fit.free_names))
    n_total = n_walkers * settings.n_ensembles

    # warm-up: half an ensemble per call, as the DE/stretch moves evaluate it
    posterior = bayes.LogPosterior(problem, bayes.build_priors(problem), fit.estimate)
    rng = np.random.default_rng(0)
    free = fit.estimate[problem.free_index] + rng.standard_normal((n_walkers // 2, 16)) * np.sqrt(
        np.diag(fit.covariance)) * 0.1
    posterior(free)
    t0 = time.perf_counter()
    for _ in range(5):
        posterior(free)
    per_set = (time.perf_counter() - t0) / (5 * free.shape[0])
    steps = int(args.budget / (per_set * n_total) * 0.95) // settings.check_every * settings.check_every
    steps = max(steps, 2 * settings.check_every)
    print(f"HT/LS, 16 free parameters, {problem.n_samples} samples x {len(problem.channels)} channels; "
          f"{settings.n_ensembles} ensembles x {n_walkers} walkers ({settings.moves} moves); "
          f"{numba.get_num_threads()} numba threads")
    print(f"warm-up: {per_set * 1e3:.2f} ms per parameter set in batches of {free.shape[0]} -> {steps} steps "
          f"for a {args.budget:.0f} s budget")

    batched = bayes.sample(problem, fit, settings=bayes.SamplerSettings(**{**settings.__dict__, "max_steps": steps}),
                           seed=args.seed, predictive=False,
                           progress=lambda line: print("  batched " + line, flush=True))
    table = batched.summary()
    ess_bulk, ess_tail = table["ess_bulk"].values, table["ess_tail"].values
    tau = batched.tau.max(axis=0)
    ess_emcee = settings.n_ensembles * n_walkers * (batched.n_steps - batched.burn_in) / tau
    wall = batched.wall_time_s

    peer_settings = bayes.SamplerSettings(**{**settings.__dict__, "max_steps": args.peer_steps,
                                             "check_every": args.peer_steps, "vectorize": False})
    peer = bayes.sample(problem, fit, settings=peer_settings, seed=args.seed, predictive=False)
    same = _same_prefix(batched, peer)
    peer_steps_per_s = peer.n_steps / peer.wall_time_s
    steps_per_s = batched.n_steps / wall
    ess_per_step = float(np.min(ess_bulk)) / batched.n_steps

    print()
    print(f"{'':<34}{'batched (ema_uq)':>20}{'one walker per call':>22}")
    print(f"{'steps run':<34}{batched.n_steps:>20d}{peer.n_steps:>22d}")
    print(f"{'simulations':<34}{batched.n_simulations:>20d}{peer.n_simulations:>22d}")
    print(f"{'wall time [s]':<34}{wall:>20.1f}{peer.wall_time_s:>22.1f}")
    print(f"{'simulations per second':<34}{batched.n_simulations / wall:>20.1f}{peer.n_simulations / peer.wall_time_s:>22.1f}")
    print(f"{'ensemble steps per second':<34}{steps_per_s:>20.3f}{peer_steps_per_s:>22.3f}")
    print(f"{'min bulk ESS':<34}{np.min(ess_bulk):>20.0f}{'(same chain)':>22}")
    print(f"{'min bulk ESS per second':<34}{np.min(ess_bulk) / wall:>20.2f}{ess_per_step * peer_steps_per_s:>22.2f}")
    print(f"{'min tail ESS':<34}{np.min(ess_tail):>20.0f}")
    print(f"{'min emcee ESS (walkers*L/tau)':<34}{np.min(ess_emcee):>20.0f}")
    print(f"{'speed-up (ESS/s)':<34}{steps_per_s / peer_steps_per_s:>20.2f}x")
    print(f"peer chain identical to the batched chain's first {peer.n_steps} steps: {same}")
    print(f"max R-hat {table['r_hat'].max():.3f}; tau per ensemble max {batched.tau.max():.1f} steps; "
          f"burn-in {batched.burn_in}, thin {batched.thin}; stopping rule met: {batched.converged}")
    ok = np.min(ess_bulk) >= TARGET_ESS and wall <= TARGET_SECONDS
    print(f"target >= {TARGET_ESS} ESS for every parameter in <= {TARGET_SECONDS:.0f} s: "
          f"{'MET' if ok else 'NOT MET'} (min bulk ESS {np.min(ess_bulk):.0f} in {wall:.0f} s)")
    print()
    print(table[["mean", "sd", "crb_sd", "ess_bulk", "ess_tail", "r_hat"]].to_string(float_format=lambda v: f"{v:.4g}"))


def _same_prefix(batched, peer) -> bool:
    """Compare the peer's raw chain with the batched one's over the peer's length."""
    # the exports are burnt-in and thinned differently; compare the un-thinned raw chains
    # through the draws both kept at the same step indices
    a, b = batched, peer
    steps_a = a.burn_in + a.thin * np.arange(a.idata.posterior.sizes["draw"])
    steps_b = b.burn_in + b.thin * np.arange(b.idata.posterior.sizes["draw"])
    common = np.intersect1d(steps_a, steps_b)
    if common.size == 0:
        return False
    ia = np.searchsorted(steps_a, common)
    ib = np.searchsorted(steps_b, common)
    return bool(np.array_equal(a.draws()[:, ia], b.draws()[:, ib]))


if __name__ == "__main__":
    main()
