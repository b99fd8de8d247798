"""What the verbs of the command line share: the program's name and the names it knows without
loading the numerics, the argument types and the options several verbs take, and the
translation of argument values into package objects (parameter vectors, effects, measurement
files, fits, studies) and into the provenance block every result records.

Nothing here imports numpy or a model at module level: ``ema-uq --help`` builds every verb's
parser from this module alone.
"""
from __future__ import annotations

import argparse
import math
from typing import Sequence

from ..errors import EmaUqError

PROG = "ema-uq"
#: answers of ``identify --unidentifiable`` (ema_uq.identify.UNIDENTIFIABLE_MODES; not imported
#: here, the parser builds without loading the numerics)
UNIDENTIFIABLE_MODES = ("fix", "error")
#: concepts (ema_uq.models.concepts()) and reference experiments (ema_uq.experiments.EXPERIMENTS)
#: named here for the same reason: ``--help`` loads neither numpy nor numba (a test keeps them equal)
CONCEPTS = ("cranfield", "emps", "htls", "lths")
EXPERIMENT_NAMES = ("deploy-retract", "validation")


class CLIError(EmaUqError):
    """A command-line value that the package cannot use."""


# --------------------------------------------------------------------------------------
# argument types and options shared by several verbs
# --------------------------------------------------------------------------------------
def fraction(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (math.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"{text!r} must be a finite fraction >= 0")
    return value


def noise_fraction(text: str) -> float:
    """A noise level: a fraction of each channel's RMS, at most 0.5 (as the study schema's data.noise)."""
    value = fraction(text)
    if value > 0.5:
        raise argparse.ArgumentTypeError(f"{text!r} is over 0.5: the noise is a fraction of each channel's RMS "
                                         "(0.02 is 2 %)")
    return value


#: file types a figure can be written as (matplotlib's savefig chooses the format by the suffix)
FIGURE_SUFFIXES = (".png", ".pdf", ".svg", ".jpg", ".jpeg", ".eps", ".ps", ".tif", ".tiff", ".webp")


def check_figure_path(path: str, option: str = "--figure") -> None:
    """A figure path whose suffix matplotlib can write, checked before any work is done."""
    import os

    suffix = os.path.splitext(path)[1].lower()
    if suffix not in FIGURE_SUFFIXES:
        kind = suffix or "a file without suffix"
        raise CLIError(f"{option} {path}: cannot write a figure as {kind}; end the name in one of "
                       f"{', '.join(FIGURE_SUFFIXES)}")


def _whole_number(text: str, minimum: int, kind: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if value < minimum:
        raise argparse.ArgumentTypeError(f"{text!r} must be a {kind} integer")
    return value


def positive_int(text: str) -> int:
    return _whole_number(text, 1, "positive")


def non_negative_int(text: str) -> int:
    return _whole_number(text, 0, "non-negative")


def split_names(values: Sequence[str] | None) -> list[str] | None:
    """Names given space- or comma-separated (``--channels Omega y1`` or ``Omega,y1``)."""
    if values is None:
        return None
    return [n.strip() for v in values for n in v.split(",") if n.strip()]


def chunk_spec(text: str) -> tuple[int, int]:
    index, sep, total = text.partition("/")
    try:
        if not sep:
            raise ValueError
        return int(index), int(total)
    except ValueError:
        raise argparse.ArgumentTypeError(f"cannot read {text!r}: write I/N, e.g. 0/8 (chunks are numbered from 0)") from None


def add_concept(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--concept", required=True, choices=CONCEPTS, help="actuator concept")


def add_seed(parser: argparse.ArgumentParser, default: int = 0) -> None:
    parser.add_argument("--seed", type=non_negative_int, default=default, metavar="N",
                        help=f"seed of the random generator (default {default})")


def add_set(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                        help="override an estimated parameter or a design constant (SI units); repeatable; "
                             "laid over the study's data.set")


def add_study(parser: argparse.ArgumentParser, what: str, required: bool = False) -> None:
    parser.add_argument("--study", required=required, default=None, metavar="STUDY.yaml",
                        help=f"take {what} from this study (options given here override it)")


def add_data(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("data", nargs="+", metavar="DATA", help="measurement files (.nc or .csv)")


# --------------------------------------------------------------------------------------
# argument values as package objects
# --------------------------------------------------------------------------------------
def model_vectors(model, assignments: Sequence[str]):
    """(theta, constants) full vectors: nominal values overridden by ``--set`` items,
    each checked against its bounds."""
    from ..params import parse_assignments

    params, consts = model.split_assignments(parse_assignments(assignments))
    theta = model.parameters.vector(params)
    model.parameters.check_within_bounds(theta, what="--set value")
    constants = model.constants_vector(consts)
    model.constants.check_within_bounds(constants, what="--set value")
    return theta, constants


def read_all(paths: Sequence[str], concept: str):
    from .. import io

    return [io.read_measurement(p, concept=concept) for p in paths]


def read_fit(path: str, concept: str):
    """A FIT.json of the same concept (``--start``/``--init``)."""
    from .. import io
    from ..identify import FitResult

    data = io.read_json(path)
    if not isinstance(data, dict) or "parameters" not in data or "concept" not in data:
        raise CLIError(f"{path} is not a FIT.json written by 'ema-uq identify'")
    if data["concept"] != concept:
        raise CLIError(f"{path} holds a fit of concept {data['concept']}, but --concept {concept} was given; "
                       "use a fit of the same concept")
    return FitResult.from_json(data)


def load_study_for(path: str, concept: str):
    """A validated study whose concept must be ``concept``."""
    from ..study import load_study

    study = load_study(path)
    if study["concept"] != concept:
        raise CLIError(f"{path} is a study of concept {study['concept']}, but --concept {concept} was given; "
                       "use the study of the same concept")
    return study


# --------------------------------------------------------------------------------------
# unmodelled effects: the one place where --effect meets the simulator
# --------------------------------------------------------------------------------------
def resolve_effects(model, specs: Sequence[str]):
    """Turn ``--effect`` items into (augmented model, {effect: {parameter: value}}).

    Each item is read by :func:`ema_uq.models.effects.parse_effect` against the concept's
    catalogue (names, short or full parameter names, finite numbers); unnamed parameters keep
    the effect's nominal value. Without ``--effect`` the nominal model comes back unchanged.
    """
    from ..models.effects import EffectError, parse_effect

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
# provenance: one recipe for every result file
# --------------------------------------------------------------------------------------
def run_provenance(args: argparse.Namespace, inputs: Sequence[str] = (), *, seed: int | None = None,
                   settings: object = None, leave_out: Sequence[str] = ()) -> dict:
    """The provenance block of a verb's result (:func:`ema_uq.provenance.provenance`): checksums
    of ``inputs``, ``seed`` and the hash of ``settings``, by default every argument of the verb
    after the study was laid under it, less ``leave_out`` (arguments that cannot change a number
    of the result). The bound handler is never part of it: it is code, not a setting."""
    from ..provenance import provenance

    if settings is None:
        settings = {k: v for k, v in vars(args).items() if k not in ("handler", *leave_out)}
    return provenance(inputs, seed=seed, settings=settings)
