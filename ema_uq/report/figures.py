"""Figures (matplotlib only here). Each function returns a Figure; nothing is shown or saved."""
from __future__ import annotations

from typing import Mapping, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

STYLES = {"GN": dict(color="tab:blue", lw=1.2), "LM": dict(color="tab:red", lw=1.0, ls="--")}


def fit_comparison(time: np.ndarray, measured: np.ndarray, predictions: Mapping[str, np.ndarray],
                   channels: Sequence[str], units: Sequence[str], title: str = ""):
    """Measured vs model outputs per channel (the paper's Fig. 2/3).

    ``measured`` is (n_samples, n_channels); ``predictions`` maps a label to the same shape.
    """
    n = len(channels)
    ncols = 2 if n > 3 else 1
    nrows = int(np.ceil(n / ncols))
    fig, axes = plt.subplots(nrows, ncols, figsize=(11, 2.1 * nrows + 0.6), sharex=True, squeeze=False)
    for j, (ch, unit) in enumerate(zip(channels, units)):
        ax = axes[j // ncols][j % ncols]
        ax.plot(time, measured[:, j], color="0.55", lw=0.6, label="measured")
        for label, pred in predictions.items():
            ax.plot(time, pred[:, j], label=label, **STYLES.get(label, {}))
        ax.set_ylabel(f"{ch} [{unit}]", fontsize=8)
        ax.tick_params(labelsize=7)
        ax.grid(alpha=0.3)
    for ax in axes.flat[n:]:
        ax.set_visible(False)
    for ax in axes[-1]:
        ax.set_xlabel("time [s]", fontsize=8)
    axes[0][0].legend(fontsize=7, loc="upper right")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return fig


def convergence(histories: Mapping[str, Sequence[dict]]):
    """log det R over the iterations of each fit."""
    fig, ax = plt.subplots(figsize=(5.5, 3.2))
    for label, history in histories.items():
        ax.plot([h["iteration"] for h in history], [h["log_det_R"] for h in history], marker="o",
                label=label, **{k: v for k, v in STYLES.get(label, {}).items() if k != "lw"})
    from matplotlib.ticker import MaxNLocator

    ax.xaxis.set_major_locator(MaxNLocator(integer=True))   # iterations are counted, not measured
    ax.set_xlabel("iteration")
    ax.set_ylabel("log det R")
    ax.grid(alpha=0.3)
    ax.legend()
    fig.tight_layout()
    return fig


def to_png_base64(fig, dpi: int = 110) -> str:
    import base64
    import io

    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=dpi)
    plt.close(fig)
    return base64.b64encode(buffer.getvalue()).decode("ascii")
