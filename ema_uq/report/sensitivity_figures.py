"""Sensitivity and identifiability figures (matplotlib only). Each function takes a result
object (:class:`~ema_uq.sensitivity.SobolResult`, :class:`~ema_uq.identifiability.IdentifiabilityResult`)
or its JSON form (SOBOL.json / IDENT.json as read back) and returns a Figure; nothing is
shown or saved."""
from __future__ import annotations

from typing import Any, Mapping, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from ..errors import ReportError  # noqa: E402

DEFAULT_QOI = ("cost", "rms_Omega", "rms_I_A", "tracking_error", "peak_torque", "energy")
OUTPUT_LABELS = {"Omega": "Ω [rad/s]", "y1": "y1 [m]", "I_A": "I_A [A]"}
VERDICT_COLORS = {"identifiable": "#4c9a4c", "practically_non_identifiable": "#e0a030",
                  "structurally_non_identifiable": "#c84040"}
VERDICT_SHORT = {"identifiable": "identifiable", "practically_non_identifiable": "practically NI",
                 "structurally_non_identifiable": "structurally NI"}


def _sobol(result):
    from ..sensitivity import SobolResult

    return SobolResult.from_json(result) if isinstance(result, Mapping) else result


def _ident(result) -> dict[str, Any]:
    return result if isinstance(result, Mapping) else result.to_json()


def sobol_bars(result, qoi: Sequence[str] | str | None = None, ncols: int = 2):
    """S1 and ST (bars) with their 95 % bootstrap intervals (error bars) per parameter, one
    panel per QoI (default: the cost, Ω and current RMS, tracking error, peak torque, energy)."""
    res = _sobol(result)
    if qoi is None:
        qoi = [q for q in DEFAULT_QOI if q in res.qoi] or list(res.qoi)[:6]
    elif isinstance(qoi, str):
        qoi = [qoi]
    unknown = [q for q in qoi if q not in res.qoi]
    if unknown:
        raise ReportError(f"no Sobol indices for {', '.join(unknown)}; QoI: {', '.join(res.qoi)}")
    ncols = min(ncols, len(qoi))
    nrows = int(np.ceil(len(qoi) / ncols))
    d = len(res.names)
    fig, axes = plt.subplots(nrows, ncols, figsize=(5.6 * ncols, 2.7 * nrows + 0.5), squeeze=False)
    x = np.arange(d)
    for k, q in enumerate(qoi):
        ax = axes[k // ncols][k % ncols]
        r = res.qoi[q]
        ax.bar(x - 0.2, r["S1"], 0.4, yerr=r["S1_conf"], capsize=2, color="tab:blue", label="S1 (first order)",
               error_kw={"lw": 0.8})
        ax.bar(x + 0.2, r["ST"], 0.4, yerr=r["ST_conf"], capsize=2, color="tab:orange", label="ST (total)",
               error_kw={"lw": 0.8})
        flag = "" if res.convergence.get("qoi", {}).get(q, {}).get("converged", True) else "  (not converged)"
        unit = f" [{r['unit']}]" if r.get("unit") not in (None, "", "1") else ""
        ax.set_title(f"{q}{unit}{flag}", fontsize=9)
        ax.set_xticks(x)
        ax.set_xticklabels(res.names, rotation=60, fontsize=7)
        ax.axhline(0, color="0.3", lw=0.6)
        ax.grid(axis="y", alpha=0.3)
        ax.tick_params(axis="y", labelsize=7)
    for ax in axes.flat[len(qoi):]:
        ax.set_visible(False)
    axes[0][0].legend(fontsize=7, loc="upper right")
    fig.suptitle(f"Sobol indices, {res.concept}: N = {res.n_base} ({res.n_evaluations} runs), "
                 f"95 % bootstrap intervals", fontsize=10)
    fig.tight_layout()
    return fig


def time_resolved(result, outputs: Sequence[str] | None = None, top: int = 5):
    """Total (solid, with 95 % band) and first-order (dashed) indices over time for the ``top``
    parameters of each output (by mean ST), with the flap command φ_r on a grey right axis.
    Estimates outside [-0.05, 1.05] (small designs) are clipped by the axis."""
    res = _sobol(result)
    outputs = list(outputs or res.time_resolved)
    fig, axes = plt.subplots(len(outputs), 1, figsize=(10, 2.6 * len(outputs) + 0.6), sharex=True, squeeze=False)
    palette = plt.get_cmap("tab10" if len(res.names) <= 10 else "tab20")
    for k, out in enumerate(outputs):
        ax = axes[k][0]
        tr = res.time_resolved[out]
        st, s1, conf = tr["ST"], tr["S1"], tr["ST_conf"]
        with np.errstate(invalid="ignore"):
            mean_st = np.nanmean(np.where(np.isfinite(st), st, np.nan), axis=1) if np.any(np.isfinite(st)) \
                else np.zeros(len(res.names))
        order = np.argsort(-np.nan_to_num(mean_st))[:top]
        for j in order:
            # one colour per parameter in every panel; with tab20 the dark shades first
            color = palette(j) if palette.N == 10 else palette((2 * j) % 20 + (2 * j) // 20 % 2)
            ax.plot(res.time, st[j], color=color, lw=1.2, label=res.names[j])
            ax.fill_between(res.time, st[j] - conf[j], st[j] + conf[j], color=color, alpha=0.15, lw=0)
            ax.plot(res.time, s1[j], color=color, lw=0.9, ls="--")
        ax.set_ylabel(f"indices of {OUTPUT_LABELS.get(out, out)}", fontsize=8)
        ax.set_ylim(-0.05, 1.05)
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=7)
        ax.legend(fontsize=7, loc="upper left", ncol=min(top, 5), title="ST solid, S1 dashed", title_fontsize=7)
        twin = ax.twinx()
        twin.plot(res.time, np.degrees(res.phi_r), color="0.45", lw=1.0, ls=":")
        twin.set_ylabel("flap command φ_r [deg]", fontsize=8, color="0.4")
        twin.tick_params(labelsize=7, colors="0.4")
    axes[-1][0].set_xlabel("time [s]", fontsize=8)
    fig.suptitle(f"Time-resolved Sobol indices, {res.concept} (grey dotted: flap command)", fontsize=10)
    fig.tight_layout()
    return fig


def profile_likelihoods(result, names: Sequence[str] | None = None, ncols: int = 4):
    """ΔV profiles of every profiled parameter, one colour per sensor set, against the relative
    deviation from that set's estimate (symmetric-log axis: linear over the narrowest profile,
    so a ±0.5 % and a ±50 % profile share one panel); dashed: the Cramér-Rao parabola; grey
    line: the 95 % threshold χ²₁(0.95)/2."""
    data = _ident(result)
    sets = data["sensor_sets"]
    threshold = data["profile_threshold"]
    profiled = [n for n in data["parameters"] if any("profile" in s["parameters"].get(n, {}) for s in sets.values())]
    names = [n for n in (names or profiled) if n in profiled]
    if not names:
        raise ReportError("no profile likelihood in this result; run identifiability with profiles")
    ncols = min(ncols, len(names))
    nrows = int(np.ceil(len(names) / ncols))
    fig, axes = plt.subplots(nrows, ncols, figsize=(3.2 * ncols, 2.4 * nrows + 0.6), squeeze=False)
    colors = dict(zip(sets, plt.get_cmap("tab10").colors))
    for k, n in enumerate(names):
        ax = axes[k // ncols][k % ncols]
        spans, notes = [], []
        for set_name, s in sets.items():
            row = s["parameters"].get(n, {})
            if "profile" not in row:
                continue
            est = row["estimate"]
            grid = np.array(row["profile"]["grid"], dtype=float)
            dv = np.array([np.nan if v is None else v for v in row["profile"]["delta_objective"]], dtype=float)
            rel = (grid - est) / abs(est) * 100
            spans.append(float(np.max(np.abs(rel))) or 1.0)
            ax.plot(rel, dv, marker="o", ms=3, color=colors[set_name], label=set_name)
            sd = row.get("crb_std")
            if sd and np.isfinite(sd):
                fine = np.linspace(rel.min(), rel.max(), 100)
                ax.plot(fine, 0.5 * (fine / 100 * abs(est) / sd) ** 2, color=colors[set_name], ls="--", lw=0.8)
            else:
                notes.append(f"{set_name}: no Cramér-Rao curve (singular information)")
            if np.nanmax(np.abs(dv)) < 0.1 * threshold:
                notes.append(f"{set_name}: flat, the data do not pin {n}")
        ax.axhline(threshold, color="0.4", lw=0.8)
        if len(spans) > 1 and max(spans) > 5 * min(spans):
            ax.set_xscale("symlog", linthresh=min(spans))
        top = max(3 * threshold, 1.0)
        ax.set_ylim(-0.1 * top, top)
        ax.set_title(n, fontsize=9)
        if notes:   # say why a panel shows a line at zero and no parabola, instead of leaving it bare
            ax.text(0.03, 0.95, "\n".join(notes), transform=ax.transAxes, fontsize=6.5, va="top",
                    bbox=dict(facecolor="white", alpha=0.85, lw=0))
        ax.set_xlabel("deviation from estimate [%]", fontsize=7)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    for ax in axes.flat[len(names):]:
        ax.set_visible(False)
    axes[0][0].set_ylabel("ΔV (profile)", fontsize=8)
    axes[0][0].legend(fontsize=7)
    fig.suptitle(f"Profile likelihoods, {data['concept']} (dashed: Cramér-Rao; line: 95 % threshold)", fontsize=10)
    fig.tight_layout()
    return fig


def sensor_set_verdicts(result):
    """Verdict per parameter (rows) and sensor set (columns), with the identifiable
    combinations of each set listed underneath."""
    data = _ident(result)
    sets = list(data["sensor_sets"])
    comparison = data["comparison"]
    names = list(comparison)
    fig, ax = plt.subplots(figsize=(2.2 * len(sets) + 2.5, 0.28 * len(names) + 1.6))
    for j, s in enumerate(sets):
        for i, n in enumerate(names):
            verdict = comparison[n].get(s)
            if verdict is None:
                continue
            ax.add_patch(plt.Rectangle((j, i), 1, 1, color=VERDICT_COLORS[verdict], alpha=0.85))
            ax.text(j + 0.5, i + 0.5, VERDICT_SHORT[verdict], ha="center", va="center", fontsize=7, color="white")
    ax.set_xlim(0, len(sets))
    ax.set_ylim(len(names), 0)
    ax.set_xticks(np.arange(len(sets)) + 0.5)
    ax.set_xticklabels(sets, fontsize=8)
    ax.set_yticks(np.arange(len(names)) + 0.5)
    ax.set_yticklabels(names, fontsize=7)
    ax.tick_params(length=0)
    lines = [f"{s}: {c['expression']} = {c['value']:.4g} ± {c['std']:.2g}"
             for s in sets for c in data["sensor_sets"][s]["combinations"]]
    if lines:
        ax.set_xlabel("\n".join(lines), fontsize=6.5, loc="left")
    ax.set_title(f"Identifiability per sensor set, {data['concept']}", fontsize=10)
    fig.tight_layout()
    return fig
