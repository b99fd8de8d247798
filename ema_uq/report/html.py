"""Assemble one self-contained HTML report per study from the workflow's result files.

Each stage contributes a section when its result file exists; a missing stage is listed
as not run, never silently dropped. The sections of the estimation stages are written in
:mod:`.html_estimation`, those of the gap in :mod:`.html_gap`, both through the number and
table formatting of :mod:`.html_format`; this module holds what spans the stages (the summary
of findings, the cost of every stage, the provenance) and the page around them.
"""
from __future__ import annotations

import html
from importlib import resources
from pathlib import Path
from string import Template
from typing import Callable

from ..io import read_benchmark
from ..models import get_model
from ..provenance import file_sha256, settings_hash
from ..rigs import rig_of
from . import html_format
from .html_estimation import (_estimate_findings, _identifiability_section, _identification_section,
                              _posterior_section, _published_section, _sobol_section)
from .html_format import _fmt, _pm, _read, _table
from .html_gap import _effect_name, _fault_label, _faults_section, _gap_section, _selfcheck_section

# the formatting and the self-check's judgement of a target, still importable from here
from .html_format import _at  # noqa: E402,F401
from .html_gap import _judged  # noqa: E402,F401


TEMPLATE = "report/templates/report.html"


def _gap_finding(gap: dict) -> str:
    """One line of the summary: the gap verdict, its confidence and the effect's fitted parameters."""
    what = {"effect": f"effect <b>{html.escape(_effect_name(gap))}</b>", "none": "no significant gap",
            "unexplained": "unexplained gap",
            "ambiguous": "ambiguous between " + html.escape(" / ".join(
                c["family"] for c in gap.get("contenders") or []))}.get(gap["verdict"],
                                                                       html.escape(str(gap["verdict"])))
    conf = f", {html.escape(str(gap['confidence']))} confidence" if gap.get("confidence") else ""
    # a dimensionless unit ("1") is not written after the number
    params = "; ".join(f"{html.escape(n)} = {_pm(v.get('estimate'), v.get('std'))}"
                       + ("" if str(v.get("unit", "")) in ("", "1") else f" {html.escape(str(v['unit']))}")
                       for n, v in (gap.get("effect_parameters") or {}).items())
    return f"Sim-to-real gap: {what}{conf}" + (f" ({params})" if params else "") + "."


def _summary_section(study: dict, results: Path, fits: dict) -> str:
    """The findings of every stage in a few lines: verdicts, estimates, convergence, Sobol."""
    items = []
    gap = _read(results, "gap.json")
    if gap:
        items.append(_gap_finding(gap))
    faults = _read(results, "faults.json")
    if faults:
        rows = faults["diagnoses"]
        labelled = [r for r in rows if r["record_set"] in faults["expected"]]
        right = sum(_fault_label(r) == faults["expected"][r["record_set"]] for r in labelled)
        unlabelled = len(rows) - len(labelled)
        items.append(f"Fault diagnosis of measured records against the healthy fit: {right} of {len(labelled)} record "
                     "sets of known fault as expected" + (f", {unlabelled} of no known fault" if unlabelled else "")
                     + " (" + ", ".join(f"{html.escape(r['record_set'])} → "
                                                      f"{html.escape(_fault_label(r))}" for r in rows) + ").")
    ident = _read(results, "ident.json")
    if ident:
        from ..identifiability import VERDICTS

        for name, r in ident["sensor_sets"].items():
            counts = [sum(t["verdict"] == v for t in r["parameters"].values()) for v in VERDICTS]
            items.append(f"Identifiability, {html.escape(name)} sensors: {counts[0]} identifiable, {counts[1]} "
                         f"practically and {counts[2]} structurally non-identifiable.")
    items += _estimate_findings(study, results, fits)
    if (results / "posterior.nc").exists():
        from ..bayes import PosteriorResult

        post = PosteriorResult.from_netcdf(results / "posterior.nc")
        table = post.summary()
        items.append(f"Posterior: max R-hat {_fmt(float(table['r_hat'].max()), 4)}, min bulk ESS "
                     f"{float(table['ess_bulk'].min()):.0f}, converged "
                     + ("yes" if post.converged else '<span class="flag">no</span> ('
                        + html.escape(str(post.attrs.get("stop_reason", "step cap reached"))) + ")") + ".")
    sobol = _read(results, "sobol.json")
    if sobol and "cost" in sobol["qoi"]:
        st, conf = sobol["qoi"]["cost"]["ST"], sobol["qoi"]["cost"].get("ST_conf", {})
        top = sorted(st, key=lambda n: -st[n])[:3]
        items.append("Sobol, largest total indices of the det R cost (± 95 % interval): "
                     + ", ".join(f"{html.escape(n)} {_pm(st[n], conf.get(n), 2)}" for n in top) + ".")
    if not items:
        return '<p class="muted">No stage has written results yet.</p>'
    return "<ul>" + "".join(f"<li>{i}</li>" for i in items) + "</ul>"


def _stage_cost_section(results: Path) -> str:
    """Wall time and peak memory of every workflow job, from Snakemake's benchmark files."""
    rows, total = [], 0.0
    for path in sorted((results / "benchmarks").glob("*.tsv")):
        record = read_benchmark(path)
        if record is None:
            continue  # a benchmark still being written, or from another Snakemake version
        total += record["s"]
        rows.append([html.escape(path.stem), f"{record['s']:.1f}", _fmt(record["cpu_s"], 3), f"{record['max_rss']:.0f}"])
    if not rows:
        return '<p class="muted">No benchmark files (the stages were not run by the workflow).</p>'
    rows.append(["<b>total</b>", f"<b>{total:.1f}</b>", "", ""])
    return ("<p>From the workflow's benchmark files (one per job; the report's own job is listed from its "
            "previous run). Peak memory is the maximum resident set size.</p>"
            + _table(["job", "wall time [s]", "CPU time [s]", "peak memory [MB]"], rows))


#: the dependencies whose versions can change a number of the report
DEPENDENCIES = ("numpy", "scipy", "numba", "xarray", "pandas", "emcee", "arviz", "SALib", "matplotlib", "snakemake")


def _source_state() -> tuple[str, str]:
    """(commit, state) of the git checkout the package is imported from: state is "clean",
    "dirty (n files changed)" or why there is no commit (an installed wheel, no git)."""
    import subprocess

    root = Path(__file__).resolve().parents[2]
    try:
        commit = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True,
                                timeout=20)
        if commit.returncode != 0:
            return "–", "not a git checkout (an installed copy)"
        status = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                                capture_output=True, text=True, timeout=20)
    except (OSError, subprocess.SubprocessError):
        return "–", "git not available"
    changed = [line for line in status.stdout.splitlines() if line.strip()]
    return commit.stdout.strip(), f"dirty ({len(changed)} tracked files changed)" if changed else "clean"


def _versions() -> str:
    from importlib import metadata

    out = []
    for name in DEPENDENCIES:
        try:
            out.append(f"{name} {metadata.version(name)}")
        except metadata.PackageNotFoundError:
            out.append(f"{name} not installed")
    return ", ".join(out)


def _provenance_section(study: dict, study_path: Path, results: Path, fits: dict) -> str:
    import platform

    from .. import __version__

    commit, state = _source_state()
    rows = [["package version", __version__], ["git commit", commit],
            ["working tree", f'<span class="flag">{state}</span>' if state.startswith("dirty") else state],
            ["Python", platform.python_version()], ["dependencies", html.escape(_versions())],
            ["study file", html.escape(str(study_path.name))],
            ["study hash", settings_hash(study)], ["seed", study.get("seed")]]
    for f in sorted(results.rglob("*")):
        if f.is_file() and f.suffix in (".nc", ".csv", ".mat") and "logs" not in f.parts:
            rows.append([f"sha256 {html.escape(str(f.relative_to(results)))}", file_sha256(f)[:32] + "…"])
    rig = rig_of(study["concept"])
    for label, f in rig.data_files(study) if rig is not None else ():
        rows.append([f"sha256 {html.escape(label)}", file_sha256(f)[:32] + "…" if f.is_file() else "not found"])
    for k, fit in fits.items():
        rows.append([f"{k} fit created", html.escape(str(fit.get("provenance", {}).get("created", "")))])
    return _table(["item", "value"], [[html.escape(str(a)), str(b)] for a, b in rows], name_cols=2)


def build_report(study: dict, study_path: str | Path, results: str | Path,
                 progress: Callable[[str], None] | None = None, selfcheck_evaluation: dict | None = None) -> str:
    """HTML text of the report for ``study`` from the result files in ``results``; ``progress``
    is called with a line after every figure drawn (drawing is the slow part);
    ``selfcheck_evaluation``: the evaluation block of the default gap method's frozen protocol (a
    SELFCHECK.json), shown beside the study's own self-check."""
    html_format.PROGRESS = progress
    try:
        return _sections_of(study, Path(study_path), Path(results), selfcheck_evaluation)
    finally:
        html_format.PROGRESS = None


def _sections_of(study: dict, study_path: Path, results: Path, selfcheck_evaluation: dict | None = None) -> str:
    rig = rig_of(study["concept"])
    if rig is not None and rig.fault_diagnosis:  # measured fault records: one stage, healthy fit and diagnoses
        return _render(study, [("summary", "Summary of findings", _summary_section(study, results, {})),
                               ("faults", "Fault diagnosis of measured records", _faults_section(results)),
                               ("cost", "Time and memory per stage", _stage_cost_section(results)),
                               ("provenance", "Provenance", _provenance_section(study, study_path, results, {}))])
    ident, fits = _identification_section(study, results)
    sections = [("summary", "Summary of findings", _summary_section(study, results, fits)),
                ("identification", "Maximum-likelihood identification", ident)]
    if rig is not None and rig.published_comparison is not None:
        sections.append((rig.concept, f"{rig.title}: ML vs the published identification", _published_section(study, results)))
    sections.append(("posterior", "Bayesian posterior", _posterior_section(study, results)))
    if rig is None:  # synthetic data of an EMA concept: Sobol and identifiability of its friction terms
        sections.append(("sobol", "Sobol sensitivity", _sobol_section(results)))
        sections.append(("identifiability", "Identifiability of the friction and damping parameters",
                         _identifiability_section(study, results)))
    if (results / "gap.json").exists():
        sections.append(("gap", "Sim-to-real gap", _gap_section(study, results)))
    if (results / "selfcheck.json").exists():
        sections.append(("selfcheck", "Blind self-check of the gap diagnosis",
                         _selfcheck_section(results, selfcheck_evaluation)))
    stages = {"posterior": "Bayesian posterior", "sobol": "Sobol sensitivity",
              "ident": "Identifiability", "gap": "Sim-to-real gap"}
    if rig is not None:  # Sobol and identifiability concern the EMA friction terms
        stages = {k: v for k, v in stages.items() if k in ("posterior", "gap")}
    pending = [title for key, title in stages.items() if not any(results.glob(f"{key}*"))]
    if pending:
        sections.append(("pending", "Stages not run", "<p class=\"muted\">" + ", ".join(pending) + "</p>"))
    sections.append(("cost", "Time and memory per stage", _stage_cost_section(results)))
    sections.append(("provenance", "Provenance", _provenance_section(study, study_path, results, fits)))
    return _render(study, sections)


def _render(study: dict, sections: list[tuple[str, str, str]]) -> str:
    body = "\n".join(f'<h2 id="{key}">{title}</h2>\n{content}' for key, title, content in sections)
    nav = " ".join(f'<a href="#{key}">{title}</a>' for key, title, _ in sections)
    template = Template(resources.files("ema_uq").joinpath(TEMPLATE).read_text())
    model = get_model(study["concept"])
    return template.substitute(title=html.escape(f"{study['name']} — {model.title}"),
                               description=html.escape(study.get("description", "")),
                               nav=nav, sections=body)
