"""What a workflow run cost, stage by stage, from Snakemake's benchmark files, beside the
issue's target (the default workflow in 15 min of wall time on 2 cores, so at most 30 CPU-min)
and, with ``--compare``, beside another run's results folder.

Every rule writes a benchmark file (``results/<study>/benchmarks/<job>.tsv``, the workflow-wide
ones under ``results/benchmarks/``); a job's stage is its file name without a trailing part or
chunk number (``gap_selfcheck_3`` -> ``gap_selfcheck``) or role and method (``simulate_validation``
-> ``simulate``, ``identify_lm`` -> ``identify``). CPU time is what to read on a shared
machine: wall times of jobs that ran side by side add up to more than the run took. The run's
own wall time comes from its Snakemake log (``--log``: the first and last time stamps).

Usage: python benchmarks/workflow.py RESULTS [--log SNAKEMAKE.log] [--compare OTHER_RESULTS]
"""
from __future__ import annotations

import argparse
import re
from collections import defaultdict
from datetime import datetime
from pathlib import Path

from ema_uq.io import read_benchmark

#: 15 min of wall time on 2 cores (issue 28, target 6)
TARGET_CPU_MIN = 30.0
_PART = re.compile(r"_\d+$")
#: rules whose benchmark file names carry a wildcard other than a number
_NAMED_BY_WILDCARD = ("simulate", "identify")
_STAMP = re.compile(r"^\[(\w{3} \w{3} +\d+ \d\d:\d\d:\d\d \d{4})\]")


def job_costs(results: Path) -> list[dict]:
    """One row per benchmark file: study (``-`` for workflow-wide jobs), stage, job, wall time [s],
    CPU time [s] and peak resident memory [MB]. A file being written is skipped."""
    rows = []
    for path in sorted(results.rglob("benchmarks/*.tsv")):
        record = read_benchmark(path)
        if record is None:
            continue
        study = path.parent.parent.name if path.parent.parent != results else "-"
        stage = _PART.sub("", path.stem)
        stage = next((rule for rule in _NAMED_BY_WILDCARD if stage.startswith(rule + "_")), stage)
        rows.append({"study": study, "stage": stage, "job": path.stem,
                     "wall_s": record["s"], "cpu_s": record["cpu_s"], "rss_mb": record["max_rss"]})
    return rows


def by_stage(rows: list[dict]) -> dict[str, dict]:
    """Stage -> jobs, CPU-min, largest job's CPU-min and study, peak memory [MB]."""
    stages: dict[str, dict] = defaultdict(lambda: {"jobs": 0, "cpu_min": 0.0, "largest": (0.0, ""), "rss_mb": 0.0})
    for row in rows:
        stage = stages[row["stage"]]
        cpu_min = row["cpu_s"] / 60.0
        stage["jobs"] += 1
        stage["cpu_min"] += cpu_min
        stage["largest"] = max(stage["largest"], (cpu_min, row["study"]))
        stage["rss_mb"] = max(stage["rss_mb"], row["rss_mb"])
    return dict(stages)


def run_wall_minutes(log: Path) -> float | None:
    """Minutes from the first to the last time stamp of a Snakemake log (None: fewer than two)."""
    stamps = [datetime.strptime(" ".join(m.group(1).split()), "%a %b %d %H:%M:%S %Y")
              for line in log.read_text(encoding="utf-8", errors="replace").splitlines()
              if (m := _STAMP.match(line))]
    return (stamps[-1] - stamps[0]).total_seconds() / 60.0 if len(stamps) > 1 else None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("results", type=Path, help="the run's results folder")
    ap.add_argument("--log", type=Path, help="its Snakemake log (.snakemake/log/*.snakemake.log)")
    ap.add_argument("--compare", type=Path, help="another run's results folder, printed beside it")
    args = ap.parse_args()
    for folder in (args.results, args.compare):
        if folder is not None and not folder.is_dir():
            raise SystemExit(f"{folder}: no such results folder; give the folder the workflow wrote (results/)")
    runs = {"this run": by_stage(job_costs(args.results))}
    if args.compare is not None:
        runs["compared"] = by_stage(job_costs(args.compare))
    if not runs["this run"]:
        raise SystemExit(f"{args.results}: no benchmark files; run the workflow first (each rule writes one)")
    names = sorted(set().union(*runs.values()), key=lambda s: -runs["this run"].get(s, {"cpu_min": 0})["cpu_min"])
    head = f"{'stage':24s} {'jobs':>5s} {'CPU-min':>8s} {'largest (study)':>18s} {'peak MB':>8s}"
    if "compared" in runs:
        head += f"  {'compared CPU-min':>17s}"
    print(head)
    totals = {k: 0.0 for k in runs}
    for name in names:
        mine = runs["this run"].get(name)
        line = f"{name:24s} "
        if mine:
            largest = f"{mine['largest'][0]:.1f} ({mine['largest'][1]})"
            line += f"{mine['jobs']:5d} {mine['cpu_min']:8.1f} {largest:>18s} {mine['rss_mb']:8.0f}"
        else:
            line += f"{'-':>5s} {'-':>8s} {'-':>18s} {'-':>8s}"
        if "compared" in runs:
            other = runs["compared"].get(name)
            line += f"  {other['cpu_min']:17.1f}" if other else f"  {'-':>17s}"
        print(line)
        for key, run in runs.items():
            totals[key] += run.get(name, {"cpu_min": 0.0})["cpu_min"]
    total = f"{'total':24s} {'':5s} {totals['this run']:8.1f}"
    if "compared" in runs:
        total += f" {'':18s} {'':8s}  {totals['compared']:17.1f}"
    print(total)
    print(f"target: {TARGET_CPU_MIN:.0f} CPU-min (15 min of wall time on 2 cores); "
          f"this run {totals['this run'] / TARGET_CPU_MIN:.1f}x that")
    if args.log is not None:
        minutes = run_wall_minutes(args.log)
        print(f"wall time of the run (its log): {minutes:.1f} min" if minutes is not None
              else f"{args.log}: fewer than two time stamps")


if __name__ == "__main__":
    main()
