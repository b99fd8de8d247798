"""benchmarks/workflow.py: a run's cost by stage from Snakemake's benchmark files."""
from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
HEADER = "s\th:m:s\tmax_rss\tmax_vms\tmax_uss\tmax_pss\tio_in\tio_out\tmean_load\tcpu_time\n"


def _costs():
    spec = importlib.util.spec_from_file_location("workflow_costs", ROOT / "benchmarks" / "workflow.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _bench(path: Path, wall: float, cpu: float, rss: float) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(HEADER + f"{wall}\t0:00:01\t{rss}\t0\t0\t0\t0\t0\t50\t{cpu}\n")


def test_jobs_are_grouped_by_stage_and_their_cpu_summed(tmp_path):
    costs = _costs()
    _bench(tmp_path / "benchmarks" / "compile.tsv", 100, 90, 500)
    for part, cpu in enumerate((600, 660)):
        _bench(tmp_path / "lths" / "benchmarks" / f"gap_selfcheck_{part}.tsv", cpu + 5, cpu, 600)
    _bench(tmp_path / "htls" / "benchmarks" / "gap_selfcheck_0.tsv", 200, 180, 400)
    _bench(tmp_path / "htls" / "benchmarks" / "gap_selfcheck.tsv", 3, 2.5, 300)      # the gather
    _bench(tmp_path / "htls" / "benchmarks" / "simulate_rig_validation.tsv", 2, 1, 200)
    _bench(tmp_path / "htls" / "benchmarks" / "identify_lm.tsv", 3, 3, 300)
    (tmp_path / "htls" / "benchmarks" / "sample.tsv").write_text(HEADER)             # being written
    stages = costs.by_stage(costs.job_costs(tmp_path))
    assert set(stages) == {"compile", "gap_selfcheck", "simulate", "identify"}
    selfcheck = stages["gap_selfcheck"]
    assert selfcheck["jobs"] == 4 and selfcheck["cpu_min"] == pytest.approx((600 + 660 + 180 + 2.5) / 60)
    assert selfcheck["largest"] == (pytest.approx(11.0), "lths") and selfcheck["rss_mb"] == 600
    assert stages["compile"]["largest"][1] == "-"


def test_the_run_wall_time_is_read_from_the_snakemake_log(tmp_path):
    log = tmp_path / "run.log"
    log.write_text("Building DAG of jobs...\n[Sun Nov  1 09:05:00 2026]\nlocalrule compile:\n"
                   "[Sun Nov  1 10:20:30 2026]\nFinished job 3.\n")
    assert _costs().run_wall_minutes(log) == pytest.approx(75.5)
    log.write_text("nothing ran\n")
    assert _costs().run_wall_minutes(log) is None


def test_a_benchmark_without_cpu_time_reads_as_nan_and_a_header_alone_as_none(tmp_path):
    from ema_uq.io import read_benchmark

    path = tmp_path / "job.tsv"
    path.write_text(HEADER + "12.5\t0:00:12\t300\t0\t0\t0\t0\t0\t50\tNA\n")
    record = read_benchmark(path)
    assert record["s"] == 12.5 and record["max_rss"] == 300 and record["cpu_s"] != record["cpu_s"]
    path.write_text(HEADER)
    assert read_benchmark(path) is None
