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

How the variants differ from the catalogue's forms
--------------------------------------------------
``backlash_two_mass`` (family ``backlash``)
    Catalogue: kinematic play operator in the bevel gear(s), load side held by its friction,
    relaxation state. Here: ONE dead band +-delta at the motor coupling (LT/HS: after the
    magnetic gear) inside a compliant two-mass drive train - motor and load inertia (split of
    J by ``load_share``), a spring of mode ``frequency`` (25-60 Hz) and a damper that act only
    outside the dead band (no torque inside it, no pulling torque at separation). ``delta`` is
    the half play seen at the carriage [m].
``backlash_output_deadzone`` (``backlash``)
    Play between the screw nut and the carriage: the carriage follows the nut through an exact
    play operator of half width ``delta`` [m] (projected after every RK4 step); the rig measures
    the carriage (y1, y2, and the position loop closes on it); the load reaches the screw only
    while a flank is in contact.
``stribeck_exponential`` / ``stribeck_gaussian`` / ``stribeck_rational`` (``stribeck``)
    Catalogue: C (1 + rho exp(-(v/v_s)^2)) tanh(v/eps), v referred to the screw shaft. Here v
    is each friction term's own shaft speed and the curves are C (1 + rho exp(-|v|/v_s)),
    C (1 + rho exp(-(|v|/v_s)^2)) with the algebraic sign v / sqrt(v^2 + eps^2), and
    C (1 + rho / (1 + (v/v_s)^2)).
``torque_ripple_harmonics`` (``torque_ripple``)
    Catalogue: one harmonic k_n A sin(n_p theta + phi). Here three: sum_k A_k sin(k n_p theta +
    phi_k), k = 1..3, amplitudes in N m, n_p as the catalogue (HT/LS 6, LT/HS 4).
``sensor_delay_hermite`` / ``sensor_delay_allpass`` (``sensor_delay``)
    Catalogue: linear interpolation. Here: cubic Hermite (Catmull-Rom) interpolation, or a
    Thiran all-pass IIR filter (order <= 3, maximally flat group delay tau; phase-dispersive
    like a real sensor filter). tau is drawn away from multiples of the sample time.
``shaft_compliance_two_mass`` (``shaft_compliance``)
    Catalogue: modal form with period, damping ratio and load fraction. Here: absolute
    coordinates (load speed and angle as states), the load share drawn from 0.6-0.8 (HT/LS) /
    0.45-0.65 (LT/HS), mode frequency [Hz] and damping ratio.
``load_friction_linear`` / ``load_friction_power`` (``load_dependent_friction``)
    Catalogue: C_TS + mu r |F|. Here: mu r (sqrt(F^2 + F0^2) - F0), or a power law
    mu r F_ref (|F|_s / F_ref)^1.2 - mu r F_ref (F0 / F_ref)^1.2, |F|_s = sqrt(F^2 + F0^2),
    F0 = 200 N, F_ref = 10 kN, on both ball screws.
``ujoint_cardan`` (``ujoint_kinematics``)
    Catalogue: eq. 8 at the design angles scaled by a ripple factor, one yoke phase for both
    stations (``ujoint_kinematics``) or a factor and a phase per station (``ujoint_stations``). Here: the
    Cardan relation tan(phi_out) = tan(phi_in) / cos(beta) differentiated,
    d phi_out / d phi_in = cos(beta) / (cos^2(beta) cos^2(phi_in) + sin^2(phi_in)), at a rig joint
    angle beta_k larger than designed and a yoke phase per station; the ideal joint passes the
    screw torque back times the same ratio (power balance), on top of the model's 1/cos(beta).

Out of the catalogue (family ``None``): ``motor_torque_lag`` (first-order lag tau_e of the motor
torque; HT/LS measures the lagged current), ``current_sensor_error`` (measured I_A = (1 + g) I_A
+ offset), ``position_friction_spot`` (Coulomb friction bump on screw 1 over a raised-cosine
window of carriage position) and ``load_follows_position`` (the rig's load is set from the
measured carriage position, not from the command: each carriage feels an extra
-stiffness / 2 x (y_k - k_y phi_r)). A lightly damped flap resonance was tried and left out:
the position loops move the carriages so smoothly (bandwidth ~1 rad/s) that even a 20 t
equivalent flap mass at 3-10 Hz changes the records by less than 2 % noise shows.

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
from dataclasses import dataclass, field
from typing import Any, Mapping, Sequence

import numpy as np
from numba import njit

from ..experiments import Experiment, Measurement, add_noise, deploy_retract, validation
from ..models import get_model
from ..errors import EmaUqError

TWO_PI = 2.0 * math.pi
CONCEPTS = ("htls", "lths")
FAMILIES = ("backlash", "stribeck", "torque_ripple", "sensor_delay", "shaft_compliance",
            "load_dependent_friction", "ujoint_kinematics")
#: rig sensors per concept (as ``ema_uq.identifiability.REALISTIC_CHANNELS``)
REALISTIC_CHANNELS = {"htls": ("Omega", "y1", "y2", "I_A"), "lths": ("Omega", "y1", "y2", "I_A", "U_A")}
#: ripple periods per motor revolution (as the catalogue's torque_ripple)
RIPPLE_PERIODS = {"htls": 6.0, "lths": 4.0}
RIG_PERTURBATION = 0.01     # rig-measured gains (p_ACE, p_PCE) move inside their 2 % uncertainty
LOAD_SMOOTHING = 200.0      # N, F0 of the smoothed |F| of the load-friction variants
LOAD_REFERENCE = 10e3       # N, F_ref of the power-law load friction
LOAD_EXPONENT = 1.2
CONTACT_RAMP = 0.1          # fraction of the output play over which the load is taken up
DELAY_CLEARANCE = 0.1       # drawn delays stay this fraction of a sample away from a multiple


class VariantError(EmaUqError):
    """An unknown variant or concept, or a variant parameter that is missing, unknown or out of bounds."""


# ------------------------------------------------------------------------------------------
# variant descriptions
# ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class VariantParameter:
    """One variant parameter: unit, physical bounds [lower, upper] (checked on every value)
    and the draw range [low, high] (per concept where ``concept_ranges`` says so).

    ``kind``: ``magnitude`` (drawn log-uniform; ``weak`` = the end that is least visible,
    "low" or "high"), ``phase`` (uniform in [0, 2 pi)) or ``shape`` (uniform in the range).
    """

    name: str
    unit: str
    low: float
    high: float
    kind: str
    lower: float
    upper: float
    description: str
    weak: str = "low"
    concept_ranges: Mapping[str, tuple[float, float]] = field(default_factory=dict)

    def draw_range(self, concept: str | None) -> tuple[float, float]:
        if self.concept_ranges:
            if concept not in self.concept_ranges:
                raise VariantError(f"parameter {self.name} has a range per concept; give concept= one of "
                                   f"{', '.join(self.concept_ranges)}")
            return self.concept_ranges[concept]
        return self.low, self.high


@dataclass(frozen=True)
class Variant:
    """One effect variant: ``family`` is the catalogue effect the diagnosis should name
    (``None``: outside the catalogue, the right verdict is ``unexplained``)."""

    name: str
    family: str | None
    description: str
    parameters: tuple[VariantParameter, ...]
    kernel_id: int                 # dynamics inside the RK4 kernel (0: post-processing only)
    step_divisor: int = 1          # RK4 step = the concept's step / step_divisor

    @property
    def parameter_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.parameters)

    def weakest(self, concept: str) -> dict[str, float]:
        """Every magnitude at its least visible end, phases 0, shapes mid-range."""
        out = {}
        for p in self.parameters:
            low, high = p.draw_range(concept)
            if p.kind == "magnitude":
                out[p.name] = low if p.weak == "low" else high
            else:
                out[p.name] = 0.0 if p.kind == "phase" else 0.5 * (low + high)
        return out

    def ranges(self, concept: str | None = None) -> dict[str, tuple[float, float]]:
        return {p.name: p.draw_range(concept) for p in self.parameters}


def _mag(name, unit, low, high, lower, upper, description, weak="low", per_concept=None):
    return VariantParameter(name, unit, low, high, "magnitude", lower, upper, description, weak,
                            per_concept or {})


def _phase(name, description):
    return VariantParameter(name, "rad", 0.0, TWO_PI, "phase", -1e3, 1e3, description)


def _shape(name, unit, low, high, lower, upper, description, per_concept=None):
    return VariantParameter(name, unit, low, high, "shape", lower, upper, description, "low", per_concept or {})


# kernel ids of the dynamic variants
(V_NONE, V_BACKLASH_TWO_MASS, V_DEADZONE, V_STRIBECK_EXP, V_STRIBECK_GAUSS, V_STRIBECK_RATIONAL, V_RIPPLE,
 V_SHAFT_TWO_MASS, V_LOAD_LINEAR, V_LOAD_POWER, V_CARDAN, V_TORQUE_LAG, V_SPOT, V_LOAD_FOLLOW) = range(14)

_STRIBECK = (_mag("ratio", "1", 0.4, 3.0, 0.0, 50.0, "breakaway excess C_s / C - 1 of every Coulomb term"),
             _mag("speed", "rad/s", 0.5, 4.0, 1e-4, 1e3, "Stribeck speed of each term's own shaft"))
_DELAY = (_mag("tau", "s", 0.006, 0.035, 0.0, 0.5, "delay of every measured channel"),)
_MODE = (_mag("damping", "1", 0.03, 0.2, 1e-4, 2.0, "damping ratio of the torsional mode", weak="high"),)


def _build_variants() -> dict[str, Variant]:
    variants = (
        Variant("backlash_two_mass", "backlash",
                "dead band +-delta in a compliant two-mass drive train between motor and screws",
                (_mag("delta", "m", 4e-5, 3e-4, 0.0, 0.01, "half play seen at the carriage"),
                 _mag("frequency", "Hz", 25.0, 60.0, 1.0, 500.0, "torsional mode in contact", weak="high"),
                 *_MODE,
                 _shape("load_share", "1", 0.3, 0.7, 0.05, 0.95, "load-side share of the inertia J")),
                V_BACKLASH_TWO_MASS),
        Variant("backlash_output_deadzone", "backlash",
                "play between screw nut and carriage; the rig measures the carriage",
                (_mag("delta", "m", 3e-5, 3e-4, 0.0, 0.01, "half play between nut and carriage"),), V_DEADZONE),
        Variant("stribeck_exponential", "stribeck", "C (1 + rho exp(-|v|/v_s)) on every Coulomb term",
                _STRIBECK, V_STRIBECK_EXP),
        Variant("stribeck_gaussian", "stribeck",
                "C (1 + rho exp(-(|v|/v_s)^2)) v / sqrt(v^2 + eps^2) on every Coulomb term",
                _STRIBECK, V_STRIBECK_GAUSS),
        Variant("stribeck_rational", "stribeck", "C (1 + rho / (1 + (v/v_s)^2)) on every Coulomb term",
                _STRIBECK, V_STRIBECK_RATIONAL),
        Variant("torque_ripple_harmonics", "torque_ripple", "motor torque ripple sum_k A_k sin(k n_p theta + phi_k)",
                tuple(_mag(f"amplitude{k}", "N m", 0.0, 0.0, 0.0, 1e3, f"ripple amplitude of harmonic {k}",
                           per_concept={"htls": (0.3, 3.0), "lths": (0.012, 0.1)}) for k in (1, 2, 3))
                + tuple(_phase(f"phase{k}", f"phase of harmonic {k} at theta = 0") for k in (1, 2, 3)),
                V_RIPPLE, step_divisor=4),
        Variant("sensor_delay_hermite", "sensor_delay", "every channel delayed by tau, cubic Hermite interpolation",
                _DELAY, V_NONE),
        Variant("sensor_delay_allpass", "sensor_delay", "every channel through a Thiran all-pass of delay tau",
                _DELAY, V_NONE),
        Variant("shaft_compliance_two_mass", "shaft_compliance",
                "torsional spring and damper between motor and drive train, two masses in absolute coordinates",
                (_mag("frequency", "Hz", 15.0, 50.0, 1.0, 500.0, "torsional mode", weak="high"), *_MODE,
                 _shape("load_share", "1", 0.0, 0.0, 0.05, 0.95, "load-side share of the inertia J",
                        per_concept={"htls": (0.6, 0.8), "lths": (0.45, 0.65)})),
                V_SHAFT_TWO_MASS),
        Variant("load_friction_linear", "load_dependent_friction", "ball-screw friction + mu r (sqrt(F^2 + F0^2) - F0)",
                (_mag("mu", "1", 1.5e-3, 1.5e-2, 0.0, 0.5, "load coefficient of the ball-screw friction"),),
                V_LOAD_LINEAR),
        Variant("load_friction_power", "load_dependent_friction",
                "ball-screw friction + mu r F_ref (|F|/F_ref)^1.2 (smoothed |F|)",
                (_mag("mu", "1", 1.5e-3, 1.5e-2, 0.0, 0.5, "load coefficient at F_ref = 10 kN"),), V_LOAD_POWER),
        Variant("ujoint_cardan", "ujoint_kinematics", "exact Cardan speed ratio at rig joint angles above design",
                (_mag("beta1", "rad", math.radians(8.0), math.radians(16.0), 0.0, 1.2, "rig joint angle, station 1"),
                 _mag("beta2", "rad", math.radians(10.0), math.radians(20.0), 0.0, 1.2, "rig joint angle, station 2"),
                 _phase("phase1", "yoke phase of station 1"), _phase("phase2", "yoke phase of station 2")),
                V_CARDAN),
        Variant("motor_torque_lag", None, "first-order lag of the motor torque",
                (_mag("tau", "s", 0.0, 0.0, 2.5e-4, 1.0, "time constant of the torque lag",
                      per_concept={"htls": (0.005, 0.02), "lths": (3e-4, 2e-3)}),), V_TORQUE_LAG),
        Variant("current_sensor_error", None, "measured I_A = (1 + gain) I_A + offset",
                (_mag("gain", "1", 0.03, 0.08, -0.5, 0.5, "relative gain error of the current sensor"),
                 _mag("offset", "A", 0.2, 1.0, -100.0, 100.0, "offset of the current sensor")), V_NONE),
        Variant("position_friction_spot", None, "Coulomb friction bump on screw 1 over a window of carriage position",
                (_mag("friction", "N m", 2.0, 6.0, 0.0, 100.0, "peak extra Coulomb torque at screw 1"),
                 _shape("position", "m", 0.06, 0.18, -1.0, 1.0, "carriage position of the spot centre"),
                 _shape("width", "m", 0.02, 0.05, 1e-4, 1.0, "half width of the raised-cosine window")), V_SPOT),
        Variant("load_follows_position", None,
                "the rig load follows the measured carriage position: extra -stiffness/2 (y_k - k_y phi_r)",
                (_mag("stiffness", "N/m", 2e4, 1.2e5, 0.0, 1e7,
                      "load gradient with carriage position (the profiles' own: ~1.1e5 N/m)"),), V_LOAD_FOLLOW),
    )
    return {v.name: v for v in variants}


VARIANTS: dict[str, Variant] = _build_variants()


def get_variant(name: str) -> Variant:
    try:
        return VARIANTS[name]
    except (KeyError, TypeError):
        raise VariantError(f"unknown variant {name!r}; choose one of: {', '.join(VARIANTS)}") from None


def _check_concept(concept: str) -> str:
    if concept not in CONCEPTS:
        raise VariantError(f"unknown concept {concept!r} for the independent simulator; choose htls or lths")
    return concept


def draw_variant_parameters(name: str, rng: np.random.Generator, concept: str | None = None) -> dict[str, float]:
    """Random parameters of variant ``name``: magnitudes log-uniform over their range, phases
    uniform in [0, 2 pi), shapes uniform. ``concept`` is needed by variants whose ranges differ
    per concept (``torque_ripple_harmonics``, ``shaft_compliance_two_mass``). Sensor delays are
    redrawn until they lie at least ``DELAY_CLEARANCE`` samples away from a multiple of 10 ms."""
    variant = get_variant(name)
    while True:
        values = {}
        for p in variant.parameters:
            low, high = p.draw_range(concept)
            if p.kind == "magnitude":
                values[p.name] = float(math.exp(rng.uniform(math.log(low), math.log(high))))
            elif p.kind == "phase":
                values[p.name] = float(rng.uniform(0.0, TWO_PI))
            else:
                values[p.name] = float(rng.uniform(low, high))
        if variant.family != "sensor_delay":
            return values
        lag = values["tau"] / 0.01
        if abs(lag - round(lag)) >= DELAY_CLEARANCE:
            return values


def check_variant_parameters(name: str, params: Mapping[str, float]) -> dict[str, float]:
    """The parameters as floats; a missing, unknown, non-finite or out-of-bounds one is a VariantError."""
    variant = get_variant(name)
    params = dict(params)
    names = variant.parameter_names
    stray = [k for k in params if k not in names]
    if stray:
        raise VariantError(f"variant {name} has no parameter {stray[0]!r}; its parameters are {', '.join(names)}")
    missing = [k for k in names if k not in params]
    if missing:
        raise VariantError(f"variant {name} needs a value for {', '.join(missing)}; "
                           f"draw them with draw_variant_parameters({name!r}, rng)")
    out = {}
    for p in variant.parameters:
        try:
            value = float(params[p.name])
        except (TypeError, ValueError):
            raise VariantError(f"variant {name}: {p.name} = {params[p.name]!r} is not a number") from None
        if not (math.isfinite(value) and p.lower <= value <= p.upper):
            raise VariantError(f"variant {name}: {p.name} = {value:g} {p.unit} lies outside "
                               f"[{p.lower:g}, {p.upper:g}]; give a finite value inside")
        out[p.name] = value
    return out


# ------------------------------------------------------------------------------------------
# the independent simulator: layouts
# ------------------------------------------------------------------------------------------
#: base parameters in this kernel's own order (absent ones of a concept are 0 and never read)
PARAMETER_LAYOUT = ("J", "B_TS1", "C_TS1", "B_U1", "C_U1", "B_TP1", "C_TP1",
                    "B_TS2", "C_TS2", "B_U2", "C_U2", "B_TP2", "C_TP2",
                    "k_n", "p_ACE", "p_PCE", "B_MG", "C_MG", "R_A", "L_A", "k_s")
(T_J, T_BTS1, T_CTS1, T_BU1, T_CU1, T_BTP1, T_CTP1, T_BTS2, T_CTS2, T_BU2, T_CU2, T_BTP2, T_CTP2,
 T_KN, T_PACE, T_PPCE, T_BMG, T_CMG, T_RA, T_LA, T_KS) = range(21)
STATION_STRIDE = 6  # station-2 losses follow station 1's in the same order
#: design constants in this kernel's own order, then the values derived from them
CONSTANT_LAYOUT = ("omega_eps", "r", "gamma", "beta1", "beta2", "k_y", "M_Bmax", "K_b", "Omega_half",
                   "i_TP1", "i_TP2", "i_MG", "i_BG1", "i_BG2", "D_IS", "M_min", "M_max", "U_max")
(K_EPS, K_R, K_GAMMA, K_BETA1, K_BETA2, K_KY, K_MBMAX, K_KB, K_OHALF, K_ITP1, K_ITP2, K_IMG, K_IBG1, K_IBG2,
 K_DIS, K_MMIN, K_MMAX, K_UMAX, K_LEAD, K_RSC, K_INVCB1, K_INVCB2) = range(22)

#: state layout after the concept offset o (LT/HS: x[0] = I_A, o = 1; HT/LS: o = 0)
(S_OMEGA, S_Y1, S_Y2, S_THETA, S_LOAD_SPEED, S_LOAD_ANGLE, S_LAG, S_CARRIAGE1, S_CARRIAGE2) = range(9)
N_STATE = 10

HTLS_OUTPUTS = ("Omega", "y1", "y2", "I_A", "Omega_TP1", "Omega_TP2", "Omega_U1", "Omega_U2",
                "M_ER1", "M_ER2", "M_TSER1", "M_TSER2", "M_UER1", "M_UER2", "M_TPER1", "M_TPER2")
LTHS_OUTPUTS = ("Omega", "y1", "y2", "I_A", "U_A", "Omega_MG", "Omega_TP1", "Omega_MG2", "Omega_TP2",
                "Omega_U1", "Omega_U2", "M_ER1", "M_ER2", "M_TSER1", "M_TSER2", "M_UER1", "M_UER2",
                "M_MG2", "M_TPER", "M_MGER")
KERNEL_OUTPUTS = {"htls": HTLS_OUTPUTS, "lths": LTHS_OUTPUTS}
N_VARIANT_VALUES = 8


def _kernel_parameters(concept: str, base: Mapping[str, float]) -> np.ndarray:
    model_names = get_model(concept).parameters.names
    return np.array([float(base[n]) if n in model_names else 0.0 for n in PARAMETER_LAYOUT])


def _kernel_constants(concept: str, offsets: Mapping[str, float] | None = None) -> np.ndarray:
    """Design constants in kernel order, each times (1 + ``offsets[name]``) (a rig built off its
    drawing), then the values derived from them."""
    constants = get_model(concept).constants
    values = dict(zip(constants.names, constants.nominal))
    for name, offset in (offsets or {}).items():
        if name not in values:
            raise VariantError(f"{concept} has no design constant {name!r}; offsets apply to "
                               f"{', '.join(values)}")
        if not (math.isfinite(offset) and abs(offset) < 0.5):
            raise VariantError(f"design constant offset {name} = {offset!r} must be finite and within +-0.5")
        values[name] = values[name] * (1.0 + float(offset))
    c = [float(values.get(n, 0.0)) for n in CONSTANT_LAYOUT]
    r, gamma = values["r"], values["gamma"]
    c += [r * math.tan(gamma), r * math.sin(gamma) * math.cos(gamma),
          1.0 / math.cos(values["beta1"]), 1.0 / math.cos(values["beta2"])]
    return np.array(c)


def _carriage_per_motor_radian(concept: str, c: np.ndarray) -> float:
    """d y1 / d theta [m/rad]: station 1's carriage travel per motor radian (rigid train)."""
    if concept == "htls":
        return c[K_LEAD] / c[K_ITP1]
    return c[K_LEAD] / (c[K_IMG] * c[K_IBG1])


def _kernel_values(concept: str, variant: Variant | None, params: Mapping[str, float], c: np.ndarray) -> np.ndarray:
    """The variant's parameters in kernel units (rad/s, motor radians, ...), padded to N_VARIANT_VALUES."""
    v = np.zeros(N_VARIANT_VALUES)
    if variant is None or variant.kernel_id == V_NONE:
        return v
    p, kid = params, variant.kernel_id
    if kid in (V_BACKLASH_TWO_MASS, V_SHAFT_TWO_MASS):
        delta = p["delta"] / _carriage_per_motor_radian(concept, c) if kid == V_BACKLASH_TWO_MASS else 0.0
        v[:4] = (p["load_share"], TWO_PI * p["frequency"], p["damping"], delta)
    elif kid == V_DEADZONE:
        v[0] = p["delta"]
    elif kid in (V_STRIBECK_EXP, V_STRIBECK_GAUSS, V_STRIBECK_RATIONAL):
        v[:2] = (p["ratio"], p["speed"])
    elif kid == V_RIPPLE:
        v[:7] = (p["amplitude1"], p["amplitude2"], p["amplitude3"], p["phase1"], p["phase2"], p["phase3"],
                 RIPPLE_PERIODS[concept])
    elif kid in (V_LOAD_LINEAR, V_LOAD_POWER, V_TORQUE_LAG):
        v[0] = p["mu"] if kid != V_TORQUE_LAG else p["tau"]
    elif kid == V_CARDAN:
        v[:4] = (p["beta1"], p["beta2"], p["phase1"], p["phase2"])
    elif kid == V_SPOT:
        v[:3] = (p["friction"], p["position"], p["width"])
    elif kid == V_LOAD_FOLLOW:
        v[0] = p["stiffness"]
    return v


# ------------------------------------------------------------------------------------------
# the independent simulator: right-hand sides (own code, not the package's equation modules)
# ------------------------------------------------------------------------------------------
@njit(cache=True, error_model="numpy")
def _coulomb(level, v, eps, vid, vv):
    """A Coulomb term of level ``level`` [N m] at shaft speed ``v`` [rad/s], nominal or Stribeck."""
    if vid == V_STRIBECK_EXP:
        return level * (1.0 + vv[0] * math.exp(-abs(v) / vv[1])) * math.tanh(v / eps)
    if vid == V_STRIBECK_GAUSS:
        q = abs(v) / vv[1]
        return level * (1.0 + vv[0] * math.exp(-q * q)) * v / math.sqrt(v * v + eps * eps)
    if vid == V_STRIBECK_RATIONAL:
        q = v / vv[1]
        return level * (1.0 + vv[0] / (1.0 + q * q)) * math.tanh(v / eps)
    return level * math.tanh(v / eps)


@njit(cache=True, error_model="numpy")
def _brake(engaged, v, c):
    """Eq. 3 against the motion of a shaft at speed v; 0 when released."""
    if engaged == 0.0:
        return 0.0
    full = c[K_MBMAX]
    holding = full - 0.5 * full * (1.0 - math.exp(-c[K_KB] * abs(v) / c[K_OHALF]))
    return engaged * holding * math.tanh(v / c[K_EPS])


@njit(cache=True, error_model="numpy")
def _station(k, vid, w_tp, a_tp, x, u, th, c, vv, o):
    """Station k (0, 1): U-joint and ball screw driven at bevel-output speed w_tp, angle a_tp.

    Returns (Omega_U, M_ER, M_TSER, M_UER, carriage position)."""
    eps = c[K_EPS]
    s = STATION_STRIDE * k
    ratio = 1.0
    if vid == V_CARDAN:  # d phi_out / d phi_in of tan(phi_out) = tan(phi_in) / cos(beta)
        cb = math.cos(vv[k])
        phi = a_tp + vv[2 + k]
        ratio = cb / (cb * cb * math.cos(phi) ** 2 + math.sin(phi) ** 2)
    w_u = ratio * w_tp
    nut = x[o + S_Y1 + k]
    force = u[1 + k]
    contact = 1.0
    carriage = nut
    if vid == V_LOAD_FOLLOW:
        force -= 0.5 * vv[0] * (nut - c[K_KY] * u[0])
    elif vid == V_DEADZONE and vv[0] > 0.0:
        carriage = min(max(x[o + S_CARRIAGE1 + k], nut - vv[0]), nut + vv[0])
        ramp = min(max((abs(nut - carriage) / vv[0] - 1.0 + CONTACT_RAMP) / CONTACT_RAMP, 0.0), 1.0)
        contact = ramp * ramp * (3.0 - 2.0 * ramp)
    c_ts = th[T_CTS1 + s]
    if vid == V_LOAD_LINEAR:
        c_ts += vv[0] * c[K_R] * (math.sqrt(force * force + LOAD_SMOOTHING ** 2) - LOAD_SMOOTHING)
    elif vid == V_LOAD_POWER:
        size = math.sqrt(force * force + LOAD_SMOOTHING ** 2) / LOAD_REFERENCE
        c_ts += vv[0] * c[K_R] * LOAD_REFERENCE * (size ** LOAD_EXPONENT
                                                   - (LOAD_SMOOTHING / LOAD_REFERENCE) ** LOAD_EXPONENT)
    elif vid == V_SPOT and k == 0:
        xi = (nut - vv[1]) / vv[2]
        if abs(xi) < 1.0:
            c_ts += vv[0] * 0.5 * (1.0 + math.cos(math.pi * xi))
    m_er = -c[K_RSC] * force * contact
    m_tser = th[T_BTS1 + s] * w_u + _coulomb(c_ts, w_u, eps, vid, vv) + m_er
    m_uer = ratio * m_tser * c[K_INVCB1 + k] + th[T_BU1 + s] * w_u + _coulomb(th[T_CU1 + s], w_u, eps, vid, vv)
    return w_u, m_er, m_tser, m_uer, carriage


@njit(cache=True, error_model="numpy")
def _coupling_torque(twist, twist_rate, stiffness, damping, half_play):
    """Torque through a spring-damper with a dead band of +-half_play (no torque inside it, and
    no pulling torque while the flanks separate); half_play = 0 is a plain shaft."""
    if half_play <= 0.0:
        return stiffness * twist + damping * twist_rate
    if twist > half_play:
        return max(stiffness * (twist - half_play) + damping * twist_rate, 0.0)
    if twist < -half_play:
        return min(stiffness * (twist + half_play) + damping * twist_rate, 0.0)
    return 0.0


@njit(cache=True, error_model="numpy")
def _two_mass(drive, load, omega, theta, w_load, a_load, inertia, vv, dx, o):
    """Motor inertia (1 - share) J under ``drive``, load inertia share J under ``load`` [N m],
    joined by the coupling of mode vv[1] [rad/s], damping ratio vv[2], half play vv[3] [rad]."""
    share, wn, zeta = vv[0], vv[1], vv[2]
    j_motor, j_load = (1.0 - share) * inertia, share * inertia
    j_red = j_motor * j_load / inertia
    torque = _coupling_torque(theta - a_load, omega - w_load, j_red * wn * wn, 2.0 * zeta * wn * j_red, vv[3])
    dx[o + S_OMEGA] = (drive - torque) / j_motor
    dx[o + S_LOAD_SPEED] = (torque - load) / j_load
    dx[o + S_LOAD_ANGLE] = w_load


@njit(cache=True, error_model="numpy")
def _ripple(vid, theta, vv):
    if vid != V_RIPPLE:
        return 0.0
    total = 0.0
    for j in range(3):
        total += vv[j] * math.sin((j + 1) * vv[6] * theta + vv[3 + j])
    return total


@njit(cache=True, error_model="numpy")
def _htls_rhs(vid, x, u, th, c, vv, dx, y, outputs):
    """HT/LS: dx (N_STATE,) and, if ``outputs``, y in HTLS_OUTPUTS order."""
    dx[:] = 0.0
    eps = c[K_EPS]
    omega, theta = x[S_OMEGA], x[S_THETA]
    two_mass = vid == V_BACKLASH_TWO_MASS or vid == V_SHAFT_TWO_MASS
    w_d = x[S_LOAD_SPEED] if two_mass else omega
    a_d = x[S_LOAD_ANGLE] if two_mass else theta
    i1, i2 = c[K_ITP1], c[K_ITP2]
    w_tp1, w_tp2 = w_d / i1, w_d / i2
    w_u1, m_er1, m_tser1, m_uer1, y1 = _station(0, vid, w_tp1, a_d / i1, x, u, th, c, vv, 0)
    w_u2, m_er2, m_tser2, m_uer2, y2 = _station(1, vid, w_tp2, a_d / i2, x, u, th, c, vv, 0)
    brake = u[3]
    m_tper1 = (m_uer1 / i1 + th[T_BTP1] * w_tp1 + _coulomb(th[T_CTP1], w_tp1, eps, vid, vv)
               + _brake(brake, w_tp1, c))
    m_tper2 = (m_uer2 / i2 + th[T_BTP2] * w_tp2 + _coulomb(th[T_CTP2], w_tp2, eps, vid, vv)
               + _brake(brake, w_tp2, c))
    command = th[T_PPCE] * (th[T_PACE] * (c[K_KY] * u[0] - 0.5 * (y1 + y2)) - omega)
    m_n = min(max(command, c[K_MMIN]), c[K_MMAX])
    m_motor = m_n
    if vid == V_TORQUE_LAG:  # the lagged torque is what the current sensor sees
        m_motor = x[S_LAG]
        dx[S_LAG] = (m_n - m_motor) / vv[0]
    i_a = m_motor / th[T_KN]
    drive = m_motor + _ripple(vid, theta, vv) - _brake(brake, omega, c)
    if two_mass:
        _two_mass(drive, m_tper1 + m_tper2, omega, theta, w_d, a_d, th[T_J], vv, dx, 0)
    else:
        dx[S_OMEGA] = (drive - m_tper1 - m_tper2) / th[T_J]
    dx[S_Y1] = c[K_LEAD] * w_u1
    dx[S_Y2] = c[K_LEAD] * w_u2
    dx[S_THETA] = omega
    if outputs:
        values = (omega, y1, y2, i_a, w_tp1, w_tp2, w_u1, w_u2, m_er1, m_er2, m_tser1, m_tser2,
                  m_uer1, m_uer2, m_tper1, m_tper2)
        for j in range(16):
            y[j] = values[j]


@njit(cache=True, error_model="numpy")
def _lths_rhs(vid, x, u, th, c, vv, dx, y, outputs):
    """LT/HS: dx (N_STATE,) and, if ``outputs``, y in LTHS_OUTPUTS order (x[0] = I_A)."""
    dx[:] = 0.0
    eps = c[K_EPS]
    i_a, omega, theta = x[0], x[1 + S_OMEGA], x[1 + S_THETA]
    two_mass = vid == V_BACKLASH_TWO_MASS or vid == V_SHAFT_TWO_MASS
    w_d = x[1 + S_LOAD_SPEED] if two_mass else omega   # drive side of the magnetic gear, motor-referred
    a_d = x[1 + S_LOAD_ANGLE] if two_mass else theta
    i_mg, i_bg1, i_bg2, i_tp2 = c[K_IMG], c[K_IBG1], c[K_IBG2], c[K_ITP2]
    w_tp1 = w_d / (i_mg * i_bg1)
    w_mg2 = w_d / (i_mg * i_bg2)
    w_tp2 = w_mg2 / i_tp2
    w_u1, m_er1, m_tser1, m_uer1, y1 = _station(0, vid, w_tp1, a_d / (i_mg * i_bg1), x, u, th, c, vv, 1)
    w_u2, m_er2, m_tser2, m_uer2, y2 = _station(1, vid, w_tp2, a_d / (i_mg * i_bg2 * i_tp2), x, u, th, c, vv, 1)
    brake = u[3]
    m_mg2 = (m_uer2 / i_tp2 + th[T_BTP2] * w_tp2 + _coulomb(th[T_CTP2], w_tp2, eps, vid, vv)
             + _brake(brake, w_tp2, c))
    m_tper = (m_uer1 / i_bg1 + m_mg2 / i_bg2 + th[T_BTP1] * w_tp1 + _coulomb(th[T_CTP1], w_tp1, eps, vid, vv)
              + _brake(brake, w_tp1, c))
    m_iser = m_tper + c[K_DIS] * a_d / i_mg
    w_mg = omega / i_mg   # the magnetic gear turns with the motor (a compliance sits behind it)
    mg_loss = th[T_BMG] * w_mg + _coulomb(th[T_CMG], w_mg, eps, vid, vv)
    m_mger = m_iser / i_mg + mg_loss
    command = th[T_PPCE] / th[T_KN] * (th[T_PACE] * (c[K_KY] * u[0] - 0.5 * (y1 + y2)) - omega)
    u_a = min(max(command, -c[K_UMAX]), c[K_UMAX])
    dx[0] = (-th[T_RA] * i_a - th[T_KS] * omega + u_a) / th[T_LA]
    m_motor = th[T_KN] * i_a
    if vid == V_TORQUE_LAG:
        dx[1 + S_LAG] = (m_motor - x[1 + S_LAG]) / vv[0]
        m_motor = x[1 + S_LAG]
    drive = m_motor + _ripple(vid, theta, vv)
    if two_mass:
        _two_mass(drive - mg_loss, m_iser / i_mg, omega, theta, w_d, a_d, th[T_J], vv, dx, 1)
    else:
        dx[1 + S_OMEGA] = (drive - m_mger) / th[T_J]
    dx[1 + S_Y1] = c[K_LEAD] * w_u1
    dx[1 + S_Y2] = c[K_LEAD] * w_u2
    dx[1 + S_THETA] = omega
    if outputs:
        values = (omega, y1, y2, i_a, u_a, w_mg, w_tp1, w_mg2, w_tp2, w_u1, w_u2, m_er1, m_er2,
                  m_tser1, m_tser2, m_uer1, m_uer2, m_mg2, m_tper, m_mger)
        for j in range(20):
            y[j] = values[j]


@njit(cache=True, error_model="numpy")
def _rhs(concept_id, vid, x, u, th, c, vv, dx, y, outputs):
    if concept_id == 0:
        _htls_rhs(vid, x, u, th, c, vv, dx, y, outputs)
    else:
        _lths_rhs(vid, x, u, th, c, vv, dx, y, outputs)


@njit(cache=True, error_model="numpy")
def _run(concept_id, vid, th, c, vv, inputs, h, n_sub, out):
    """Fixed-step RK4 from rest over held inputs (n_samples, 4); outputs (n_samples, n_outputs)
    at t_k from x(t_k) and u_k. The output play is projected after every step."""
    o = concept_id  # LT/HS carries I_A ahead of the common states
    x = np.zeros(N_STATE)
    xt = np.empty(N_STATE)
    k1, k2, k3, k4 = np.empty(N_STATE), np.empty(N_STATE), np.empty(N_STATE), np.empty(N_STATE)
    scratch = np.empty(out.shape[1])
    n = inputs.shape[0]
    for k in range(n):
        u = inputs[k]
        _rhs(concept_id, vid, x, u, th, c, vv, k1, out[k], True)
        if k == n - 1:
            break
        for sub in range(n_sub):
            if sub > 0:
                _rhs(concept_id, vid, x, u, th, c, vv, k1, scratch, False)
            for i in range(N_STATE):
                xt[i] = x[i] + 0.5 * h * k1[i]
            _rhs(concept_id, vid, xt, u, th, c, vv, k2, scratch, False)
            for i in range(N_STATE):
                xt[i] = x[i] + 0.5 * h * k2[i]
            _rhs(concept_id, vid, xt, u, th, c, vv, k3, scratch, False)
            for i in range(N_STATE):
                xt[i] = x[i] + h * k3[i]
            _rhs(concept_id, vid, xt, u, th, c, vv, k4, scratch, False)
            for i in range(N_STATE):
                x[i] += h / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])
            if vid == V_DEADZONE:
                for j in range(2):
                    nut = x[o + S_Y1 + j]
                    x[o + S_CARRIAGE1 + j] = min(max(x[o + S_CARRIAGE1 + j], nut - vv[0]), nut + vv[0])


# ------------------------------------------------------------------------------------------
# measurement-side variants (after the kernel)
# ------------------------------------------------------------------------------------------
def delay_hermite(values: np.ndarray, tau: float, dt: float) -> np.ndarray:
    """Every column of (n_samples, n_channels) ``values`` read at t_k - tau by cubic Hermite
    (Catmull-Rom) interpolation; samples with t_k < tau hold the first value."""
    values = np.asarray(values, dtype=float)
    if tau == 0.0:
        return values.copy()
    n = values.shape[0]
    src = np.arange(n) - tau / dt
    j = np.floor(src).astype(np.int64)
    f = (src - j)[:, None]
    p0, p1, p2, p3 = (values[np.clip(j + d, 0, n - 1)] for d in (-1, 0, 1, 2))
    m1, m2 = 0.5 * (p2 - p0), 0.5 * (p3 - p1)
    out = ((2 * f ** 3 - 3 * f ** 2 + 1) * p1 + (f ** 3 - 2 * f ** 2 + f) * m1
           + (-2 * f ** 3 + 3 * f ** 2) * p2 + (f ** 3 - f ** 2) * m2)
    out[src <= 0.0] = values[0]
    return out


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


__all__ = ["CONCEPTS", "FAMILIES", "REALISTIC_CHANNELS", "STRESS_CONSTANTS", "STRESS_RANGES", "VARIANTS", "Variant",
           "VariantError", "VariantParameter", "check_stress", "check_variant_parameters", "coloured_noise",
           "delay_allpass", "delay_hermite", "draw_stress", "draw_variant_parameters", "get_variant", "make_records",
           "perturbed_base", "quantise", "record_channels", "shape_command", "simulate_variant", "validation_scaled",
           "visibility"]
