"""The Snakemake workflow: dry run, lint, a real smoke run, exact reproducibility and
re-run scoping. Each test works on a private copy of the workflow files; the one real smoke
run (``smoke_run``, conftest.py) is shared by every test, and a test that runs stages again
does so in a copy of it."""
from __future__ import annotations

import json
import re
import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[2]
WORKFLOW_FILES = ["Snakefile", "config", "studies", "report", "envs"]
TEMPLATE = ROOT / "ema_uq/report/templates/report.html"
VOLATILE = {"wall_time_s", "created", "evaluation_time_s", "analysis_time_s", "evaluations_per_s"}

pytestmark = pytest.mark.skipif(shutil.which("snakemake") is None, reason="snakemake not installed")


def copy_workflow(dest: Path) -> Path:
    for item in WORKFLOW_FILES:
        src = ROOT / item
        target = dest / item
        target.parent.mkdir(parents=True, exist_ok=True)
        if src.is_dir():
            shutil.copytree(src, target)
        else:
            shutil.copy2(src, target)
    return dest


def snakemake(workdir: Path, *args: str, check: bool = True) -> subprocess.CompletedProcess:
    # the whole smoke run takes ~15 min on two shared cores; the timeout only stops a hung run
    proc = subprocess.run(["snakemake", "--cores", "2", *args], cwd=workdir, capture_output=True, text=True,
                          timeout=3600)
    if check and proc.returncode != 0:
        raise AssertionError(f"snakemake {' '.join(args)} failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-3000:]}")
    return proc


def planned_jobs(proc: subprocess.CompletedProcess) -> dict[str, int]:
    """Rule -> job count from a dry run's job-stats table."""
    text = proc.stdout + proc.stderr
    jobs = {}
    for line in text.splitlines():
        m = re.match(r"^(\w+)\s+(\d+)$", line.strip())
        if m and m.group(1) not in ("total", "count"):
            jobs[m.group(1)] = int(m.group(2))
    return jobs


def numbers_of(obj, path=""):
    """Flatten a JSON object to {path: value}, leaving out volatile timing fields."""
    if isinstance(obj, dict):
        out = {}
        for k, v in obj.items():
            # upstream result files (fits, Sobol chunks) record their own wall time, so their
            # checksums differ between runs while every number in them is equal (compared here
            # directly); checksums of the data files do count
            if k not in VOLATILE and not (path.endswith("/provenance/inputs") and k.endswith((".npz", ".json"))):
                out.update(numbers_of(v, f"{path}/{k}"))
        return out
    if isinstance(obj, list):
        out = {}
        for i, v in enumerate(obj):
            out.update(numbers_of(v, f"{path}[{i}]"))
        return out
    return {path: obj}


SMOKE = ["--config", "studies=[smoke]"]


def test_default_dry_run_plans_every_study(tmp_path):
    from ema_uq.io import CRANFIELD_HEALTHY, cranfield_file, emps_files
    from ema_uq.study import load_study

    workdir = copy_workflow(tmp_path)
    jobs = planned_jobs(snakemake(workdir, "-n"))
    emps = all(p.is_file() for p in emps_files(load_study(ROOT / "studies/emps.yaml"), must_exist=False).values())
    cranfield_study = load_study(ROOT / "studies/cranfield.yaml")
    cranfield = cranfield_file(CRANFIELD_HEALTHY, cranfield_study, must_exist=False).is_file()
    synthetic, real = 2, int(emps)
    # per EMA study: estimation, validation and the two rig-like records; Sobol chunks from the studies
    assert jobs["simulate"] == 4 * synthetic, jobs
    assert jobs["identify"] == 2 * (synthetic + real), jobs
    assert jobs["report"] == synthetic + real + int(cranfield), jobs
    # the measured fault records have one stage of their own, planned only when the data is there
    assert jobs.get("fault_diagnosis", 0) == int(cranfield), jobs
    assert jobs["sample"] == jobs["gap"] == synthetic + real, jobs
    assert jobs["identifiability"] == jobs["sensitivity"] == jobs["gap_selfcheck"] == synthetic, jobs
    assert jobs["sensitivity_chunk"] == 16, jobs
    assert jobs["gap_selfcheck_case"] == 8 * synthetic, jobs     # the self-check scattered, one job per part


def test_lint_is_clean(tmp_path):
    workdir = copy_workflow(tmp_path)
    proc = snakemake(workdir, "--lint", check=False)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    # every rule that runs a command names the one environment file, and that file installs the package
    text = (workdir / "Snakefile").read_text()
    assert text.count("conda:") == text.count("shell:") > 0
    assert "-e .." in (workdir / "envs/ema_uq.yaml").read_text()


def test_smoke_study_runs_end_to_end(smoke_run):
    report = smoke_run / "reports" / "smoke.html"
    assert report.stat().st_size > 10_000
    text = report.read_text()
    assert "data:image/png;base64" in text and "Provenance" in text
    for section in ('id="posterior"', 'id="sobol"', 'id="identifiability"', 'id="gap"', 'id="selfcheck"',
                    'id="cost"'):
        assert section in text, section
    assert "Stages not run" not in text
    results = smoke_run / "results/smoke"
    for name in ("posterior.nc", "sobol.json", "ident.json", "gap.json", "selfcheck.json", "gap_ledger.png"):
        assert (results / name).stat().st_size > 0, name
    gap = json.loads((results / "gap.json").read_text())
    assert gap["verdict"] == "effect" and gap["effect"] == "sensor_delay"  # the study's hidden effect
    for method in ("gn", "lm"):
        fit = json.loads((smoke_run / f"results/smoke/fit_{method}.json").read_text())
        assert fit["converged"]
        assert (smoke_run / f"results/smoke/logs/identify_{method}.log").exists()
        assert (smoke_run / f"results/smoke/benchmarks/identify_{method}.tsv").exists()


def test_report_opens_in_headless_chromium_without_console_errors(smoke_run, tmp_path):
    from ema_uq.report.browser import check_page, find_browser

    if find_browser() is None:
        pytest.skip("no Chromium on this machine (Debian: apt-get install chromium)")
    page = check_page(smoke_run / "reports" / "smoke.html", tmp_path / "smoke.png")
    assert page.console_errors == ()
    png = page.screenshot.read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 20_000  # a rendered page, not a blank one


def test_rerun_reproduces_every_number(smoke_run, tmp_path):
    # every stage of the data and its consumers again, in a copy of the shared run: forcing the
    # simulations and the Sobol chunks re-runs everything downstream of them (fits, posterior,
    # Sobol, identifiability, gap, report). The self-check is left out: it reads no stage's
    # output, is seeded case by case, and re-running it would double the suite's longest stage.
    again = tmp_path / "wf"
    shutil.copytree(smoke_run, again, symlinks=True)
    jobs = planned_jobs(snakemake(again, *SMOKE, "--forcerun", "simulate", "sensitivity_chunk"))
    assert "gap_selfcheck" not in jobs and {"simulate", "identify", "sample", "gap", "identifiability",
                                            "sensitivity"} <= set(jobs), jobs
    for name in ("fit_gn.json", "fit_lm.json", "sobol.json", "ident.json", "gap.json"):
        first = numbers_of(json.loads((smoke_run / "results/smoke" / name).read_text()))
        second = numbers_of(json.loads((again / "results/smoke" / name).read_text()))
        assert first == second, name
    import xarray as xr

    with xr.open_dataset(smoke_run / "results/smoke/posterior.nc", group="posterior") as a, \
            xr.open_dataset(again / "results/smoke/posterior.nc", group="posterior") as b:
        assert all(np.array_equal(a[v].values, b[v].values) for v in a.data_vars)


def test_editing_the_report_template_reruns_only_the_report(smoke_run):
    # Snakemake (>= 9.18) compares checksums, so the template gets a real edit, then is restored
    assert planned_jobs(snakemake(smoke_run, "-n", *SMOKE)) == {}
    original = TEMPLATE.read_text()
    try:
        TEMPLATE.write_text(original + "<!-- edited -->\n")
        jobs = planned_jobs(snakemake(smoke_run, "-n", *SMOKE))
    finally:
        TEMPLATE.write_text(original)
    assert set(jobs) <= {"report", "all"} and jobs.get("report") == 1, jobs


@pytest.mark.parametrize("section,key,value,expected", [
    ("identify", "perturb", 0.1, {"identify": 2, "sample": 1, "identifiability": 1, "report": 1}),
    ("data", "noise", 0.03, {"simulate": 4, "identify": 2, "sample": 1, "identifiability": 1, "gap": 1,
                             "sensitivity_chunk": 2, "sensitivity": 1, "report": 1}),
    ("sensitivity", "bootstrap", 30, {"sensitivity_chunk": 2, "sensitivity": 1, "report": 1}),
    ("gap", "candidates", ["sensor_delay", "backlash"], {"gap": 1, "report": 1}),
    # data.set reaches every stage that simulates the study's data, not the self-check's own cases
    ("data", "set", {"k_y": 0.45}, {"simulate": 4, "identify": 2, "sample": 1, "identifiability": 1, "gap": 1,
                                    "sensitivity_chunk": 2, "sensitivity": 1, "report": 1}),
    ("gap", "rig_effects", ["backlash"], {"simulate": 2, "gap": 1, "report": 1}),
    ("gap", "selfcheck", "full", {"gap_selfcheck_case": 8, "gap_selfcheck": 1, "report": 1}),
])
def test_changed_study_value_reruns_exactly_the_affected_rules(smoke_run, tmp_path, section, key, value, expected):
    workdir = tmp_path / "wf"
    shutil.copytree(smoke_run, workdir, symlinks=True)
    study_file = workdir / "studies/smoke.yaml"
    study = yaml.safe_load(study_file.read_text())
    study[section][key] = value
    study_file.write_text(yaml.safe_dump(study))
    jobs = planned_jobs(snakemake(workdir, "-n", *SMOKE))
    jobs.pop("all", None)
    assert jobs == expected


@pytest.mark.parametrize("change,named", [
    ({"identfy": {}}, "identfy"),
    ({"seed": "one"}, "seed"),
    ({"identify": {"perturb": 2.0}}, "identify.perturb"),
    ({"data": {"noise": -0.1}}, "data.noise"),
])
def test_bad_study_is_rejected_at_parse_time_naming_the_key(tmp_path, change, named):
    workdir = copy_workflow(tmp_path)
    study_file = workdir / "studies/smoke.yaml"
    study = yaml.safe_load(study_file.read_text())
    study.update(change)
    study_file.write_text(yaml.safe_dump(study))
    proc = snakemake(workdir, "-n", *SMOKE, check=False)
    assert proc.returncode != 0
    assert named in proc.stdout + proc.stderr


def test_changed_sample_settings_rerun_the_stage_with_the_old_chains_moved_aside(smoke_run, tmp_path):
    workdir = tmp_path / "wf"
    shutil.copytree(smoke_run, workdir, symlinks=True)
    chains = workdir / "results/smoke/posterior.h5"
    before = chains.read_bytes()
    study_file = workdir / "studies/smoke.yaml"
    study = yaml.safe_load(study_file.read_text())
    study["sample"]["defensive"] = 0.2
    study_file.write_text(yaml.safe_dump(study))
    jobs = planned_jobs(snakemake(workdir, "-n", *SMOKE))
    jobs.pop("all", None)
    assert jobs == {"sample": 1, "report": 1}
    snakemake(workdir, *SMOKE)                    # a backend of another run no longer stops the stage
    assert (workdir / "results/smoke/posterior.stale.h5").read_bytes() == before
    assert "the chains of another run found there were moved to" in \
        (workdir / "results/smoke/logs/sample.log").read_text()
    import arviz as az

    posterior = az.from_netcdf(workdir / "results/smoke/posterior.nc").posterior
    assert "20% of draws from a 2x wider component" in posterior.attrs["move_mix"]
    report = next(workdir.glob("reports/smoke*.html")).read_text()
    assert "20% of draws from a 2x wider component" in report and "simulated with rk4" in report
