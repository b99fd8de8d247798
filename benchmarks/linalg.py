"""The hot linear algebra, einsum (the former forms) against the matrix products of
ema_uq.statistics, at the sizes of the HT/LS default study, best of ``--repeat`` interleaved
calls (a shared machine: the ratio is the figure to read):

- residual covariance R of a batch of walkers: (64, 3800, 16) residuals;
- Fisher information Σ_k S_k R⁻¹ S_kᵀ of the gap diagnosis: 24 parameters x 7600 samples x 16
  channels (estimation + validation records);
- ``FitProblem.predict`` row/channel selection of a (64, 3800, 18) simulator output, 16
  contiguous channels: the former double fancy index (two copies) against a view (every sample
  complete) or one indexing step into the result (some samples missing).

Usage: python benchmarks/linalg.py [--repeat 20]
"""
from __future__ import annotations

import argparse
import time

import numpy as np

from ema_uq import statistics


def _best(fn, repeat):
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=20)
    args = ap.parse_args()
    rng = np.random.default_rng(0)
    e = rng.standard_normal((64, 3800, 16))
    sens = rng.standard_normal((24, 7600, 16))
    a = rng.standard_normal((16, 16))
    r_inv = np.linalg.inv(a @ a.T + 16 * np.eye(16))
    out = rng.standard_normal((64, 3800, 18))
    rows, cols = np.arange(3800), np.arange(16)
    holed = np.delete(rows, np.arange(100, 3800, 50))                 # some samples missing
    result = np.empty((64, holed.size, 16))

    def one_step():
        result[:] = out[:, holed, 0:16]
        return result
    cases = {
        "covariance (64 x 3800 x 16)": (lambda: np.einsum("...ki,...kj->...ij", e, e) / 3800,
                                        lambda: statistics.covariance(e)),
        "information (24 x 7600 x 16)": (lambda: np.einsum("jkc,cd,lkd->jl", sens, r_inv, sens),
                                         lambda: statistics.information(sens, r_inv)),
        "predict, all samples (view)": (lambda: out[:, rows][:, :, cols], lambda: out[:, :, 0:16]),
        "predict, samples missing": (lambda: out[:, holed][:, :, cols], one_step),
    }
    for name, (before, after) in cases.items():
        np.testing.assert_allclose(np.asarray(after()), before(), rtol=1e-9, atol=1e-9)
    print(f"best of {args.repeat} interleaved calls, ms (shared machine)")
    print(f"{'':<32}{'einsum/copy':>12}{'matmul/view':>12}{'ratio':>8}")
    for name, (before, after) in cases.items():
        tb, ta = np.inf, np.inf
        for _ in range(args.repeat):
            tb = min(tb, _best(before, 1))
            ta = min(ta, _best(after, 1))
        print(f"{name:<32}{tb * 1e3:>12.2f}{ta * 1e3:>12.3f}{tb / ta:>8.1f}")


if __name__ == "__main__":
    main()
