"""Reference experiments (input profiles), measurement containers and measurement noise."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Mapping, Sequence

import numpy as np

from .models import INPUTS, REQUIRED_INPUTS, Model, concepts, get_model
from .models.components import DEG
from .errors import EmaUqError

SAMPLE_TIME = 0.01  # s, output sample time of the reference experiments
#: largest magnitude a sample of any input or channel may have, in SI units: above every force,
#: speed, current or angle of the rigs by orders of magnitude, and far below where squares of
#: residuals overflow; a sample beyond it is a corrupt value, not a measurement
MAX_MAGNITUDE = 1e12
#: longest sample interval [s]: the actuators' dynamics run at milliseconds; a longer step is a
#: time column in other units (milliseconds read as seconds), and would simulate for hours
MAX_SAMPLE_TIME = 1.0


class ExperimentError(EmaUqError):
    """An experiment or measurement that is malformed (shapes, time grid, channels)."""


@dataclass(frozen=True)
class Experiment:
    """Input signals on a uniform time grid.

    ``inputs`` maps input names (``phi_r`` [rad], ``F_ER1``/``F_ER2`` [N, positive aiding
    extension], optional ``brake`` in [0, 1]) to (n_samples,) arrays held over each interval.
    """

    name: str
    time: np.ndarray
    inputs: Mapping[str, np.ndarray]

    def __post_init__(self) -> None:
        time = np.asarray(self.time, dtype=float)
        check_time_grid(time)
        inputs = {}
        families = _input_families()
        known = tuple(dict.fromkeys(name for names, _ in families for name in names))
        for key, values in self.inputs.items():
            if key not in known:
                raise ExperimentError(f"unknown input {key!r}; inputs are {', '.join(known)}")
            values = np.asarray(values, dtype=float)
            if values.shape != time.shape:
                raise ExperimentError(f"input {key} has shape {values.shape}, time has {time.shape}")
            if not np.all(np.isfinite(values)):
                raise ExperimentError(f"input {key} contains NaN or infinite samples; inputs must be complete")
            check_magnitude(values, time, f"input {key}")
            inputs[key] = values
        # the concept family whose inputs hold every given input (EMA first)
        names, required = next(((n, r) for n, r in families if set(inputs) <= set(n)), families[0])
        missing = [k for k in required if k not in inputs]
        if missing:
            raise ExperimentError(f"missing input(s) {', '.join(missing)}; an experiment needs {', '.join(required)}")
        object.__setattr__(self, "time", time)
        object.__setattr__(self, "inputs", inputs)

    @property
    def n_samples(self) -> int:
        return self.time.size

    @property
    def dt(self) -> float:
        return float(self.time[1] - self.time[0])

    def input_matrix(self, model: Model | None = None) -> np.ndarray:
        """(n_samples, n_inputs) inputs in ``model.inputs`` order (default: the EMA layout);
        an absent optional input (brake, EMPS pulse) is zero."""
        names = INPUTS if model is None else model.inputs
        return np.column_stack([self.inputs.get(name, np.zeros_like(self.time)) for name in names])

    def slice(self, start: int, stop: int) -> "Experiment":
        return Experiment(self.name, self.time[start:stop], {k: v[start:stop] for k, v in self.inputs.items()})


def _input_families() -> list[tuple[tuple[str, ...], tuple[str, ...]]]:
    """(inputs, required inputs) of every registered concept, without repeats, EMA first."""
    families = dict.fromkeys((m.inputs, m.required_inputs) for m in map(get_model, concepts()))
    return sorted(families, key=lambda family: family[0] != INPUTS)


def check_time_grid(time: np.ndarray, where: str = "time") -> None:
    """A time axis must be 1-D, finite, strictly increasing and uniform (to 1e-6 relative)."""
    if time.ndim != 1 or time.size < 2:
        raise ExperimentError(f"{where} must be a 1-D axis with at least two samples, got shape {time.shape}")
    if not np.all(np.isfinite(time)):
        raise ExperimentError(f"{where} contains NaN or infinite values; give finite times in seconds")
    steps = np.diff(time)
    if np.any(steps <= 0):
        k = int(np.argmax(steps <= 0))
        raise ExperimentError(f"{where} is not strictly increasing at sample {k + 1} ({time[k]:g} -> {time[k + 1]:g} s); sort or repair the time axis")
    if np.max(np.abs(steps - steps[0])) > 1e-6 * max(steps[0], 1e-12) + 1e-9:
        k = int(np.argmax(np.abs(steps - steps[0])))
        raise ExperimentError(f"{where} is not uniform: step {steps[k]:g} s at sample {k + 1} differs from {steps[0]:g} s; resample to a uniform grid")
    if steps[0] > MAX_SAMPLE_TIME:
        raise ExperimentError(f"{where} steps by {steps[0]:g} s, over {MAX_SAMPLE_TIME:g} s between samples; give the "
                              "time in seconds (a column in milliseconds reads 1000 times too coarse)")


def check_magnitude(values: np.ndarray, time: np.ndarray, where: str) -> None:
    """A finite sample beyond :data:`MAX_MAGNITUDE` is a corrupt value: an error naming the first."""
    with np.errstate(invalid="ignore"):
        huge = np.abs(values) > MAX_MAGNITUDE
    if huge.any():
        k = int(np.argmax(huge.any(axis=1) if huge.ndim == 2 else huge))
        value = values[k][np.argmax(huge[k])] if huge.ndim == 2 else values[k]
        fix = "repair it or trim the record" if where.startswith("input") else "repair it or mark it missing (NaN)"
        raise ExperimentError(f"{where} has a sample of {value:g} at t = {time[k]:g} s, beyond {MAX_MAGNITUDE:g} in SI "
                              f"units: a corrupt value; {fix}")


def _piecewise_linear(time: np.ndarray, knots: Sequence[tuple[float, float]]) -> np.ndarray:
    t, v = np.array(knots, dtype=float).T
    return np.interp(time, t, v)


def _flap_experiment(name, knots_deg, duration, f_base, f_slope, split1) -> Experiment:
    time = np.round(np.arange(0.0, duration, SAMPLE_TIME), 10)
    phi_deg = _piecewise_linear(time, knots_deg)
    f_a = f_base + f_slope * phi_deg / 40.0
    return Experiment(name, time, {
        "phi_r": phi_deg * DEG,
        "F_ER1": -split1 * f_a,
        "F_ER2": -(1.0 - split1) * f_a,
    })


def deploy_retract() -> Experiment:
    """The identification run of docs/MODEL_SPEC.md: 38 s, 3800 samples, deploy to 20° and 35°, retract."""
    return _flap_experiment(
        "deploy-retract",
        [(0, 0), (1, 0), (9, 20), (13, 20), (19, 35), (24, 35), (34, 0), (38, 0)],
        38.0, 5e3, 30e3, 0.55,
    )


def validation() -> Experiment:
    """Validation run, not used for estimation: five reversals, 2.5-5 °/s, heavier and
    differently split load (F_a = 3 kN + 40 kN·φ/40°, 60/40)."""
    return _flap_experiment(
        "validation",
        [(0, 0), (1, 0), (4, 15), (6, 15), (10, 5), (12, 5), (17, 30), (19, 30),
         (23, 10), (25, 10), (28, 25), (30, 25), (37, 0), (40, 0)],
        40.0, 3e3, 40e3, 0.60,
    )


EXPERIMENTS = {"deploy-retract": deploy_retract, "validation": validation}


def get_experiment(name: str) -> Experiment:
    try:
        return EXPERIMENTS[name]()
    except KeyError:
        raise ExperimentError(f"unknown experiment {name!r}; choose one of: {', '.join(EXPERIMENTS)}") from None


@dataclass(frozen=True)
class Measurement:
    """Measured (or simulated-and-noised) output channels of one concept on one experiment.

    ``values`` is (n_samples, n_channels) in ``channels`` order; NaN marks a missing sample.
    ``attrs`` holds provenance (noise fraction, seed, source) — never the hidden truth.
    """

    concept: str
    experiment: Experiment
    channels: tuple[str, ...]
    values: np.ndarray
    attrs: Mapping[str, object] = field(default_factory=dict)

    def __post_init__(self) -> None:
        model = get_model(self.concept)
        channels = tuple(self.channels)
        wrong = [k for k in self.experiment.inputs if k not in model.inputs]
        missing = [k for k in model.required_inputs if k not in self.experiment.inputs]
        if wrong or missing:
            raise ExperimentError(
                f"experiment {self.experiment.name!r} has inputs {', '.join(self.experiment.inputs)}, but concept "
                f"{self.concept} takes {', '.join(model.inputs)} (required: {', '.join(model.required_inputs)})")
        model.output_index(channels)  # unknown names raise here
        if len(set(channels)) != len(channels):
            raise ExperimentError(f"duplicate channels in {channels}")
        values = np.asarray(self.values, dtype=float)
        if values.shape != (self.experiment.n_samples, len(channels)):
            raise ExperimentError(
                f"measured values have shape {values.shape}; expected ({self.experiment.n_samples}, {len(channels)})"
            )
        for c, name in enumerate(channels):
            check_magnitude(values[:, c], self.experiment.time, f"channel {name}")
        object.__setattr__(self, "channels", channels)
        object.__setattr__(self, "values", values)
        object.__setattr__(self, "attrs", dict(self.attrs))

    @property
    def model(self) -> Model:
        return get_model(self.concept)

    @property
    def time(self) -> np.ndarray:
        return self.experiment.time

    def __getitem__(self, channel: str) -> np.ndarray:
        if channel in self.channels:
            return self.values[:, self.channels.index(channel)]
        if channel in self.experiment.inputs:
            return self.experiment.inputs[channel]
        raise KeyError(f"no channel {channel!r} in this measurement; channels: {', '.join(self.channels)}")

    def select(self, channels: Sequence[str]) -> "Measurement":
        missing = [c for c in channels if c not in self.channels]
        if missing:
            raise ExperimentError(
                f"channel(s) {', '.join(missing)} not in this measurement; it has {', '.join(self.channels)}"
            )
        idx = [self.channels.index(c) for c in channels]
        return Measurement(self.concept, self.experiment, tuple(channels), self.values[:, idx], self.attrs)

    def summary(self) -> str:
        rows = [f"Measurement of {self.concept} on {self.experiment.name!r}: {self.experiment.n_samples} samples, "
                f"dt = {self.experiment.dt:g} s, {len(self.channels)} channels"]
        for i, ch in enumerate(self.channels):
            col = self.values[:, i]
            n_nan = int(np.isnan(col).sum())
            rows.append(f"  {ch:<10} rms {np.sqrt(np.nanmean(col ** 2)):>11.4g}  missing {n_nan}")
        return "\n".join(rows)


def channel_rms(values: np.ndarray) -> np.ndarray:
    """Per-channel RMS of (n_samples, n_channels) values, ignoring NaN."""
    return np.sqrt(np.nanmean(np.asarray(values) ** 2, axis=0))


def noise_std(clean: np.ndarray, fraction: float) -> np.ndarray:
    """Per-channel noise standard deviation: ``fraction`` of each channel's RMS."""
    if not fraction >= 0:
        raise ExperimentError(f"noise fraction must be >= 0, got {fraction}")
    return fraction * channel_rms(clean)


def add_noise(clean: np.ndarray, fraction: float, rng: np.random.Generator) -> np.ndarray:
    """Independent Gaussian white noise, per channel ``fraction`` × RMS (docs/MODEL_SPEC.md, section 4)."""
    sigma = noise_std(clean, fraction)
    return clean + rng.standard_normal(clean.shape) * sigma


def synthesize(
    model: Model | str,
    experiment: Experiment,
    theta: np.ndarray | None = None,
    *,
    noise: float = 0.02,
    seed: int | None = 0,
    channels: Sequence[str] | None = None,
    constants: np.ndarray | None = None,
) -> Measurement:
    """Simulate ``theta`` (default nominal) and return noisy "hypothetical data" (paper, sec. 4)."""
    from .simulate import simulate_batch

    model = get_model(model) if isinstance(model, str) else model
    theta = model.parameters.nominal if theta is None else np.asarray(theta, dtype=float)
    clean = simulate_batch(model, theta, experiment.time, experiment.input_matrix(model), constants=constants)
    channels = tuple(model.outputs if channels is None else channels)
    clean = clean[:, model.output_index(channels)]
    rng = np.random.default_rng(seed)
    values = add_noise(clean, noise, rng) if noise > 0 else clean
    attrs = {"noise_fraction": noise, "seed": -1 if seed is None else int(seed), "source": "simulated"}
    return Measurement(model.name, experiment, channels, values, attrs)
