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


def _add_data(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("data", nargs="+", metavar="DATA", help="measurement files (.nc or .csv)")


def _read_all(paths: Sequence[str], concept: str):
    from . import io

    return [io.read_measurement(p, concept=concept) for p in paths]


def _read_fit(path: str, concept: str):
    """A FIT.json of the same concept (``--start``/``--init``)."""
    from . import io
    from .identify import FitResult

    data = io.read_json(path)
    if not isinstance(data, dict) or "parameters" not in data or "concept" not in data:
        raise CLIError(f"{path} is not a FIT.json written by 'ema-uq identify'")
    if data["concept"] != concept:
        raise CLIError(f"{path} holds a fit of concept {data['concept']}, but --concept {concept} was given; "
                       "use a fit of the same concept")
    return FitResult.from_json(data)


def _add_identify(subparsers) -> None:
    p = subparsers.add_parser(
        "identify", help="maximum-likelihood parameter estimation (det R; Gauss-Newton or Levenberg-Marquardt)",
        description="Estimate the free parameters from one or more measurement files by output-error "
                    "maximum likelihood (cost det R) and write estimates, Cramér-Rao bounds, correlations "
                    "and the iteration history to FIT.json.")
    _add_data(p)
    _add_concept(p)
    p.add_argument("--method", choices=("gn", "lm"), default="gn",
                   help="gn: Gauss-Newton with step halving; lm: Levenberg-Marquardt (default gn)")
    p.add_argument("--start", default="nominal", metavar="nominal|FIT.json",
                   help="start values: the nominal set or the estimate of an earlier fit")
    p.add_argument("--perturb", type=_fraction, default=0.0, metavar="FRACTION",
                   help="scale each free start value by 1+U(-FRACTION, FRACTION), seeded by --seed")
    _add_seed(p)
    _add_set(p)
    p.add_argument("--fix", nargs="+", default=[], metavar="NAME", help="hold these parameters at their value")
    p.add_argument("--channels", nargs="+", metavar="NAME", help="fit only these channels (default: all common)")
    p.add_argument("--validate", nargs="+", default=[], metavar="DATA",
                   help="data NOT used for estimation: report per-channel fit and residual tests")
    p.add_argument("--max-iterations", type=int, default=50, metavar="N")
    p.add_argument("--out", required=True, metavar="FIT.json")
    p.set_defaults(handler=_run_identify)


def _run_identify(args: argparse.Namespace) -> str:
    from . import io
    from .identify import FitProblem, Settings, estimate, perturbed_start
    from .identify.validation import validate
    from .models import get_model
    from .provenance import provenance

    model = get_model(args.concept)
    theta, constants = _model_vectors(model, args.set)
    parameters = model.parameters.with_nominal(model.parameters.as_dict(theta)).fixing(args.fix)
    io.prepare_output(args.out)
    measurements = _read_all(args.data, args.concept)
    validation_data = _read_all(args.validate, args.concept)
    problem = FitProblem(measurements, parameters=parameters, channels=_names(args.channels), constants=constants)
    start = theta if args.start == "nominal" else _read_fit(args.start, args.concept).estimate
    if args.perturb > 0:
        start = perturbed_start(parameters, args.perturb, args.seed, around=start)
    fit = estimate(problem, method=args.method, start=start, seed=args.seed,
                   settings=Settings(max_iterations=args.max_iterations))
    fit.provenance = provenance(args.data + args.validate, seed=args.seed,
                                settings={k: v for k, v in vars(args).items() if k != "handler"})
    out = fit.to_json()
    out["validation"] = [validate(fit.estimate, m, channels=problem.channels, constants=constants).to_json()
                         for m in validation_data]
    io.write_json(args.out, out)
    worst = min((c["fit_percent"] for v in out["validation"] for c in v["channels"].values()), default=None)
    tail = f", validation worst-channel fit {worst:.1f} %" if worst is not None else ""
    return (f"wrote {args.out}: {model.name} {args.method.upper()} "
            f"{'converged' if fit.converged else 'NOT converged'} in {fit.iterations} iterations, "
            f"{fit.n_simulations} simulations, {fit.wall_time_s:.1f} s{tail}")


def _add_sample(subparsers) -> None:
    p = subparsers.add_parser(
        "sample", help="Bayesian posterior by emcee, started from an ML fit; ArviZ NetCDF output",
        description="Sample the posterior of the init fit's free parameters (det R or known-sigma likelihood, "
                    "flat/lognormal/uniform priors, rig priors of p_ACE and p_PCE) with independent emcee "
                    "ensembles until every chain is longer than 50 autocorrelation times, and write the "
                    "ArviZ InferenceData to POSTERIOR.nc. The HDF5 backend lets a killed run resume.")
    _add_data(p)
    _add_concept(p)
    p.add_argument("--init", required=True, metavar="FIT.json", help="ML fit of the same concept (ema-uq identify)")
    p.add_argument("--out", required=True, metavar="POSTERIOR.nc")
    _add_seed(p)
    p.add_argument("--walkers", type=int, default=None, metavar="N",
                   help="walkers per ensemble (default max(2 x free parameters, 16))")
    p.add_argument("--chains", type=int, default=4, metavar="N", help="independent ensembles (default 4)")
    p.add_argument("--max-steps", type=int, default=20000, metavar="N", help="step cap per ensemble (default 20000)")
    p.add_argument("--check-every", type=int, default=100, metavar="N",
                   help="steps between stopping-rule checks (default 100)")
    p.add_argument("--spread", type=float, default=1.0, metavar="C",
                   help="start walkers from N(estimate, C x Cramér-Rao covariance) (default 1)")
    p.add_argument("--moves", choices=("de", "stretch"), default="de", help="emcee moves (default de)")
    p.add_argument("--backend", default=None, metavar="FILE.h5",
                   help="HDF5 chain store; an existing one of the same run is resumed (default: --out with .h5)")
    p.add_argument("--noise-sigma", choices=("estimated", "known"), default="estimated",
                   help="estimated: concentrated det R likelihood; known: Gaussian with each channel's "
                        "RMS residual at the ML estimate as its sigma (default estimated)")
    p.add_argument("--prior", action="append", default=[], metavar="NAME=KIND:A,B",
                   help="prior of a free parameter: lognormal:mu,sigma (of ln value), uniform:lo,hi or "
                        "normal:mean,sd; repeatable (default: flat on the bounds, rig normal for p_ACE, p_PCE)")
    p.add_argument("--predictive", type=int, default=100, metavar="N",
                   help="posterior draws simulated for the predictive group (default 100)")
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    p.set_defaults(handler=_run_sample)


def _run_sample(args: argparse.Namespace) -> str:
    from pathlib import Path

    from . import io
    from .bayes import BayesError, SamplerSettings, parse_prior, sample
    from .identify import FitProblem
    from .models import get_model

    if args.walkers is not None and args.walkers < 2:
        raise CLIError(f"--walkers {args.walkers}: give a positive even number of walkers")
    out = io.prepare_output(args.out)
    backend = Path(args.backend) if args.backend else out.with_suffix(".h5")
    io.prepare_output(backend)
    priors = {}
    for text in args.prior:
        name, kind, a, b = parse_prior(text)
        if name in priors:
            raise BayesError(f"--prior {name} given twice; give one prior per parameter")
        priors[name] = (kind, a, b)
    fit = _read_fit(args.init, args.concept)
    model = get_model(args.concept)
    parameters = model.parameters.freeing_only(fit.free_names)
    measurements = _read_all(args.data, args.concept)
    problem = FitProblem(measurements, parameters=parameters, channels=fit.channels or None)
    settings = SamplerSettings(n_walkers=args.walkers, n_ensembles=args.chains, max_steps=args.max_steps,
                               check_every=args.check_every, spread=args.spread, moves=args.moves,
                               n_predictive=args.predictive)

    def progress(line: str) -> None:
        print(f"{PROG} sample: {line}", file=sys.stderr, flush=True)

    result = sample(problem, fit, priors=priors, noise_sigma=args.noise_sigma, settings=settings, seed=args.seed,
                    backend=backend, progress=None if args.quiet else progress)
    result.to_netcdf(out)
    table = result.summary()
    return (f"wrote {out}: {model.name} posterior of {len(result.names)} parameters, "
            f"{'converged' if result.converged else 'NOT converged (step cap)'} after {result.n_steps} steps, "
            f"max R-hat {table['r_hat'].max():.3f}, min bulk ESS {table['ess_bulk'].min():.0f}, "
            f"{result.wall_time_s:.1f} s (chains in {backend})")


def _add_report(subparsers) -> None:
    p = subparsers.add_parser("report", help="write the self-contained HTML report of a study",
                              description="Collect a study's result files into one HTML report with embedded figures.")
    p.add_argument("--study", required=True, metavar="STUDY.yaml")
    p.add_argument("--results", required=True, metavar="DIR", help="the study's results folder")
    p.add_argument("--out", required=True, metavar="REPORT.html")
    p.set_defaults(handler=_run_report)


def _run_report(args: argparse.Namespace) -> str:
    from pathlib import Path

    from .report import build_report
    from .study import load_study

    study = load_study(args.study)
    if not Path(args.results).is_dir():
        raise CLIError(f"results folder {args.results} does not exist; run the workflow first")
    text = build_report(study, args.study, args.results)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(text, encoding="utf-8")
    return f"wrote {out} ({len(text) / 1e6:.1f} MB)"


def _add_check_study(subparsers) -> None:
    p = subparsers.add_parser("check-study", help="validate a study file against the schema",
                              description="Validate a study YAML against the package schema; print it with defaults.")
    p.add_argument("study", metavar="STUDY.yaml")
    p.set_defaults(handler=_run_check_study)


def _run_check_study(args: argparse.Namespace) -> str:
    from .study import load_study

    study = load_study(args.study)
    return f"{args.study}: valid study {study['name']!r} ({study['concept']})"


def _add_screenshot(subparsers) -> None:
    p = subparsers.add_parser("screenshot", help="open a report in headless Chromium and save its first screen",
                              description="Render an HTML report in headless Chromium, write a PNG of its first "
                                          "screen and fail when the page logs console errors.")
    p.add_argument("report", metavar="REPORT.html")
    p.add_argument("--out", required=True, metavar="SCREEN.png")
    p.add_argument("--width", type=int, default=1280)
    p.add_argument("--height", type=int, default=900)
    p.set_defaults(handler=_run_screenshot)


def _run_screenshot(args: argparse.Namespace) -> str:
    from .report.browser import BrowserError, check_page

    try:
        page = check_page(args.report, args.out, width=args.width, height=args.height)
    except BrowserError as exc:
        raise CLIError(str(exc)) from None
    if not page.ok:
        raise CLIError(f"{args.report} logs console errors in Chromium: {' | '.join(page.console_errors[:3])}")
    return page.summary()


# --------------------------------------------------------------------------------------
# entry point
# --------------------------------------------------------------------------------------
#: Register functions, one per verb, in the order ``--help`` lists them.
VERBS: tuple[Callable, ...] = (_add_simulate, _add_identify, _add_sample, _add_report, _add_check_study,
                               _add_screenshot)


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
