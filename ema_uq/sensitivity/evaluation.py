"""Evaluation of design rows: QoI and decimated series from one batched simulator call per
batch, in independent chunks that can run in separate processes and be gathered."""
from __future__ import annotations

import json
import os
import time as _time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from .. import statistics
from ..simulate import simulate_batch
from .indices import SensitivityError
from .setup import INTEGRATOR, QOI_KINDS, TIME_RESOLVED_OUTPUTS, SensitivitySetup


# --------------------------------------------------------------------------------------
# evaluation (pure: design rows -> QoI and decimated series)
# --------------------------------------------------------------------------------------
def _qoi_batch(setup: SensitivitySetup, thetas: np.ndarray, out: np.ndarray, nominal_out: np.ndarray,
               k_y: float, phi_r: np.ndarray, dt: float) -> np.ndarray:
    """QoI (n_sets, n_qoi) from simulated outputs (n_sets, n_samples, n_outputs)."""
    model = setup.model
    oi = {c: i for i, c in enumerate(model.outputs)}
    k_n = thetas[:, model.parameters.index("k_n")][:, None]
    i_a = out[:, :, oi["I_A"]]
    torque = k_n * i_a
    cols = []
    for kind in setup.qoi_kinds:
        if kind == "cost":
            e = setup.reference[None] - out[:, :, model.output_index(setup.reference_channels)]
            cols.append(statistics.log_det_r(statistics.covariance(e)))  # singular R: +inf, refused by sobol_indices
        elif kind == "rms":
            idx = model.output_index(setup.rms_channels)
            rms = np.sqrt(np.mean((out[:, :, idx] - nominal_out[None, :, idx]) ** 2, axis=1))
            cols += list(rms.T)
        elif kind == "tracking_error":
            y_s = 0.5 * (out[:, :, oi["y1"]] + out[:, :, oi["y2"]])
            cols.append(np.sqrt(np.mean((k_y * phi_r - y_s) ** 2, axis=1)))
        elif kind == "peak_torque":
            cols.append(np.max(np.abs(torque), axis=1))
        elif kind == "peak_current":
            cols.append(np.max(np.abs(i_a), axis=1))
        elif kind == "energy":
            cols.append(np.sum(np.maximum(torque * out[:, :, oi["Omega"]], 0.0), axis=1) * dt)
        else:  # pragma: no cover - the schema enumerates the kinds
            raise SensitivityError(f"unknown QoI {kind!r}; choose from {', '.join(QOI_KINDS)}")
    return np.column_stack(cols)


def evaluate(setup: SensitivitySetup, rows: np.ndarray,
             progress: Callable[[int], None] | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Evaluate design rows (n, D): returns QoI (n, n_qoi) and the time-resolved series
    (n, len(TIME_RESOLVED_OUTPUTS), n_times), in batches of ``setup.batch_size`` sets per
    simulator call. Deterministic per row: any split into chunks gives the same numbers."""
    model = setup.model
    exp = setup.experiment
    inputs = exp.input_matrix(model)
    nominal_out = simulate_batch(model, setup.nominal, exp.time, inputs, constants=setup.constants,
                                 integrator=INTEGRATOR)
    k_y = float(setup.constants[model.constants.index("k_y")])
    phi_r = exp.inputs["phi_r"]
    series_idx = model.output_index(TIME_RESOLVED_OUTPUTS)
    rows = np.atleast_2d(np.asarray(rows, dtype=float))
    n = rows.shape[0]
    qoi = np.empty((n, len(setup.qoi_names)))
    series = np.empty((n, len(TIME_RESOLVED_OUTPUTS), setup.time_index.size))
    for start in range(0, n, setup.batch_size):
        stop = min(start + setup.batch_size, n)
        thetas = setup.thetas(rows[start:stop])
        out = simulate_batch(model, thetas, exp.time, inputs, constants=setup.constants, integrator=INTEGRATOR)
        bad = ~np.all(np.isfinite(out), axis=(1, 2))
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            values = ", ".join(f"{nm}={v:.4g}" for nm, v in zip(setup.names, rows[start + k]))
            raise SensitivityError(f"{int(bad.sum())} parameter set(s) give a non-finite trajectory, e.g. {values}; "
                                   "narrow the ranges (sensitivity.range_fraction or sensitivity.parameters)")
        qoi[start:stop] = _qoi_batch(setup, thetas, out, nominal_out, k_y, phi_r, exp.dt)
        series[start:stop] = out[:, setup.time_index][:, :, series_idx].transpose(0, 2, 1)
        if progress is not None:
            progress(stop - start)
    return qoi, series


def chunk_rows(n_rows: int, chunk_index: int, n_chunks: int) -> tuple[int, int]:
    """Row range [start, stop) of chunk ``chunk_index`` (0-based) of ``n_chunks`` near-equal parts."""
    if n_chunks < 1 or not 0 <= chunk_index < n_chunks:
        raise SensitivityError(f"chunk {chunk_index}/{n_chunks}: give 0 <= I < N with N >= 1 (chunks are numbered from 0)")
    if n_chunks > n_rows:
        raise SensitivityError(f"{n_chunks} chunks for {n_rows} runs; use at most {n_rows} chunks")
    edges = np.linspace(0, n_rows, n_chunks + 1).round().astype(int)
    return int(edges[chunk_index]), int(edges[chunk_index + 1])


@dataclass
class SobolChunk:
    """The evaluated rows [start, stop) of a design: QoI (n, n_qoi) and series (n, 3, n_times)."""

    concept: str
    digest: str
    chunk_index: int
    n_chunks: int
    start: int
    stop: int
    qoi_names: tuple[str, ...]
    qoi: np.ndarray
    series: np.ndarray
    wall_time_s: float

    def save(self, path: str | os.PathLike) -> Path:
        """Write as .npz (atomically: a killed job never leaves a chunk that looks finished)."""
        from .. import io

        path = io.prepare_output(path)
        meta = {"concept": self.concept, "digest": self.digest, "chunk_index": self.chunk_index,
                "n_chunks": self.n_chunks, "start": self.start, "stop": self.stop,
                "qoi_names": list(self.qoi_names), "wall_time_s": self.wall_time_s}
        tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}.npz")
        np.savez(tmp, meta=np.array(json.dumps(meta)), qoi=self.qoi, series=self.series)
        os.replace(tmp, path)
        return path

    @classmethod
    def load(cls, path: str | os.PathLike) -> "SobolChunk":
        path = Path(path)
        try:
            with np.load(path, allow_pickle=False) as f:
                meta = json.loads(str(f["meta"]))
                return cls(meta["concept"], meta["digest"], int(meta["chunk_index"]), int(meta["n_chunks"]),
                           int(meta["start"]), int(meta["stop"]), tuple(meta["qoi_names"]), f["qoi"], f["series"],
                           float(meta["wall_time_s"]))
        except FileNotFoundError:
            raise SensitivityError(f"{path}: no such chunk file; run 'ema-uq sensitivity --chunk I/N' first") from None
        except (OSError, ValueError, KeyError) as exc:
            raise SensitivityError(f"{path}: not a chunk written by 'ema-uq sensitivity --chunk' ({exc})") from None


def evaluate_chunk(setup: SensitivitySetup, design: np.ndarray, chunk_index: int, n_chunks: int,
                   progress: Callable[[int], None] | None = None) -> SobolChunk:
    """Evaluate one of ``n_chunks`` independent parts of ``design`` (a job of its own in a workflow)."""
    start, stop = chunk_rows(design.shape[0], chunk_index, n_chunks)
    t0 = _time.perf_counter()
    qoi, series = evaluate(setup, design[start:stop], progress)
    return SobolChunk(setup.concept, setup.digest(), chunk_index, n_chunks, start, stop, setup.qoi_names,
                      qoi, series, _time.perf_counter() - t0)


def gather(setup: SensitivitySetup, chunks: Sequence[SobolChunk]) -> tuple[np.ndarray, np.ndarray, float]:
    """Join chunks into the full (QoI, series) arrays; every chunk of one design exactly once."""
    if not chunks:
        raise SensitivityError("no chunk given to gather; pass every chunk file of the design")
    digest = setup.digest()
    n_chunks = {c.n_chunks for c in chunks}
    if len(n_chunks) != 1:
        raise SensitivityError(f"chunks of different splits {sorted(n_chunks)} given; gather the chunks of one split")
    n_chunks = n_chunks.pop()
    for c in chunks:
        if c.digest != digest or c.qoi_names != setup.qoi_names:
            raise SensitivityError(f"chunk {c.chunk_index}/{c.n_chunks} was evaluated for another study or design "
                                   f"({c.concept}, fingerprint {c.digest} != {digest}); re-run it with this study")
    seen = sorted(c.chunk_index for c in chunks)
    if seen != list(range(n_chunks)):
        missing = sorted(set(range(n_chunks)) - set(seen))
        dup = sorted({i for i in seen if seen.count(i) > 1})
        raise SensitivityError(f"chunks of {n_chunks}: missing {missing or 'none'}, repeated {dup or 'none'}; "
                               "give each chunk file exactly once")
    ordered = sorted(chunks, key=lambda c: c.chunk_index)
    qoi = np.concatenate([c.qoi for c in ordered])
    series = np.concatenate([c.series for c in ordered])
    if qoi.shape[0] != setup.n_evaluations or ordered[-1].stop != setup.n_evaluations:
        raise SensitivityError(f"chunks hold {qoi.shape[0]} runs, the design has {setup.n_evaluations}")
    return qoi, series, float(sum(c.wall_time_s for c in ordered))
