"""The ``ema-uq`` command line (also ``python -m ema_uq``); contract in docs/INTERFACES.md.

Each verb is one ``_add_<verb>(subparsers)`` function that registers its subparser and
binds one ``_run_<verb>(args) -> str`` handler; adding a verb means writing that pair and
listing the register function in :data:`VERBS`. Handlers only translate arguments into
package calls and files; the numerics live in the package.

Every expected failure (an :class:`~ema_uq.errors.EmaUqError` from the package, such as
:class:`~ema_uq.io.DataFileError`, ``ParameterError`` or ``ExperimentError``, a file that
is missing or may not be read or written, or a bad argument) ends the program with one line
``ema-uq: error: <message>`` on stderr and exit status 2. Any other exception is a fault of
the package: its traceback is shown with a request to report it, exit status 3. Success
prints a one-line summary on stdout and exits 0.
"""
from __future__ import annotations

import argparse
import math
import sys
import traceback
from typing import Callable, Sequence

from . import __version__
from .errors import FILE_ACCESS_ERRORS, EmaUqError

PROG = "ema-uq"
#: answers of ``identify --unidentifiable`` (ema_uq.identify.UNIDENTIFIABLE_MODES; not imported
#: here, the parser builds without loading the numerics)
UNIDENTIFIABLE_MODES = ("fix", "error")
#: concepts (ema_uq.models.concepts()) and reference experiments (ema_uq.experiments.EXPERIMENTS)
#: named here for the same reason: ``--help`` loads neither numpy nor numba (a test keeps them equal)
CONCEPTS = ("cranfield", "emps", "htls", "lths")
EXPERIMENT_NAMES = ("deploy-retract", "validation")
#: verbs that run the numba simulator: a first run compiles its kernels, and says so first
SIMULATING_VERBS = frozenset({"simulate", "identify", "sample", "sensitivity", "identifiability", "gap",
                              "gap-selfcheck", "fault-diagnosis"})
EXIT_OK = 0
EXIT_ERROR = 2
EXIT_BUG = 3
BUG_REPORT = (f"{PROG}: this is a fault of {PROG} {__version__}, not of your input; please report it "
              "with the command line and the traceback above")


class CLIError(EmaUqError):
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
    parser.add_argument("--concept", required=True, choices=CONCEPTS, help="actuator concept")


def _add_seed(parser: argparse.ArgumentParser, default: int = 0) -> None:
    parser.add_argument("--seed", type=_seed, default=default, metavar="N",
                        help=f"seed of the random generator (default {default})")


def _add_set(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                        help="override an estimated parameter or a design constant (SI units); repeatable; "
                             "laid over the study's data.set")


def _add_study(parser: argparse.ArgumentParser, what: str, required: bool = False) -> None:
    parser.add_argument("--study", required=required, default=None, metavar="STUDY.yaml",
                        help=f"take {what} from this study (options given here override it)")


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
def _resolve_effects(model, specs: Sequence[str]):
    """Turn ``--effect`` items into (augmented model, {effect: {parameter: value}}).

    Each item is read by :func:`ema_uq.models.effects.parse_effect` against the concept's
    catalogue (names, short or full parameter names, finite numbers); unnamed parameters keep
    the effect's nominal value. Without ``--effect`` the nominal model comes back unchanged.
    """
    from .models.effects import EffectError, parse_effect

    if not specs:
        return model, {}
    names, values = [], {}
    for spec in specs:
        try:
            name, settings = parse_effect(spec, model.effect_catalogue)
        except EffectError as exc:
            raise CLIError(f"--effect of concept {model.name}: {exc}") from None
        values.update(settings)
        names.append(name)
    augmented = model.with_effects(names, values)
    return augmented, {n: {p.name: p.nominal for p in augmented.parameters if p.name.startswith(n + "_")}
                       for n in names}


# --------------------------------------------------------------------------------------
# simulate
# --------------------------------------------------------------------------------------
def _add_simulate(subparsers) -> None:
    from .study import DATA_ROLES

    p = subparsers.add_parser(
        "simulate", help="simulate a reference experiment and write noisy measurement data",
        description="Simulate a concept on a reference experiment (nominal parameters unless --set) "
                    "and write the outputs plus Gaussian white noise (fraction of each channel's RMS) "
                    "to a NetCDF (.nc) or CSV (.csv) file.")
    _add_concept(p)
    _add_study(p, "experiment, noise, seed, data.set, channels and (rig roles) hidden effects of a data role")
    p.add_argument("--role", choices=tuple(DATA_ROLES), default=None,
                   help="with --study: which of the study's records to write")
    p.add_argument("--experiment", choices=EXPERIMENT_NAMES, default=None,
                   help="input profile (required without --study)")
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
    from pathlib import Path

    from . import io
    from .experiments import get_experiment, synthesize
    from .models import get_model

    if args.experiment is None:
        raise CLIError("give --experiment, or --study with --role")
    model, effects = _resolve_effects(get_model(args.concept), args.effect)
    theta, constants = _model_vectors(model, args.set)  # --set also reaches effect parameters
    channels = _names(args.channels)
    if channels is not None:
        model.output_index(channels)
    io.prepare_output(args.out, measurement=True)  # fail on a bad --out before simulating
    experiment = get_experiment(args.experiment)
    measurement = synthesize(model, experiment, theta, noise=args.noise, seed=args.seed,
                             channels=channels, constants=constants)
    path = io.write_measurement(args.out, measurement)
    tail = ""
    if effects:
        # the data file never names the effect (the gap diagnosis must find it blind);
        # the truth goes to a sidecar so benchmarks can score the diagnosis
        truth = {name: {p: float(theta[model.parameters.index(p)]) for p in values}
                 for name, values in effects.items()}
        truth_path = f"{path}.truth.json"
        io.write_json(truth_path, {"concept": model.name, "experiment": experiment.name,
                                   "effects": truth, "seed": args.seed, "noise_fraction": args.noise})
        tail = "; effects " + ", ".join(
            f"{name}({', '.join(f'{p[len(name) + 1:]}={v:g}' for p, v in values.items())})"
            for name, values in truth.items()) + f" (truth in {truth_path})"
    else:  # a truth file left by an earlier run with effects would now be wrong
        Path(f"{path}.truth.json").unlink(missing_ok=True)
    return (f"wrote {path}: {model.name} on {experiment.name}, {experiment.n_samples} samples x "
            f"{len(measurement.channels)} channels, noise {args.noise:g}, seed {args.seed}{tail}")


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
    _add_study(p, "seed, start perturbation, iteration cap, fixed parameters, channels and data.set")
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
    p.add_argument("--unidentifiable", choices=UNIDENTIFIABLE_MODES, default="fix",
                   help="when the channels cannot determine every free parameter (singular information matrix at "
                        "the start): fix holds the undetermined ones at their start values, estimates the rest and "
                        "reports the identifiable combinations; error stops naming the direction (default fix)")
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
    from .rigs import rig_of

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
    from .progress import Progress

    with Progress(args.max_iterations, f"{PROG} identify {args.method}", "iteration") as bar:
        def progress(iteration: int, line: str) -> None:
            bar.update(iteration - bar.n, line)

        fit = estimate(problem, method=args.method, start=start, seed=args.seed,
                       settings=Settings(max_iterations=args.max_iterations), unidentifiable=args.unidentifiable,
                       progress=progress)
    fit.provenance = provenance(args.data + args.validate, seed=args.seed,
                                settings={k: v for k, v in vars(args).items() if k != "handler"})
    out = fit.to_json()
    out["validation"] = [validate(fit.estimate, m, channels=problem.channels, constants=constants).to_json()
                         for m in validation_data]
    rig = rig_of(model.name)
    if rig is not None and rig.published_comparison is not None:  # the report's table beside the published values
        out["published_comparison"] = rig.published_comparison(fit, measurements[0], next(iter(validation_data), None))
    io.write_json(args.out, out)
    _write_fit_outputs(args.out, model, fit.estimate, problem.channels, constants,
                       [("estimation", m) for m in measurements] + [("validation", m) for m in validation_data])
    worst = min((c["fit_percent"] for v in out["validation"] for c in v["channels"].values()), default=None)
    tail = f", validation worst-channel fit {worst:.1f} %" if worst is not None else ""
    if fit.fixed:
        tail += (f"; held {len(fit.fixed)} parameters the channels cannot determine ({', '.join(fit.fixed)}), "
                 + "; ".join(f"{c['expression']} = {c['value']:.4g} +/- {c['std']:.2g}" for c in fit.combinations))
    return (f"wrote {args.out}: {model.name} {args.method.upper()} "
            f"{'converged' if fit.converged else 'NOT converged'} in {fit.iterations} iterations, "
            f"{fit.n_simulations} simulations, {fit.wall_time_s:.1f} s{tail}")


def _write_fit_outputs(fit_json: str, model, theta, channels, constants, records) -> None:
    """Measured and predicted outputs of every (role, measurement) record beside FIT.json, so the
    report draws the fit without simulating (:mod:`ema_uq.report.outputs`)."""
    from .report.outputs import fit_outputs_path, write_fit_outputs
    from .rigs import rig_of
    from .simulate import simulate_batch

    rig = rig_of(model.name)
    own = rig.record_constants if rig is not None else None  # records that carry their own (EMPS: gains, start)
    rows = []
    for role, m in records:
        names = [c for c in m.channels if c in channels]
        if own is not None:
            constants = own(m)
        predicted = simulate_batch(model, theta, m.time, m.experiment.input_matrix(model), constants=constants)
        rows.append({"role": role, "experiment": m.experiment.name, "channels": names,
                     "units": [model.unit_of(c) for c in names], "time": m.time,
                     "measured": m.select(names).values, "predicted": predicted[:, model.output_index(names)]})
    write_fit_outputs(fit_outputs_path(fit_json), rows)


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
    _add_study(p, "seed, sampler budgets, moves, integrator and data.set")
    _add_seed(p)
    _add_set(p)
    p.add_argument("--walkers", type=int, default=None, metavar="N",
                   help="walkers per ensemble (default 16 for --moves independence, else "
                        "max(2 x free parameters, 16))")
    p.add_argument("--chains", "--ensembles", dest="chains", type=int, default=4, metavar="N",
                   help="independent ensembles; R-hat and ESS compare them (default 4)")
    p.add_argument("--max-steps", type=int, default=20000, metavar="N", help="step cap per ensemble (default 20000)")
    p.add_argument("--check-every", type=int, default=50, metavar="N",
                   help="steps between stopping-rule checks (default 50)")
    p.add_argument("--spread", type=float, default=9.0, metavar="C",
                   help="start walkers from N(estimate, C x Cramér-Rao covariance) (default 9: overdispersed, "
                        "3 Cramér-Rao sd)")
    p.add_argument("--moves", choices=("independence", "de", "stretch"), default="independence",
                   help="emcee moves: independence (Student-t proposal around the ML estimate mixed with "
                        "differential evolution), de (differential evolution) or stretch (default independence)")
    p.add_argument("--defensive", type=float, default=0.0, metavar="W",
                   help="independence moves: fraction W of proposals drawn from a 2x wider component, which "
                        "bounds pi/q where the posterior reaches further than the proposal (default 0)")
    p.add_argument("--backend", default=None, metavar="FILE.h5",
                   help="HDF5 chain store; an existing one of the same run is resumed (default: --out with .h5)")
    p.add_argument("--replace-stale-backend", action="store_true",
                   help="a backend holding another run (other data or settings) is moved aside to FILE.stale.h5 "
                        "and the run starts afresh (default: refuse it)")
    p.add_argument("--integrator", choices=("rk4", "dopri5", "hybrid"), default=None,
                   help="integrator of the likelihood's simulations (default: the concept's, rk4): dopri5 is "
                        "1.6-2.7x faster, hybrid (exact steps where the model is linear, dopri5 elsewhere) "
                        "5-10x; their step selection jitters log L by ~1e-4, harmless to MCMC, which "
                        "needs no smooth objective (the ML fit does)")
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
    # the data's truth and constants: the rig priors centre on it, the likelihood simulates with it
    theta, constants = _model_vectors(model, args.set)
    parameters = model.parameters.with_nominal(model.parameters.as_dict(theta)).freeing_only(fit.free_names)
    measurements = _read_all(args.data, args.concept)
    problem = FitProblem(measurements, parameters=parameters, channels=fit.channels or None, constants=constants)
    settings = SamplerSettings(n_walkers=args.walkers, n_ensembles=args.chains, max_steps=args.max_steps,
                               check_every=args.check_every, spread=args.spread, moves=args.moves,
                               n_predictive=args.predictive, defensive_weight=args.defensive,
                               integrator=args.integrator)

    from .progress import Progress

    def progress(line: str) -> None:
        print(f"{PROG} sample: {line}", file=sys.stderr, flush=True)

    with Progress(settings.max_steps, f"{PROG} sample", "step", enabled=not args.quiet) as bar:
        result = sample(problem, fit, priors=priors, noise_sigma=args.noise_sigma, settings=settings, seed=args.seed,
                        backend=backend, progress=None if args.quiet else progress,
                        steps=lambda n: bar.update(n - bar.n), replace_stale_backend=args.replace_stale_backend)
    result.to_netcdf(out)
    table = result.summary()
    return (f"wrote {out}: {model.name} posterior of {len(result.names)} parameters, "
            f"{'converged' if result.converged else 'NOT converged (step cap)'} after {result.n_steps} steps, "
            f"max R-hat {table['r_hat'].max():.3f}, min bulk ESS {table['ess_bulk'].min():.0f}, "
            f"{result.wall_time_s:.1f} s (chains in {backend}"
            + (f"; the chains of another run found there were moved to {moved}" if (moved := result.attrs.get(
                "stale_backend_moved_to")) else "") + ")")


def _load_study_for(path: str, concept: str):
    """A validated study whose concept must be ``concept``."""
    from .study import load_study

    study = load_study(path)
    if study["concept"] != concept:
        raise CLIError(f"{path} is a study of concept {study['concept']}, but --concept {concept} was given; "
                       "use the study of the same concept")
    return study


def _chunk_spec(text: str) -> tuple[int, int]:
    index, sep, total = text.partition("/")
    try:
        if not sep:
            raise ValueError
        return int(index), int(total)
    except ValueError:
        raise argparse.ArgumentTypeError(f"cannot read {text!r}: write I/N, e.g. 0/8 (chunks are numbered from 0)") from None


def _add_sensitivity(subparsers) -> None:
    p = subparsers.add_parser(
        "sensitivity", help="global Sobol sensitivity (SALib) of the friction/damping parameters",
        description="Sobol indices (first, total, second order with bootstrap 95 % intervals) of the B_* and C_* "
                    "parameters over the study's ranges for the det R cost, per-channel RMS deviation, tracking "
                    "error, peak torque/current and energy, time-resolved indices of Omega, y1, I_A, and an N/2 vs N "
                    "convergence check. --chunk I/N evaluates one part of the design into a .npz; --gather "
                    "analyses all parts; without either everything runs in one process.")
    _add_concept(p)
    p.add_argument("--study", required=True, metavar="STUDY.yaml", help="ranges, budgets and seed (section sensitivity)")
    p.add_argument("--out", required=True, metavar="SOBOL.json|CHUNK.npz")
    group = p.add_mutually_exclusive_group()
    group.add_argument("--chunk", type=_chunk_spec, metavar="I/N", help="evaluate chunk I (from 0) of N and write it to --out (.npz)")
    group.add_argument("--gather", nargs="+", metavar="CHUNK.npz", help="analyse these evaluated chunks (all of one split)")
    p.add_argument("--n-base", type=int, default=None, metavar="N",
                   help="Sobol base samples (power of 2), overriding the study's sensitivity.n_base")
    p.set_defaults(handler=_run_sensitivity)


def _run_sensitivity(args: argparse.Namespace) -> str:
    from pathlib import Path

    from . import io
    from . import sensitivity as sobol
    from .provenance import provenance
    from .study import settings_for

    study = _load_study_for(args.study, args.concept)
    out = Path(args.out)
    if args.chunk is not None and out.suffix != ".npz":
        raise CLIError(f"--out {out}: a chunk is written as .npz; give e.g. chunk_{args.chunk[0]}.npz")
    if args.chunk is None and out.suffix != ".json":
        raise CLIError(f"--out {out}: Sobol indices are written as JSON; give e.g. sobol.json")
    io.prepare_output(out)
    design = settings_for(study, "sensitivity")["design"]
    setup = sobol.setup_from_study({"concept": study["concept"], **design}, n_base=args.n_base)
    from .progress import Progress

    if args.chunk is not None:
        index, total = args.chunk
        start, stop = sobol.chunk_rows(setup.n_evaluations, index, total)
        with Progress(stop - start, f"{PROG} sensitivity chunk {index}/{total}", "run") as bar:
            chunk = sobol.evaluate_chunk(setup, setup.design(), index, total, bar.update)
        chunk.save(out)
        rate = (chunk.stop - chunk.start) / chunk.wall_time_s if chunk.wall_time_s > 0 else float("nan")
        return (f"wrote {out}: {setup.concept} Sobol chunk {index}/{total}, runs {chunk.start}..{chunk.stop - 1} "
                f"of {setup.n_evaluations}, {chunk.wall_time_s:.1f} s ({rate:.1f} runs/s)")
    if args.gather:
        result = sobol.analyze_chunks(setup, [sobol.SobolChunk.load(path) for path in args.gather])
        inputs = list(args.gather)
    else:
        with Progress(setup.n_evaluations, f"{PROG} sensitivity", "run") as bar:
            result = sobol.run(setup, bar.update)
        inputs = []
    result.provenance = provenance([args.study, *inputs], seed=setup.seed,
                                   settings={"study": study.get("sensitivity"), "n_base": setup.n_base})
    io.write_json(out, result.to_json())
    return (f"wrote {out}: {setup.concept} Sobol indices of {len(setup.names)} parameters for "
            f"{len(setup.qoi_names)} QoI, N = {setup.n_base} ({result.n_evaluations} runs, "
            f"{result.evaluations_per_s:.1f} runs/s), {'converged' if result.converged else 'NOT converged'} (N/2 vs N)")


def _add_identifiability(subparsers) -> None:
    p = subparsers.add_parser(
        "identifiability", help="which parameters each sensor set can determine (FIM, collinearity, profiles)",
        description="From an ML fit (--init): Fisher information (rank, condition, named null directions), "
                    "correlations, Brun collinearity indices and profile likelihoods of the friction/damping "
                    "parameters, with a verdict per parameter and the identifiable combination of every lumped "
                    "group, for each sensor set (default: full instrumentation and the realistic rig set). "
                    "Before any fit (--at): the expected information at a point, on the noise-free outputs there "
                    "of the DATA's experiments (or --experiment) with --noise x each channel's RMS as the noise; "
                    "profiles are skipped (they need measured data's likelihood minimum), verdicts come from the "
                    "information matrix.")
    p.add_argument("data", nargs="*", metavar="DATA",
                   help="measurement files (.nc or .csv); with --at only their experiments (inputs) are used")
    _add_concept(p)
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--init", metavar="FIT.json", help="ML fit of the same concept (ema-uq identify)")
    where.add_argument("--at", metavar="nominal|PARAMS.json",
                       help="assess at this point without a fit: the nominal set (with --set / data.set), a FIT.json "
                            "or a JSON object {parameter: value} over the nominal set")
    p.add_argument("--experiment", nargs="+", default=None, metavar="NAME",
                   help="with --at and no DATA: the input profile(s) to assess (e.g. deploy-retract)")
    p.add_argument("--noise", type=_fraction, default=0.02, metavar="FRACTION",
                   help="with --at: sensor noise as a fraction of each channel's RMS (default: the study's data.noise, "
                        "else 0.02)")
    p.add_argument("--out", required=True, metavar="IDENT.json")
    _add_study(p, "sensor sets, profile settings, noise level and data.set (its design constants)")
    _add_set(p)
    p.add_argument("--sensor-sets", nargs="+", default=None, choices=("full", "realistic"), metavar="SET",
                   help="built-in sensor sets to assess: full, realistic (default: the study's, else both)")
    p.add_argument("--channels", nargs="+", default=None, metavar="NAME",
                   help="assess this one custom channel set instead")
    p.add_argument("--profile", nargs="+", default=None, metavar="NAME",
                   help="parameters to profile (default: every free B_* and C_*)")
    p.add_argument("--profile-points", type=int, default=9, metavar="N", help="grid points per profile (default 9)")
    p.add_argument("--profile-sigmas", type=float, default=4.0, metavar="K",
                   help="profile half-span in Cramér-Rao standard deviations (default 4)")
    p.add_argument("--profile-span", type=float, default=0.5, metavar="FRACTION",
                   help="relative half-span used instead when narrower or without a Cramér-Rao bound (default 0.5)")
    p.add_argument("--max-relative-width", type=float, default=1.0, metavar="FRACTION",
                   help="a closed 95 %% profile interval wider than this fraction of the estimate is practically "
                        "non-identifiable (default 1)")
    p.add_argument("--collinearity-threshold", type=float, default=20.0, metavar="GAMMA",
                   help="Brun collinearity index above which a subset is non-identifiable (default 20)")
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    p.set_defaults(handler=_run_identifiability)


def _run_identifiability(args: argparse.Namespace) -> str:
    from . import io
    from . import identifiability as ident
    from .models import get_model
    from .provenance import provenance

    model = get_model(args.concept)
    if args.profile_points < 3:
        raise CLIError(f"--profile-points {args.profile_points}: give at least 3")
    settings = ident.ProfileSettings.from_section(vars(args))
    if args.channels:
        sets = [{"name": "custom", "channels": _names(args.channels)}]
    else:
        sets = args.sensor_sets or ["full", "realistic"]
    theta, constants = _model_vectors(model, args.set)  # a fit holds the parameters; the data's constants
    io.prepare_output(args.out)
    if args.at is not None:
        result = _identifiability_at(args, model, sets, settings, theta, constants)
    else:
        if not args.data:
            raise CLIError("give the data the fit was made on (DATA), or --at to assess a point without a fit")
        fit = _read_fit(args.init, args.concept)
        measurements = _read_all(args.data, args.concept)

        def progress(line: str) -> None:
            print(f"{PROG} identifiability: {line}", file=sys.stderr, flush=True)

        # parameters the fit held because its channels cannot determine them are assessed as well
        free = [n for n in model.parameters.names if n in fit.free_names or n in fit.fixed]
        result = ident.sensor_set_study(measurements, fit.estimate, free, sets, settings=settings,
                                        profile_names=_names(args.profile),
                                        constants=constants, progress=None if args.quiet else progress)
    result.data = list(args.data)
    inputs = [*args.data] + ([args.init] if args.init else [] if args.at == "nominal" else [args.at])
    result.provenance = provenance(inputs, settings={k: v for k, v in vars(args).items() if k != "handler"})
    io.write_json(args.out, result.to_json())
    parts = []
    for name, r in result.sets.items():
        counts = [sum(v[0] == verdict for v in r.verdicts.values()) for verdict in ident.VERDICTS]
        parts.append(f"{name}: rank {r.info.rank}/{len(r.names)}, {counts[0]} identifiable, "
                     f"{counts[1]} practically and {counts[2]} structurally non-identifiable")
    parts += [f"{name} skipped ({why})" for name, why in result.skipped.items()]
    return f"wrote {args.out}: {model.name} " + "; ".join(parts)


def _read_point(text: str, model, theta):
    """The full parameter vector of ``--at``: ``nominal`` (``theta``, i.e. with --set), a FIT.json's
    estimate, or a JSON object {parameter: value} laid over ``theta``; checked against the bounds."""
    import numpy as np

    from . import io

    if text == "nominal":
        return theta
    data = io.read_json(text)
    if isinstance(data, dict) and "parameters" in data and "concept" in data:
        return _read_fit(text, model.name).estimate
    if not isinstance(data, dict) or not all(isinstance(v, (int, float)) for v in data.values()):
        raise CLIError(f"{text} is neither a FIT.json nor a JSON object of parameter values "
                       '(e.g. {"B_TS1": 0.4}); give one of these or --at nominal')
    unknown = [n for n in data if n not in model.parameters]
    if unknown:
        raise CLIError(f"{text}: unknown parameter {unknown[0]!r} for {model.name}; parameters: "
                       f"{', '.join(model.parameters.names)}")
    point = np.array(theta, dtype=float)
    for name, value in data.items():
        point[model.parameters.index(name)] = float(value)
    model.parameters.check_within_bounds(point, what=f"value in {text}")
    return point


def _identifiability_at(args, model, sets, settings, theta, constants):
    """The sensor-set study at ``--at`` without a fit (expected information, no profiles)."""
    from . import identifiability as ident
    from .experiments import get_experiment

    if args.data and args.experiment:
        raise CLIError("give either DATA (its experiments are used) or --experiment with --at, not both")
    if args.data:
        experiments = [m.experiment for m in _read_all(args.data, args.concept)]
    elif args.experiment:
        experiments = [get_experiment(name) for name in _names(args.experiment)]
    else:
        raise CLIError("--at needs the experiment to assess: give DATA files or --experiment (e.g. deploy-retract)")
    point = _read_point(args.at, model, theta)
    result = ident.sensor_set_study_at(model, experiments, point, model.parameters.free_names, sets,
                                       noise=args.noise, settings=settings, constants=constants)
    result.at = args.at
    return result


def _add_gap(subparsers) -> None:
    p = subparsers.add_parser(
        "gap", help="sim-to-real gap: where the nominal model departs from data, which effect causes it",
        description="Fit the nominal model by ML, localise its residual (channels, time, operating regimes, "
                    "shaft orders, residual tests), refit the model augmented by each catalogue effect, and "
                    "write the open-set verdict (effect / ambiguous / unexplained / none), the ranking and the held-out gap before "
                    "and after the winning effect to GAP.json. Held-out data: the --validate files, else the "
                    "last --holdout fraction of each DATA record.")
    _add_data(p)
    _add_concept(p)
    _add_study(p, "candidate effects, channels and data.set (its design constants)")
    _add_set(p)
    p.add_argument("--validate", nargs="+", default=[], metavar="DATA",
                   help="held-out data of the same concept (default: hold out the end of each DATA record)")
    p.add_argument("--holdout", type=_fraction, default=0.3, metavar="FRACTION",
                   help="fraction held out at the end of each record when no --validate is given (default 0.3)")
    p.add_argument("--candidates", nargs="+", metavar="EFFECT",
                   help="candidate effects (default: the concept's whole catalogue)")
    p.add_argument("--channels", nargs="+", metavar="NAME", help="use only these channels (default: all common)")
    p.add_argument("--figure", metavar="LEDGER.png", help="also write the gap ledger figure")
    _add_seed(p)
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    p.add_argument("--out", required=True, metavar="GAP.json")
    p.set_defaults(handler=_run_gap)


def _run_gap(args: argparse.Namespace) -> str:
    from dataclasses import replace

    from . import io
    from .gap import diagnose, strategy_for
    from .models import get_model
    from .provenance import provenance

    if not 0 < args.holdout < 1:
        raise CLIError(f"--holdout {args.holdout:g}: give a fraction between 0 and 1 (e.g. 0.3)")
    io.prepare_output(args.out)
    if args.figure:
        io.prepare_output(args.figure)
    measurements = _read_all(args.data, args.concept)
    validation_data = _read_all(args.validate, args.concept)
    channels = _names(args.channels)
    if channels is not None:  # the held-out channels follow: those of these the validation data have
        measurements = [m.select(channels) for m in measurements]

    def progress(line: str) -> None:
        print(f"{PROG} gap: {line}", file=sys.stderr, flush=True)

    model = get_model(measurements[0].concept)
    strategy = strategy_for(model)
    if args.set:  # the refits estimate the parameters; the data's design constants must be the simulator's
        if strategy.constants is not None:
            raise CLIError(f"concept {model.name} takes its design constants from each record; drop --set "
                           "(study key data.set)")
        _, constants = _model_vectors(model, args.set)
        strategy = replace(strategy, constants=lambda _record: constants)
    result = diagnose(measurements, validation_data, candidates=_names(args.candidates), strategy=strategy,
                      settings=replace(strategy.settings, holdout_fraction=args.holdout), seed=args.seed,
                      progress=None if args.quiet else progress)
    result.provenance = provenance(args.data + args.validate, seed=args.seed,
                                   settings={k: v for k, v in vars(args).items() if k != "handler"})
    io.write_json(args.out, result.to_json())
    tail = ""
    if args.figure:  # the rig's own figure where it has one (its study computes the arrays), else the ledger
        from .report.gap_figures import gap_figure
        from .rigs import rig_of

        rig = rig_of(model.name)
        data = (rig.gap_figure_data(result, validation_data or measurements)
                if rig is not None and rig.gap_figure_data is not None else None)
        gap_figure(model.name, result, data).savefig(args.figure, dpi=110)
        tail = f", ledger {args.figure}"
    what = result.headline()
    shrink = "" if result.gap["shrink"] is None else (f" (shrink {result.gap['shrink']:.2f} +/- "
                                                     f"{result.gap['shrink_se']:.2f} on the {result.gap['shrink_record']})")
    return (f"wrote {args.out}: {result.concept} verdict {what}; held-out gap {result.gap['before']:.3g} -> "
            f"{result.gap['after']:.3g}{shrink}, {result.wall_time_s:.0f} s{tail}")


def _add_gap_selfcheck(subparsers) -> None:
    p = subparsers.add_parser(
        "gap-selfcheck", help="blind self-check of the gap diagnosis on records of an independent simulator",
        description="Simulate seeded rig-like records with the independent simulator and effect variants "
                    "(ema_uq.gap.variants: every in-catalogue variant with random magnitudes and phases, "
                    "no-effect cases (every second one with model-form stress: coloured and quantised sensor "
                    "noise, design constants off, command shaping), effects outside the catalogue, and every "
                    "in-catalogue variant with its family left out of the catalogue; base parameters up to 10 "
                    "percent off nominal; full and realistic sensor sets), diagnose each without its label and "
                    "score the diagnosis: top-1 family accuracy, false alarms (a named effect on a no-effect "
                    "case), left-out and out-of-catalogue flagged ('unexplained' or 'ambiguous'), a wrong family "
                    "named with high confidence, honest shrink, confusion matrices. --quick runs 3 cases of the "
                    "first concept. Scatter: --chunk I/N runs every N-th case from the I-th; --gather joins the "
                    "parts into the result of one run.")
    _add_study(p, "seed, concept and set size (gap.selfcheck, gap.selfcheck_none_per_set)")
    p.add_argument("--quick", action="store_true", help="3 cases of the first concept instead of the full set")
    p.add_argument("--concepts", nargs="+", default=["htls", "lths"], metavar="C",
                   help="concepts of the full set (default htls lths)")
    p.add_argument("--sensors", nargs="+", default=["full", "realistic"], metavar="SET",
                   help="sensor sets: full (every output) and/or realistic (the rig's sensors); default both")
    p.add_argument("--none-per-set", type=_seed, default=5, metavar="N",
                   help="no-effect cases per concept and sensor set (default 5; the odd-numbered ones stressed)")
    p.add_argument("--kinds", nargs="+", default=["effect", "none", "out_of_catalogue", "left_out"], metavar="KIND",
                   help="case kinds to run: effect (in-catalogue variants), none, out_of_catalogue, left_out (a "
                        "variant diagnosed without its family's forms) (default all); e.g. --kinds none "
                        "--none-per-set 15 extends the false-alarm count")
    p.add_argument("--jobs", type=_seed, default=1, metavar="N",
                   help="worker processes; the results do not depend on N (default 1)")
    p.add_argument("--chunk", default=None, metavar="I/N",
                   help="run only the cases I, I+N, I+2N, ... of the full list, I from 0 (a part for --gather)")
    p.add_argument("--gather", nargs="+", default=None, metavar="PART.json",
                   help="join the parts of a --chunk run (0/N..N-1/N) into the result of one run; runs no case")
    p.add_argument("--cache", default=None, metavar="DIR",
                   help="keep each case's outcome in DIR and read it back on a rerun (resume)")
    _add_seed(p, default=2024)
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    p.add_argument("--out", required=True, metavar="SELFCHECK.json")
    p.set_defaults(handler=_run_gap_selfcheck)


def _run_gap_selfcheck(args: argparse.Namespace) -> str:
    from . import io
    from .gap.selfcheck import SelfCheckError, gather, parse_chunk, self_check
    from .provenance import provenance

    if args.jobs < 1:
        raise CLIError(f"--jobs {args.jobs}: give at least 1 worker process")
    io.prepare_output(args.out)

    def progress(line: str) -> None:
        print(f"{PROG} gap-selfcheck: {line}", file=sys.stderr, flush=True)

    try:
        if args.gather:
            if args.chunk:
                raise CLIError("--gather joins the parts of a run; give it without --chunk")
            result = gather([io.read_json(path) for path in args.gather])
            io.write_json(args.out, result.to_json())
            return f"wrote {args.out}: {len(result.outcomes)} cases gathered from {len(args.gather)} part(s); " + \
                _selfcheck_scores(result)
        result = self_check(seed=args.seed, quick=args.quick, concepts=_names(args.concepts), sensors=_names(args.sensors),
                            none_per_set=args.none_per_set, kinds=_names(args.kinds), jobs=args.jobs,
                            progress=None if args.quiet else progress, chunk=parse_chunk(args.chunk),
                            cache=args.cache)
    except SelfCheckError as exc:
        raise CLIError(str(exc)) from None
    result.provenance = provenance(seed=args.seed, settings={k: v for k, v in vars(args).items()
                                                             if k not in ("handler", "jobs", "chunk", "cache", "out")})
    io.write_json(args.out, result.to_json())
    part = f" (part {args.chunk})" if args.chunk else ""
    return f"wrote {args.out}: {len(result.outcomes)} cases{part}, " + _selfcheck_scores(result)


def _selfcheck_scores(result) -> str:
    status = result.status
    return (f"top-1 {result.top1_accuracy:.2f} ({status['top1_accuracy']}), false alarms "
            f"{result.false_alarm_rate:.2f} ({status['false_alarm_rate']}), out of catalogue flagged "
            f"{result.out_of_catalogue_rate:.2f} ({status['out_of_catalogue_flagged']}), left out flagged "
            f"{result.left_out_rate:.2f} ({status['left_out_flagged']}), wrong family with high confidence "
            f"{result.wrong_family_confident['value']:.2f} ({status['wrong_family_confident']}), "
            f"median honest shrink {result.shrink['median']:.2f}, {result.wall_time_s:.0f} s")


def _add_fault_diagnosis(subparsers) -> None:
    p = subparsers.add_parser(
        "fault-diagnosis", help="fit a real rig on its healthy records and diagnose its faulted record sets",
        description="Study of measured seeded-fault records (concept cranfield): the rig model is fitted on "
                    "healthy runs, then every record set is diagnosed by the gap diagnosis against that fit "
                    "(base parameters held, only effect parameters fitted; shrink scored on runs not used to "
                    "select the effect). Data folder: the study's data.path or EMA_UQ_CRANFIELD_DIR.")
    _add_study(p, "the data folder, channels and seed", required=True)
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    p.add_argument("--out", required=True, metavar="FAULTS.json")
    p.set_defaults(handler=_run_fault_diagnosis)


def _run_fault_diagnosis(args: argparse.Namespace) -> str:
    from . import io
    from .rigs.cranfield import CHANNELS, run_study
    from .provenance import provenance
    from .rigs import rig_of
    from .study import load_study

    study = load_study(args.study)
    rig = rig_of(study["concept"])
    if rig is None or not rig.fault_diagnosis:
        raise CLIError(f"{args.study} is a study of concept {study['concept']}; fault-diagnosis needs a "
                       "study of concept cranfield")
    channels = tuple(study["data"].get("channels") or CHANNELS)
    if channels != CHANNELS:
        raise CLIError(f"{args.study}: the fault diagnosis fits the channels {', '.join(CHANNELS)}; "
                       "drop data.channels or give exactly those")
    io.prepare_output(args.out)

    def read(name: str, runs):
        return io.read_cranfield(io.cranfield_file(name, study), runs=runs, channels=CHANNELS)

    def progress(line: str) -> None:
        print(f"{PROG} fault-diagnosis: {line}", file=sys.stderr, flush=True)

    result = run_study(read, seed=int(study.get("seed", 0)), progress=None if args.quiet else progress)
    payload = result.to_json()
    payload["provenance"] = provenance(seed=int(study.get("seed", 0)), settings={"study": args.study})
    io.write_json(args.out, payload)
    matches = sum(result.verdict_of(d.record_set) == result.expected.get(d.record_set) for d in result.diagnoses)
    verdicts = ", ".join(f"{d.record_set} {result.verdict_of(d.record_set)}" for d in result.diagnoses)
    return (f"wrote {args.out}: {matches} of {len(result.diagnoses)} record sets as expected ({verdicts}), "
            f"{result.wall_time_s:.0f} s")


def _add_report(subparsers) -> None:
    p = subparsers.add_parser("report", help="write the self-contained HTML report of a study",
                              description="Collect a study's result files into one HTML report with embedded figures.")
    p.add_argument("--study", required=True, metavar="STUDY.yaml")
    p.add_argument("--results", required=True, metavar="DIR", help="the study's results folder")
    p.add_argument("--out", required=True, metavar="REPORT.html")
    p.set_defaults(handler=_run_report)


def _run_report(args: argparse.Namespace) -> str:
    from pathlib import Path

    import time

    from .report import build_report, html
    from .study import load_study

    study = load_study(args.study)
    if not Path(args.results).is_dir():
        raise CLIError(f"results folder {args.results} does not exist; run the workflow first")
    t0 = time.perf_counter()
    html.PROGRESS = lambda line: print(f"{PROG} report: {line}, {time.perf_counter() - t0:.0f} s",
                                       file=sys.stderr, flush=True)
    try:
        text = build_report(study, args.study, args.results)
    finally:
        html.PROGRESS = None
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
# sbc
# --------------------------------------------------------------------------------------
def _add_sbc(subparsers) -> None:
    p = subparsers.add_parser(
        "sbc", help="simulation-based calibration of the posterior: one replicate, or gather them",
        description="--replicate I: replicate I of the SBC campaign of a study (truth drawn from the prior, "
                    "data simulated, ML fit, posterior sampled with the study's settings, ranks of the truth "
                    "among L thinned draws) written as JSON; resumable through --backend. --gather: join "
                    "replicate files into the rank-uniformity result (chi-square and KS p per parameter) "
                    "and, with --figure, the rank histograms.")
    _add_study(p, "concept, data, free parameters and sampler settings of the campaign")
    p.add_argument("--replicate", type=int, metavar="I", help="replicate index (0, 1, ...)")
    p.add_argument("--seed", type=_seed, default=0, help="campaign seed (default 0)")
    p.add_argument("--draws", type=int, default=99, metavar="L", help="thinned posterior draws per replicate (default 99)")
    p.add_argument("--prior-spread", type=float, default=0.1, metavar="S",
                   help="priors of the free parameters without a rig value: ln(theta) ~ N(ln nominal, S) (default 0.1)")
    p.add_argument("--backend", metavar="FILE.h5", help="sampler backend of the replicate (resumes a killed run)")
    p.add_argument("--gather", nargs="+", metavar="REPLICATE.json", help="replicate files to join")
    p.add_argument("--bins", type=int, default=10, help="rank bins of the uniformity tests (default 10)")
    p.add_argument("--figure", metavar="FILE.png", help="with --gather: rank histograms")
    p.add_argument("--out", required=True, metavar="FILE.json")
    p.set_defaults(handler=_run_sbc)


def _run_sbc(args: argparse.Namespace) -> str:
    import json

    from . import io
    from .bayes import sbc

    out = io.prepare_output(args.out)
    if args.gather:
        if args.replicate is not None:
            raise CLIError("give --replicate or --gather, not both")
        records = []
        for path in args.gather:
            with open(path) as fh:
                records.append(json.load(fh))
        result = sbc.gather_replicates(records, n_bins=args.bins)
        out.write_text(result.to_json())
        if args.figure:
            from .report.bayes_figures import sbc_rank_histogram

            sbc_rank_histogram(result).savefig(io.prepare_output(args.figure), dpi=110)
        return (f"wrote {out}: SBC of {result.n_replicates} replicates x {len(result.names)} parameters, "
                f"min chi-square p {result.min_p:.3f}, pooled p {result.pooled_uniformity()[1]:.3f}")
    if args.replicate is None or args.study is None:
        raise CLIError("give --study and --replicate I (one replicate) or --gather FILES")
    from .study import load_study

    campaign = sbc.campaign_from_study(load_study(args.study), prior_spread=args.prior_spread)
    record = sbc.sbc_replicate(**campaign, index=args.replicate, seed=args.seed, n_draws=args.draws,
                               backend=io.prepare_output(args.backend) if args.backend else None)
    out.write_text(json.dumps(record, indent=1))
    return (f"wrote {out}: SBC replicate {args.replicate}, ranks {record['ranks']} of {args.draws}, "
            f"{'converged' if record['converged'] else 'NOT converged'} after {record['n_steps']} steps, "
            f"{record['wall_time_s']:.1f} s")


# --------------------------------------------------------------------------------------
# compile
# --------------------------------------------------------------------------------------
def _add_compile(subparsers) -> None:
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

    from .compile import compile_kernels

    t0 = time.perf_counter()
    rows = compile_kernels(args.concept)
    total = time.perf_counter() - t0
    if args.out:
        with open(args.out, "w") as fh:
            json.dump({"seconds": total, "paths": rows}, fh, indent=1)
    skipped = sum(r["status"] != "ok" for r in rows)
    return (f"compiled {len(rows) - skipped} kernel paths in {total:.1f} s"
            + (f" ({skipped} not applicable)" if skipped else "") + (f" -> {args.out}" if args.out else ""))


# --------------------------------------------------------------------------------------
# entry point
# --------------------------------------------------------------------------------------
#: Register functions, one per verb, in the order ``--help`` lists them.
VERBS: tuple[Callable, ...] = (_add_simulate, _add_identify, _add_sample, _add_sensitivity,
                               _add_identifiability, _add_gap, _add_gap_selfcheck, _add_fault_diagnosis, _add_report, _add_check_study,
                               _add_screenshot, _add_sbc, _add_compile)


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
    from .study import STUDY_VERBS, load_study, settings_for

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


def main(argv: Sequence[str] | None = None) -> int:
    """Run one verb; returns the exit status (0 success, 2 bad input, 3 a fault of the package)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        _apply_study(args, _given_options(argv))
        if args.verb in SIMULATING_VERBS:
            from .progress import first_compile_notice

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


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
