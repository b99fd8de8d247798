"""Rig-like records from an independent simulator: the non-circular self-check of the gap diagnosis.

Why this module exists
----------------------
The blind self-check of :mod:`ema_uq.gap.selfcheck` makes its records with the same effect
kernels (``models/effect_kernels.py``) that the diagnosis fits to explain them, so it can only
show that the diagnosis recovers its own equations. Real rigs are not built from those
equations: a rig's play sits in a compliant drive train, its friction curve has its own shape,
its sensors their own filters. This module is a second, independently written simulator of the
HT/LS and LT/HS models of MODEL_SPEC.md (its own numba fixed-step RK4 kernel, its own parameter
and constant layouts, zero-order-hold inputs, outputs at t_k from x(t_k) and u_k) with effect
VARIANTS written without the catalogue's kernels. Each variant belongs to the catalogue FAMILY
(a catalogue effect name) the diagnosis should name, or to no family (``None``): physics
outside the catalogue, for which the right verdict is ``unexplained``. It imports from the
package only names, nominal values, input profiles and the measurement/noise helpers - never
an equation (``models.htls/lths.evaluate``, ``models.components``, ``models.effect_kernels``,
``simulate``).

Where its parts live: :mod:`ema_uq.gap.variant_catalogue` describes every variant and how it
differs from the catalogue's forms, and draws and checks its parameters;
:mod:`ema_uq.gap.variant_kernel` is the simulator's own numba RK4 kernel. This module turns
them into records: the measurement-side variants, :func:`simulate_variant`, the model-form
stress and :func:`make_records`.

Model-form stress of no-effect records (:func:`draw_stress`, ``make_records(stress=...)``)
---------------------------------------------------------------------------------------
A rig with no unmodelled effect still differs from the fitted model in ways no catalogue
effect describes, and a diagnosis should not name an effect for them: coloured sensor noise
(AR(1), coefficient U(0.3, 0.8), same variance as the white noise), quantisation of every
sensor (step U(0.2 %, 1 %) of the channel's RMS), design constants off their drawing (gear
ratios, screw radius and lead angle, joint angles: each times 1 + U(-3 %, 3 %)) and command
shaping the experiment does not record (first-order filter of phi_r, time constant
U(10, 50) ms). The ranges are :data:`STRESS_RANGES`.

Magnitudes are drawn log-uniform from "just visible at 2 % noise" to "strong", phases uniform in
[0, 2 pi), other shape parameters uniform (:func:`draw_variant_parameters`). The records of
:func:`make_records` carry no label; their truth is returned separately.
"""
from __future__ import annotations

import math
from typing import Any, Mapping

import numpy as np

from ..experiments import Experiment, Measurement, add_noise, deploy_retract, validation
from ..models import get_model
from .variant_catalogue import (CONCEPTS, UNSEEN_VARIANTS, UNSEEN_VARIANTS_2, UNSEEN_VARIANTS_3, VARIANTS, Variant,
                                VariantError, _check_concept, check_variant_parameters, get_variant)
from .variant_kernel import KERNEL_OUTPUTS, _kernel_constants, _kernel_parameters, _kernel_values, _run

# The variants and the kernel's layouts stay importable from here, where they were defined
# before they had rooms of their own (the self-check, the benchmark and the tests reach them so).
from .variant_catalogue import (DELAY_CLEARANCE, FAMILIES, TWO_PI, VariantParameter,  # noqa: F401
                                draw_variant_parameters)
from .variant_kernel import (CONSTANT_LAYOUT, CONTACT_RAMP, HTLS_OUTPUTS, LOAD_EXPONENT,  # noqa: F401
                             LOAD_REFERENCE, LOAD_SMOOTHING, LTHS_OUTPUTS, N_STATE, N_VARIANT_VALUES,
                             PARAMETER_LAYOUT, RIPPLE_PERIODS, STATION_STRIDE)

#: rig sensors per concept (as ``ema_uq.identifiability.REALISTIC_CHANNELS``)
REALISTIC_CHANNELS = {"htls": ("Omega", "y1", "y2", "I_A"), "lths": ("Omega", "y1", "y2", "I_A", "U_A")}
RIG_PERTURBATION = 0.01     # rig-measured gains (p_ACE, p_PCE) move inside their 2 % uncertainty


# ------------------------------------------------------------------------------------------
# measurement-side variants (after the kernel)
# ------------------------------------------------------------------------------------------
def delay_hermite(values: np.ndarray, tau: float, dt: float) -> np.ndarray:
    """Every column of (n_samples, n_channels) ``values`` read at t_k - tau by cubic Hermite
    (Catmull-Rom) interpolation; samples with t_k < tau hold the first value."""
    values = np.asarray(values, dtype=float)
    if tau == 0.0:
        return values.copy()
    src = np.arange(values.shape[0]) - tau / dt
    out = read_between_samples(values, src)
    out[src <= 0.0] = values[0]
    return out


def read_between_samples(values: np.ndarray, src: np.ndarray) -> np.ndarray:
    """Every column of (n_samples, n_channels) ``values`` read at the fractional sample indices
    ``src`` by cubic Hermite (Catmull-Rom) interpolation (indices outside the record clamp)."""
    n = values.shape[0]
    j = np.floor(src).astype(np.int64)
    f = (src - j)[:, None]
    p0, p1, p2, p3 = (values[np.clip(j + d, 0, n - 1)] for d in (-1, 0, 1, 2))
    m1, m2 = 0.5 * (p2 - p0), 0.5 * (p3 - p1)
    return ((2 * f ** 3 - 3 * f ** 2 + 1) * p1 + (f ** 3 - 2 * f ** 2 + f) * m1
            + (-2 * f ** 3 + 3 * f ** 2) * p2 + (f ** 3 - f ** 2) * m2)


def sample_hold(values: np.ndarray, period: float, offset: float, dt: float) -> np.ndarray:
    """Every column of ``values`` (recorded at t_k = k dt) as a sensor that samples at
    offset x period + j x period and holds: at t_k the value at the last sensor instant
    (the first recorded value before the first instant)."""
    values = np.asarray(values, dtype=float)
    t = np.arange(values.shape[0]) * dt
    first = offset * period
    instants = first + period * np.floor((t - first) / period)
    out = read_between_samples(values, instants / dt)
    out[t < first] = values[0]
    return out


def window_average(values: np.ndarray, window: float, dt: float) -> np.ndarray:
    """Every column of ``values`` (recorded at t_k = k dt) as a sensor that reports the mean of
    its signal over the last ``window`` [s]: (1 / W) x the integral over [t_k - W, t_k] of the
    cubic Hermite (Catmull-Rom) curve through the samples, integrated exactly; the signal is
    taken as held at its first value before t_0."""
    values = np.asarray(values, dtype=float)
    if window == 0.0:
        return values.copy()
    n = values.shape[0]
    k = np.arange(n)
    p0, p1, p2, p3 = (values[np.clip(k + d, 0, n - 1)] for d in (-1, 0, 1, 2))
    m1, m2 = 0.5 * (p2 - p0), 0.5 * (p3 - p1)
    # the curve's integral from sample 0 to sample k, in sample units (a segment's: the Hermite weights' integrals)
    segments = 0.5 * (p1 + p2) + (m1 - m2) / 12.0
    whole = np.concatenate([np.zeros((1,) + values.shape[1:]), np.cumsum(segments[:-1], axis=0)])
    start = k - window / dt
    j = np.clip(np.floor(start).astype(np.int64), 0, n - 1)
    f = np.clip(start - j, 0.0, 1.0)[:, None]
    # integrals over [0, f] of the Hermite basis functions h00, h10, h01, h11
    part = ((f ** 4 / 2 - f ** 3 + f) * p1[j] + (f ** 4 / 4 - 2 * f ** 3 / 3 + f ** 2 / 2) * m1[j]
            + (-f ** 4 / 2 + f ** 3) * p2[j] + (f ** 4 / 4 - f ** 3 / 3) * m2[j])
    before = np.minimum(start, 0.0)[:, None] * values[0]   # the held first value ahead of t_0
    return (whole - np.where(start[:, None] >= 0.0, whole[j] + part, before)) * dt / window


def thiran_coefficients(delay: float, order: int) -> np.ndarray:
    """Denominator a_0..a_N of the order-N Thiran all-pass of ``delay`` samples (stable for delay > N - 1)."""
    a = np.ones(order + 1)
    for k in range(1, order + 1):
        prod = np.prod([(delay - order + n) / (delay - order + k + n) for n in range(order + 1)])
        a[k] = (-1) ** k * math.comb(order, k) * prod
    return a


def delay_allpass(values: np.ndarray, tau: float, dt: float) -> np.ndarray:
    """Every column through a whole-sample shift and a Thiran all-pass (order <= 3) of total
    low-frequency delay tau; the signal is taken as held at its first value before t_0."""
    from scipy.signal import lfilter

    values = np.asarray(values, dtype=float)
    lag = tau / dt
    if lag == 0.0:
        return values.copy()
    order = min(3, max(1, int(round(lag))))
    shift = max(0, int(round(lag)) - 3)
    a = thiran_coefficients(lag - shift, order)
    held = values - values[0]
    if shift:
        held = np.concatenate([np.zeros((shift,) + held.shape[1:]), held[:-shift]])
    return lfilter(a[::-1], a, held, axis=0) + values[0]


def _measure(concept: str, variant: Variant | None, params: Mapping[str, float], out: np.ndarray,
             dt: float) -> np.ndarray:
    """Apply the measurement-side variants to outputs (n_samples, n_outputs) in kernel order."""
    if variant is None:
        return out
    if variant.name == "sensor_delay_hermite":
        return delay_hermite(out, params["tau"], dt)
    if variant.name == "sensor_delay_allpass":
        return delay_allpass(out, params["tau"], dt)
    if variant.name == "sensor_delay_sample_hold":
        return sample_hold(out, params["period"], params["offset"], dt)
    if variant.name == "sensor_delay_window":
        return window_average(out, params["window"], dt)
    if variant.name == "current_sensor_error":
        out = out.copy()
        k = KERNEL_OUTPUTS[concept].index("I_A")
        out[:, k] = (1.0 + params["gain"]) * out[:, k] + params["offset"]
    return out


# ------------------------------------------------------------------------------------------
# simulation and records
# ------------------------------------------------------------------------------------------
def _base_values(concept: str, base) -> dict[str, float]:
    model = get_model(concept)
    if base is None:
        return dict(zip(model.parameters.names, model.parameters.nominal))
    if not isinstance(base, Mapping):
        vector = np.asarray(base, dtype=float)
        if vector.shape != (len(model.parameters),):
            raise VariantError(f"base parameters have shape {vector.shape}; {concept} needs "
                               f"({len(model.parameters)},) in {', '.join(model.parameters.names)} order")
        base = dict(zip(model.parameters.names, vector))
    missing = [n for n in model.parameters.names if n not in base]
    stray = [n for n in base if n not in model.parameters.names]
    if missing or stray:
        raise VariantError(f"base parameters of {concept}: " + (f"missing {', '.join(missing)}" if missing else
                           f"unknown {', '.join(stray)}") + f"; give {', '.join(model.parameters.names)}")
    bad = [n for n, v in base.items() if not np.isfinite(v)]
    if bad:
        raise VariantError(f"base parameter {bad[0]} = {base[bad[0]]} is not finite; give a finite value")
    return {n: float(v) for n, v in base.items()}


def simulate_variant(concept: str, experiment: Experiment, base=None, variant: str | None = None,
                     params: Mapping[str, float] | None = None, *, step: float | None = None,
                     constant_offsets: Mapping[str, float] | None = None,
                     input_filter: float = 0.0) -> np.ndarray:
    """Clean outputs of the independent simulator: (n_samples, n_outputs) in
    ``get_model(concept).outputs`` order.

    ``base``: parameter values by name or a vector in ``model.parameters`` order (default
    nominal); ``variant``/``params``: an effect variant of :data:`VARIANTS` and its parameters
    (None: the nominal model). ``step``: RK4 step [s] (default the concept's converged step
    divided by the variant's ``step_divisor``), rounded to divide the sample time.
    ``constant_offsets``: relative offsets of design constants (the rig built off its drawing);
    ``input_filter``: time constant [s] of a first-order command shaping of ``phi_r``
    (:func:`shape_command`) that the experiment, and so the diagnosis, does not know of.
    """
    model = get_model(_check_concept(concept))
    values = _base_values(concept, base)
    var = None if variant is None else get_variant(variant)
    checked = {} if var is None else check_variant_parameters(variant, params or {})
    if var is None and params:
        raise VariantError("variant parameters given without a variant; name the variant")
    c = _kernel_constants(concept, constant_offsets)
    th = _kernel_parameters(concept, values)
    vv = _kernel_values(concept, var, checked, c)
    dt = experiment.dt
    h_wanted = step if step is not None else model.integration_step / (1 if var is None else var.step_divisor)
    if not h_wanted > 0:
        raise VariantError(f"RK4 step must be positive, got {h_wanted}")
    n_sub = max(1, int(round(dt / h_wanted)))
    inputs = np.ascontiguousarray(np.column_stack(
        [experiment.inputs.get(n, np.zeros_like(experiment.time)) for n in ("phi_r", "F_ER1", "F_ER2", "brake")]))
    if input_filter:
        inputs[:, 0] = shape_command(inputs[:, 0], input_filter, dt)
    # the command's rate as a drive differentiates its sampled set point (a speed feed-forward reads it)
    inputs = np.column_stack([inputs, np.concatenate([[0.0], np.diff(inputs[:, 0]) / dt])])
    names = KERNEL_OUTPUTS[concept]
    out = np.empty((experiment.n_samples, len(names)))
    _run(CONCEPTS.index(concept), 0 if var is None else var.kernel_id, th, c, vv, inputs, dt / n_sub, n_sub, out)
    out = _measure(concept, var, checked, out, dt)
    return out[:, [names.index(ch) for ch in model.outputs]]


def shape_command(values: np.ndarray, tau: float, dt: float) -> np.ndarray:
    """First-order low-pass of time constant ``tau`` [s] on a held signal sampled every ``dt``:
    y_k = y_(k-1) + (1 - exp(-dt / tau)) (u_k - y_(k-1)), y_0 = u_0 (the exact step response
    of a first-order lag to a held input, one sample late)."""
    values = np.asarray(values, dtype=float)
    if not (math.isfinite(tau) and tau >= 0.0):
        raise VariantError(f"command filter time constant must be finite and >= 0, got {tau!r}")
    if tau == 0.0 or values.size == 0:
        return values.copy()
    from scipy.signal import lfilter

    alpha = 1.0 - math.exp(-dt / tau)
    out, _ = lfilter([alpha], [1.0, -(1.0 - alpha)], values[1:], zi=[(1.0 - alpha) * values[0]])
    return np.concatenate([values[:1], out])


# ------------------------------------------------------------------------------------------
# model-form stress of no-effect records: what a rig always differs by
# ------------------------------------------------------------------------------------------
#: stated ranges of the stress draws (:func:`draw_stress`)
STRESS_RANGES = {
    "ar1": (0.3, 0.8),              # AR(1) coefficient of the sensor noise (same variance as white)
    "quantisation": (0.002, 0.01),  # quantisation step of every sensor, fraction of its clean RMS
    "constant_offset": 0.03,        # design constants each times 1 + U(-0.03, 0.03)
    "input_filter": (0.01, 0.05),   # s, first-order command shaping of phi_r
}
#: design constants the stress moves (those a concept has)
STRESS_CONSTANTS = ("r", "gamma", "beta1", "beta2", "i_TP1", "i_TP2", "i_MG", "i_BG1", "i_BG2")


def draw_stress(concept: str, rng: np.random.Generator) -> dict[str, Any]:
    """Random model-form stress of a no-effect record within :data:`STRESS_RANGES`: AR(1)
    coefficient and quantisation step fraction uniform, one offset per design constant of
    :data:`STRESS_CONSTANTS` the concept has (uniform in +-``constant_offset``), command filter
    time constant uniform. Every stress at once: the rig differs from the model in all of them."""
    names = get_model(_check_concept(concept)).constants.names
    offset = STRESS_RANGES["constant_offset"]
    return {"ar1": float(rng.uniform(*STRESS_RANGES["ar1"])),
            "quantisation": float(rng.uniform(*STRESS_RANGES["quantisation"])),
            "constants": {n: float(rng.uniform(-offset, offset)) for n in STRESS_CONSTANTS if n in names},
            "input_filter": float(rng.uniform(*STRESS_RANGES["input_filter"]))}


def check_stress(stress: Mapping[str, Any] | None) -> dict[str, Any]:
    """The stress as plain values (keys ``ar1``, ``quantisation``, ``constants``, ``input_filter``,
    each optional); an unknown key or a value out of bounds is a VariantError."""
    if not stress:
        return {}
    stray = [k for k in stress if k not in ("ar1", "quantisation", "constants", "input_filter")]
    if stray:
        raise VariantError(f"unknown stress {stray[0]!r}; give ar1, quantisation, constants or input_filter")
    out: dict[str, Any] = {}
    for key, lower, upper in (("ar1", 0.0, 0.99), ("quantisation", 0.0, 0.5), ("input_filter", 0.0, 10.0)):
        if key in stress:
            value = float(stress[key])
            if not (math.isfinite(value) and lower <= value <= upper):
                raise VariantError(f"stress {key} = {value!r} lies outside [{lower}, {upper}]")
            out[key] = value
    if "constants" in stress:
        out["constants"] = {str(k): float(v) for k, v in dict(stress["constants"]).items()}
    return out


def coloured_noise(clean: np.ndarray, fraction: float, ar1: float, rng: np.random.Generator) -> np.ndarray:
    """``clean`` plus AR(1) Gaussian noise e_k = a e_(k-1) + sqrt(1 - a^2) w_k, stationary from
    the first sample, of standard deviation ``fraction`` x each channel's RMS (as white noise)."""
    from scipy.signal import lfilter

    clean = np.asarray(clean, dtype=float)
    sigma = fraction * np.sqrt(np.mean(clean ** 2, axis=0))
    w = rng.standard_normal(clean.shape)
    if ar1 == 0.0 or clean.shape[0] < 2:
        return clean + w * sigma
    e = np.empty_like(w)
    e[0] = w[0]
    e[1:], _ = lfilter([math.sqrt(1.0 - ar1 ** 2)], [1.0, -ar1], w[1:], axis=0, zi=ar1 * w[:1])
    return clean + e * sigma


def quantise(values: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """Every column rounded to a multiple of its step (a step of 0 leaves it as it is)."""
    steps = np.asarray(steps, dtype=float)
    safe = np.where(steps > 0, steps, 1.0)
    return np.where(steps > 0, np.round(values / safe) * safe, values)


def perturbed_base(concept: str, rng: np.random.Generator, fraction: float = 0.10,
                   rig_fraction: float = RIG_PERTURBATION) -> dict[str, float]:
    """Nominal parameters times U(1 - fraction, 1 + fraction); the rig-measured gains (those
    with a prior, p_ACE and p_PCE) by U(+-rig_fraction), inside their measured uncertainty."""
    parameters = get_model(_check_concept(concept)).parameters
    out = {}
    for p in parameters:
        spread = rig_fraction if p.prior_std is not None else fraction
        out[p.name] = float(np.clip(p.nominal * (1.0 + rng.uniform(-spread, spread)), p.lower, p.upper))
    return out


def validation_scaled() -> Experiment:
    """A second held-out profile: the validation run's reversals at 0.8 x the angles and
    1.25 x the durations (slower), 1.2 x its load (F_a = 3.6 kN + 48 kN phi/40 deg, split 60/40)."""
    knots = np.array([(0, 0), (1, 0), (4, 15), (6, 15), (10, 5), (12, 5), (17, 30), (19, 30),
                      (23, 10), (25, 10), (28, 25), (30, 25), (37, 0), (40, 0)], dtype=float)
    time = np.round(np.arange(0.0, 50.0, 0.01), 10)
    phi_deg = np.interp(time, 1.25 * knots[:, 0], 0.8 * knots[:, 1])
    load = 1.2 * (3e3 + 40e3 * phi_deg / 40.0)
    return Experiment("validation-scaled", time, {"phi_r": np.radians(phi_deg), "F_ER1": -0.6 * load,
                                                  "F_ER2": -0.4 * load})


def record_channels(concept: str, channels) -> tuple[str, ...]:
    """None or "full": every output; "realistic": the rig sensors; else the named channels."""
    model = get_model(_check_concept(concept))
    if channels is None or channels == "full":
        return tuple(model.outputs)
    if channels == "realistic":
        return REALISTIC_CHANNELS[concept]
    channels = (channels,) if isinstance(channels, str) else tuple(channels)
    unknown = [ch for ch in channels if ch not in model.outputs]
    if unknown or not channels:
        raise VariantError(f"unknown channel {unknown[0] if unknown else '(none given)'!r} for {concept}; "
                           f"give 'realistic', 'full' or some of {', '.join(model.outputs)}")
    return channels


def make_records(concept: str, variant: str | None, params: Mapping[str, float] | None, *, seed: int,
                 base_perturbation: float = 0.10, noise: float = 0.02, channels=None,
                 rig_perturbation: float = RIG_PERTURBATION, stress: Mapping[str, Any] | None = None
                 ) -> tuple[Measurement, Measurement, Measurement, dict[str, Any]]:
    """Rig-like records of one concept with a hidden variant: (estimation on deploy-retract,
    validation, second validation on :func:`validation_scaled`, truth).

    The base parameters are the nominal ones perturbed by U(+-``base_perturbation``) (rig-measured
    gains by U(+-``rig_perturbation``)); each record gets independent Gaussian noise of
    ``noise`` x its channel's RMS. ``variant`` None makes a no-effect record (expected verdict
    ``none``). ``channels``: None/"full", "realistic" or a list. The measurements carry no label;
    ``truth`` holds variant, family, expected verdict (the family, ``unexplained`` or ``none``),
    parameters, base parameters, seed and settings. Everything derives from ``seed``.

    ``stress`` (:func:`draw_stress`, :func:`check_stress`): model-form differences a rig always
    has, for no-effect records that should still read ``none``: ``ar1`` coloured noise
    (:func:`coloured_noise`), ``quantisation`` of every recorded channel to a step of that
    fraction of its clean RMS on the estimation record (the same step on every record, as a
    rig's converters), design ``constants`` off by relative offsets and an ``input_filter``
    time constant of command shaping (:func:`shape_command`). ``truth["stress"]`` holds them
    with the quantisation steps per channel.
    """
    concept = _check_concept(concept)
    if variant is None:
        if params:
            raise VariantError("variant parameters given without a variant; name the variant")
        family, checked, expected = None, {}, "none"
    else:
        family = get_variant(variant).family
        checked = check_variant_parameters(variant, params or {})
        expected = family if family is not None else "unexplained"
    if not (0.0 <= base_perturbation < 1.0 and 0.0 <= rig_perturbation < 1.0):
        raise VariantError(f"perturbations must lie in [0, 1), got {base_perturbation} and {rig_perturbation}")
    chosen = record_channels(concept, channels)
    model = get_model(concept)
    index = [model.outputs.index(ch) for ch in chosen]
    stress = check_stress(stress)
    streams = np.random.SeedSequence(int(seed)).spawn(4)
    base = perturbed_base(concept, np.random.default_rng(streams[0]), base_perturbation, rig_perturbation)
    records, steps = [], None
    for experiment, stream in zip((deploy_retract(), validation(), validation_scaled()), streams[1:]):
        clean = simulate_variant(concept, experiment, base, variant, checked,
                                 constant_offsets=stress.get("constants"),
                                 input_filter=stress.get("input_filter", 0.0))[:, index]
        rng = np.random.default_rng(stream)
        if noise > 0 and stress.get("ar1", 0.0) > 0:
            values = coloured_noise(clean, noise, stress["ar1"], rng)
        else:
            values = add_noise(clean, noise, rng) if noise > 0 else clean
        if stress.get("quantisation", 0.0) > 0:
            if steps is None:   # the estimation record's RMS sets the converters' steps
                steps = stress["quantisation"] * np.sqrt(np.mean(clean ** 2, axis=0))
            values = quantise(values, steps)
        records.append(Measurement(concept, experiment, chosen, values,
                                   {"noise_fraction": noise, "seed": int(seed),
                                    "source": "simulated (independent simulator, gap variants)"}))
    if steps is not None:
        stress = {**stress, "steps": dict(zip(chosen, map(float, steps)))}
    truth = {"concept": concept, "variant": variant, "family": family, "expected": expected,
             "parameters": checked, "base_parameters": base, "seed": int(seed), "noise": noise,
             "base_perturbation": base_perturbation, "rig_perturbation": rig_perturbation,
             "channels": list(chosen), "experiments": [r.experiment.name for r in records], "stress": stress}
    return records[0], records[1], records[2], truth


def visibility(concept: str, variant: str, params: Mapping[str, float], *, experiment: Experiment | None = None,
               noise: float = 0.02, channels=None, base=None) -> dict[str, float]:
    """Noise-normalised chi-square excess of the variant against the nominal model, per channel:
    sum_k ((y_variant - y_nominal) / (noise x RMS(y_nominal)))^2 on ``experiment`` (default
    deploy-retract), at the same base parameters (default nominal). Pure noise makes the
    chi-square fluctuate by sqrt(2 n_samples); an excess above twice that is visible."""
    experiment = deploy_retract() if experiment is None else experiment
    chosen = record_channels(concept, "realistic" if channels is None else channels)
    model = get_model(concept)
    index = [model.outputs.index(ch) for ch in chosen]
    nominal = simulate_variant(concept, experiment, base)[:, index]
    varied = simulate_variant(concept, experiment, base, variant, params)[:, index]
    sigma = noise * np.sqrt(np.mean(nominal ** 2, axis=0))
    excess = np.sum(((varied - nominal) / sigma) ** 2, axis=0)
    return dict(zip(chosen, map(float, excess)))


__all__ = ["CONCEPTS", "FAMILIES", "REALISTIC_CHANNELS", "STRESS_CONSTANTS", "STRESS_RANGES", "UNSEEN_VARIANTS",
           "UNSEEN_VARIANTS_2", "UNSEEN_VARIANTS_3", "VARIANTS", "Variant", "VariantError", "VariantParameter",
           "check_stress", "check_variant_parameters", "coloured_noise", "delay_allpass", "delay_hermite",
           "draw_stress", "draw_variant_parameters", "get_variant", "make_records", "perturbed_base", "quantise",
           "read_between_samples", "record_channels", "sample_hold", "shape_command", "simulate_variant",
           "validation_scaled", "visibility", "window_average"]
