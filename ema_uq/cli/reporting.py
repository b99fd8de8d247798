"""The verbs around the workflow rather than inside the numerics: ``report`` (the HTML report
of a study), ``screenshot`` (that report checked in a headless browser), ``check-study`` (a
study file against the schema) and ``compile`` (the numba cache filled ahead of a run).
"""
from __future__ import annotations

import argparse
import sys

from .arguments import CONCEPTS, PROG, CLIError, positive_int


# --------------------------------------------------------------------------------------
# report
# --------------------------------------------------------------------------------------
def add_report(subparsers) -> None:
    p = subparsers.add_parser("report", help="write the self-contained HTML report of a study",
                              description="Collect a study's result files into one HTML report with embedded figures.")
    p.add_argument("--study", required=True, metavar="STUDY.yaml")
    p.add_argument("--results", required=True, metavar="DIR", help="the study's results folder")
    p.add_argument("--out", required=True, metavar="REPORT.html")
    p.add_argument("--selfcheck-evaluation", metavar="SELFCHECK.json",
                   help="the evaluation block of the default gap method's frozen protocol, shown beside the "
                        "study's own self-check (the workflow gives benchmarks/protocol_outcomes/.../evaluation.json)")
    p.set_defaults(handler=_run_report)


def _run_report(args: argparse.Namespace) -> str:
    from pathlib import Path

    import time

    from ..report import build_report
    from ..study import load_study

    from .. import io

    study = load_study(args.study)
    if not Path(args.results).is_dir():
        raise CLIError(f"results folder {args.results} does not exist; run the workflow first")
    if not any(Path(args.results).glob("*.json")):
        raise CLIError(f"results folder {args.results} holds no stage result (no .json file); run the workflow "
                       "first, or give the study's results folder (results/<study>)")
    evaluation = None
    if args.selfcheck_evaluation:
        path = Path(args.selfcheck_evaluation)
        if not path.is_file():
            raise CLIError(f"--selfcheck-evaluation {path}: no such file; give the evaluation.json of a frozen "
                           "protocol's block (benchmarks/protocol_outcomes) or leave the option out")
        evaluation = io.read_json(path)
        if not {"top1", "targets", "n_cases"} <= set(evaluation):
            raise CLIError(f"--selfcheck-evaluation {path}: not a self-check result (no top1, targets or n_cases); "
                           "give the evaluation.json that benchmarks/gap.py --protocol writes")
    out = io.prepare_output(args.out)
    t0 = time.perf_counter()

    def progress(line: str) -> None:
        print(f"{PROG} report: {line}, {time.perf_counter() - t0:.0f} s", file=sys.stderr, flush=True)

    text = build_report(study, args.study, args.results, progress=progress, selfcheck_evaluation=evaluation)
    out.write_text(text, encoding="utf-8")
    return f"wrote {out} ({len(text) / 1e6:.1f} MB)"


# --------------------------------------------------------------------------------------
# screenshot
# --------------------------------------------------------------------------------------
def add_screenshot(subparsers) -> None:
    p = subparsers.add_parser("screenshot", help="open a report in headless Chromium and save its first screen",
                              description="Render an HTML report in headless Chromium, write a PNG of its first "
                                          "screen and fail when the page logs console errors.")
    p.add_argument("report", metavar="REPORT.html")
    p.add_argument("--out", required=True, metavar="SCREEN.png")
    p.add_argument("--width", type=positive_int, default=1280)
    p.add_argument("--height", type=positive_int, default=900)
    p.set_defaults(handler=_run_screenshot)


def _run_screenshot(args: argparse.Namespace) -> str:
    from ..report.browser import BrowserError, check_page

    try:
        page = check_page(args.report, args.out, width=args.width, height=args.height)
    except BrowserError as exc:
        raise CLIError(str(exc)) from None
    if not page.ok:
        raise CLIError(f"{args.report} logs console errors in Chromium: {' | '.join(page.console_errors[:3])}")
    return page.summary()


# --------------------------------------------------------------------------------------
# check-study
# --------------------------------------------------------------------------------------
def add_check_study(subparsers) -> None:
    p = subparsers.add_parser("check-study", help="validate a study file against the schema",
                              description="Validate a study YAML against the package schema; print it with defaults.")
    p.add_argument("study", metavar="STUDY.yaml")
    p.set_defaults(handler=_run_check_study)


def _run_check_study(args: argparse.Namespace) -> str:
    from ..study import load_study

    study = load_study(args.study)
    return f"{args.study}: valid study {study['name']!r} ({study['concept']})"


# --------------------------------------------------------------------------------------
# compile
# --------------------------------------------------------------------------------------
def add_compile(subparsers) -> None:
    p = subparsers.add_parser(
        "compile", help="fill the numba cache of every simulation kernel",
        description="Call every simulation kernel once on a few samples (each concept, integrator "
                    "and catalogue effect, and the self-check simulator) so later commands load "
                    "compiled code instead of compiling it. The cache lives beside the package "
                    "modules, or under NUMBA_CACHE_DIR.")
    p.add_argument("--concept", nargs="+", choices=CONCEPTS, default=None,
                   help="only these concepts (default: all)")
    p.add_argument("--out", metavar="FILE.json", default=None,
                   help="write the paths compiled and their seconds (a workflow stamp)")
    p.set_defaults(handler=_run_compile)


def _run_compile(args: argparse.Namespace) -> str:
    import json
    import time

    from ..compile import compile_kernels

    t0 = time.perf_counter()
    rows = compile_kernels(args.concept)
    total = time.perf_counter() - t0
    if args.out:
        with open(args.out, "w") as fh:
            json.dump({"seconds": total, "paths": rows}, fh, indent=1)
    skipped = sum(r["status"] != "ok" for r in rows)
    return (f"compiled {len(rows) - skipped} kernel paths in {total:.1f} s"
            + (f" ({skipped} not applicable)" if skipped else "") + (f" -> {args.out}" if args.out else ""))
