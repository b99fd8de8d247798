"""The verbs that make measurement data and estimate parameters from it: ``simulate``,
``identify`` (maximum likelihood), ``sample`` (the Bayesian posterior) and ``sbc`` (the
calibration of that posterior). Each is an ``add_<verb>`` that registers its parser and a
``_run_<verb>`` handler that turns the arguments into package calls and files; numerics are
imported inside the handlers only.
"""
from __future__ import annotations

import argparse
import sys

from .arguments import (EXPERIMENT_NAMES, PROG, UNIDENTIFIABLE_MODES, CLIError, add_concept, add_data, add_seed,
                        add_set, add_study, check_figure_path, fraction, model_vectors, noise_fraction,
                        non_negative_int, positive_int, read_all, read_fit, resolve_effects, run_provenance,
                        split_names)


# --------------------------------------------------------------------------------------
# simulate
# --------------------------------------------------------------------------------------
def add_simulate(subparsers) -> None:
    from ..study import DATA_ROLES

    p = subparsers.add_parser(
        "simulate", help="simulate a reference experiment and write noisy measurement data",
        description="Simulate a concept on a reference experiment (nominal parameters unless --set) "
                    "and write the outputs plus Gaussian white noise (fraction of each channel's RMS) "
                    "to a NetCDF (.nc) or CSV (.csv) file.")
    add_concept(p)
    add_study(p, "experiment, noise, seed, data.set, channels and (rig roles) hidden effects of a data role")
    p.add_argument("--role", choices=tuple(DATA_ROLES), default=None,
                   help="with --study: which of the study's records to write")
    p.add_argument("--experiment", choices=EXPERIMENT_NAMES, default=None,
                   help="input profile (required without --study)")
    p.add_argument("--noise", type=noise_fraction, default=0.02, metavar="FRACTION",
                   help="noise standard deviation as a fraction of each channel's RMS (default 0.02)")
    add_seed(p)
    add_set(p)
    p.add_argument("--effect", action="append", default=[], metavar="NAME[:param=value,...]",
                   help="add an unmodelled effect from the catalogue; repeatable")
    p.add_argument("--channels", nargs="+", metavar="NAME",
                   help="write only these output channels (default: all)")
    p.add_argument("--out", required=True, metavar="FILE.{nc,csv}", help="measurement file to write")
    p.set_defaults(handler=_run_simulate)


def _run_simulate(args: argparse.Namespace) -> str:
    from pathlib import Path

    from .. import io
    from ..experiments import get_experiment, synthesize
    from ..models import get_model

    if args.experiment is None:
        raise CLIError("give --experiment, or --study with --role")
    model, effects = resolve_effects(get_model(args.concept), args.effect)
    theta, constants = model_vectors(model, args.set)  # --set also reaches effect parameters
    channels = split_names(args.channels)
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


# --------------------------------------------------------------------------------------
# identify
# --------------------------------------------------------------------------------------
def add_identify(subparsers) -> None:
    p = subparsers.add_parser(
        "identify", help="maximum-likelihood parameter estimation (det R; Gauss-Newton or Levenberg-Marquardt)",
        description="Estimate the free parameters from one or more measurement files by output-error "
                    "maximum likelihood (cost det R) and write estimates, Cramér-Rao bounds, correlations "
                    "and the iteration history to FIT.json.")
    add_data(p)
    add_concept(p)
    add_study(p, "seed, start perturbation, iteration cap, fixed parameters, channels and data.set")
    p.add_argument("--method", choices=("gn", "lm"), default="gn",
                   help="gn: Gauss-Newton with step halving; lm: Levenberg-Marquardt (default gn)")
    p.add_argument("--start", default="nominal", metavar="nominal|FIT.json",
                   help="start values: the nominal set or the estimate of an earlier fit")
    p.add_argument("--perturb", type=fraction, default=0.0, metavar="FRACTION",
                   help="scale each free start value by 1+U(-FRACTION, FRACTION), seeded by --seed")
    add_seed(p)
    add_set(p)
    p.add_argument("--fix", nargs="+", default=[], metavar="NAME", help="hold these parameters at their value")
    p.add_argument("--channels", nargs="+", metavar="NAME", help="fit only these channels (default: all common)")
    p.add_argument("--unidentifiable", choices=UNIDENTIFIABLE_MODES, default="fix",
                   help="when the channels cannot determine every free parameter (singular information matrix at "
                        "the start): fix holds the undetermined ones at their start values, estimates the rest and "
                        "reports the identifiable combinations; error stops naming the direction (default fix)")
    p.add_argument("--validate", nargs="+", default=[], metavar="DATA",
                   help="data NOT used for estimation: report per-channel fit and residual tests")
    p.add_argument("--max-iterations", type=positive_int, default=50, metavar="N")
    p.add_argument("--out", required=True, metavar="FIT.json")
    p.set_defaults(handler=_run_identify)


def _run_identify(args: argparse.Namespace) -> str:
    from .. import io
    from ..identify import FitProblem, Settings, estimate, perturbed_start
    from ..identify.validation import validate
    from ..models import get_model
    from ..rigs import rig_of

    model = get_model(args.concept)
    theta, constants = model_vectors(model, args.set)
    parameters = model.parameters.with_nominal(model.parameters.as_dict(theta)).fixing(args.fix)
    io.prepare_output(args.out)
    measurements = read_all(args.data, args.concept)
    validation_data = read_all(args.validate, args.concept)
    problem = FitProblem(measurements, parameters=parameters, channels=split_names(args.channels), constants=constants)
    start = theta if args.start == "nominal" else read_fit(args.start, args.concept).estimate
    if args.perturb > 0:
        start = perturbed_start(parameters, args.perturb, args.seed, around=start)
    from ..progress import Progress

    with Progress(args.max_iterations, f"{PROG} identify {args.method}", "iteration") as bar:
        def progress(iteration: int, line: str) -> None:
            bar.update(iteration - bar.n, line)

        fit = estimate(problem, method=args.method, start=start, seed=args.seed,
                       settings=Settings(max_iterations=args.max_iterations), unidentifiable=args.unidentifiable,
                       progress=progress)
    fit.provenance = run_provenance(args, args.data + args.validate, seed=args.seed)
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
    from ..report.outputs import fit_outputs_path, write_fit_outputs
    from ..rigs import rig_of
    from ..simulate import simulate_batch

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


# --------------------------------------------------------------------------------------
# sample
# --------------------------------------------------------------------------------------
def add_sample(subparsers) -> None:
    p = subparsers.add_parser(
        "sample", help="Bayesian posterior by emcee, started from an ML fit; ArviZ NetCDF output",
        description="Sample the posterior of the init fit's free parameters (det R or known-sigma likelihood, "
                    "flat/lognormal/uniform priors, rig priors of p_ACE and p_PCE) with independent emcee "
                    "ensembles until every chain is longer than 50 autocorrelation times, and write the "
                    "ArviZ InferenceData to POSTERIOR.nc. The HDF5 backend lets a killed run resume.")
    add_data(p)
    add_concept(p)
    p.add_argument("--init", required=True, metavar="FIT.json", help="ML fit of the same concept (ema-uq identify)")
    p.add_argument("--out", required=True, metavar="POSTERIOR.nc")
    add_study(p, "seed, sampler budgets, moves, integrator and data.set")
    add_seed(p)
    add_set(p)
    p.add_argument("--walkers", type=positive_int, default=None, metavar="N",
                   help="walkers per ensemble (default 16 for --moves independence, else "
                        "max(2 x free parameters, 16))")
    p.add_argument("--chains", "--ensembles", dest="chains", type=positive_int, default=4, metavar="N",
                   help="independent ensembles; R-hat and ESS compare them (default 4)")
    p.add_argument("--max-steps", type=positive_int, default=20000, metavar="N",
                   help="step cap per ensemble (default 20000)")
    p.add_argument("--check-every", type=positive_int, default=50, metavar="N",
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
    p.add_argument("--predictive", type=non_negative_int, default=100, metavar="N",
                   help="posterior draws simulated for the predictive group (default 100)")
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    p.set_defaults(handler=_run_sample)


def _run_sample(args: argparse.Namespace) -> str:
    from pathlib import Path

    from .. import io
    from ..bayes import BayesError, SamplerSettings, parse_prior, sample
    from ..identify import FitProblem
    from ..models import get_model

    if args.walkers is not None and args.walkers < 2:
        raise CLIError(f"--walkers {args.walkers}: give at least 2 walkers")
    out = io.prepare_output(args.out)
    if out.suffix.lower() != ".nc":
        raise CLIError(f"--out {out}: the posterior is written as ArviZ NetCDF; give a .nc file, e.g. posterior.nc")
    backend = Path(args.backend) if args.backend else out.with_suffix(".h5")
    if backend.resolve() == out.resolve():
        raise CLIError(f"--backend {backend} is the --out file; the chains and the posterior need two files")
    io.prepare_output(backend)
    priors = {}
    for text in args.prior:
        name, kind, a, b = parse_prior(text)
        if name in priors:
            raise BayesError(f"--prior {name} given twice; give one prior per parameter")
        priors[name] = (kind, a, b)
    fit = read_fit(args.init, args.concept)
    model = get_model(args.concept)
    # the data's truth and constants: the rig priors centre on it, the likelihood simulates with it
    theta, constants = model_vectors(model, args.set)
    parameters = model.parameters.with_nominal(model.parameters.as_dict(theta)).freeing_only(fit.free_names)
    measurements = read_all(args.data, args.concept)
    problem = FitProblem(measurements, parameters=parameters, channels=fit.channels or None, constants=constants)
    settings = SamplerSettings(n_walkers=args.walkers, n_ensembles=args.chains, max_steps=args.max_steps,
                               check_every=args.check_every, spread=args.spread, moves=args.moves,
                               n_predictive=args.predictive, defensive_weight=args.defensive,
                               integrator=args.integrator)

    from ..progress import Progress

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


# --------------------------------------------------------------------------------------
# sbc
# --------------------------------------------------------------------------------------
def add_sbc(subparsers) -> None:
    p = subparsers.add_parser(
        "sbc", help="simulation-based calibration of the posterior: one replicate, or gather them",
        description="--replicate I: replicate I of the SBC campaign of a study (truth drawn from the prior, "
                    "data simulated, ML fit, posterior sampled with the study's settings, ranks of the truth "
                    "among L thinned draws) written as JSON; resumable through --backend. --gather: join "
                    "replicate files into the rank-uniformity result (chi-square and KS p per parameter) "
                    "and, with --figure, the rank histograms.")
    add_study(p, "concept, data, free parameters and sampler settings of the campaign")
    p.add_argument("--replicate", type=non_negative_int, metavar="I", help="replicate index (0, 1, ...)")
    p.add_argument("--seed", type=non_negative_int, default=0, help="campaign seed (default 0)")
    p.add_argument("--draws", type=positive_int, default=99, metavar="L",
                   help="thinned posterior draws per replicate (default 99)")
    p.add_argument("--prior-spread", type=float, default=0.1, metavar="S",
                   help="priors of the free parameters without a rig value: ln(theta) ~ N(ln nominal, S) (default 0.1)")
    p.add_argument("--backend", metavar="FILE.h5", help="sampler backend of the replicate (resumes a killed run)")
    p.add_argument("--gather", nargs="+", metavar="REPLICATE.json", help="replicate files to join")
    p.add_argument("--bins", type=positive_int, default=10, help="rank bins of the uniformity tests (default 10)")
    p.add_argument("--figure", metavar="FILE.png", help="with --gather: rank histograms")
    p.add_argument("--out", required=True, metavar="FILE.json")
    p.set_defaults(handler=_run_sbc)


def _run_sbc(args: argparse.Namespace) -> str:
    import json

    from .. import io
    from ..bayes import sbc

    if args.figure:
        check_figure_path(args.figure)
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
            from ..report.bayes_figures import sbc_rank_histogram

            sbc_rank_histogram(result).savefig(io.prepare_output(args.figure), dpi=110)
        return (f"wrote {out}: SBC of {result.n_replicates} replicates x {len(result.names)} parameters, "
                f"min chi-square p {result.min_p:.3f}, pooled p {result.pooled_uniformity()[1]:.3f}")
    if args.replicate is None or args.study is None:
        raise CLIError("give --study and --replicate I (one replicate) or --gather FILES")
    from ..study import load_study

    campaign = sbc.campaign_from_study(load_study(args.study), prior_spread=args.prior_spread)
    record = sbc.sbc_replicate(**campaign, index=args.replicate, seed=args.seed, n_draws=args.draws,
                               backend=io.prepare_output(args.backend) if args.backend else None)
    out.write_text(json.dumps(record, indent=1))
    return (f"wrote {out}: SBC replicate {args.replicate}, ranks {record['ranks']} of {args.draws}, "
            f"{'converged' if record['converged'] else 'NOT converged'} after {record['n_steps']} steps, "
            f"{record['wall_time_s']:.1f} s")
