"""Posterior figures (matplotlib only): trace, corner-style pair plot and posterior
predictive bands. Each function takes a :class:`~ema_uq.bayes.PosteriorResult` and returns a
Figure; nothing is shown or saved."""
from __future__ import annotations

from typing import Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from ..errors import ReportError  # noqa: E402

ENSEMBLE_COLORS = ("tab:blue", "tab:orange", "tab:green", "tab:red", "tab:purple", "tab:brown")


def _names(result, names: Sequence[str] | None, limit: int | None = None) -> list[str]:
    names = list(result.names if names is None else names)
    unknown = [n for n in names if n not in result.names]
    if unknown:
        raise ReportError(f"no posterior for {', '.join(unknown)}; sampled parameters: {', '.join(result.names)}")
    return names[:limit] if limit else names


def trace(result, names: Sequence[str] | None = None, max_walkers: int = 8):
    """Per parameter: kept draws of up to ``max_walkers`` walkers of every ensemble (left,
    colour = ensemble) and each ensemble's marginal histogram (right)."""
    post = result.idata.posterior
    names = _names(result, names)
    ensemble = post["ensemble"].values
    fig, axes = plt.subplots(len(names), 2, figsize=(10, 1.6 * len(names) + 0.6), squeeze=False,
                             gridspec_kw={"width_ratios": (3, 1)})
    for i, name in enumerate(names):
        values = post[name].values                     # (chain, draw)
        unit = post[name].attrs.get("units", "")
        for k in np.unique(ensemble):
            color = ENSEMBLE_COLORS[int(k) % len(ENSEMBLE_COLORS)]
            rows = values[ensemble == k]
            for row in rows[:max_walkers]:
                axes[i, 0].plot(row, color=color, lw=0.4, alpha=0.5)
            axes[i, 1].hist(rows.ravel(), bins=40, density=True, histtype="step", color=color,
                            orientation="horizontal", label=f"ensemble {k}")
        axes[i, 0].set_ylabel(f"{name}\n[{unit}]", fontsize=8)
        axes[i, 1].set_ylim(axes[i, 0].get_ylim())
        for ax in axes[i]:
            ax.tick_params(labelsize=7)
            ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel(f"kept draw (burn-in {result.burn_in}, thin {result.thin} steps)", fontsize=8)
    axes[-1, 1].set_xlabel("density", fontsize=8)
    axes[0, 1].legend(fontsize=6)
    fig.tight_layout()
    return fig


def pair(result, names: Sequence[str] | None = None, max_params: int = 5, max_points: int = 4000, seed: int = 0):
    """Corner-style plot of up to ``max_params`` parameters (default: the first ones):
    marginal histograms on the diagonal, scatter of a seeded subsample below it, ML
    estimate (black cross) and its Cramér-Rao ±2σ (dashed) for reference."""
    names = _names(result, names, max_params)
    post = result.idata.posterior
    cols = {n: post[n].values.ravel() for n in names}
    n_draws = next(iter(cols.values())).size
    pick = np.random.default_rng(seed).choice(n_draws, size=min(max_points, n_draws), replace=False)
    ml = dict(zip(result.names, result.ml_estimate))
    crb = dict(zip(result.names, result.crb_std))
    k = len(names)
    fig, axes = plt.subplots(k, k, figsize=(1.9 * k + 0.8, 1.9 * k + 0.6), squeeze=False)
    for i, yi in enumerate(names):
        for j, xj in enumerate(names):
            ax = axes[i, j]
            if j > i:
                ax.set_visible(False)
                continue
            if i == j:
                ax.hist(cols[xj], bins=40, density=True, color="0.45", histtype="stepfilled", alpha=0.6)
                ax.axvline(ml[xj], color="k", lw=0.8)
                for s in (-2, 2):
                    ax.axvline(ml[xj] + s * crb[xj], color="k", lw=0.6, ls="--")
                ax.set_yticks([])
            else:
                ax.scatter(cols[xj][pick], cols[yi][pick], s=1, alpha=0.25, color="tab:blue", rasterized=True)
                ax.plot(ml[xj], ml[yi], "kx", ms=6)
            ax.tick_params(labelsize=6)
            if i == k - 1:
                ax.set_xlabel(xj, fontsize=8)
            if j == 0 and i > 0:
                ax.set_ylabel(yi, fontsize=8)
    fig.tight_layout()
    return fig


def predictive_bands(result, channels: Sequence[str] | None = None, experiment: str | None = None,
                     prob: float = 0.9):
    """Measured data with the posterior predictive central ``prob`` band (with noise, light)
    and the model band (noise-free output, dark) and median, per channel, for one experiment
    (default: the first)."""
    idata = result.idata
    if "posterior_predictive" not in idata.groups():
        raise ReportError("this posterior has no posterior_predictive group; sample with predictive draws")
    obs = idata.observed_data
    pp = idata.posterior_predictive
    channels = list(obs.data_vars if channels is None else channels)
    experiments = obs["experiment"].values
    experiment = str(experiments[0]) if experiment is None else experiment
    rows = experiments == experiment
    if not np.any(rows):
        raise ReportError(f"no observations of experiment {experiment!r}; have {sorted(set(map(str, experiments)))}")
    t = obs["time"].values[rows]
    lo_q, hi_q = 0.5 - prob / 2, 0.5 + prob / 2
    fig, axes = plt.subplots(len(channels), 1, figsize=(10, 1.9 * len(channels) + 0.6), sharex=True, squeeze=False)
    for ax, ch in zip(axes[:, 0], channels):
        rep = pp[ch].values.reshape(-1, rows.size)[:, rows]
        mod = pp[f"{ch}_model"].values.reshape(-1, rows.size)[:, rows]
        ax.plot(t, obs[ch].values[rows], color="0.5", lw=0.5, label="measured")
        ax.fill_between(t, *np.quantile(rep, [lo_q, hi_q], axis=0), color="tab:blue", alpha=0.2,
                        lw=0, label=f"predictive {prob:.0%}")
        ax.fill_between(t, *np.quantile(mod, [lo_q, hi_q], axis=0), color="tab:blue", alpha=0.5,
                        lw=0, label=f"model {prob:.0%}")
        ax.plot(t, np.median(mod, axis=0), color="tab:blue", lw=0.8, label="model median")
        ax.set_ylabel(f"{ch} [{obs[ch].attrs.get('units', '')}]", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7, loc="upper right", ncol=4)
    axes[-1, 0].set_xlabel(f"time [s] ({experiment})", fontsize=8)
    fig.tight_layout()
    return fig


def sbc_rank_histogram(sbc, band: float = 0.99):
    """Rank histograms of a simulation-based calibration (:class:`~ema_uq.bayes.sbc.SbcResult`),
    one panel per parameter: counts per bin, the expected count R / B and the central ``band``
    of a bin's Binomial(R, 1 / B) count under calibration (grey), χ² p-value in the title."""
    from scipy import stats

    counts = sbc.counts()                                  # (n_free, n_bins)
    n_params, n_bins = counts.shape
    lo, hi = stats.binom.interval(band, sbc.n_replicates, 1.0 / n_bins)
    edges = np.linspace(0, sbc.n_draws + 1, n_bins + 1)
    n_cols = min(n_params, 4)
    n_rows = -(-n_params // n_cols)
    fig, axes = plt.subplots(n_rows, n_cols, figsize=(2.8 * n_cols, 2.3 * n_rows + 0.4), squeeze=False)
    uniformity = sbc.uniformity()
    for ax, name, row in zip(axes.flat, sbc.names, counts):
        p = uniformity[name][1]
        ax.axhspan(lo, hi, color="0.85", lw=0, label=f"{band:.0%} band")
        ax.axhline(sbc.n_replicates / n_bins, color="0.4", lw=0.8, ls="--", label="expected")
        ax.bar(edges[:-1], row, width=np.diff(edges), align="edge", color="tab:blue", alpha=0.7, edgecolor="white")
        ax.set_title(f"{name}: χ² p = {p:.3f}", fontsize=8)
        ax.set_xlabel(f"rank of the truth among {sbc.n_draws} draws", fontsize=7)
        ax.tick_params(labelsize=7)
    for ax in list(axes.flat)[n_params:]:
        ax.set_visible(False)
    axes[0, 0].set_ylabel(f"replicates (of {sbc.n_replicates})", fontsize=7)
    axes[0, 0].legend(fontsize=6, loc="lower right")
    fig.tight_layout()
    return fig
