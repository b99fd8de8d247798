"""The smoke study through a real SLURM scheduler: a one-node cluster on this host
(cluster/start-slurm.sh, as root, with slurm-wlm, slurmdbd, munge and mariadb-server installed)
runs ``snakemake --profile profiles/slurm`` and ``sacct`` lists every job as COMPLETED.

Deselected by default (marker ``slurm``): ``python -m pytest -m slurm tests/workflow/test_slurm.py -s``
(about 20 min on 2 cores).
"""
from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

from .test_workflow import copy_workflow

ROOT = Path(__file__).resolve().parents[2]
pytestmark = [
    pytest.mark.slurm,
    pytest.mark.skipif(shutil.which("slurmctld") is None or shutil.which("sbatch") is None,
                       reason="SLURM not installed (apt-get install slurm-wlm slurmdbd munge mariadb-server)"),
    pytest.mark.skipif(os.geteuid() != 0, reason="the cluster script starts daemons as root"),
]


def _sacct_since(start: str) -> list[list[str]]:
    out = subprocess.run(["sacct", "-X", "-n", "-P", "-S", start, "--format=JobID,Comment,State,ExitCode,Elapsed"],
                         capture_output=True, text=True, check=True).stdout
    return [line.split("|") for line in out.splitlines() if line.strip()]


def test_smoke_study_runs_on_slurm(tmp_path):
    pytest.importorskip("snakemake_executor_plugin_slurm")
    subprocess.run([str(ROOT / "cluster" / "start-slurm.sh")], check=True, timeout=300)
    start = subprocess.run(["date", "+%Y-%m-%dT%H:%M:%S"], capture_output=True, text=True, check=True).stdout.strip()
    workdir = copy_workflow(tmp_path)
    shutil.copytree(ROOT / "profiles", workdir / "profiles")
    proc = subprocess.run(["snakemake", "--profile", "profiles/slurm", "--config", "studies=[smoke]"], cwd=workdir,
                          capture_output=True, text=True, timeout=3600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (workdir / "reports" / "smoke.html").is_file()
    jobs = _sacct_since(start)
    print("\n".join("|".join(j) for j in jobs))
    rules = [j[1] for j in jobs]
    # one SLURM job per workflow job: compile, 4 simulate, 2 identify, sample, 2 Sobol chunks and
    # their gather, identifiability, gap, its self-check, report
    assert len(jobs) >= 15, jobs
    assert any("compile" in r for r in rules) and sum("simulate" in r for r in rules) == 4, rules
    assert all(j[2] == "COMPLETED" and j[3] == "0:0" for j in jobs), jobs
