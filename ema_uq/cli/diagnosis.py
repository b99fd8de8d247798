"""The verbs of the sim-to-real gap: ``gap`` (diagnose one set of records), ``gap-selfcheck``
(the blind self-check of that diagnosis on an independent simulator) and ``fault-diagnosis``
(the measured seeded-fault records of a real rig against its healthy fit). Numerics are
imported inside the handlers only.
"""
from __future__ import annotations

import argparse
import sys

from .arguments import (PROG, CLIError, add_concept, add_data, add_seed, add_set, add_study, check_figure_path,
                        fraction, model_vectors, non_negative_int, read_all, run_provenance, split_names)


# --------------------------------------------------------------------------------------
# gap
# --------------------------------------------------------------------------------------
def add_gap(subparsers) -> None:
    p = subparsers.add_parser(
        "gap", help="sim-to-real gap: where the nominal model departs from data, which effect causes it",
        description="Fit the nominal model by ML, localise its residual (channels, time, operating regimes, "
                    "shaft orders, residual tests), refit the model augmented by each catalogue effect, and "
                    "write the open-set verdict (effect / ambiguous / unexplained / none), the ranking and the held-out gap before "
                    "and after the winning effect to GAP.json. Held-out data: the --validate files, else the "
                    "last --holdout fraction of each DATA record.")
    add_data(p)
    add_concept(p)
    add_study(p, "candidate effects, channels and data.set (its design constants)")
    add_set(p)
    p.add_argument("--validate", nargs="+", default=[], metavar="DATA",
                   help="held-out data of the same concept (default: hold out the end of each DATA record)")
    p.add_argument("--holdout", type=fraction, default=0.3, metavar="FRACTION",
                   help="fraction held out at the end of each record when no --validate is given (default 0.3)")
    p.add_argument("--candidates", nargs="+", metavar="EFFECT",
                   help="candidate effects (default: the concept's whole catalogue)")
    p.add_argument("--channels", nargs="+", metavar="NAME", help="use only these channels (default: all common)")
    p.add_argument("--figure", metavar="LEDGER.png", help="also write the gap ledger figure")
    add_method_version(p)
    add_seed(p)
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    p.add_argument("--out", required=True, metavar="GAP.json")
    p.set_defaults(handler=_run_gap)


def add_method_version(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--method-version", type=int, default=None, metavar="N",
                        help="gap method version (docs/gap-diagnosis.md: what each changed; default: the "
                             "package's default version); HT/LS and LT/HS only")


def _method_switches(version: int | None, concept: str | None = None) -> dict:
    """The settings switches of ``--method-version`` (none without it), refused for a measured rig
    (``concept`` None: records of the synthetic concepts, as the self-check's)."""
    from ..gap.strategy import method_switches
    from ..rigs import is_measured, no_method_version

    if version is None:
        return {}
    if concept is not None and is_measured(concept):
        raise CLIError(f"--method-version {version}: {no_method_version(concept)}; drop the option")
    try:
        return method_switches(version)
    except ValueError as exc:
        raise CLIError(f"--method-version {version}: {exc}") from None


def _run_gap(args: argparse.Namespace) -> str:
    from dataclasses import replace

    from .. import io
    from ..gap import diagnose, strategy_for
    from ..gap.strategy import method_version_of
    from ..models import get_model
    from ..rigs import is_measured

    if not 0 < args.holdout < 1:
        raise CLIError(f"--holdout {args.holdout:g}: give a fraction between 0 and 1 (e.g. 0.3)")
    if args.figure:
        check_figure_path(args.figure)
    io.prepare_output(args.out)
    if args.figure:
        io.prepare_output(args.figure)
    measurements = read_all(args.data, args.concept)
    validation_data = read_all(args.validate, args.concept)
    channels = split_names(args.channels)
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
        _, constants = model_vectors(model, args.set)
        strategy = replace(strategy, constants=lambda _record: constants)
    settings = replace(strategy.settings, holdout_fraction=args.holdout,
                       **_method_switches(args.method_version, model.name))
    result = diagnose(measurements, validation_data, candidates=split_names(args.candidates), strategy=strategy,
                      settings=settings, seed=args.seed,
                      progress=None if args.quiet else progress)
    result.provenance = run_provenance(args, args.data + args.validate, seed=args.seed)
    # which method decided, in the file itself (a measured rig's strategy has no version)
    io.write_json(args.out, {**result.to_json(),
                             "method_version": None if is_measured(model.name) else method_version_of(settings)})
    tail = ""
    if args.figure:  # the rig's own figure where it has one (its study computes the arrays), else the ledger
        from ..report.gap_figures import gap_figure
        from ..rigs import rig_of

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


# --------------------------------------------------------------------------------------
# gap-selfcheck
# --------------------------------------------------------------------------------------
def add_gap_selfcheck(subparsers) -> None:
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
    add_study(p, "seed, concept and set size (gap.selfcheck, gap.selfcheck_none_per_set)")
    p.add_argument("--quick", action="store_true", help="3 cases of the first concept instead of the full set")
    p.add_argument("--concepts", nargs="+", default=["htls", "lths"], metavar="C",
                   help="concepts of the full set (default htls lths)")
    p.add_argument("--sensors", nargs="+", default=["full", "realistic"], metavar="SET",
                   help="sensor sets: full (every output) and/or realistic (the rig's sensors); default both")
    p.add_argument("--none-per-set", type=non_negative_int, default=5, metavar="N",
                   help="no-effect cases per concept and sensor set (default 5; the odd-numbered ones stressed)")
    p.add_argument("--kinds", nargs="+", default=["effect", "none", "out_of_catalogue", "left_out"], metavar="KIND",
                   help="case kinds to run: effect (in-catalogue variants), none, out_of_catalogue, left_out (a "
                        "variant diagnosed without its family's forms) (default all); e.g. --kinds none "
                        "--none-per-set 15 extends the false-alarm count")
    p.add_argument("--jobs", type=non_negative_int, default=1, metavar="N",
                   help="worker processes; the results do not depend on N (default 1)")
    p.add_argument("--chunk", default=None, metavar="I/N",
                   help="run only the cases I, I+N, I+2N, ... of the full list, I from 0 (a part for --gather)")
    p.add_argument("--gather", nargs="+", default=None, metavar="PART.json",
                   help="join the parts of a --chunk run (0/N..N-1/N) into the result of one run; runs no case")
    p.add_argument("--cache", default=None, metavar="DIR",
                   help="keep each case's outcome in DIR and read it back on a rerun (resume)")
    add_method_version(p)
    add_seed(p, default=2024)
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    p.add_argument("--out", required=True, metavar="SELFCHECK.json")
    p.set_defaults(handler=_run_gap_selfcheck)


def _run_gap_selfcheck(args: argparse.Namespace) -> str:
    from .. import io
    from ..gap.selfcheck import SelfCheckError, gather, parse_chunk, self_check
    from ..gap.strategy import DiagnosisSettings

    switches = _method_switches(args.method_version)
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
            _refuse_failed_cases(result, args.out)
            return f"wrote {args.out}: {len(result.outcomes)} cases gathered from {len(args.gather)} part(s); " + \
                _selfcheck_scores(result)
        result = self_check(seed=args.seed, quick=args.quick, concepts=split_names(args.concepts), sensors=split_names(args.sensors),
                            none_per_set=args.none_per_set, kinds=split_names(args.kinds), jobs=args.jobs,
                            progress=None if args.quiet else progress, chunk=parse_chunk(args.chunk),
                            cache=args.cache, settings=DiagnosisSettings(**switches) if switches else None)
    except SelfCheckError as exc:
        raise CLIError(str(exc)) from None
    # how the cases are scattered and where they are cached cannot change a score
    result.provenance = run_provenance(args, seed=args.seed, leave_out=("jobs", "chunk", "cache", "out"))
    io.write_json(args.out, result.to_json())
    _refuse_failed_cases(result, args.out)
    part = f" (part {args.chunk})" if args.chunk else ""
    return f"wrote {args.out}: {len(result.outcomes)} cases{part}, " + _selfcheck_scores(result)


class SelfCheckFault(RuntimeError):
    """Self-check cases whose diagnosis raised: a fault of the package, not of the input."""


def _refuse_failed_cases(result, out) -> None:
    """End the run as a fault (exit status 3) when a case's diagnosis raised: its scores would
    count a crash as a wrong verdict, and a workflow would report them as the method's. The
    outcomes are written first, so the cases that did run are kept."""
    failed = [o for o in result.outcomes if o.verdict == "error"]
    if failed:
        first = failed[0]
        raise SelfCheckFault(f"{len(failed)} of {len(result.outcomes)} self-check cases ended in an error (first: "
                             f"{first.case.case_id}: {first.message}); the outcomes are in {out}, but no score of "
                             "this run stands for the method")


def _selfcheck_scores(result) -> str:
    status = result.status
    return (f"top-1 {result.top1_accuracy:.2f} ({status['top1_accuracy']}), false alarms "
            f"{result.false_alarm_rate:.2f} ({status['false_alarm_rate']}), out of catalogue flagged "
            f"{result.out_of_catalogue_rate:.2f} ({status['out_of_catalogue_flagged']}), left out flagged "
            f"{result.left_out_rate:.2f} ({status['left_out_flagged']}), wrong family with high confidence "
            f"{result.wrong_family_confident['value']:.2f} ({status['wrong_family_confident']}), "
            f"median honest shrink {result.shrink['median']:.2f}, {result.wall_time_s:.0f} s")


# --------------------------------------------------------------------------------------
# fault-diagnosis
# --------------------------------------------------------------------------------------
def add_fault_diagnosis(subparsers) -> None:
    p = subparsers.add_parser(
        "fault-diagnosis", help="fit a real rig on its healthy records and diagnose its faulted record sets",
        description="Study of measured seeded-fault records (concept cranfield): the rig model is fitted on "
                    "healthy runs, then every record set is diagnosed by the gap diagnosis against that fit "
                    "(base parameters held, only effect parameters fitted; shrink scored on runs not used to "
                    "select the effect). Data folder: the study's data.path or EMA_UQ_CRANFIELD_DIR.")
    add_study(p, "the data folder, channels and seed", required=True)
    p.add_argument("--splits", choices=("none", "all"), default=None,
                   help="all: also run the study under every leave-half-the-runs-out split of the ten runs and "
                        "report each record set's verdict counts (default: the study's gap.fault_splits)")
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    p.add_argument("--out", required=True, metavar="FAULTS.json")
    p.set_defaults(handler=_run_fault_diagnosis)


def _run_fault_diagnosis(args: argparse.Namespace) -> str:
    from .. import io
    from ..rigs.cranfield import CHANNELS, run_split_study, run_study
    from ..rigs import rig_of
    from ..study import load_study

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

    records = io.CranfieldRecords(study, CHANNELS)   # each file read once: the run splits ask for it again
    read, runs_of = records.read, records.runs_of

    def progress(line: str) -> None:
        print(f"{PROG} fault-diagnosis: {line}", file=sys.stderr, flush=True)

    record_sets = io.cranfield_record_sets(study)
    named = bool((study.get("data") or {}).get("record_sets"))

    for name in record_sets:                    # every file readable before the healthy fit starts
        try:
            runs_of(name)
        except io.DataFileError as exc:
            if named or name in io.CRANFIELD_FILES:
                raise
            raise io.DataFileError(f"{exc}; it was read because it lies in the data folder: move it out, or list "
                                   "the record sets to read in the study's data.record_sets") from None

    result = run_study(read, seed=int(study.get("seed", 0)), progress=None if args.quiet else progress,
                       record_sets=record_sets, runs_of=runs_of)
    payload = result.to_json()
    splits = args.splits or (study.get("gap") or {}).get("fault_splits", "none")
    split_line, wall = "", result.wall_time_s
    if splits == "all":
        table = run_split_study(read, record_sets=record_sets, runs_of=runs_of, seed=int(study.get("seed", 0)),
                                progress=None if args.quiet else progress)
        payload["splits"] = table.to_json()
        normal = table.counts.get("normal", {})
        split_line = (f"; over {len(table.rows)} run splits normal none in {normal.get('none', 0)} of "
                      f"{sum(normal.values())}")
        wall += table.wall_time_s
    payload["provenance"] = run_provenance(args, seed=int(study.get("seed", 0)),
                                           settings={"study": args.study, "splits": splits})
    io.write_json(args.out, payload)
    labelled = [d for d in result.diagnoses if d.record_set in result.expected]
    matches = sum(result.verdict_of(d.record_set) == result.expected[d.record_set] for d in labelled)
    verdicts = ", ".join(f"{d.record_set} {result.verdict_of(d.record_set)}" for d in result.diagnoses)
    unlabelled = len(result.diagnoses) - len(labelled)
    return (f"wrote {args.out}: {matches} of {len(labelled)} record sets of known fault as expected"
            + (f", {unlabelled} of no known fault" if unlabelled else "")
            + f" ({verdicts}){split_line}, {wall:.0f} s")
