"""The verbs that analyse a model around its parameters: ``sensitivity`` (global Sobol indices,
in one process or scattered in chunks) and ``identifiability`` (which parameters each sensor
set determines, from a fit or at a point before any fit). Numerics are imported inside the
handlers only.
"""
from __future__ import annotations

import argparse
import sys

from .arguments import (PROG, CLIError, add_concept, add_set, add_study, chunk_spec, load_study_for, model_vectors,
                        noise_fraction, positive_int, read_all, read_fit, run_provenance, split_names)


# --------------------------------------------------------------------------------------
# sensitivity
# --------------------------------------------------------------------------------------
def add_sensitivity(subparsers) -> None:
    p = subparsers.add_parser(
        "sensitivity", help="global Sobol sensitivity (SALib) of the friction/damping parameters",
        description="Sobol indices (first, total, second order with bootstrap 95 % intervals) of the B_* and C_* "
                    "parameters over the study's ranges for the det R cost, per-channel RMS deviation, tracking "
                    "error, peak torque/current and energy, time-resolved indices of Omega, y1, I_A, and an N/2 vs N "
                    "convergence check. --chunk I/N evaluates one part of the design into a .npz; --gather "
                    "analyses all parts; without either everything runs in one process.")
    add_concept(p)
    p.add_argument("--study", required=True, metavar="STUDY.yaml", help="ranges, budgets and seed (section sensitivity)")
    p.add_argument("--out", required=True, metavar="SOBOL.json|CHUNK.npz")
    group = p.add_mutually_exclusive_group()
    group.add_argument("--chunk", type=chunk_spec, metavar="I/N", help="evaluate chunk I (from 0) of N and write it to --out (.npz)")
    group.add_argument("--gather", nargs="+", metavar="CHUNK.npz", help="analyse these evaluated chunks (all of one split)")
    p.add_argument("--n-base", type=positive_int, default=None, metavar="N",
                   help="Sobol base samples (power of 2), overriding the study's sensitivity.n_base")
    p.set_defaults(handler=_run_sensitivity)


def _run_sensitivity(args: argparse.Namespace) -> str:
    from pathlib import Path

    from .. import io
    from .. import sensitivity as sobol
    from ..study import settings_for

    study = load_study_for(args.study, args.concept)
    out = Path(args.out)
    if args.chunk is not None and out.suffix != ".npz":
        raise CLIError(f"--out {out}: a chunk is written as .npz; give e.g. chunk_{args.chunk[0]}.npz")
    if args.chunk is None and out.suffix != ".json":
        raise CLIError(f"--out {out}: Sobol indices are written as JSON; give e.g. sobol.json")
    io.prepare_output(out)
    design = settings_for(study, "sensitivity")["design"]
    setup = sobol.setup_from_study({"concept": study["concept"], **design}, n_base=args.n_base)
    from ..progress import Progress

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
    result.provenance = run_provenance(args, [args.study, *inputs], seed=setup.seed,
                                       settings={"study": study.get("sensitivity"), "n_base": setup.n_base})
    io.write_json(out, result.to_json())
    return (f"wrote {out}: {setup.concept} Sobol indices of {len(setup.names)} parameters for "
            f"{len(setup.qoi_names)} QoI, N = {setup.n_base} ({result.n_evaluations} runs, "
            f"{result.evaluations_per_s:.1f} runs/s), {'converged' if result.converged else 'NOT converged'} (N/2 vs N)")


# --------------------------------------------------------------------------------------
# identifiability
# --------------------------------------------------------------------------------------
def add_identifiability(subparsers) -> None:
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
    add_concept(p)
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--init", metavar="FIT.json", help="ML fit of the same concept (ema-uq identify)")
    where.add_argument("--at", metavar="nominal|PARAMS.json",
                       help="assess at this point without a fit: the nominal set (with --set / data.set), a FIT.json "
                            "or a JSON object {parameter: value} over the nominal set")
    p.add_argument("--experiment", nargs="+", default=None, metavar="NAME",
                   help="with --at and no DATA: the input profile(s) to assess (e.g. deploy-retract)")
    p.add_argument("--noise", type=noise_fraction, default=0.02, metavar="FRACTION",
                   help="with --at: sensor noise as a fraction of each channel's RMS (default: the study's data.noise, "
                        "else 0.02)")
    p.add_argument("--out", required=True, metavar="IDENT.json")
    add_study(p, "sensor sets, profile settings, noise level and data.set (its design constants)")
    add_set(p)
    p.add_argument("--sensor-sets", nargs="+", default=None, choices=("full", "realistic"), metavar="SET",
                   help="built-in sensor sets to assess: full, realistic (default: the study's, else both)")
    p.add_argument("--channels", nargs="+", default=None, metavar="NAME",
                   help="assess this one custom channel set instead")
    p.add_argument("--profile", nargs="+", default=None, metavar="NAME",
                   help="parameters to profile (default: every free B_* and C_*)")
    p.add_argument("--profile-points", type=positive_int, default=9, metavar="N",
                   help="grid points per profile (default 9)")
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
    from .. import io
    from .. import identifiability as ident
    from ..models import get_model

    model = get_model(args.concept)
    if args.profile_points < 3:
        raise CLIError(f"--profile-points {args.profile_points}: give at least 3")
    settings = ident.ProfileSettings.from_section(vars(args))
    if args.channels:
        sets = [{"name": "custom", "channels": split_names(args.channels)}]
    else:
        sets = args.sensor_sets or ["full", "realistic"]
    theta, constants = model_vectors(model, args.set)  # a fit holds the parameters; the data's constants
    io.prepare_output(args.out)
    if args.at is not None:
        result = _identifiability_at(args, model, sets, settings, theta, constants)
    else:
        if not args.data:
            raise CLIError("give the data the fit was made on (DATA), or --at to assess a point without a fit")
        fit = read_fit(args.init, args.concept)
        measurements = read_all(args.data, args.concept)

        def progress(line: str) -> None:
            print(f"{PROG} identifiability: {line}", file=sys.stderr, flush=True)

        # parameters the fit held because its channels cannot determine them are assessed as well
        free = [n for n in model.parameters.names if n in fit.free_names or n in fit.fixed]
        result = ident.sensor_set_study(measurements, fit.estimate, free, sets, settings=settings,
                                        profile_names=split_names(args.profile),
                                        constants=constants, progress=None if args.quiet else progress)
    result.data = list(args.data)
    inputs = [*args.data] + ([args.init] if args.init else [] if args.at == "nominal" else [args.at])
    result.provenance = run_provenance(args, inputs)
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

    from .. import io

    if text == "nominal":
        return theta
    data = io.read_json(text)
    if isinstance(data, dict) and "parameters" in data and "concept" in data:
        return read_fit(text, model.name).estimate
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
    from .. import identifiability as ident
    from ..experiments import get_experiment

    if args.data and args.experiment:
        raise CLIError("give either DATA (its experiments are used) or --experiment with --at, not both")
    if args.data:
        experiments = [m.experiment for m in read_all(args.data, args.concept)]
    elif args.experiment:
        experiments = [get_experiment(name) for name in split_names(args.experiment)]
    else:
        raise CLIError("--at needs the experiment to assess: give DATA files or --experiment (e.g. deploy-retract)")
    point = _read_point(args.at, model, theta)
    result = ident.sensor_set_study_at(model, experiments, point, model.parameters.free_names, sets,
                                       noise=args.noise, settings=settings, constants=constants)
    result.at = args.at
    return result
