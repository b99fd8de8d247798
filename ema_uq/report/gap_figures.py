"""The gap ledger figure (matplotlib only here): where the nominal model's gap sits over
time (with the flap command) and by operating regime and channel, before and after the
winning effect of a :class:`~ema_uq.gap.GapResult`, and :func:`gap_figure`, the figure of
``ema-uq gap --figure`` chosen by concept (:data:`RIG_GAP_FIGURES`). Returns a Figure; nothing
is shown or saved, and nothing is simulated: a rig's figure draws the arrays its study
computed (``Rig.gap_figure_data``)."""
from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from . import emps_figures  # noqa: E402

BEFORE = dict(color="tab:red", label="nominal model")
AFTER = dict(color="tab:blue")
COMMAND = dict(color="0.45", lw=0.9, ls="--")


#: concept -> its own gap figure, drawn from the arrays of ``Rig.gap_figure_data``; every
#: other concept gets the ledger (:func:`gap_ledger`)
RIG_GAP_FIGURES = {"emps": emps_figures.gap_figure}


def gap_figure(concept: str, result, data=None):
    """The gap figure of a concept: its rig's own figure of ``data`` where it has one and the
    data were computed, else the ledger of ``result``."""
    draw = RIG_GAP_FIGURES.get(concept)
    return draw(data) if draw is not None and data is not None else gap_ledger(result)


def _after_label(result) -> str:
    name = result.gap.get("effect_of_after") or (result.best.effect if result.best else None)
    return f"+ {name}" if name else "after"


def _time_panel(ax, before: dict, after: dict | None, title: str, after_label: str) -> None:
    t = np.asarray(before["time"])
    ax.step(t, before["systematic_nrmse"], where="mid", lw=1.3, **BEFORE)
    if after and after.get("time"):
        ax.step(after["time"], after["systematic_nrmse"], where="mid", lw=1.3, label=after_label,
                **{k: v for k, v in AFTER.items()})
    ax.set_ylabel("systematic NRMSE", fontsize=8)
    ax.set_title(title, fontsize=9, loc="left")
    ax.grid(alpha=0.3)
    ax.tick_params(labelsize=7)
    twin = ax.twinx()
    twin.plot(t, before["phi_r_deg"], label="flap command φ_r", **COMMAND)
    twin.set_ylabel("φ_r [deg]", fontsize=8, color="0.35")
    twin.tick_params(labelsize=7, colors="0.35")
    lines = ax.get_legend_handles_labels()
    more = twin.get_legend_handles_labels()
    ax.legend(lines[0] + more[0], lines[1] + more[1], fontsize=7, loc="upper right")


def gap_ledger(result):
    """Gap ledger of a diagnosis: one time panel per record (estimation, then held-out) with
    the systematic NRMSE per window before and after the winning effect and the flap command,
    then the systematic NRMSE by regime and by channel (estimation data) before and after."""
    loc, after = result.localization, result.localization_after
    label = _after_label(result)
    panels = []
    for before_loc, after_loc in ((loc, after), (result.localization_held_out, result.localization_after_held_out)):
        panels += [(name, before_loc.windows[name], after_loc.windows.get(name) if after_loc else None)
                   for name in before_loc.windows]
    n_time = len(panels)
    fig = plt.figure(figsize=(11, 2.3 * n_time + 3.4))
    grid = fig.add_gridspec(n_time + 1, 2, height_ratios=[1.0] * n_time + [1.35], hspace=0.55, wspace=0.25)
    for i, (title, before, aft) in enumerate(panels):
        _time_panel(fig.add_subplot(grid[i, :]), before, aft, title, label)

    regimes = [r for r in loc.regimes if np.isfinite(r.systematic_nrmse)]
    names = [r.name for r in regimes]
    x = np.arange(len(names))
    ax = fig.add_subplot(grid[n_time, 0])
    ax.bar(x - 0.2, [r.systematic_nrmse for r in regimes], width=0.4, **BEFORE)
    if after is not None:
        after_by = {r.name: r.systematic_nrmse for r in after.regimes}
        ax.bar(x + 0.2, [after_by.get(n, np.nan) for n in names], width=0.4, label=label, **AFTER)
    held = set(result.where.get("regimes", []))
    ax.set_xticks(x, [f"{n}{' *' if n in held else ''}" for n in names], rotation=30, ha="right", fontsize=7)
    ax.set_ylabel("systematic NRMSE", fontsize=8)
    ax.set_title("by regime (* holds the gap)", fontsize=9, loc="left")
    ax.tick_params(labelsize=7)
    ax.grid(alpha=0.3, axis="y")
    ax.legend(fontsize=7)

    channels = sorted(loc.channels, key=lambda c: -c.systematic_nrmse)[:10]
    x = np.arange(len(channels))
    ax = fig.add_subplot(grid[n_time, 1])
    ax.bar(x - 0.2, [c.systematic_nrmse for c in channels], width=0.4, **BEFORE)
    if after is not None:
        after_by = {c.channel: c.systematic_nrmse for c in after.channels}
        ax.bar(x + 0.2, [after_by.get(c.channel, np.nan) for c in channels], width=0.4, label=label, **AFTER)
    ax.set_xticks(x, [c.channel for c in channels], rotation=30, ha="right", fontsize=7)
    ax.set_title("by channel (largest 10)", fontsize=9, loc="left")
    ax.tick_params(labelsize=7)
    ax.grid(alpha=0.3, axis="y")

    verdict = result.headline()
    # the pair the shrink is computed from (the held-out part that did not choose the effect),
    # the same numbers as the report's text and candidate table
    g = result.gap
    scored = g.get("shrink_gap_before") is not None
    before, after = (g["shrink_gap_before"], g.get("shrink_gap_after")) if scored else (g["before"], g["after"])
    after = float("nan") if after is None else after
    shrink = "" if g.get("shrink") is None else (
        f", shrink {g['shrink']:.2f}" + (f" ± {g['shrink_se']:.2f}" if g.get("shrink_se") is not None else ""))
    fig.suptitle(f"Gap ledger, {result.concept}: {verdict}; held-out systematic NRMSE (scoring part) "
                 f"{before:.3g} -> {after:.3g}{shrink}", fontsize=10)
    return fig


def selfcheck_confusion(selfcheck: dict):
    """Confusion matrix of a self-check (SELFCHECK.json as a dict): rows the truth family
    (``none``, ``outside catalogue``), columns the verdict label, cells the case counts;
    the right cell of each row is framed. Returns a Figure."""
    matrix = selfcheck["confusion"]

    def order(label):
        return ({"none": 1, "unexplained": 2, "outside catalogue": 2}.get(label, 0), label)

    rows = sorted(matrix, key=order)
    columns = sorted({lab for row in matrix.values() for lab in row} | {r for r in rows if r != "outside catalogue"}
                     | ({"unexplained"} if "outside catalogue" in rows else set()), key=order)
    counts = np.array([[matrix[r].get(c, 0) for c in columns] for r in rows], dtype=float)
    fig, ax = plt.subplots(figsize=(1.1 * len(columns) + 3.0, 0.45 * len(rows) + 2.2))
    shares = counts / np.maximum(counts.sum(axis=1, keepdims=True), 1.0)
    ax.imshow(shares, cmap="Blues", vmin=0.0, vmax=1.0, aspect="auto")
    for i, r in enumerate(rows):
        for j, c in enumerate(columns):
            if counts[i, j]:
                ax.text(j, i, f"{counts[i, j]:.0f}", ha="center", va="center", fontsize=8,
                        color="white" if shares[i, j] > 0.6 else "black")
            if c == ("unexplained" if r == "outside catalogue" else r):
                ax.add_patch(plt.Rectangle((j - 0.5, i - 0.5), 1, 1, fill=False, lw=1.5, ec="tab:green"))
    ax.set_xticks(range(len(columns)), columns, rotation=35, ha="right", fontsize=8)
    ax.set_yticks(range(len(rows)), rows, fontsize=8)
    ax.set_xlabel("verdict (family named, none, unexplained)", fontsize=8)
    ax.set_ylabel("truth family", fontsize=8)
    ax.set_title(f"Gap self-check: {selfcheck['n_cases']} cases (green frame: right verdict)", fontsize=9, loc="left")
    fig.tight_layout()
    return fig
