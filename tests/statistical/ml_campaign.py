"""Seeded Monte-Carlo campaign for the ML estimator: synthetic deploy-retract data with 2 %
noise, rig pseudo-measurements drawn around the truth, starts perturbed by up to ±30 %."""
from __future__ import annotations

import numpy as np

from ema_uq import deploy_retract, get_model, synthesize
from ema_uq.identify import FitProblem, estimate, perturbed_start


def run(concept: str, method: str, seeds) -> dict:
    model = get_model(concept)
    truth = model.parameters.nominal
    z, excess = [], []
    for seed in seeds:
        data = synthesize(concept, deploy_retract(), noise=0.02, seed=seed)
        rng = np.random.default_rng([seed, 2024])
        rig = {p.name: rng.normal(p.nominal, p.prior_std) for p in model.parameters if p.prior_std}
        params = model.parameters.with_nominal(rig)
        start = perturbed_start(params, 0.3, seed=10_000 + seed, around=truth)
        problem = FitProblem([data], parameters=params)
        fit = estimate(problem, method=method, start=start)
        at_truth, _ = problem.objective(problem.residuals(truth[None])[0], truth[problem.free_index])
        excess.append(fit.objective - at_truth)
        assert fit.converged, f"{concept}/{method} seed {seed}: {fit.message}"
        z.append((fit.estimate - truth) / fit.std)
    return {"names": model.parameters.names, "z": np.array(z), "excess": np.array(excess)}
