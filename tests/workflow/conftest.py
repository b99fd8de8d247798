"""The one real smoke run of the workflow, shared by every workflow test (it takes minutes:
a test that runs stages again works on a copy of it, never on a run of its own)."""
from __future__ import annotations

from pathlib import Path

import pytest

from .test_workflow import SMOKE, copy_workflow, snakemake


@pytest.fixture(scope="session")
def smoke_run(tmp_path_factory) -> Path:
    workdir = copy_workflow(tmp_path_factory.mktemp("wf"))
    snakemake(workdir, *SMOKE)
    return workdir
