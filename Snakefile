# ema_uq workflow: every rule calls the `ema-uq` CLI; the numerics live in the package.
#
# Every rule hands its CLI verb the study file (`--study`); the verb reads its settings through
# ema_uq.study.settings_for. The study file is never an input: the rule carries those same
# settings as its `settings` param, so a changed study value re-runs exactly the rules whose
# verb reads it.
# Every rule declares the one conda environment envs/ema_uq.yaml (the package with the
# dependencies of pyproject.toml): `snakemake --use-conda` builds it, a plain `snakemake`
# runs in the environment where `pip install -e .` put the package.
import json
import sys
from importlib import resources
from pathlib import Path

from snakemake.utils import validate

from ema_uq.io import CRANFIELD_HEALTHY, cranfield_file, cranfield_record_sets, emps_files
from ema_uq.study import DATA_ROLES, load_study, settings_for

configfile: "config/config.yaml"

CONDA_ENV = "envs/ema_uq.yaml"


def _number(text):
    """`--config 'sbc={study: smoke, replicates: 4}'` passes the numbers as text."""
    if not isinstance(text, str):
        return text
    for kind in (int, float):
        try:
            return kind(text)
        except (TypeError, ValueError):
            pass
    return text


if isinstance(config.get("sbc"), dict):
    config["sbc"] = {k: v if k == "study" else _number(v) for k, v in config["sbc"].items()}


validate(config, "config/config.schema.yaml")


def _load(name):
    study = load_study(f"studies/{name}.yaml")
    if study["concept"] == "emps" and not all(p.is_file() for p in emps_files(study, must_exist=False).values()):
        print(f"study {name}: EMPS data files not found (data.path or EMA_UQ_EMPS_DIR); study skipped",
              file=sys.stderr)
        return None
    if study["concept"] == "cranfield" and not cranfield_file(CRANFIELD_HEALTHY, study, must_exist=False).is_file():
        print(f"study {name}: Cranfield record sets not found (data.path or EMA_UQ_CRANFIELD_DIR); study skipped",
              file=sys.stderr)
        return None
    return study


STUDIES = {name: s for name in config["studies"] if (s := _load(name)) is not None}
#: stamp of `ema-uq compile`: every rule that simulates waits for it, so no stage pays numba
#: compilation (its time, not its date, matters: ancient)
COMPILED = "results/compile.json"
#: the SBC campaign of the `sbc` target (config/config.yaml, section sbc)
SBC = config.get("sbc", {})
REPORT_TEMPLATE = str(resources.files("ema_uq").joinpath("report/templates/report.html"))
SYNTHETIC = ("htls", "lths")  # concepts whose data the workflow simulates


def study(wildcards):
    return STUDIES[wildcards.study]


def concept(wildcards):
    return study(wildcards)["concept"]


def settings(verb):
    """A params value that changes exactly when the study settings the verb reads change."""
    return lambda w: json.dumps(settings_for(study(w), verb, role=getattr(w, "role", None)), sort_keys=True)


def study_file(wildcards):
    return f"studies/{wildcards.study}.yaml"


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
    if s["concept"] == "cranfield":  # measured fault records: healthy fit and fault diagnosis in one stage
        return {"faults": f"results/{w.study}/faults.json"}
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
    role="|".join(DATA_ROLES),
    method="gn|lm",
    chunk="[0-9]+",


rule all:
    input:
        expand("reports/{study}.html", study=STUDIES),


rule compile:
    output:
        COMPILED,
    params:
        # the concepts of the configured studies and of the SBC campaign
        concepts=lambda w: " ".join(sorted({s["concept"] for s in STUDIES.values()}
                                           | {load_study(f"studies/{SBC.get('study', 'htls')}.yaml")["concept"]})),
    log:
        "results/logs/compile.log",
    benchmark:
        "results/benchmarks/compile.tsv"
    resources:
        mem_mb=2000,
        runtime=20,
    conda:
        CONDA_ENV
    shell:
        "ema-uq compile --concept {params.concepts} --out {output} > {log} 2>&1"


rule simulate:
    input:
        compiled=ancient(COMPILED),
    output:
        "results/{study}/data/{role}.nc",
    params:
        concept=concept,
        study_file=study_file,
        # the rig-like records carry the study's hidden effects; the data file does not name them
        settings=settings("simulate"),
    log:
        "results/{study}/logs/simulate_{role}.log",
    benchmark:
        "results/{study}/benchmarks/simulate_{role}.tsv"
    resources:
        mem_mb=1000,
        runtime=5,
    conda:
        CONDA_ENV
    shell:
        "ema-uq simulate --concept {params.concept} --study {params.study_file} --role {wildcards.role} "
        "--out {output} > {log} 2>&1"


rule identify:
    input:
        compiled=ancient(COMPILED),
        estimation=data_file("estimation"),
        validation=data_file("validation"),
    output:
        "results/{study}/fit_{method}.json",
    params:
        concept=concept,
        study_file=study_file,
        settings=settings("identify"),
    log:
        "results/{study}/logs/identify_{method}.log",
    benchmark:
        "results/{study}/benchmarks/identify_{method}.tsv"
    resources:
        mem_mb=2000,
        runtime=15,
    conda:
        CONDA_ENV
    shell:
        "ema-uq identify {input.estimation} --concept {params.concept} --study {params.study_file} "
        "--method {wildcards.method} --validate {input.validation} --out {output} > {log} 2>&1"


rule sample:
    input:
        compiled=ancient(COMPILED),
        estimation=data_file("estimation"),
        fit="results/{study}/fit_gn.json",
    output:
        "results/{study}/posterior.nc",
    params:
        concept=concept,
        study_file=study_file,
        settings=settings("sample"),
    log:
        "results/{study}/logs/sample.log",
    benchmark:
        "results/{study}/benchmarks/sample.tsv"
    threads: workflow.cores
    resources:
        mem_mb=4000,
        runtime=60,
    conda:
        CONDA_ENV
    shell:
        "ema-uq sample {input.estimation} --concept {params.concept} --study {params.study_file} "
        "--init {input.fit} --replace-stale-backend --backend results/{wildcards.study}/posterior.h5 --out {output} > {log} 2>&1"


rule sensitivity_chunk:
    input:
        compiled=ancient(COMPILED),
    output:
        "results/{study}/sobol/chunk_{chunk}.npz",
    params:
        concept=concept,
        study_file=study_file,
        n_chunks=lambda w: study(w)["sensitivity"]["chunks"],
        settings=settings("sensitivity"),
    log:
        "results/{study}/logs/sensitivity_chunk_{chunk}.log",
    benchmark:
        "results/{study}/benchmarks/sensitivity_chunk_{chunk}.tsv"
    resources:
        mem_mb=2000,
        runtime=30,
    conda:
        CONDA_ENV
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
        settings=settings("sensitivity"),
    log:
        "results/{study}/logs/sensitivity.log",
    benchmark:
        "results/{study}/benchmarks/sensitivity.tsv"
    resources:
        mem_mb=2000,
        runtime=10,
    conda:
        CONDA_ENV
    shell:
        "ema-uq sensitivity --concept {params.concept} --study {params.study_file} --gather {input} "
        "--out {output} > {log} 2>&1"


rule identifiability:
    input:
        compiled=ancient(COMPILED),
        estimation=data_file("estimation"),
        fit="results/{study}/fit_gn.json",
    output:
        "results/{study}/ident.json",
    params:
        concept=concept,
        study_file=study_file,
        settings=settings("identifiability"),
    log:
        "results/{study}/logs/identifiability.log",
    benchmark:
        "results/{study}/benchmarks/identifiability.tsv"
    threads: workflow.cores
    resources:
        mem_mb=3000,
        runtime=60,
    conda:
        CONDA_ENV
    shell:
        "ema-uq identifiability {input.estimation} --concept {params.concept} --init {input.fit} "
        "--study {params.study_file} --out {output} > {log} 2>&1"


rule gap:
    input:
        compiled=ancient(COMPILED),
        estimation=lambda w: data_file("rig_estimation")(w),
        validation=lambda w: data_file("rig_validation")(w),
    output:
        result="results/{study}/gap.json",
        ledger=report("results/{study}/gap_ledger.png", caption="report/gap_ledger.rst", category="Gap"),
    params:
        concept=concept,
        study_file=study_file,
        settings=settings("gap"),
    log:
        "results/{study}/logs/gap.log",
    benchmark:
        "results/{study}/benchmarks/gap.tsv"
    threads: workflow.cores
    resources:
        mem_mb=3000,
        runtime=30,
    conda:
        CONDA_ENV
    shell:
        "ema-uq gap {input.estimation} --concept {params.concept} --study {params.study_file} "
        "--validate {input.validation} --figure {output.ledger} --out {output.result} > {log} 2>&1"


SELFCHECK_CHUNKS = 8  # self-check scatter: every case is seeded on its own, so parts do not depend on it


def selfcheck_chunks(w):
    """Parts of a study's self-check: one job each (the quick subset is one part)."""
    return 1 if study(w)["gap"]["selfcheck"] == "quick" else SELFCHECK_CHUNKS


rule gap_selfcheck_case:
    # one part of the self-check: every N-th case from case I (counted from 0); a failed part reruns alone
    input:
        compiled=ancient(COMPILED),
    output:
        "results/{study}/selfcheck/part_{chunk}.json",
    params:
        study_file=study_file,
        settings=settings("gap-selfcheck"),
        chunks=selfcheck_chunks,
    log:
        "results/{study}/logs/gap_selfcheck_{chunk}.log",
    benchmark:
        "results/{study}/benchmarks/gap_selfcheck_{chunk}.tsv"
    threads: 1
    resources:
        mem_mb=3000,
        runtime=240,
    conda:
        CONDA_ENV
    shell:
        "ema-uq gap-selfcheck --study {params.study_file} --chunk {wildcards.chunk}/{params.chunks} "
        "--jobs 1 --out {output} > {log} 2>&1"


rule gap_selfcheck:
    # gathers the parts into the result of one run (cheap: no diagnosis)
    input:
        lambda w: expand("results/{study}/selfcheck/part_{chunk}.json", study=w.study,
                         chunk=range(selfcheck_chunks(w))),
    output:
        "results/{study}/selfcheck.json",
    log:
        "results/{study}/logs/gap_selfcheck.log",
    benchmark:
        "results/{study}/benchmarks/gap_selfcheck.tsv"
    resources:
        mem_mb=1000,
        runtime=5,
    conda:
        CONDA_ENV
    shell:
        "ema-uq gap-selfcheck --gather {input} --out {output} > {log} 2>&1"


rule fault_diagnosis:
    input:
        # every record set of the data folder (or the study's data.record_sets): a set added there is diagnosed
        lambda w: [str(cranfield_file(f, study(w))) for f in cranfield_record_sets(study(w))],
        compiled=ancient(COMPILED),
    output:
        "results/{study}/faults.json",
    params:
        study_file=study_file,
        # the stage reads the study's data and gap sections and seed itself
        settings=lambda w: json.dumps({k: study(w).get(k) for k in ("data", "seed", "gap")}, sort_keys=True),
    log:
        "results/{study}/logs/fault_diagnosis.log",
    benchmark:
        "results/{study}/benchmarks/fault_diagnosis.tsv"
    resources:
        mem_mb=2000,
        runtime=15,
    conda:
        CONDA_ENV
    shell:
        "ema-uq fault-diagnosis --study {params.study_file} --out {output} > {log} 2>&1"


# the out-of-sample figures of the default gap method (version 4): the evaluation block of its frozen
# protocol (benchmarks/gap_protocol_v4.yaml), shown in the report beside a study's own self-check
SELFCHECK_EVALUATION = "benchmarks/protocol_outcomes/method4/evaluation.json"


def selfcheck_evaluation(w):
    """The evaluation block for a study with a self-check (none where the file is not beside the workflow)."""
    return [SELFCHECK_EVALUATION] if "selfcheck" in stage_outputs(w) and Path(SELFCHECK_EVALUATION).is_file() else []


rule report:
    input:
        unpack(stage_outputs),
        study="studies/{study}.yaml",
        template=REPORT_TEMPLATE,
        selfcheck_evaluation=selfcheck_evaluation,
    output:
        report("reports/{study}.html", caption="report/caption.rst", category="Reports"),
    params:
        evaluation=lambda w, input: " ".join(f"--selfcheck-evaluation {f}" for f in input.selfcheck_evaluation),
    log:
        "results/{study}/logs/report.log",
    benchmark:
        "results/{study}/benchmarks/report.tsv"
    resources:
        mem_mb=2000,
        runtime=10,
    conda:
        CONDA_ENV
    shell:
        "ema-uq report --study {input.study} --results results/{wildcards.study} --out {output} "
        "{params.evaluation} > {log} 2>&1"


# --- simulation-based calibration (target `sbc`, not part of `all`) ----------------------------
# One job per replicate (its own resources; resumable: a replicate's sampler backend keeps its
# chains), gathered by a cheap rule into the rank-uniformity figures. The campaign is the
# config's sbc section: `snakemake sbc` runs the production campaign of the HT/LS default study;
# `snakemake sbc --config 'sbc={study: smoke, replicates: 4}'` a few replicates of another study.
rule sbc:
    input:
        f"results/sbc/{SBC.get('study', 'htls')}/sbc.json",


rule sbc_replicate:
    input:
        compiled=ancient(COMPILED),
        study="studies/{study}.yaml",
    output:
        "results/sbc/{study}/replicate_{replicate}.json",
    params:
        seed=SBC.get("seed", 0),
        draws=SBC.get("draws", 99),
        prior_spread=SBC.get("prior_spread", 0.1),
    log:
        "results/sbc/{study}/logs/replicate_{replicate}.log",
    benchmark:
        "results/sbc/{study}/benchmarks/replicate_{replicate}.tsv"
    wildcard_constraints:
        replicate="[0-9]+",
    threads: SBC.get("threads", 1)
    resources:
        mem_mb=SBC.get("mem_mb", 3000),
        runtime=SBC.get("runtime", 240),
    conda:
        CONDA_ENV
    shell:
        "ema-uq sbc --study {input.study} --replicate {wildcards.replicate} --seed {params.seed} "
        "--draws {params.draws} --prior-spread {params.prior_spread} --backend results/sbc/{wildcards.study}/replicate_{wildcards.replicate}.h5 "
        "--out {output} > {log} 2>&1"


rule sbc_gather:
    input:
        lambda w: expand("results/sbc/{study}/replicate_{replicate}.json", study=w.study,
                         replicate=range(SBC.get("replicates", 100))),
    output:
        result="results/sbc/{study}/sbc.json",
        figure="results/sbc/{study}/sbc_ranks.png",
    params:
        bins=SBC.get("bins", 10),
    log:
        "results/sbc/{study}/logs/gather.log",
    resources:
        mem_mb=1000,
        runtime=5,
    conda:
        CONDA_ENV
    shell:
        "ema-uq sbc --gather {input} --bins {params.bins} --out {output.result} --figure {output.figure} > {log} 2>&1"
