"""The ``ema-uq`` program as a whole: the parser assembled from every verb, a study's settings
laid under the options given, and the one place where failures become exit statuses.

Every expected failure (an :class:`~ema_uq.errors.EmaUqError` from the package, such as
:class:`~ema_uq.io.DataFileError`, ``ParameterError`` or ``ExperimentError``, a file that
is missing or may not be read or written, or a bad argument) ends the program with one line
``ema-uq: error: <message>`` on stderr and exit status 2. Any other exception is a fault of
the package: its traceback is shown with a request to report it, exit status 3. Success
prints a one-line summary on stdout and exits 0.
"""
from __future__ import annotations

import argparse
import sys
import traceback
from typing import Callable, Sequence

from .. import __version__
from ..errors import FILE_ACCESS_ERRORS, EmaUqError
from .analysis import add_identifiability, add_sensitivity
from .arguments import PROG, CLIError
from .diagnosis import add_fault_diagnosis, add_gap, add_gap_selfcheck
from .estimation import add_identify, add_sample, add_sbc, add_simulate
from .reporting import add_check_study, add_compile, add_report, add_screenshot

#: verbs that run the numba simulator: a first run compiles its kernels, and says so first
SIMULATING_VERBS = frozenset({"simulate", "identify", "sample", "sensitivity", "identifiability", "gap",
                              "gap-selfcheck", "fault-diagnosis"})
EXIT_OK = 0
EXIT_ERROR = 2
EXIT_BUG = 3
BUG_REPORT = (f"{PROG}: this is a fault of {PROG} {__version__}, not of your input; please report it "
              "with the command line and the traceback above")
#: Register functions, one per verb, in the order ``--help`` lists them.
VERBS: tuple[Callable, ...] = (add_simulate, add_identify, add_sample, add_sensitivity,
                               add_identifiability, add_gap, add_gap_selfcheck, add_fault_diagnosis, add_report,
                               add_check_study, add_screenshot, add_sbc, add_compile)


# --------------------------------------------------------------------------------------
# the parser and its errors
# --------------------------------------------------------------------------------------
class _Parser(argparse.ArgumentParser):
    """argparse reports usage errors in the same one-line form as every other error."""

    def error(self, message: str):  # noqa: D401 - argparse API
        _print_error(message)
        raise SystemExit(EXIT_ERROR)


def _print_error(message: object) -> None:
    print(f"{PROG}: error: {' '.join(str(message).split())}", file=sys.stderr)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog=PROG, description="Modelling, identification and uncertainty "
                                            "quantification of electromechanical flap actuators.")
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    parser.add_argument("--traceback", action="store_true",
                        help="on error, show the full Python traceback (for debugging)")
    subparsers = parser.add_subparsers(dest="verb", title="verbs", required=True)
    for register in VERBS:
        register(subparsers)
    # names the verbs in the "required" error, which otherwise only says "verb"
    subparsers.metavar = "{" + ",".join(subparsers.choices) + "}"
    return parser


# --------------------------------------------------------------------------------------
# a study's settings under the options given
# --------------------------------------------------------------------------------------
def _given_options(argv: Sequence[str] | None) -> set[str]:
    """Destinations of the options given on the command line: a second parse in which no
    option of any verb has a default, so only the given ones appear."""
    parser = build_parser()
    verbs = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    for verb_parser in verbs.choices.values():
        for action in verb_parser._actions:
            action.default = argparse.SUPPRESS
    return set(vars(parser.parse_args(argv))) - {"handler", "verb"}


def _apply_study(args: argparse.Namespace, given: set[str]) -> None:
    """Lay the study's settings of this verb (:func:`ema_uq.study.settings_for`, the one route
    from a study to a stage) under the options given on the command line; ``--set`` items are
    laid over the study's ``data.set`` name by name."""
    from ..study import STUDY_VERBS, load_study, settings_for

    if getattr(args, "role", None) and not args.study:
        raise CLIError("--role picks one of a study's records: give --study STUDY.yaml with it")
    if args.verb not in STUDY_VERBS or not args.study:
        return
    study = load_study(args.study)
    concept = getattr(args, "concept", None)
    if concept is not None and study["concept"] != concept:
        raise CLIError(f"{args.study} is a study of concept {study['concept']}, but --concept {concept} was "
                       "given; use the study of the same concept")
    for dest, value in settings_for(study, args.verb, role=getattr(args, "role", None)).items():
        if dest == "set":
            args.set = [f"{name}={number!r}" for name, number in value.items()] + list(args.set)
        elif hasattr(args, dest) and dest not in given:
            setattr(args, dest, value)


# --------------------------------------------------------------------------------------
# entry point
# --------------------------------------------------------------------------------------
def main(argv: Sequence[str] | None = None) -> int:
    """Run one verb; returns the exit status (0 success, 2 bad input, 3 a fault of the package)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        if args.verb in SIMULATING_VERBS:
            from ..threads import follow_scheduler_threads

            # before the study is read: reading it imports the models, and so numba, which takes
            # its thread count once; told afterwards, it launched a thread per core and refused
            # the job's share at the next compilation (every case of a one-thread self-check job)
            follow_scheduler_threads()
        _apply_study(args, _given_options(argv))
        if args.verb in SIMULATING_VERBS:
            from ..progress import first_compile_notice

            first_compile_notice(("simulate.integrators", "gap.variants") if args.verb == "gap-selfcheck"
                                 else ("simulate.integrators",))
        summary = args.handler(args)
    except (EmaUqError, *FILE_ACCESS_ERRORS) as exc:
        if args.traceback:
            raise
        _print_error(exc)
        return EXIT_ERROR
    except Exception:  # noqa: BLE001 - a fault of the package: shown whole, never as a user error
        traceback.print_exc()
        print(BUG_REPORT, file=sys.stderr)
        return EXIT_BUG
    if summary:
        print(summary)
    return EXIT_OK
