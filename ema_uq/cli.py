"""The ``ema-uq`` command line (also ``python -m ema_uq``); contract in INTERFACES.md.

Each verb is one ``_add_<verb>(subparsers)`` function that registers its subparser and
binds one ``_run_<verb>(args) -> str`` handler; adding a verb means writing that pair and
listing the register function in :data:`VERBS`. Handlers only translate arguments into
package calls and files; the numerics live in the package.

Every expected failure (a ``ValueError`` from the package, such as :class:`~ema_uq.io.DataFileError`,
``ParameterError`` or ``ExperimentError``, an ``OSError``, or a bad argument) ends the
program with one line ``ema-uq: error: <message>`` on stderr and exit status 2. Success
prints a one-line summary on stdout and exits 0.
"""
from __future__ import annotations

import argparse
import math
import sys
from typing import Callable, Sequence

from . import __version__

PROG = "ema-uq"
EXIT_OK = 0
EXIT_ERROR = 2


class CLIError(ValueError):
    """A command-line value that the package cannot use."""


class _Parser(argparse.ArgumentParser):
    """argparse reports usage errors in the same one-line form as every other error."""

    def error(self, message: str):  # noqa: D401 - argparse API
        _print_error(message)
        raise SystemExit(EXIT_ERROR)


def _print_error(message: object) -> None:
    print(f"{PROG}: error: {' '.join(str(message).split())}", file=sys.stderr)


# --------------------------------------------------------------------------------------
# argument types and options shared by several verbs
# --------------------------------------------------------------------------------------
def _fraction(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"{text!r} must be a finite fraction >= 0 (0.02 is 2 % of the channel RMS)")
    return value


def _seed(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be a non-negative integer")
    return value


def _names(values: Sequence[str] | None) -> list[str] | None:
    """Names given space- or comma-separated (``--channels Omega y1`` or ``Omega,y1``)."""
    if values is None:
        return None
    return [n.strip() for v in values for n in v.split(",") if n.strip()]


def _add_concept(parser: argparse.ArgumentParser) -> None:
    from .models import concepts

    parser.add_argument("--concept", required=True, choices=concepts(), help="actuator concept")


def _add_seed(parser: argparse.ArgumentParser, default: int = 0) -> None:
    parser.add_argument("--seed", type=_seed, default=default, metavar="N",
                        help=f"seed of the random generator (default {default})")


def _add_set(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                        help="override an estimated parameter or a design constant (SI units); repeatable")


def _model_vectors(model, assignments: Sequence[str]):
    """(theta, constants) full vectors: nominal values overridden by ``--set`` items,
    each checked against its bounds."""
    from .params import parse_assignments

    params, consts = model.split_assignments(parse_assignments(assignments))
    theta = model.parameters.vector(params)
    model.parameters.check_within_bounds(theta, what="--set value")
    constants = model.constants_vector(consts)
    model.constants.check_within_bounds(constants, what="--set value")
    return theta, constants


# --------------------------------------------------------------------------------------
# unmodelled effects: the one place where --effect meets the simulator
# --------------------------------------------------------------------------------------
def parse_effect(spec: str) -> tuple[str, dict[str, float]]:
    """``NAME[:param=value,...]`` -> (name, {param: value}); e.g. ``backlash:delta=0.002``."""
    name, _, rest = spec.partition(":")
    name = name.strip()
    if not name:
        raise CLIError(f"cannot read --effect {spec!r}: write NAME[:param=value,...], e.g. backlash:delta=0.002")
    settings: dict[str, float] = {}
    for item in filter(None, (s.strip() for s in rest.split(","))):
        key, sep, value = item.partition("=")
        try:
            if not sep or not key.strip():
                raise ValueError
            settings[key.strip()] = float(value)
        except ValueError:
            raise CLIError(f"cannot read --effect {spec!r} at {item!r}: write NAME[:param=value,...] "
                           "with numeric values, e.g. backlash:delta=0.002") from None
    return name, settings


def _resolve_effects(model, specs: Sequence[str]):
    """Turn ``--effect`` items into what the simulator needs for ``model``.

    The simulator has no unmodelled effects wired in yet, so any requested effect is an
    error. When the catalogue (models/effects.py) lands, build the effect configuration
    here and pass it on to ``synthesize``; no other part of the CLI has to change.
    """
    effects = [parse_effect(spec) for spec in specs]
    if effects:
        raise CLIError(f"effect {effects[0][0]} is not available yet: the simulator has no "
                       "unmodelled effects wired in; run without --effect")
    return None


# --------------------------------------------------------------------------------------
# simulate
# --------------------------------------------------------------------------------------
def _add_simulate(subparsers) -> None:
    from .experiments import EXPERIMENTS

    p = subparsers.add_parser(
        "simulate", help="simulate a reference experiment and write noisy measurement data",
        description="Simulate a concept on a reference experiment (nominal parameters unless --set) "
                    "and write the outputs plus Gaussian white noise (fraction of each channel's RMS) "
                    "to a NetCDF (.nc) or CSV (.csv) file.")
    _add_concept(p)
    p.add_argument("--experiment", required=True, choices=tuple(EXPERIMENTS), help="input profile")
    p.add_argument("--noise", type=_fraction, default=0.02, metavar="FRACTION",
                   help="noise standard deviation as a fraction of each channel's RMS (default 0.02)")
    _add_seed(p)
    _add_set(p)
    p.add_argument("--effect", action="append", default=[], metavar="NAME[:param=value,...]",
                   help="add an unmodelled effect from the catalogue; repeatable")
    p.add_argument("--channels", nargs="+", metavar="NAME",
                   help="write only these output channels (default: all)")
    p.add_argument("--out", required=True, metavar="FILE.{nc,csv}", help="measurement file to write")
    p.set_defaults(handler=_run_simulate)


def _run_simulate(args: argparse.Namespace) -> str:
    from . import io
    from .experiments import get_experiment, synthesize
    from .models import get_model

    model = get_model(args.concept)
    theta, constants = _model_vectors(model, args.set)
    _resolve_effects(model, args.effect)
    channels = _names(args.channels)
    if channels is not None:
        model.output_index(channels)
    io.prepare_output(args.out, measurement=True)  # fail on a bad --out before simulating
    experiment = get_experiment(args.experiment)
    measurement = synthesize(model, experiment, theta, noise=args.noise, seed=args.seed,
                             channels=channels, constants=constants)
    path = io.write_measurement(args.out, measurement)
    return (f"wrote {path}: {model.name} on {experiment.name}, {experiment.n_samples} samples x "
            f"{len(measurement.channels)} channels, noise {args.noise:g}, seed {args.seed}")


# --------------------------------------------------------------------------------------
# entry point
# --------------------------------------------------------------------------------------
#: Register functions, one per verb, in the order ``--help`` lists them.
VERBS: tuple[Callable, ...] = (_add_simulate,)


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


def main(argv: Sequence[str] | None = None) -> int:
    """Run one verb; returns the exit status (0 success, 2 bad input)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        summary = args.handler(args)
    except (ValueError, OSError) as exc:
        if args.traceback:
            raise
        _print_error(exc)
        return EXIT_ERROR
    if summary:
        print(summary)
    return EXIT_OK


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
