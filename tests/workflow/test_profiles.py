"""The SLURM profile names only rules of the workflow: every rule under ``set-resources`` /
``set-threads`` of profiles/slurm/config.yaml is one that ``snakemake --list-rules`` lists."""
from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[2]
PROFILE = ROOT / "profiles" / "slurm" / "config.yaml"

def workflow_rules() -> set[str]:
    proc = subprocess.run(["snakemake", "--list-rules", "--config", "studies=[smoke]"], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return {line.strip() for line in proc.stdout.splitlines() if line.strip() and " " not in line.strip()}


def profile_rule_names(profile: dict) -> set[str]:
    names = set()
    for key in ("set-resources", "set-threads"):
        names |= set(profile.get(key) or {})
    return names


@pytest.mark.skipif(shutil.which("snakemake") is None, reason="snakemake not installed")
def test_slurm_profile_names_only_rules_of_the_workflow():
    rules = workflow_rules()
    assert {"all", "simulate", "sample", "compile", "sbc_replicate", "gap_selfcheck_case"} <= rules  # listing read
    profile = yaml.safe_load(PROFILE.read_text())
    assert profile["executor"] == "slurm"
    unknown = profile_rule_names(profile) - rules
    assert not unknown, f"profiles/slurm names rules the Snakefile does not have: {sorted(unknown)}"


def test_a_misspelt_rule_would_be_caught():
    profile = {"set-resources": {"sample": {}, "sensitivty_chunk": {}}, "set-threads": {"gap": 2}}
    assert profile_rule_names(profile) - {"sample", "sensitivity_chunk", "gap"} == {"sensitivty_chunk"}
