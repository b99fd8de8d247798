"""The actuator study of one concept: the friction/damping parameters and their ranges, the
reference data and the quantities of interest, resolved from a study file."""
from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from typing import Any, Mapping

import numpy as np

from ..experiments import Experiment, get_experiment, synthesize
from ..models import Model, get_model
from ..simulate import simulate_batch
from .indices import SensitivityError, _check_n_base, design_size, sample

#: scalar QoI kinds of the study schema, in report order
QOI_KINDS = ("cost", "rms", "tracking_error", "peak_torque", "peak_current", "energy")
#: outputs with time-resolved indices
TIME_RESOLVED_OUTPUTS = ("Omega", "y1", "I_A")
#: Sobol runs are forward simulations only (no finite differences), where an adaptive
#: integrator's step choice per parameter set costs nothing: the hybrid one (exact steps over
#: the intervals where the model is linear) takes 2.5x (HT/LS) to 10x (LT/HS) less time than
#: plain Dormand-Prince on the deploy-retract run, at its accuracy
INTEGRATOR = "hybrid"
_QOI_UNITS = {"cost": "1", "tracking_error": "m", "peak_torque": "N m", "peak_current": "A", "energy": "J"}


# --------------------------------------------------------------------------------------
# the actuator study: parameters, ranges, reference data, QoI
# --------------------------------------------------------------------------------------
def friction_names(model: Model) -> tuple[str, ...]:
    """The friction/damping parameters (B_*, C_*) of a concept, in layout order."""
    return tuple(n for n in model.parameters.names if n.startswith(("B_", "C_")))


_MOTOR_CONSTANTS = ("k_n", "R_A", "L_A", "k_s")


@dataclass(frozen=True)
class SensitivitySetup:
    """Everything one concept's Sobol study needs, resolved from a study file.

    ``nominal`` is the full parameter vector around which ranges are set and at which every
    parameter outside ``names`` is held; ``bounds`` (D, 2) are the uniform ranges of ``names``.
    ``reference`` (n_samples, n_channels) is the noisy estimation data the cost QoI compares
    with; ``time_index`` the samples kept for the time-resolved indices.
    """

    concept: str
    names: tuple[str, ...]
    bounds: np.ndarray
    nominal: np.ndarray
    constants: np.ndarray
    experiment: Experiment
    reference_channels: tuple[str, ...]
    reference: np.ndarray
    rms_channels: tuple[str, ...]
    qoi_kinds: tuple[str, ...]
    time_index: np.ndarray
    n_base: int
    seed: int
    chunks: int = 1
    batch_size: int = 128
    bootstrap: int = 100

    @property
    def model(self) -> Model:
        return get_model(self.concept)

    @property
    def problem(self) -> dict[str, Any]:
        """The plain SALib problem description."""
        return {"num_vars": len(self.names), "names": list(self.names), "bounds": self.bounds.tolist()}

    @property
    def qoi_names(self) -> tuple[str, ...]:
        names: list[str] = []
        for kind in self.qoi_kinds:
            names += [f"rms_{c}" for c in self.rms_channels] if kind == "rms" else [kind]
        return tuple(names)

    def qoi_unit(self, name: str) -> str:
        if name.startswith("rms_"):
            return self.model.unit_of(name[4:])
        return _QOI_UNITS[name]

    @property
    def n_evaluations(self) -> int:
        return design_size(self.n_base, len(self.names))

    def digest(self) -> str:
        """Fingerprint of everything that determines the evaluated numbers (chunks must share it)."""
        h = hashlib.sha256()
        h.update(json.dumps([self.concept, self.names, self.reference_channels, self.rms_channels, self.qoi_kinds,
                             self.n_base, self.seed, self.experiment.name, INTEGRATOR]).encode())
        for arr in (self.bounds, self.nominal, self.constants, self.reference, self.time_index):
            h.update(np.ascontiguousarray(arr).tobytes())
        return h.hexdigest()[:16]

    def design(self) -> np.ndarray:
        return sample(self.problem, self.n_base, self.seed)

    def thetas(self, rows: np.ndarray) -> np.ndarray:
        """Full parameter vectors (n, n_params) for design rows (n, D)."""
        full = np.repeat(self.nominal[None, :], rows.shape[0], axis=0)
        full[:, [self.model.parameters.index(n) for n in self.names]] = rows
        return full


def setup_from_study(study: Mapping[str, Any], *, n_base: int | None = None) -> SensitivitySetup:
    """Resolve a (validated) study's ``sensitivity`` section into a :class:`SensitivitySetup`."""
    from ..study import section

    model = get_model(study["concept"])
    if not friction_names(model) or "I_A" not in model.outputs or "k_y" not in model.constants:
        raise SensitivityError(f"concept {model.name} has no EMA friction parameters and outputs; "
                               "the Sobol study covers htls and lths")
    sens = section(study, "sensitivity")
    data = section(study, "data")
    n_base = int(sens["n_base"] if n_base is None else n_base)
    _check_n_base(n_base)
    params, consts = model.split_assignments(dict(data.get("set") or {}))
    nominal = model.parameters.vector(params)
    constants = model.constants_vector(consts)

    names = list(friction_names(model))
    if sens["include_inertia"]:
        names.insert(0, "J")
    if sens["include_motor"]:
        names += [n for n in _MOTOR_CONSTANTS if n in model.parameters]
    fraction = float(sens["range_fraction"])
    if not 0 < fraction < 1:
        raise SensitivityError(f"sensitivity.range_fraction = {fraction} must lie in (0, 1)")
    ranges = {n: (nominal[model.parameters.index(n)] * (1 - fraction),
                  nominal[model.parameters.index(n)] * (1 + fraction)) for n in names}
    for name, (lo, hi) in dict(sens["parameters"]).items():
        if name not in model.parameters:
            raise SensitivityError(f"sensitivity.parameters: unknown parameter {name!r} for {model.name}")
        if not lo < hi:
            raise SensitivityError(f"sensitivity.parameters.{name}: lower {lo} must be below upper {hi}")
        ranges[name] = (float(lo), float(hi))
        if name not in names:
            names.append(name)
    for name in names:
        p = model.parameters[name]
        lo, hi = ranges[name]
        if lo < p.lower or hi > p.upper or not lo < hi:
            raise SensitivityError(f"range of {name} [{lo:g}, {hi:g}] leaves its bounds [{p.lower:g}, {p.upper:g}] "
                                   "or is empty; narrow range_fraction or give sensitivity.parameters")
    bounds = np.array([ranges[n] for n in names], dtype=float)

    experiment = get_experiment(data["estimation"])
    ref_channels = tuple(data.get("channels") or model.outputs)
    seed = int(study.get("seed", 1))
    reference = synthesize(model, experiment, nominal, noise=float(data["noise"]), seed=seed,
                           channels=ref_channels, constants=constants).values
    if not np.all(np.isfinite(reference)):
        raise SensitivityError("the reference data have missing samples; the cost QoI needs complete data")
    if sens["rms_channels"]:
        rms_channels = tuple(sens["rms_channels"])
        model.output_index(rms_channels)
    else:
        # channels set by the inputs alone (M_ER) do not move with any parameter
        moving = _moving_channels(model, experiment, nominal, bounds, names, constants)
        rms_channels = tuple(c for c in model.outputs if c in moving)
    n = experiment.n_samples
    time_index = np.unique(np.round(np.linspace(0, n - 1, min(int(sens["time_points"]), n))).astype(np.int64))
    return SensitivitySetup(
        concept=model.name, names=tuple(names), bounds=bounds, nominal=nominal, constants=constants,
        experiment=experiment, reference_channels=ref_channels, reference=reference, rms_channels=rms_channels,
        qoi_kinds=tuple(sens["qoi"]), time_index=time_index, n_base=n_base,
        seed=seed + int(sens["seed_offset"]), chunks=int(sens["chunks"]), batch_size=int(sens["batch_size"]),
        bootstrap=int(sens["bootstrap"]),
    )


def _moving_channels(model, experiment, nominal, bounds, names, constants) -> set[str]:
    """Channels that differ between the nominal run and the two range corners."""
    idx = [model.parameters.index(n) for n in names]
    thetas = np.repeat(nominal[None], 3, axis=0)
    thetas[1, idx] = bounds[:, 0]
    thetas[2, idx] = bounds[:, 1]
    out = simulate_batch(model, thetas, experiment.time, experiment.input_matrix(model), constants=constants,
                         integrator=INTEGRATOR)
    spread = np.max(np.abs(out[1:] - out[:1]), axis=(0, 1))
    scale = np.max(np.abs(out[0]), axis=0)
    return {c for c, s, m in zip(model.outputs, spread, scale) if s > 1e-9 * max(m, 1e-300)}
