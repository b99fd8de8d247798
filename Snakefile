# ema_uq workflow: every rule calls the `ema-uq` CLI; the numerics live in the package.
# Study values enter rules as params (not the study file as an input), so a changed value
# re-runs exactly the rules that use it; the report reads the whole study and depends on it.
# `snakemake --lint` asks for a conda environment per rule: the software is the package
# itself, installed once by `pip install -e .` (pyproject.toml pins its dependencies), so
# every rule shares that one environment and none is declared.
from importlib import resources

from snakemake.utils import validate

from ema_uq.study import load_study

configfile: "config/config.yaml"


validate(config, "config/config.schema.yaml")

STUDIES = {name: load_study(f"studies/{name}.yaml") for name in config["studies"]}
REPORT_TEMPLATE = str(resources.files("ema_uq").joinpath("report/templates/report.html"))


def study(wildcards):
    return STUDIES[wildcards.study]


def data_seed(wildcards):
    # estimation and validation noise must be independent draws
    return study(wildcards)["seed"] + (0 if wildcards.role == "estimation" else 1000)


def option(flag, values):
    return f"{flag} {' '.join(values)}" if values else ""


wildcard_constraints:
    study="[A-Za-z0-9_-]+",
    role="estimation|validation",
    method="gn|lm",


rule all:
    input:
        expand("reports/{study}.html", study=STUDIES),


rule simulate:
    output:
        "results/{study}/data/{role}.nc",
    params:
        concept=lambda w: study(w)["concept"],
        experiment=lambda w: study(w)["data"][w.role],
        noise=lambda w: study(w)["data"]["noise"],
        seed=data_seed,
        sets=lambda w: " ".join(f"--set {k}={v}" for k, v in study(w)["data"].get("set", {}).items()),
        channels=lambda w: option("--channels", study(w)["data"].get("channels")),
    log:
        "results/{study}/logs/simulate_{role}.log",
    benchmark:
        "results/{study}/benchmarks/simulate_{role}.tsv"
    shell:
        "ema-uq simulate --concept {params.concept} --experiment {params.experiment} "
        "--noise {params.noise} --seed {params.seed} {params.sets} {params.channels} "
        "--out {output} > {log} 2>&1"


rule identify:
    input:
        estimation="results/{study}/data/estimation.nc",
        validation="results/{study}/data/validation.nc",
    output:
        "results/{study}/fit_{method}.json",
    params:
        concept=lambda w: study(w)["concept"],
        perturb=lambda w: study(w)["identify"]["perturb"],
        seed=lambda w: study(w)["seed"],
        max_iterations=lambda w: study(w)["identify"]["max_iterations"],
        fix=lambda w: option("--fix", study(w)["identify"].get("fix")),
    log:
        "results/{study}/logs/identify_{method}.log",
    benchmark:
        "results/{study}/benchmarks/identify_{method}.tsv"
    shell:
        "ema-uq identify {input.estimation} --concept {params.concept} --method {wildcards.method} "
        "--perturb {params.perturb} --seed {params.seed} --max-iterations {params.max_iterations} "
        "{params.fix} --validate {input.validation} --out {output} > {log} 2>&1"


rule report:
    input:
        fits=lambda w: expand("results/{study}/fit_{method}.json", study=w.study,
                              method=study(w)["identify"]["methods"]),
        study="studies/{study}.yaml",
        template=REPORT_TEMPLATE,
    output:
        report("reports/{study}.html", caption="report/caption.rst", category="Reports"),
    log:
        "results/{study}/logs/report.log",
    benchmark:
        "results/{study}/benchmarks/report.tsv"
    shell:
        "ema-uq report --study {input.study} --results results/{wildcards.study} --out {output} > {log} 2>&1"
