"""Study files: YAML validated against the package's JSON schema (used by the CLI and the
Snakefile alike), with defaults filled in."""
from __future__ import annotations

import json
from importlib import resources
from pathlib import Path
from typing import Any

import yaml


class StudyError(ValueError):
    """A study file that does not validate; the message names the offending key."""


def schema() -> dict[str, Any]:
    return json.loads(resources.files("ema_uq").joinpath("schema/study.schema.json").read_text())


def _fill_defaults(node: dict, sch: dict) -> None:
    for key, sub in sch.get("properties", {}).items():
        if key not in node and "default" in sub:
            node[key] = sub["default"]
        if sub.get("type") == "object" and "properties" in sub:
            node.setdefault(key, {})
            _fill_defaults(node[key], sub)


def validate_study(study: Any, source: str = "study") -> dict[str, Any]:
    """Validate a parsed study; return a copy with defaults filled in."""
    import jsonschema

    sch = schema()
    validator = jsonschema.Draft202012Validator(sch)
    errors = sorted(validator.iter_errors(study), key=lambda e: list(e.absolute_path))
    if errors:
        err = errors[0]
        where = ".".join(str(p) for p in err.absolute_path) or "(top level)"
        if err.validator == "additionalProperties":
            extra = sorted(set(err.instance) - set(err.schema.get("properties", {})))
            where = ".".join([*map(str, err.absolute_path), extra[0]]) if extra else where
            raise StudyError(f"{source}: unknown key {where!r}; allowed here: "
                             f"{', '.join(err.schema.get('properties', {}))}")
        raise StudyError(f"{source}: key {where!r}: {err.message}")
    study = json.loads(json.dumps(study))
    _fill_defaults(study, sch)
    _check_semantics(study, source)
    return study


def _check_semantics(study: dict, source: str) -> None:
    """Checks a schema cannot express: names that must exist in the concept's model."""
    from .models import UnknownConceptError, get_model

    try:
        model = get_model(study["concept"])
    except UnknownConceptError:
        return  # concepts outside the registry (emps) are checked by their own stage
    for name in study["identify"].get("fix", []):
        if name not in model.parameters:
            raise StudyError(f"{source}: key 'identify.fix': unknown parameter {name!r} for {model.name}")
    for name in study["data"].get("set", {}):
        if name not in model.parameters and name not in model.constants:
            raise StudyError(f"{source}: key 'data.set': unknown parameter or constant {name!r} for {model.name}")
    channels = study["data"].get("channels")
    if channels:
        for ch in channels:
            if ch not in model.outputs:
                raise StudyError(f"{source}: key 'data.channels': unknown channel {ch!r} for {model.name}")
    _check_uq_sections(study, model, source)
    _check_gap_section(study, model, source)


def _check_gap_section(study: dict, model, source: str) -> None:
    """Hidden rig effects and diagnosis candidates must be effects of the concept."""
    from .models.effects import parse_effect

    gap = section(study, "gap")
    available = model.available_effects
    for spec in gap["rig_effects"]:
        try:
            name, values = parse_effect(spec, model.effect_catalogue)
            model.with_effects([name], values)
        except ValueError as exc:
            raise StudyError(f"{source}: key 'gap.rig_effects': {exc}") from None
    for name in gap["candidates"] or []:
        if name not in available:
            raise StudyError(f"{source}: key 'gap.candidates': effect {name!r} is not available for {model.name}; "
                             f"available: {', '.join(available)}")


def section(study: dict[str, Any], name: str) -> dict[str, Any]:
    """A top-level section of a study with the schema defaults filled in (also for a study
    dict that did not go through :func:`validate_study`)."""
    sub = schema()["properties"][name]
    node = json.loads(json.dumps(study.get(name) or {}))
    _fill_defaults(node, sub)
    return node


def _check_uq_sections(study: dict, model, source: str) -> None:
    """Names in the sensitivity and identifiability sections must exist in the concept."""
    sens = section(study, "sensitivity")
    n_base = sens["n_base"]
    if n_base & (n_base - 1):
        raise StudyError(f"{source}: key 'sensitivity.n_base': {n_base} is not a power of 2 (Sobol sequences "
                         f"need one); use e.g. {1 << (n_base.bit_length() - 1)} or {1 << n_base.bit_length()}")
    for name, (lower, upper) in sens["parameters"].items():
        if name not in model.parameters:
            raise StudyError(f"{source}: key 'sensitivity.parameters': unknown parameter {name!r} for {model.name}")
        p = model.parameters[name]
        if not (p.lower <= lower < upper <= p.upper):
            raise StudyError(f"{source}: key 'sensitivity.parameters.{name}': range [{lower:g}, {upper:g}] must have "
                             f"lower < upper inside the bounds [{p.lower:g}, {p.upper:g}]")
    for ch in sens["rms_channels"] or []:
        if ch not in model.outputs:
            raise StudyError(f"{source}: key 'sensitivity.rms_channels': unknown channel {ch!r} for {model.name}")
    ident = section(study, "identifiability")
    for name in ident["profile_parameters"] or []:
        if name not in model.parameters:
            raise StudyError(f"{source}: key 'identifiability.profile_parameters': unknown parameter {name!r} "
                             f"for {model.name}")
    for item in ident["sensor_sets"]:
        for ch in item["channels"] if isinstance(item, dict) else []:
            if ch not in model.outputs:
                raise StudyError(f"{source}: key 'identifiability.sensor_sets.{item['name']}': unknown channel "
                                 f"{ch!r} for {model.name}")


def load_study(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    try:
        raw = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise StudyError(f"study file {path} does not exist") from None
    except yaml.YAMLError as exc:
        raise StudyError(f"{path}: not valid YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(raw, dict):
        raise StudyError(f"{path}: a study must be a mapping of keys to values")
    return validate_study(raw, source=str(path))
