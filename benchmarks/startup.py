"""Start-up cost of the command line, before/after: wall time of

- ``python -c pass`` (the interpreter alone, the floor),
- ``ema-uq --help`` and ``import ema_uq``,
- ``ema-uq identify`` (HT/LS deploy-retract, GN from the nominal start) with a warm numba cache,
  beside the fit's own wall time (FIT.json ``wall_time_s``): the rest is start-up and imports,
- ``ema-uq identify`` with a cold numba cache (an empty NUMBA_CACHE_DIR), and the same after
  ``ema-uq compile`` filled that cache (the "after" tree only: the verb is new).

Each figure is the best of ``--repeat`` runs, the trees interleaved run by run (the machine may
be shared: best-of-N keeps the least disturbed run of each). Every run is a fresh process with
PYTHONPATH set to the tree.

Usage: python benchmarks/startup.py --compare BASE_TREE [--repeat 5]
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def _run(tree: Path, args: list[str], env: dict | None = None, cwd: Path | None = None) -> float:
    """Seconds of one fresh process with the package of ``tree``. It runs in a neutral folder:
    ``python -m`` puts the working folder ahead of PYTHONPATH, so started inside a checkout it
    would import that checkout instead of ``tree``."""
    cwd = cwd or Path(tempfile.gettempdir())
    t0 = time.perf_counter()
    subprocess.run([sys.executable, *args], env={**os.environ, "PYTHONPATH": str(tree), **(env or {})},
                   cwd=cwd, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--compare", required=True, metavar="BASE_TREE", help="checkout of the base commit")
    ap.add_argument("--repeat", type=int, default=5, help="runs per figure and tree (default 5)")
    ap.add_argument("--cold-repeat", type=int, default=1, help="cold-cache identify runs per tree (default 1)")
    args = ap.parse_args()
    trees = {"before": Path(args.compare).resolve(), "after": Path(__file__).resolve().parents[1]}
    cli = ["-m", "ema_uq"]
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        data = tmp / "estimation.nc"
        _run(trees["after"], [*cli, "simulate", "--concept", "htls", "--experiment", "deploy-retract",
                              "--seed", "1", "--out", str(data)])
        identify = [*cli, "identify", str(data), "--concept", "htls", "--method", "gn"]
        for tree in trees.values():                             # warm each tree's own numba cache
            _run(tree, [*identify, "--out", str(tmp / "warmup.json")])
        figures = {k: {"python -c pass": [], "import ema_uq": [], "ema-uq --help": [], "identify (warm cache)": [],
                       "fit inside identify": []} for k in trees}
        for _ in range(args.repeat):
            for label, tree in trees.items():
                f = figures[label]
                f["python -c pass"].append(_run(tree, ["-c", "pass"]))
                f["import ema_uq"].append(_run(tree, ["-c", "import ema_uq"]))
                f["ema-uq --help"].append(_run(tree, [*cli, "--help"]))
                out = tmp / f"fit_{label}.json"
                f["identify (warm cache)"].append(_run(tree, [*identify, "--out", str(out)]))
                f["fit inside identify"].append(json.loads(out.read_text())["wall_time_s"])
        for _ in range(args.cold_repeat):
            for label, tree in trees.items():
                cache = tmp / f"numba_{label}_{time.monotonic_ns()}"
                cache.mkdir()
                env = {"NUMBA_CACHE_DIR": str(cache)}
                figures[label].setdefault("identify (cold cache)", []).append(
                    _run(tree, [*identify, "--out", str(tmp / "cold.json")], env=env))
                if label == "after":
                    cache = tmp / f"numba_compiled_{time.monotonic_ns()}"
                    cache.mkdir()
                    env = {"NUMBA_CACHE_DIR": str(cache)}
                    figures[label].setdefault("ema-uq compile (cold cache)", []).append(
                        _run(tree, [*cli, "compile"], env=env))
                    figures[label].setdefault("identify after compile", []).append(
                        _run(tree, [*identify, "--out", str(tmp / "compiled.json")], env=env))
    rows = list(dict.fromkeys(k for f in figures.values() for k in f))
    print(f"best of {args.repeat} interleaved runs (cold cache: {args.cold_repeat}); seconds; shared machine")
    print(f"{'':<30}{'before':>10}{'after':>10}")
    for row in rows:
        cells = [f"{min(figures[k][row]):>10.2f}" if figures[k].get(row) else f"{'-':>10}" for k in trees]
        print(f"{row:<30}" + "".join(cells))


if __name__ == "__main__":
    main()
