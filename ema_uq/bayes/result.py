"""The result of :func:`ema_uq.bayes.sample` and its ArviZ export.

Layout of the ArviZ export: ArviZ ``chain`` = one independent ensemble (coordinate
``ensemble``), so R-hat and ESS compare the ensembles; ``draw`` = a kept step (after burn-in
and thinning) of one walker, the walkers one after the other (coordinates ``walker`` and
``step`` say which; :func:`~ema_uq.bayes.stopping.pooled_draws`).
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..statistics import covariance
from .errors import BayesError
from .stopping import pooled_draws

HDI_PROB = 0.9


@dataclass
class PosteriorResult:
    """Outcome of :func:`~ema_uq.bayes.sample`: the ArviZ InferenceData plus run facts.

    ``idata`` groups: ``posterior`` (one variable per free parameter, dims chain = ensemble,
    draw = walker-major kept step with ``walker``/``step`` coordinates), ``sample_stats``
    (``lp`` log posterior, ``log_prior``, ``accepted`` 0/1 at each kept step,
    ``acceptance_rate`` (chain, walker)), ``log_likelihood`` (``z``: total log L of all
    data per draw; pointwise values would be N x draws), ``observed_data`` (fitted channels,
    dim ``obs`` with ``time``/``experiment`` coordinates) and ``posterior_predictive``
    (``<channel>``: replicate with noise, ``<channel>_model``: noise-free output, for a
    random subsample of draws). Run facts live in ``idata.posterior.attrs`` and are
    mirrored by the properties below.
    """

    idata: Any

    # --- run facts ---------------------------------------------------------------
    @property
    def attrs(self) -> dict[str, Any]:
        return dict(self.idata.posterior.attrs)

    def _json_attr(self, key: str):
        return json.loads(self.idata.posterior.attrs[key])

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(self._json_attr("free_parameters"))

    @property
    def converged(self) -> bool:
        return bool(int(self.idata.posterior.attrs["converged"]))

    @property
    def n_steps(self) -> int:
        return int(self.idata.posterior.attrs["n_steps"])

    @property
    def burn_in(self) -> int:
        return int(self.idata.posterior.attrs["burn_in"])

    @property
    def thin(self) -> int:
        return int(self.idata.posterior.attrs["thin"])

    @property
    def tau(self) -> np.ndarray:
        """(n_ensembles, n_free) integrated autocorrelation times [steps] at the end."""
        return np.array(self._json_attr("tau"))

    @property
    def ess_tau(self) -> np.ndarray:
        """(n_free,) emcee's ESS: steps after burn-in x walkers of all ensembles / mean τ."""
        return np.array(self._json_attr("ess_tau"))

    @property
    def seed(self) -> int:
        return int(self.idata.posterior.attrs["seed"])

    @property
    def wall_time_s(self) -> float:
        return float(self.idata.posterior.attrs["wall_time_s"])

    @property
    def n_simulations(self) -> int:
        return int(self.idata.posterior.attrs["n_simulations"])

    @property
    def ml_estimate(self) -> np.ndarray:
        return np.array(self._json_attr("ml_estimate"))

    @property
    def crb_std(self) -> np.ndarray:
        return np.array(self._json_attr("crb_std"))

    # --- numbers -----------------------------------------------------------------
    def draws(self) -> np.ndarray:
        """(n_ensembles, n_walkers x n_kept, n_free) kept samples in free-vector order."""
        return np.stack([self.idata.posterior[n].values for n in self.names], axis=-1)

    def summary(self, hdi_prob: float = HDI_PROB):
        """pandas DataFrame per free parameter: mean, sd, hdi bounds, mcse_mean, mcse_sd,
        ess_bulk, ess_tail, r_hat (ArviZ, one chain per ensemble), ess_tau (emcee's
        figure), plus the ML estimate and its Cramér-Rao σ."""
        import arviz as az

        table = az.summary(self.idata, var_names=list(self.names), hdi_prob=hdi_prob, round_to="none")
        if "ess_tau" in self.idata.posterior.attrs:           # absent in files of older runs
            table["ess_tau"] = self.ess_tau
        table["ml"] = self.ml_estimate
        table["crb_sd"] = self.crb_std
        return table

    def interval(self, prob: float = HDI_PROB) -> np.ndarray:
        """(n_free, 2) highest-density intervals."""
        import arviz as az

        hdi = az.hdi(self.idata.posterior[list(self.names)], hdi_prob=prob)
        return np.array([hdi[n].values for n in self.names])

    def report(self) -> str:
        a = self.attrs
        head = (f"[[Posterior: {a['concept']} by emcee]] {'converged' if self.converged else 'NOT converged'} "
                f"({a['stop_reason']}); {a['n_ensembles']} ensembles x {a['n_walkers']} walkers x {self.n_steps} steps, "
                f"burn-in {self.burn_in}, thin {self.thin}, max tau {float(np.max(self.tau)):.1f}; R-hat and ESS "
                f"across the ensembles; "
                f"{self.n_simulations} simulations, {self.wall_time_s:.1f} s, seed {self.seed}")
        return head + "\n" + self.summary().to_string(float_format=lambda v: f"{v:.6g}")

    # --- files -------------------------------------------------------------------
    def to_netcdf(self, path: str | os.PathLike) -> Path:
        """Write the InferenceData (all groups) to ``path`` atomically; returns the path."""
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
        try:
            self.idata.to_netcdf(str(tmp), engine="h5netcdf")
            os.replace(tmp, path)
        finally:
            if tmp.exists():
                tmp.unlink()
        return path

    @classmethod
    def from_netcdf(cls, path: str | os.PathLike) -> "PosteriorResult":
        import arviz as az

        if not Path(path).is_file():
            raise BayesError(f"file {path}: no such file; run 'ema-uq sample' first")
        idata = az.from_netcdf(str(path), engine="h5netcdf")
        if "posterior" not in idata.groups() or "free_parameters" not in idata.posterior.attrs:
            raise BayesError(f"file {path} is not a posterior written by 'ema-uq sample'")
        return cls(idata.load() if hasattr(idata, "load") else idata)


def inference_data(problem, posterior, chains, log_probs, accepted_total, burn, thin, rng, n_predictive, attrs):
    """Assemble the ArviZ InferenceData (see :class:`PosteriorResult`).

    ``chains``/``log_probs``/``accepted_total``: per ensemble the stored chain (n_steps,
    n_walkers, n_free), log posterior (n_steps, n_walkers) and accepted-move counts
    (n_walkers,); the draws kept are steps ``burn::thin``. ``rng`` (None: no predictive group)
    draws the predictive subsample of ``n_predictive`` draws and its noise. ``attrs``: run
    facts stored on the posterior group."""
    import arviz as az
    import emcee
    import xarray as xr

    from .. import __version__

    names = list(problem.parameters.free_names)
    n_ens, (n_steps, n_walkers) = len(chains), chains[0].shape[:2]
    kept = pooled_draws(chains, burn, thin)                              # (ensemble, draw, p)
    lp = pooled_draws(log_probs, burn, thin)
    moved = pooled_draws([np.any(c[1:] != c[:-1], axis=2) for c in chains], burn - 1, thin).astype(float)
    n_draw = kept.shape[1]
    log_prior = posterior.log_prior(kept.reshape(-1, len(names))).reshape(n_ens, n_draw)
    rate = np.stack([a / n_steps for a in accepted_total])              # (ensemble, walker)
    coords = {"chain": np.arange(n_ens), "draw": np.arange(n_draw)}
    steps = np.arange(burn, n_steps, thin)
    chain_coords = {"ensemble": ("chain", np.arange(n_ens)),
                    "walker": ("draw", np.repeat(np.arange(n_walkers), steps.size)),
                    "step": ("draw", np.tile(steps, n_walkers))}
    meta = {"ema_uq_version": __version__, "emcee_version": emcee.__version__,
            "arviz_version": az.__version__, "created_by": "ema_uq.bayes.sample"}
    post = xr.Dataset({n: (("chain", "draw"), kept[:, :, j], {"units": problem.parameters[n].unit})
                       for j, n in enumerate(names)}, coords={**coords, **chain_coords},
                      attrs={**meta, **attrs})
    stats = xr.Dataset({"lp": (("chain", "draw"), lp), "log_prior": (("chain", "draw"), log_prior),
                        "accepted": (("chain", "draw"), moved),
                        "acceptance_rate": (("chain", "walker"), rate)},
                       coords={**coords, "walker": np.arange(n_walkers)}, attrs=meta)
    loglik = xr.Dataset({"z": (("chain", "draw"), lp - log_prior)}, coords=coords,
                        attrs={**meta, "note": "total log likelihood of all data per draw"})
    times = np.concatenate([b.time[b.rows] for b in problem.blocks])
    exps = np.concatenate([[m.experiment.name] * b.rows.size for m, b in zip(problem.measurements, problem.blocks)])
    obs_coords = {"obs": np.arange(times.size), "time": ("obs", times), "experiment": ("obs", exps.astype(str))}
    observed = xr.Dataset({ch: ("obs", problem.observed[:, c], {"units": problem.model.unit_of(ch)})
                           for c, ch in enumerate(problem.channels)}, coords=obs_coords, attrs=meta)
    groups = {"posterior": post, "sample_stats": stats, "log_likelihood": loglik, "observed_data": observed}
    if rng is not None and n_predictive > 0:
        groups["posterior_predictive"] = _predictive(problem, posterior, kept.reshape(-1, len(names)), rng,
                                                     n_predictive, obs_coords, meta)
    return az.InferenceData(**groups)


def _predictive(problem, posterior, flat, rng, n_predictive, obs_coords, meta):
    """The ``posterior_predictive`` group: ``n_predictive`` of the kept draws ``flat``
    (n_kept, n_free), picked by ``rng`` without replacement, simulated noise-free and with
    noise N(0, R(Θ)) (det R likelihood) or the known σ."""
    import xarray as xr

    pick = np.sort(rng.choice(flat.shape[0], size=min(n_predictive, flat.shape[0]), replace=False))
    thetas = problem.full_vectors(flat[pick], posterior.base)
    model_out = problem.predict(thetas)                       # (n_pp, N, m)
    if posterior.noise_sigma is None:
        e = problem.observed[None] - model_out
        chol = np.linalg.cholesky(covariance(e))
        noise = rng.standard_normal(model_out.shape) @ np.swapaxes(chol, -1, -2)   # L z per sample
    else:
        noise = rng.standard_normal(model_out.shape) * posterior.noise_sigma
    replicate = model_out + noise
    pp_vars = {}
    for c, ch in enumerate(problem.channels):
        pp_vars[ch] = (("chain", "draw", "obs"), replicate[None, :, :, c].astype(np.float32))
        pp_vars[f"{ch}_model"] = (("chain", "draw", "obs"), model_out[None, :, :, c].astype(np.float32))
    return xr.Dataset(
        pp_vars, coords={"chain": [0], "draw": pick, **obs_coords},
        attrs={**meta, "note": "draw = index into the flattened (chain, draw) posterior; "
                               "<channel>: with noise N(0, R(theta)) or known sigma, <channel>_model: noise-free"})
