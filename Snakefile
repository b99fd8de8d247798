# ema_uq workflow: every rule calls the `ema-uq` CLI; the numerics live in the package.
#
# Study values enter rules as params (never the study file as an input), so a changed value
# re-runs exactly the rules that use it. Rules whose CLI verb reads a study section itself
# (sensitivity, identifiability) carry that section as a `settings` param for the same reason.
# `snakemake --lint` asks for a conda environment per rule: the software is the package
# itself, installed once by `pip install -e .` (pyproject.toml pins its dependencies), so
# every rule shares that one environment and none is declared.
import json
import sys
from importlib import resources

from snakemake.utils import validate

from ema_uq.io import emps_files
from ema_uq.study import load_study

configfile: "config/config.yaml"


validate(config, "config/config.schema.yaml")


def _load(name):
    study = load_study(f"studies/{name}.yaml")
    if study["concept"] == "emps" and not all(p.is_file() for p in emps_files(study, must_exist=False).values()):
        print(f"study {name}: EMPS data files not found (data.path or EMA_UQ_EMPS_DIR); study skipped",
              file=sys.stderr)
        return None
    return study


STUDIES = {name: s for name in config["studies"] if (s := _load(name)) is not None}
REPORT_TEMPLATE = str(resources.files("ema_uq").joinpath("report/templates/report.html"))
SYNTHETIC = ("htls", "lths")  # concepts whose data the workflow simulates


def study(wildcards):
    return STUDIES[wildcards.study]


def concept(wildcards):
    return study(wildcards)["concept"]


def settings(*keys):
    """A params value that changes exactly when these study sections change."""
    return lambda w: json.dumps({k: study(w).get(k) for k in keys}, sort_keys=True)


def study_file(wildcards):
    return f"studies/{wildcards.study}.yaml"


def data_seed(wildcards):
    # estimation, validation and the rig-like records must be independent noise draws
    offsets = {"estimation": 0, "validation": 1000, "rig_estimation": 2000, "rig_validation": 3000}
    return study(wildcards)["seed"] + offsets[wildcards.role]


def option(flag, values):
    return f"{flag} {' '.join(str(v) for v in values)}" if values else ""


def data_file(role):
    """Measured records of a study: simulated for the EMA concepts, the real files for EMPS."""
    def files(w):
        s = study(w)
        if s["concept"] == "emps":
            return str(emps_files(s)[role.replace("rig_", "")])
        return f"results/{w.study}/data/{role}.nc"
    return files


def has_stage(s, stage):
    """Sobol and identifiability concern the EMA friction/damping parameters (issue scope)."""
    return s["concept"] in SYNTHETIC or stage not in ("sensitivity", "identifiability", "selfcheck")


def stage_outputs(w):
    s = study(w)
    out = {"fits": expand("results/{study}/fit_{method}.json", study=w.study, method=s["identify"]["methods"]),
           "posterior": f"results/{w.study}/posterior.nc", "gap": f"results/{w.study}/gap.json"}
    if has_stage(s, "sensitivity"):
        out["sobol"] = f"results/{w.study}/sobol.json"
    if has_stage(s, "identifiability"):
        out["ident"] = f"results/{w.study}/ident.json"
    if has_stage(s, "selfcheck") and s["gap"]["selfcheck"] != "off":
        out["selfcheck"] = f"results/{w.study}/selfcheck.json"
    return out


wildcard_constraints:
    study="[A-Za-z0-9_-]+",
    role="estimation|validation|rig_estimation|rig_validation",
    method="gn|lm",
    chunk="[0-9]+",


rule all:
    input:
        expand("reports/{study}.html", study=STUDIES),


rule simulate:
    output:
        "results/{study}/data/{role}.nc",
    params:
        concept=concept,
        experiment=lambda w: study(w)["data"][w.role.replace("rig_", "")],
        noise=lambda w: study(w)["data"]["noise"],
        seed=data_seed,
        sets=lambda w: " ".join(f"--set {k}={v}" for k, v in study(w)["data"].get("set", {}).items()),
        channels=lambda w: option("--channels", study(w)["data"].get("channels")),
        # the rig-like records carry the study's hidden effects; the data file does not name them
        effects=lambda w: option("--effect", study(w)["gap"]["rig_effects"]) if w.role.startswith("rig_") else "",
    log:
        "results/{study}/logs/simulate_{role}.log",
    benchmark:
        "results/{study}/benchmarks/simulate_{role}.tsv"
    resources:
        mem_mb=1000,
        runtime=5,
    shell:
        "ema-uq simulate --concept {params.concept} --experiment {params.experiment} "
        "--noise {params.noise} --seed {params.seed} {params.sets} {params.channels} {params.effects} "
        "--out {output} > {log} 2>&1"


rule identify:
    input:
        estimation=data_file("estimation"),
        validation=data_file("validation"),
    output:
        "results/{study}/fit_{method}.json",
    params:
        concept=concept,
        perturb=lambda w: study(w)["identify"]["perturb"],
        seed=lambda w: study(w)["seed"],
        max_iterations=lambda w: study(w)["identify"]["max_iterations"],
        fix=lambda w: option("--fix", study(w)["identify"].get("fix")),
        channels=lambda w: option("--channels", study(w)["data"].get("channels")),
    log:
        "results/{study}/logs/identify_{method}.log",
    benchmark:
        "results/{study}/benchmarks/identify_{method}.tsv"
    resources:
        mem_mb=2000,
        runtime=15,
    shell:
        "ema-uq identify {input.estimation} --concept {params.concept} --method {wildcards.method} "
        "--perturb {params.perturb} --seed {params.seed} --max-iterations {params.max_iterations} "
        "{params.fix} {params.channels} --validate {input.validation} --out {output} > {log} 2>&1"


rule sample:
    input:
        estimation=data_file("estimation"),
        fit="results/{study}/fit_gn.json",
    output:
        "results/{study}/posterior.nc",
    params:
        concept=concept,
        seed=lambda w: study(w)["seed"],
        walkers=lambda w: option("--walkers", [study(w)["sample"]["walkers"]] if study(w)["sample"]["walkers"] else []),
        ensembles=lambda w: study(w)["sample"]["ensembles"],
        max_steps=lambda w: study(w)["sample"]["max_steps"],
        check_every=lambda w: study(w)["sample"]["check_every"],
        moves=lambda w: study(w)["sample"]["moves"],
        defensive=lambda w: study(w)["sample"]["defensive"],
        integrator=lambda w: option("--integrator", [study(w)["sample"]["integrator"]] if study(w)["sample"]["integrator"] else []),
    log:
        "results/{study}/logs/sample.log",
    benchmark:
        "results/{study}/benchmarks/sample.tsv"
    threads: workflow.cores
    resources:
        mem_mb=4000,
        runtime=60,
    shell:
        "ema-uq sample {input.estimation} --concept {params.concept} --init {input.fit} --seed {params.seed} "
        "{params.walkers} --ensembles {params.ensembles} --max-steps {params.max_steps} "
        "--check-every {params.check_every} --moves {params.moves} --defensive {params.defensive} {params.integrator} --quiet "
        "--replace-stale-backend --backend results/{wildcards.study}/posterior.h5 --out {output} > {log} 2>&1"


rule sensitivity_chunk:
    output:
        "results/{study}/sobol/chunk_{chunk}.npz",
    params:
        concept=concept,
        study_file=study_file,
        n_chunks=lambda w: study(w)["sensitivity"]["chunks"],
        settings=settings("seed", "data", "sensitivity"),
    log:
        "results/{study}/logs/sensitivity_chunk_{chunk}.log",
    benchmark:
        "results/{study}/benchmarks/sensitivity_chunk_{chunk}.tsv"
    resources:
        mem_mb=2000,
        runtime=30,
    shell:
        "ema-uq sensitivity --concept {params.concept} --study {params.study_file} "
        "--chunk {wildcards.chunk}/{params.n_chunks} --out {output} > {log} 2>&1"


rule sensitivity:
    input:
        lambda w: expand("results/{study}/sobol/chunk_{chunk}.npz", study=w.study,
                         chunk=range(study(w)["sensitivity"]["chunks"])),
    output:
        "results/{study}/sobol.json",
    params:
        concept=concept,
        study_file=study_file,
        settings=settings("seed", "data", "sensitivity"),
    log:
        "results/{study}/logs/sensitivity.log",
    benchmark:
        "results/{study}/benchmarks/sensitivity.tsv"
    resources:
        mem_mb=2000,
        runtime=10,
    shell:
        "ema-uq sensitivity --concept {params.concept} --study {params.study_file} --gather {input} "
        "--out {output} > {log} 2>&1"


rule identifiability:
    input:
        estimation=data_file("estimation"),
        fit="results/{study}/fit_gn.json",
    output:
        "results/{study}/ident.json",
    params:
        concept=concept,
        study_file=study_file,
        settings=settings("data", "identify", "identifiability"),
    log:
        "results/{study}/logs/identifiability.log",
    benchmark:
        "results/{study}/benchmarks/identifiability.tsv"
    threads: workflow.cores
    resources:
        mem_mb=3000,
        runtime=60,
    shell:
        "ema-uq identifiability {input.estimation} --concept {params.concept} --init {input.fit} "
        "--study {params.study_file} --quiet --out {output} > {log} 2>&1"


rule gap:
    input:
        estimation=lambda w: data_file("rig_estimation")(w),
        validation=lambda w: data_file("rig_validation")(w),
    output:
        result="results/{study}/gap.json",
        ledger=report("results/{study}/gap_ledger.png", caption="report/gap_ledger.rst", category="Gap"),
    params:
        concept=concept,
        candidates=lambda w: option("--candidates", study(w)["gap"].get("candidates")),
        channels=lambda w: option("--channels", study(w)["data"].get("channels")),
    log:
        "results/{study}/logs/gap.log",
    benchmark:
        "results/{study}/benchmarks/gap.tsv"
    threads: workflow.cores
    resources:
        mem_mb=3000,
        runtime=30,
    shell:
        "ema-uq gap {input.estimation} --concept {params.concept} --validate {input.validation} "
        "{params.candidates} {params.channels} --figure {output.ledger} --quiet --out {output.result} > {log} 2>&1"


rule gap_selfcheck:
    output:
        "results/{study}/selfcheck.json",
    params:
        concept=concept,
        quick=lambda w: "--quick" if study(w)["gap"]["selfcheck"] == "quick" else "",
        seed=lambda w: study(w)["seed"],
    log:
        "results/{study}/logs/gap_selfcheck.log",
    benchmark:
        "results/{study}/benchmarks/gap_selfcheck.tsv"
    threads: workflow.cores
    resources:
        mem_mb=3000,
        runtime=120,
    shell:
        "ema-uq gap-selfcheck --concepts {params.concept} {params.quick} --seed {params.seed} --quiet "
        "--out {output} > {log} 2>&1"


rule report:
    input:
        unpack(stage_outputs),
        study="studies/{study}.yaml",
        template=REPORT_TEMPLATE,
    output:
        report("reports/{study}.html", caption="report/caption.rst", category="Reports"),
    log:
        "results/{study}/logs/report.log",
    benchmark:
        "results/{study}/benchmarks/report.tsv"
    resources:
        mem_mb=2000,
        runtime=10,
    shell:
        "ema-uq report --study {input.study} --results results/{wildcards.study} --out {output} > {log} 2>&1"
