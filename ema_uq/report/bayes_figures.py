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

def _names(result, names: Sequence[str] | None, limit: int | None = None) -> list[str]:
    names = list(result.names if names is None else names)
    unknown = [n for n in names if n not in result.names]
    if unknown:
        raise ReportError(f"no posterior for {', '.join(unknown)}; sampled parameters: {', '.join(result.names)}")
    return names[:limit] if limit else names


def trace(result, names: Sequence[str] | None = None):
    """ArviZ's trace plot: per parameter each ensemble's marginal density (left) and its kept
    draws (right; an ensemble is one ArviZ chain, its walkers' draws concatenated, as the
    R-hat and ESS of the report compare them)."""
    import arviz as az
    from matplotlib.ticker import MaxNLocator

    names = _names(result, names)
    axes = az.plot_trace(result.idata, var_names=names, compact=False, legend=True,
                         figsize=(10, 1.35 * len(names) + 0.8), backend_kwargs={"layout": "constrained"})
    fig = axes.ravel()[0].figure
    for row, name in zip(axes, names):
        unit = result.idata.posterior[name].attrs.get("units", "")
        row[0].set_title(f"{name} [{unit}]" if unit else name, fontsize=8)
        row[1].set_title("")
        row[1].xaxis.set_major_locator(MaxNLocator(integer=True))
        for ax in row:
            ax.tick_params(labelsize=7)
    axes[-1, 1].set_xlabel(f"kept draw (burn-in {result.burn_in} steps, thin {result.thin})", fontsize=8)
    return fig


def corner_parameters(result, max_params: int = 5) -> tuple[list[str], list[str]]:
    """(shown, left out) for a corner plot: the parameters in the strongest posterior
    correlations, taken pair by pair from the largest |ρ| down until ``max_params`` are
    chosen, so the plot shows the joint shapes a table of marginals cannot; the order is
    the sampled order."""
    names = list(result.names)
    if len(names) <= max_params:
        return names, []
    draws = np.column_stack([result.idata.posterior[n].values.ravel() for n in names])
    rho = np.corrcoef(draws, rowvar=False)
    i, j = np.triu_indices(len(names), k=1)
    chosen: list[int] = []
    for k in np.argsort(-np.abs(np.nan_to_num(rho[i, j]))):
        for m in (i[k], j[k]):
            if m not in chosen and len(chosen) < max_params:
                chosen.append(int(m))
        if len(chosen) >= max_params:
            break
    shown = [names[m] for m in sorted(chosen)]
    return shown, [n for n in names if n not in shown]


def pair(result, names: Sequence[str] | None = None, max_params: int = 5, max_points: int = 2000, seed: int = 0):
    """ArviZ's pair plot with marginals of ``names`` (default: :func:`corner_parameters`), a
    seeded subsample of the draws, and the ML estimate as reference (black lines)."""
    import arviz as az

    names = _names(result, names) if names is not None else corner_parameters(result, max_params)[0]
    post = result.idata.posterior
    n_draws = post.sizes["chain"] * post.sizes["draw"]
    keep = np.sort(np.random.default_rng(seed).choice(n_draws, size=min(max_points, n_draws), replace=False))
    stacked = post[names].stack(sample=("chain", "draw")).isel(sample=keep)
    # a one-chain posterior of the subsample: ArviZ plots draws, the subsample keeps it legible
    sub = az.convert_to_inference_data({n: stacked[n].values[None, :] for n in names})
    ml = dict(zip(result.names, result.ml_estimate))
    k = len(names)
    axes = az.plot_pair(sub, var_names=names, kind="scatter", marginals=True, figsize=(1.9 * k + 0.8, 1.9 * k + 0.6),
                        scatter_kwargs={"alpha": 0.25, "s": 2, "rasterized": True},
                        reference_values={n: ml[n] for n in names},
                        reference_values_kwargs={"color": "k", "marker": "x", "markersize": 6},
                        textsize=8)
    fig = np.atleast_2d(axes).ravel()[0].figure
    fig.tight_layout()
    return fig


def _residual_bands(result, channels: Sequence[str] | None, experiment: str | None, prob: float):
    """(time, experiment, {channel: (measured − model median, band of new data, band of the
    model, share of measured points outside the band of new data)}) for one experiment."""
    idata = result.idata
    if "posterior_predictive" not in idata.groups():
        raise ReportError("this posterior has no posterior_predictive group; sample with predictive draws")
    obs = idata.observed_data
    pp = idata.posterior_predictive
    experiments = obs["experiment"].values
    experiment = str(experiments[0]) if experiment is None else experiment
    rows = experiments == experiment
    if not np.any(rows):
        raise ReportError(f"no observations of experiment {experiment!r}; have {sorted(set(map(str, experiments)))}")
    lo_q, hi_q = 0.5 - prob / 2, 0.5 + prob / 2
    bands = {}
    for ch in (list(obs.data_vars) if channels is None else channels):
        rep = pp[ch].values.reshape(-1, rows.size)[:, rows]
        mod = pp[f"{ch}_model"].values.reshape(-1, rows.size)[:, rows]
        median = np.median(mod, axis=0)
        rep_band, mod_band = np.quantile(rep, [lo_q, hi_q], axis=0), np.quantile(mod, [lo_q, hi_q], axis=0)
        measured = obs[ch].values[rows]
        outside = float(np.mean((measured < rep_band[0]) | (measured > rep_band[1])))
        bands[ch] = (measured - median, rep_band - median, mod_band - median, outside)
    return obs["time"].values[rows], experiment, bands


def predictive_channels(result, max_channels: int = 6, prob: float = 0.9) -> tuple[list[str], list[str]]:
    """(shown, left out): the ``max_channels`` channels with the largest share of measured points
    outside the central ``prob`` band of new data (where the check has most to say), in the
    data's order."""
    _, _, bands = _residual_bands(result, None, None, prob)
    worst = sorted(bands, key=lambda ch: -bands[ch][3])[:max_channels]
    shown = [ch for ch in bands if ch in worst]
    return shown, [ch for ch in bands if ch not in shown]


def predictive_bands(result, channels: Sequence[str] | None = None, experiment: str | None = None,
                     prob: float = 0.9, max_channels: int = 6):
    """Posterior predictive check as residuals: per channel the measured data minus the model's
    median, with the central ``prob`` band of new data (with noise, blue) and of the model
    output (noise-free, orange) about that median. Drawn about the median because on the signal's
    own scale a 2 % noise band is thinner than the line; ArviZ's plot_ppc draws distributions of
    whole observations, not a band over time, so this stays our own. Default channels:
    :func:`predictive_channels`."""
    if channels is None:
        channels = predictive_channels(result, max_channels, prob)[0]
    t, experiment, bands = _residual_bands(result, channels, experiment, prob)
    units = {ch: result.idata.observed_data[ch].attrs.get("units", "") for ch in bands}
    fig, axes = plt.subplots(len(bands), 1, figsize=(10, 1.7 * len(bands) + 0.8), sharex=True, squeeze=False)
    for ax, (ch, (resid, rep_band, mod_band, outside)) in zip(axes[:, 0], bands.items()):
        # the bands filled and the measured points dotted over them: a line through 3800 noisy
        # samples would paint over the band it is checked against
        ax.fill_between(t, *rep_band, color="tab:blue", alpha=0.35, lw=0, label=f"new data {prob:.0%}")
        ax.fill_between(t, *mod_band, color="tab:orange", alpha=0.9, lw=0, label=f"model {prob:.0%}")
        ax.plot(t, resid, ".", ms=1.2, color="0.15", alpha=0.6, label="measured − model median")
        ax.set_ylabel(f"{ch} [{units[ch]}]", fontsize=8)
        ax.set_title(f"{ch}: {outside:.0%} of the measured points outside the {prob:.0%} band of new data",
                     fontsize=8, loc="left")
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    axes[0, 0].legend(fontsize=7, loc="upper right", ncol=3)
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
