"""Study files: YAML validated against the package's JSON schema (used by the CLI and the
Snakefile alike), with defaults filled in."""
from __future__ import annotations

import json
import math
from importlib import resources
from pathlib import Path
from typing import Any

import yaml

from .errors import EmaUqError


class StudyError(EmaUqError):
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
    for name, value in study["data"].get("set", {}).items():
        if name not in model.parameters and name not in model.constants:
            raise StudyError(f"{source}: key 'data.set': unknown parameter or constant {name!r} for {model.name}")
        # checked here, not only by the verb that first reads it, so a workflow stops before any job
        p = (model.parameters if name in model.parameters else model.constants)[name]
        if not (math.isfinite(value) and p.lower <= value <= p.upper):
            raise StudyError(f"{source}: key 'data.set': {name} = {value} lies outside its bounds "
                             f"[{p.lower:g}, {p.upper:g}]; give a finite value inside them")
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
    from .rigs import is_measured, no_method_version

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
    if gap["method_version"] is not None and is_measured(model.name):
        raise StudyError(f"{source}: key 'gap.method_version': {no_method_version(model.name)}; drop the key")


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


def _yaml_error(path: Path, exc: yaml.YAMLError) -> str:
    """One line naming where a study file stops being YAML: line and column (1-based, as an
    editor counts them) of the problem, what PyYAML found there, and what to do."""
    mark = getattr(exc, "problem_mark", None) or getattr(exc, "context_mark", None)
    problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
    context = getattr(exc, "context", None)
    where = f"line {mark.line + 1}, column {mark.column + 1}: " if mark is not None else ""
    return (f"{path}: not valid YAML at {where}{problem}" + (f" ({context})" if context else "")
            + "; fix the indentation, quotes or brackets there")


class _DuplicateKey(yaml.YAMLError):
    def __init__(self, key: Any, mark: Any) -> None:
        super().__init__(f"duplicate key {key!r}")
        self.key, self.mark = key, mark


class _StudyLoader(yaml.SafeLoader):
    """PyYAML's safe loader, refusing a key given twice in one mapping (plain YAML keeps the
    last silently, so a second ``seed:`` line would change the study unseen)."""

    def construct_mapping(self, node, deep=False):
        seen = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=deep)
            if key in seen:
                raise _DuplicateKey(key, key_node.start_mark)
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


def load_study(path: str | Path) -> dict[str, Any]:
    path = Path(path)
    try:
        raw = yaml.load(path.read_text(), Loader=_StudyLoader)
    except FileNotFoundError:
        raise StudyError(f"study file {path} does not exist") from None
    except _DuplicateKey as exc:
        raise StudyError(f"{path}: key {exc.key!r} is given twice (line {exc.mark.line + 1}); "
                         "keep one of them") from None
    except yaml.YAMLError as exc:
        raise StudyError(_yaml_error(path, exc)) from None
    if not isinstance(raw, dict):
        raise StudyError(f"{path}: a study must be a mapping of keys to values")
    return validate_study(raw, source=str(path))


# --------------------------------------------------------------------------------------
# settings of each command-line verb: the one route from a study to a stage
# --------------------------------------------------------------------------------------
#: Data roles of a synthetic study and the offset of each one's noise seed from the study
#: seed: estimation, validation and the rig-like records (which carry ``gap.rig_effects``)
#: must be independent noise draws.
DATA_ROLES = {"estimation": 0, "validation": 1000, "rig_estimation": 2000, "rig_validation": 3000}


def _simulate_settings(study: dict, role: str | None) -> dict[str, Any]:
    if role not in DATA_ROLES:
        raise StudyError(f"simulate from a study needs a data role, one of {', '.join(DATA_ROLES)}; "
                         f"got {role!r}")
    data = section(study, "data")
    return {"experiment": data[role.removeprefix("rig_")], "noise": data["noise"],
            "seed": study.get("seed", 1) + DATA_ROLES[role], "set": dict(data.get("set") or {}),
            "channels": data.get("channels"),
            # the rig-like records carry the study's hidden effects; the data file does not name them
            "effect": list(section(study, "gap")["rig_effects"]) if role.startswith("rig_") else []}


def settings_for(study: dict[str, Any], verb: str, *, role: str | None = None) -> dict[str, Any]:
    """Everything the command-line ``verb`` takes from ``study``, with the schema's defaults.

    Keys are the verb's option destinations (``--max-iterations`` -> ``max_iterations``), so
    the CLI lays them under the options given on its command line; ``set`` is the study's
    ``data.set`` ({name: value}: the simulated truth and the design constants, which every
    stage that simulates the study's data must share). ``role`` (verb ``simulate`` only) is
    one of :data:`DATA_ROLES`. Sensitivity's ``design`` is the part of the study that defines
    the Sobol design (:func:`ema_uq.sensitivity.setup_from_study`). The workflow re-runs a
    stage exactly when this value changes.
    """
    seed = study.get("seed", 1)
    data = section(study, "data")
    overrides = dict(data.get("set") or {})
    if verb == "simulate":
        return _simulate_settings(study, role)
    if verb == "identify":
        ident = section(study, "identify")
        out = {"seed": seed, "perturb": ident["perturb"], "max_iterations": ident["max_iterations"],
               "fix": list(ident.get("fix") or []), "channels": data.get("channels"), "set": overrides}
        # only when the study names it (the CLI holds the default), so studies without it keep their settings
        if "unidentifiable" in ident:
            out["unidentifiable"] = ident["unidentifiable"]
        return out
    if verb == "sample":
        s = section(study, "sample")
        return {"seed": seed, "walkers": s["walkers"], "chains": s["ensembles"], "max_steps": s["max_steps"],
                "check_every": s["check_every"], "moves": s["moves"], "defensive": s["defensive"],
                "integrator": s["integrator"], "set": overrides}
    if verb == "sensitivity":
        sens = section(study, "sensitivity")
        return {"n_base": sens["n_base"], "design": {"seed": seed, "data": data, "sensitivity": sens}}
    if verb == "identifiability":
        ident = section(study, "identifiability")
        return {"sensor_sets": ident["sensor_sets"], "profile": ident["profile_parameters"],
                **{k: ident[k] for k in ("profile_points", "profile_sigmas", "profile_span", "max_relative_width",
                                         "collinearity_threshold")},
                "noise": data["noise"], "set": overrides}
    if verb == "gap":
        gap = section(study, "gap")
        return {"candidates": gap["candidates"], "channels": data.get("channels"), "set": overrides,
                "method_version": gap["method_version"]}
    if verb == "gap-selfcheck":
        gap = section(study, "gap")
        return {"seed": seed, "quick": gap["selfcheck"] == "quick", "concepts": [study["concept"]],
                "none_per_set": gap["selfcheck_none_per_set"], "sensors": list(gap["selfcheck_sensors"]),
                "method_version": gap["method_version"]}
    raise StudyError(f"verb {verb!r} takes no settings from a study; these do: {', '.join(STUDY_VERBS)}")


#: Verbs that take ``--study STUDY.yaml`` and read their settings through :func:`settings_for`.
STUDY_VERBS = ("simulate", "identify", "sample", "sensitivity", "identifiability", "gap", "gap-selfcheck")
