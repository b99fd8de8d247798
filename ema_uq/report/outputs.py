"""Arrays a stage writes beside its JSON result so that the report only draws (it never
simulates): the measured and predicted outputs of an ML fit, per record.

``FIT.outputs.npz`` (written by ``ema-uq identify`` next to ``FIT.json``) holds, for record
``i`` of the fit's estimation data then its ``--validate`` data: ``time_i`` (n,) [s],
``measured_i`` and ``predicted_i`` (n, c) in the channels' SI units, and ``meta``, one JSON
string: [{"role", "experiment", "channels", "units"}] per record.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, Sequence

import numpy as np


def fit_outputs_path(fit_json: str | Path) -> Path:
    """``results/fit_gn.json`` -> ``results/fit_gn.outputs.npz``."""
    return Path(fit_json).with_suffix(".outputs.npz")


def write_fit_outputs(path: str | Path, records: Sequence[dict[str, Any]]) -> Path:
    """Write records {role, experiment, channels, units, time, measured, predicted} to ``path``."""
    arrays: dict[str, np.ndarray] = {}
    meta = []
    for i, r in enumerate(records):
        arrays[f"time_{i}"] = np.asarray(r["time"], dtype=float)
        arrays[f"measured_{i}"] = np.asarray(r["measured"], dtype=float)
        arrays[f"predicted_{i}"] = np.asarray(r["predicted"], dtype=float)
        meta.append({k: r[k] for k in ("role", "experiment", "channels", "units")})
    path = Path(path)
    with path.open("wb") as handle:  # np.savez would append .npz to a name without it
        np.savez_compressed(handle, meta=np.array(json.dumps(meta)), **arrays)
    return path


def read_fit_outputs(path: str | Path) -> list[dict[str, Any]]:
    """The records of :func:`write_fit_outputs`, arrays included."""
    with np.load(path, allow_pickle=False) as data:
        meta = json.loads(str(data["meta"]))
        return [{**m, "time": data[f"time_{i}"], "measured": data[f"measured_{i}"],
                 "predicted": data[f"predicted_{i}"]} for i, m in enumerate(meta)]
