"""Simulation-based calibration (SBC, Talts et al. 2018) of the posterior of :func:`sample`.

For replicate r = 1..R: draw Θ_r from the prior the sampler uses, simulate noisy data from
Θ_r, fit ML from the prior centre (the sampler's start), sample the posterior and keep L
nearly independent draws (walkers' kept draws at least one max τ apart); the rank of Θ_r,j
among the L draws of parameter j is the number of draws below it. When the posterior is
calibrated (likelihood, prior and sampler all right) every parameter's ranks are uniform on
0..L, whatever the problem. Departures have shapes: a U (posterior too narrow), a hump (too
wide), a slope (biased).

The prior must be proper: SBC draws from it. The sampler and the draws of Θ_r use the same
:class:`~ema_uq.bayes.priors.Prior` objects (:func:`~ema_uq.bayes.priors.build_priors` of
the same overrides). With the default det R likelihood the noise covariance is integrated out
under the Jeffreys prior while the data have a fixed noise fraction; with N samples that
changes the posterior of Θ by O(1/N), far below what R = 100 replicates can see.

Uniformity test (:func:`rank_uniformity`): the ranks binned into B equal bins of the L + 1
rank values, Pearson χ² with B - 1 degrees of freedom.

Scattered campaigns: :func:`sbc_replicate` runs replicate r alone (its random stream is child r
of ``SeedSequence(seed)``, the same one :func:`sbc_ranks` gives it, so scattered and serial
campaigns agree replicate by replicate), with a sampler backend so a killed replicate resumes;
:func:`gather_replicates` joins the replicate records into an :class:`SbcResult`;
:func:`campaign_from_study` takes the problem and sampler settings of a study file.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field
from typing import Callable, Mapping, Sequence

import numpy as np
from scipy import stats

from ..experiments import Experiment, synthesize
from ..identify import FitProblem, estimate
from ..models import Model, get_model
from ..params import ParameterSet
from .errors import BayesError
from .priors import Prior, build_priors
from .result import PosteriorResult
from .settings import SamplerSettings

PRIOR_DRAW_ROUNDS = 100      # rejection rounds for a prior truncated to the bounds


# --------------------------------------------------------------------------------------
# pure pieces: prior draws, thinning, ranks, the uniformity test
# --------------------------------------------------------------------------------------
def prior_draws(priors: Sequence[Prior], rng: np.random.Generator, n: int) -> np.ndarray:
    """(n, n_free) draws from the product of ``priors``, each truncated to its support by
    rejection. A flat prior on infinite bounds is improper and cannot be drawn from."""
    out = np.empty((n, len(priors)))
    for j, p in enumerate(priors):
        out[:, j] = _draw_one(p, rng, n, j)
    return out


def _draw_one(p: Prior, rng: np.random.Generator, n: int, j: int) -> np.ndarray:
    if p.kind == "flat" and not (math.isfinite(p.lower) and math.isfinite(p.upper)):
        raise BayesError(f"free parameter {j + 1} has a flat prior on [{p.lower:g}, {p.upper:g}], which is improper: "
                         "SBC needs a proper prior; give it a normal, lognormal or uniform prior")
    kept = np.empty(0)
    for _ in range(PRIOR_DRAW_ROUNDS):
        if p.kind in ("flat", "uniform"):
            lo, hi = (p.lower, p.upper) if p.kind == "flat" else (max(p.a, p.lower), min(p.b, p.upper))
            x = rng.uniform(lo, hi, 2 * n)
        elif p.kind == "normal":
            x = rng.normal(p.a, p.b, 2 * n)
        else:
            x = np.exp(rng.normal(p.a, p.b, 2 * n))
        kept = np.concatenate([kept, x[(x >= p.lower) & (x <= p.upper)]])
        if kept.size >= n:
            return kept[:n]
    raise BayesError(f"prior {p.describe()} of free parameter {j + 1} puts almost no mass inside its bounds; "
                     "centre it inside the bounds")


def thinned_draws(result: PosteriorResult, n_draws: int) -> np.ndarray:
    """(n_draws, n_free) nearly independent posterior draws: of every walker of every
    ensemble the last kept step and then steps at least max τ (the run's largest
    autocorrelation time) apart, going backwards, the walkers interleaved. Walkers of an
    ensemble at the same step are independent at stationarity (the stationary law of an
    ensemble is the product of the posterior), so only the spacing in steps matters."""
    draws = result.draws()                                   # (ensemble, walker-major draw, p)
    n_ens, n_draw, n_free = draws.shape
    n_walkers = int(result.attrs["n_walkers"])
    per_walker = draws.reshape(n_ens * n_walkers, n_draw // n_walkers, n_free)
    stride = max(1, math.ceil(float(np.max(result.tau)) / result.thin))
    need = math.ceil(n_draws / per_walker.shape[0])
    steps = per_walker.shape[1] - 1 - stride * np.arange(need)
    if steps[-1] < 0:
        raise BayesError(f"{n_draws} draws need {need} per walker {stride} kept steps apart, but the run kept "
                         f"{per_walker.shape[1]} per walker; ask for fewer draws or more walkers")
    return np.swapaxes(per_walker[:, steps], 0, 1).reshape(-1, n_free)[:n_draws]


def ranks_of(truth: np.ndarray, draws: np.ndarray) -> np.ndarray:
    """(n_free,) rank of ``truth`` (n_free,) among ``draws`` (L, n_free): draws below it, 0..L."""
    return np.sum(np.asarray(draws) < np.asarray(truth)[None, :], axis=0).astype(int)


def rank_counts(ranks: np.ndarray, n_draws: int, n_bins: int) -> np.ndarray:
    """(n_bins,) counts of ``ranks`` (any shape, values 0..n_draws) in ``n_bins`` equal bins of
    the n_draws + 1 rank values (n_draws + 1 must be a multiple of n_bins)."""
    if n_bins < 2 or (n_draws + 1) % n_bins:
        raise BayesError(f"{n_bins} bins do not split the {n_draws + 1} rank values 0..{n_draws} evenly; "
                         "choose n_draws + 1 a multiple of n_bins")
    return np.bincount(np.ravel(ranks) * n_bins // (n_draws + 1), minlength=n_bins)


def rank_uniformity(ranks: np.ndarray, n_draws: int, n_bins: int) -> tuple[float, float]:
    """(χ², p) of Pearson's test that ``ranks`` (values 0..n_draws) are uniform, on
    ``n_bins`` equal bins (B - 1 degrees of freedom)."""
    counts = rank_counts(ranks, n_draws, n_bins)
    expected = counts.sum() / n_bins
    chi2 = float(np.sum((counts - expected) ** 2) / expected)
    return chi2, float(stats.chi2.sf(chi2, n_bins - 1))


# --------------------------------------------------------------------------------------
# the result
# --------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SbcResult:
    """Ranks of an SBC campaign and the facts of its replicates.

    ``ranks`` (R, n_free) int in 0..``n_draws``; ``truths`` (R, n_free) the Θ_r drawn from
    the prior (parameter units); per replicate (R,): ``converged`` (the sampler's stopping
    rule held), ``max_rhat``, ``n_steps`` (per ensemble), ``wall_time_s``. ``n_bins``: bins
    of the uniformity test; ``design``: what was simulated and sampled (JSON-ready).
    """

    names: tuple[str, ...]
    ranks: np.ndarray
    truths: np.ndarray
    n_draws: int
    n_bins: int
    seed: int
    converged: np.ndarray
    max_rhat: np.ndarray
    n_steps: np.ndarray
    wall_time_s: np.ndarray
    design: dict = field(default_factory=dict)

    @property
    def n_replicates(self) -> int:
        return int(self.ranks.shape[0])

    def counts(self) -> np.ndarray:
        """(n_free, n_bins) rank histogram per parameter."""
        return np.array([rank_counts(self.ranks[:, j], self.n_draws, self.n_bins) for j in range(len(self.names))])

    def uniformity(self) -> dict[str, tuple[float, float]]:
        """{parameter: (χ², p)} of the per-parameter uniformity test."""
        return {n: rank_uniformity(self.ranks[:, j], self.n_draws, self.n_bins) for j, n in enumerate(self.names)}

    def pooled_uniformity(self) -> tuple[float, float]:
        """(χ², p) of the ranks of all parameters pooled. The parameters of one replicate
        share the data, so their ranks are correlated when the posterior is: read p as
        approximate (it is too small for strongly correlated parameters)."""
        return rank_uniformity(self.ranks, self.n_draws, self.n_bins)

    @property
    def min_p(self) -> float:
        return min(p for _, p in self.uniformity().values())

    def calibrated(self, alpha: float = 0.01) -> bool:
        """Every parameter passes at the Bonferroni level alpha / n_free and the pooled ranks at alpha."""
        return self.min_p > alpha / len(self.names) and self.pooled_uniformity()[1] > alpha

    def extreme_fraction(self) -> np.ndarray:
        """(n_free,) fraction of ranks at 0 or L (2 / (L + 1) when calibrated); near 1 when
        the posterior misses the truth altogether."""
        return np.mean((self.ranks == 0) | (self.ranks == self.n_draws), axis=0)

    def summary(self) -> str:
        chi2_pooled, p_pooled = self.pooled_uniformity()
        lines = [f"[[SBC]] {self.n_replicates} replicates x {len(self.names)} parameters, L = {self.n_draws} draws, "
                 f"{self.n_bins} bins (chi2 df {self.n_bins - 1}); {int(self.converged.sum())}/{self.n_replicates} "
                 f"replicates met the stopping rule, max R-hat {float(np.max(self.max_rhat)):.4f}, "
                 f"{float(np.sum(self.wall_time_s)):.0f} s, seed {self.seed}"]
        for (name, (chi2, p)), counts, ext in zip(self.uniformity().items(), self.counts(), self.extreme_fraction()):
            lines.append(f"  {name:<8} chi2 {chi2:7.2f}  p {p:.4f}  ranks at 0 or L {ext:.1%}  "
                         f"histogram {' '.join(str(c) for c in counts)}")
        lines.append(f"  pooled   chi2 {chi2_pooled:7.2f}  p {p_pooled:.4f}; min p {self.min_p:.4f} "
                     f"(Bonferroni level at 1 %: {0.01 / len(self.names):.4f})")
        return "\n".join(lines)

    def to_dict(self) -> dict:
        out = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in asdict(self).items()}
        out["names"] = list(self.names)
        out["uniformity"] = {n: {"chi2": c, "p": p} for n, (c, p) in self.uniformity().items()}
        chi2, p = self.pooled_uniformity()
        out["pooled"] = {"chi2": chi2, "p": p}
        out["min_p"] = self.min_p
        out["ks_p"] = {n: ks_uniformity(self.ranks[:, j], self.n_draws) for j, n in enumerate(self.names)}
        return out

    def to_json(self) -> str:
        return json.dumps(self.to_dict(), indent=1)

    @classmethod
    def from_json(cls, text: str) -> "SbcResult":
        d = json.loads(text)
        arrays = {k: np.asarray(d[k]) for k in ("ranks", "truths", "converged", "max_rhat", "n_steps", "wall_time_s")}
        return cls(tuple(d["names"]), n_draws=int(d["n_draws"]), n_bins=int(d["n_bins"]), seed=int(d["seed"]),
                   design=d["design"], **arrays)


# --------------------------------------------------------------------------------------
# the campaign
# --------------------------------------------------------------------------------------
def sbc_ranks(
    model: Model | str,
    experiment: Experiment,
    parameters: ParameterSet,
    priors: Mapping[str, tuple[str, float, float]],
    *,
    n_replicates: int,
    n_draws: int = 99,
    n_bins: int = 10,
    channels: Sequence[str] | None = None,
    noise: float = 0.02,
    settings: SamplerSettings = SamplerSettings(integrator="hybrid", n_predictive=0),
    seed: int = 0,
    progress: Callable[[str], None] | None = None,
) -> SbcResult:
    """SBC ranks of the posterior of ``parameters``' free parameters (see the module).

    ``parameters``: free flags; the fixed values are the truth of every replicate and the
    free nominal values the ML start. ``priors``: {name: (kind, a, b)} overrides passed to
    :func:`~ema_uq.bayes.sample`; together with the defaults they must make every free
    parameter's prior proper. ``noise``: measurement noise as a fraction of each channel's RMS.
    Replicate r draws from its own stream (``SeedSequence(seed)`` child r), so a campaign of
    more replicates repeats the first ones exactly.
    """
    model = get_model(model) if isinstance(model, str) else model
    rank_counts(np.zeros(1, dtype=int), n_draws, n_bins)                 # checks the bins
    template = FitProblem([synthesize(model, experiment, parameters.nominal, noise=0.0, channels=channels)],
                          parameters=parameters)
    prior_list = build_priors(template, priors)
    prior_draws(prior_list, np.random.default_rng(0), 1)                # an improper prior fails here
    rows = []
    for r in range(n_replicates):
        rows.append(_replicate(model, experiment, parameters, priors, prior_list, channels, noise, settings,
                               n_draws, replicate_rng(seed, r)))
        if progress is not None:
            rank, _, converged, rhat, steps, secs = rows[-1]
            progress(f"replicate {r + 1}/{n_replicates}: ranks {rank.tolist()} of {n_draws}, "
                     f"{'converged' if converged else 'NOT converged'} after {steps} steps, R-hat {rhat:.4f}, {secs:.1f} s")
    ranks, truths, converged, rhat, steps, secs = (np.array(col) for col in zip(*rows))
    design = _design(model, experiment, template, prior_list, parameters, noise, settings)
    return SbcResult(template.parameters.free_names, ranks, truths, n_draws, n_bins, seed, converged.astype(bool),
                     rhat, steps, secs, design)


def _design(model, experiment, template, prior_list, parameters, noise, settings) -> dict:
    return {"concept": model.name, "experiment": experiment.name, "n_samples": experiment.n_samples,
            "channels": list(template.channels), "noise_fraction": noise,
            "priors": {n: p.describe() for n, p in zip(template.parameters.free_names, prior_list)},
            "fixed_values": {p.name: p.nominal for p in parameters if not p.free},
            "settings": {k: v for k, v in asdict(settings).items()}}


def replicate_rng(seed: int, index: int) -> np.random.Generator:
    """The random stream of replicate ``index`` of a campaign seeded ``seed``: child ``index``
    of ``SeedSequence(seed)``, whatever the number of replicates."""
    if index < 0:
        raise BayesError(f"replicate index {index} must be >= 0")
    return np.random.default_rng(np.random.SeedSequence(seed, spawn_key=(index,)))


def sbc_replicate(
    model: Model | str,
    experiment: Experiment,
    parameters: ParameterSet,
    priors: Mapping[str, tuple[str, float, float]],
    *,
    index: int,
    seed: int = 0,
    n_draws: int = 99,
    channels: Sequence[str] | None = None,
    noise: float = 0.02,
    settings: SamplerSettings = SamplerSettings(integrator="hybrid", n_predictive=0),
    backend=None,
) -> dict:
    """Replicate ``index`` of the campaign :func:`sbc_ranks` would run with the same arguments,
    alone: a JSON-ready record (ranks, truth, converged, max R-hat, steps, seconds, the design).
    ``backend``: the sampler's HDF5 file; a replicate killed while sampling resumes its chains
    there (a file of other settings is moved aside)."""
    model = get_model(model) if isinstance(model, str) else model
    template = FitProblem([synthesize(model, experiment, parameters.nominal, noise=0.0, channels=channels)],
                          parameters=parameters)
    prior_list = build_priors(template, priors)
    prior_draws(prior_list, np.random.default_rng(0), 1)                # an improper prior fails here
    rank, truth, converged, rhat, steps, secs = _replicate(
        model, experiment, parameters, priors, prior_list, channels, noise, settings, n_draws,
        replicate_rng(seed, index), backend=backend)
    return {"index": int(index), "seed": int(seed), "names": list(template.parameters.free_names),
            "n_draws": int(n_draws), "ranks": rank.tolist(), "truth": truth.tolist(), "converged": bool(converged),
            "max_rhat": rhat, "n_steps": int(steps), "wall_time_s": secs,
            "design": _design(model, experiment, template, prior_list, parameters, noise, settings)}


def gather_replicates(records: Sequence[Mapping], n_bins: int = 10) -> SbcResult:
    """The :class:`SbcResult` of replicate records of :func:`sbc_replicate` (one campaign:
    same parameters, draws, seed and design; each index once), ordered by index."""
    if not records:
        raise BayesError("no SBC replicate records to gather; run some replicates first")
    first = records[0]
    for key in ("names", "n_draws", "seed", "design"):
        odd = [r["index"] for r in records if r[key] != first[key]]
        if odd:
            raise BayesError(f"replicates {odd} differ from replicate {first['index']} in {key}; "
                             "gather the replicates of one campaign")
    indices = [r["index"] for r in records]
    if len(set(indices)) != len(indices):
        raise BayesError(f"replicate indices repeat: {sorted(i for i in set(indices) if indices.count(i) > 1)}")
    rows = sorted(records, key=lambda r: r["index"])
    n_draws = int(first["n_draws"])
    rank_counts(np.zeros(1, dtype=int), n_draws, n_bins)                 # checks the bins
    col = lambda key, dtype=float: np.array([r[key] for r in rows], dtype=dtype)   # noqa: E731
    return SbcResult(tuple(first["names"]), col("ranks", int), col("truth"), n_draws, n_bins, int(first["seed"]),
                     col("converged", bool), col("max_rhat"), col("n_steps", int), col("wall_time_s"),
                     {**first["design"], "replicates": [r["index"] for r in rows]})


def ks_uniformity(ranks: np.ndarray, n_draws: int) -> float:
    """p of the Kolmogorov-Smirnov test of ranks (0..n_draws) against the uniform law, on the
    centred normalised ranks (rank + ½) / (L + 1) (the ranks are discrete: p is approximate,
    conservative for large L)."""
    return float(stats.kstest((np.ravel(ranks) + 0.5) / (n_draws + 1), "uniform").pvalue)


#: default spread of the campaign priors: ln Θ_j ~ N(ln Θ_j,nominal, 0.1), about ±10 %
PRIOR_SPREAD = 0.1


def campaign_from_study(study: Mapping, prior_spread: float = PRIOR_SPREAD) -> dict:
    """Keyword arguments of :func:`sbc_replicate` for a study: its concept, estimation
    experiment, noise fraction, channels and ``data.set`` truth, every parameter free that its
    ``identify.fix`` does not fix, and the study's sampler settings (no predictive draws).

    Priors: SBC draws the truth from them, so they must be proper. A parameter with a rig
    pseudo-measurement keeps its rig normal prior; every other free parameter (flat on a
    half-infinite range by default: improper) gets ln Θ ~ N(ln Θ_nominal, ``prior_spread``)
    (a normal of sd ``prior_spread`` when its nominal value is not positive)."""
    from ..experiments import get_experiment
    from ..study import section, settings_for

    if not (math.isfinite(prior_spread) and prior_spread > 0):
        raise BayesError(f"prior spread {prior_spread} must be a positive number (0.1: about 10 %)")
    model = get_model(study["concept"])
    data = section(dict(study), "data")
    s = settings_for(dict(study), "sample")
    fix = list(settings_for(dict(study), "identify").get("fix") or [])
    overrides = {k: v for k, v in (s.get("set") or {}).items() if k in model.parameters.names}
    parameters = model.parameters.with_nominal(overrides).freeing_only(
        [n for n in model.parameters.names if n not in fix])
    priors = {}
    for p in parameters:
        if p.free and p.prior_std is None:
            priors[p.name] = (("lognormal", math.log(p.nominal), prior_spread) if p.nominal > 0
                              else ("normal", p.nominal, prior_spread))
    settings = SamplerSettings(n_walkers=s["walkers"], n_ensembles=s["chains"], max_steps=s["max_steps"],
                               check_every=s["check_every"], moves=s["moves"], defensive_weight=s["defensive"],
                               integrator=s["integrator"], n_predictive=0)
    return {"model": model, "experiment": get_experiment(data["estimation"]), "parameters": parameters,
            "priors": priors, "channels": data.get("channels"), "noise": float(data["noise"]), "settings": settings}


def _replicate(model, experiment, parameters, priors, prior_list, channels, noise, settings, n_draws, rng,
               backend=None):
    """One replicate: (ranks (n_free,), Θ_r (n_free,), converged, max R-hat, steps, seconds)."""
    from .sampler import sample

    t0 = time.perf_counter()
    truth_free = prior_draws(prior_list, rng, 1)[0]
    truth = parameters.nominal
    truth[parameters.free_index] = truth_free
    data_seed, sampler_seed = (int(s) for s in rng.integers(0, 2 ** 31, size=2))
    data = synthesize(model, experiment, truth, noise=noise, seed=data_seed, channels=channels)
    problem = FitProblem([data], parameters=parameters)
    fit = estimate(problem)
    result = sample(problem, fit, priors=priors, settings=settings, seed=sampler_seed, predictive=False,
                    backend=backend, replace_stale_backend=backend is not None)
    draws = thinned_draws(result, n_draws)
    rhat = float(np.max(result.summary()["r_hat"].values))
    return (ranks_of(truth_free, draws), truth_free, result.converged, rhat, result.n_steps,
            time.perf_counter() - t0)

