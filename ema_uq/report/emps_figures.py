"""EMPS gap figure (matplotlib only): the validation force residual of the nominal ML model and
of the model with the selected effects, over time with the reference, and its RMS by regime.
It draws arrays (:func:`ema_uq.rigs.emps.gap_figure_data`); it simulates nothing."""
from __future__ import annotations

from typing import Any, Mapping

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402


def gap_figure(data: Mapping[str, Any]):
    """Residual force [N] on the validation record before (nominal ML) and after (selected
    effects), with the reference position on a grey right axis; right panel: RMS by regime.

    ``data``: ``time`` [s], ``before`` and ``after`` force residuals [N], ``after_label``,
    ``reference`` (qg [m]) and ``regimes`` ({name: sample mask})."""
    t, before, after = (np.asarray(data[k]) for k in ("time", "before", "after"))
    fig, (ax, bx) = plt.subplots(1, 2, figsize=(12, 3.6), gridspec_kw={"width_ratios": [3, 1]})
    ax.plot(t, before, lw=0.5, color="tab:red", label="nominal model")
    ax.plot(t, after, lw=0.5, color="tab:blue", label=data["after_label"])
    ax.set_xlabel("time [s] (validation record)")
    ax.set_ylabel("force residual [N]")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper left")
    ref = ax.twinx()
    ref.plot(t, data["reference"], color="0.6", lw=0.8)
    ref.set_ylabel("reference qg [m]", color="0.5")
    masks = data["regimes"]
    names = list(masks)
    x = np.arange(len(names))
    rms = lambda r, m: float(np.sqrt(np.mean(r[m] ** 2))) if np.any(m) else 0.0  # noqa: E731
    bx.bar(x - 0.2, [rms(before, masks[n]) for n in names], 0.4, color="tab:red", label="before")
    bx.bar(x + 0.2, [rms(after, masks[n]) for n in names], 0.4, color="tab:blue", label="after")
    bx.set_xticks(x, [n.replace("_", " ") for n in names], rotation=45, ha="right", fontsize=7)
    bx.set_ylabel("RMS force residual [N]")
    bx.legend(fontsize=7)
    fig.tight_layout()
    return fig
