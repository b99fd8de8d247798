"""Sobol sensitivity throughput: the batched evaluation against one set per simulator call.

Design: SALib scrambled Sobol, second order, N base samples (default 1024) over the 12 HT/LS
friction parameters (±50 % of nominal) -> N (2D + 2) = 26 624 runs of the deploy-retract
experiment (3800 samples). Every run goes through the QoI evaluation of ``ema_uq.sensitivity``
(log det R cost against the reference data, 14 channel RMS deviations, tracking error, peak
torque and current, energy, decimated Ω/y1/I_A series).

  batched : ``sensitivity.evaluate`` on the whole design, ``batch_size`` sets per
            ``simulate_batch`` call (parallel over sets on all numba threads);
  peer    : the same evaluation with one set per ``simulate_batch`` call, on the first
            ``--peer-rows`` rows of the design, extrapolated to the full design.

Also printed: the SALib analysis time (all QoI with S2 and bootstrap, the N/2 convergence
re-analysis and the time-resolved indices). A warm-up run excludes numba compile time.

Usage: python benchmarks/sensitivity.py [--n-base N] [--peer-rows N] [--batch-size N] [--out SOBOL.json]
"""
from __future__ import annotations

import argparse
import dataclasses
import os
import time

import numba
import numpy as np

from ema_uq import sensitivity as sobol
from ema_uq.study import validate_study


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n-base", type=int, default=1024)
    parser.add_argument("--peer-rows", type=int, default=128)
    parser.add_argument("--batch-size", type=int, default=128)
    parser.add_argument("--out", default=None, help="also write the analysed result (SOBOL.json)")
    args = parser.parse_args()

    study = validate_study({"name": "bench", "concept": "htls", "seed": 1,
                            "sensitivity": {"n_base": args.n_base, "batch_size": args.batch_size}})
    setup = sobol.setup_from_study(study)
    design = setup.design()
    sobol.evaluate(setup, design[:2])  # warm-up: numba cache load / compile

    print(f"ema_uq Sobol evaluation, htls deploy-retract (3800 samples), D = {len(setup.names)} friction "
          f"parameters, N = {setup.n_base} -> {design.shape[0]} runs; numba {numba.__version__}, "
          f"{numba.get_num_threads()} threads, batch {setup.batch_size}")
    print("load average at start (1, 5, 15 min): %.2f %.2f %.2f\n" % os.getloadavg())

    t0 = time.perf_counter()
    qoi, series = sobol.evaluate(setup, design)
    batched = time.perf_counter() - t0

    single_setup = dataclasses.replace(setup, batch_size=1)
    rows = design[: args.peer_rows]
    t0 = time.perf_counter()
    peer_qoi, _ = sobol.evaluate(single_setup, rows)
    peer = time.perf_counter() - t0
    assert np.array_equal(peer_qoi, qoi[: rows.shape[0]]), "batched and single-set evaluation differ"
    peer_rate = rows.shape[0] / peer

    t0 = time.perf_counter()
    result = sobol.analyze_design(setup, qoi, series, evaluation_time_s=batched)
    analysis = time.perf_counter() - t0

    head = f"{'':<34}{'runs/s':>10}{'wall time [s]':>16}"
    print(head)
    print("-" * len(head))
    print(f"{'peer: one set per call (extrap.)':<34}{peer_rate:>10.1f}{design.shape[0] / peer_rate:>16.1f}"
          f"   ({rows.shape[0]} rows measured in {peer:.1f} s)")
    print(f"{'batched simulate_batch':<34}{design.shape[0] / batched:>10.1f}{batched:>16.1f}")
    print(f"\nspeed-up batched / peer: {design.shape[0] / batched / peer_rate:.2f}x "
          "(results identical row for row)")
    print(f"analysis ({len(setup.qoi_names)} QoI with S2 + N/2 re-analysis + 3 x {setup.time_index.size} "
          f"time points): {analysis:.1f} s")
    print(f"total (evaluation + analysis): {batched + analysis:.1f} s; converged N/2 vs N: {result.converged}")
    print("cost QoI, largest total indices: " + ", ".join(f"{n} {v:.2f}" for n, v in result.ranking("cost")[:4]))
    print("load average at end (1, 5, 15 min): %.2f %.2f %.2f" % os.getloadavg())
    if args.out:
        from ema_uq import io

        io.write_json(args.out, result.to_json())


if __name__ == "__main__":
    main()
