"""The sim-to-real catalogue: unmodelled effects that can be switched into a concept.

Each :class:`Effect` names a piece of physics the nominal models of MODEL_SPEC.md leave out,
its few parameters (prefixed with the effect name, physical bounds, ``nominal`` = a typical
rig magnitude), where an ML refit should start them (``start``: small, not degenerate) and
the values at which the effect vanishes exactly (``off``). ``Model.with_effects(names)``
returns the augmented model: the nominal parameters followed by each effect's parameters,
extra states where the physics needs them, the same outputs, its own ``model_id``.

The kernels (``effect_kernels.py``) reduce to the nominal arithmetic at the ``off`` values,
so an augmented model with its effects off reproduces the nominal outputs to the last bit
(``sensor_delay`` is an output post-processing step, skipped at tau = 0).

Physics of the seven MODEL_SPEC effects on HT/LS and LT/HS (all angles and speeds that are
"referred to the screw" are those of the ball-screw shaft, so one value means the same
carriage motion in both concepts; r tanγ converts them to carriage metres):

``backlash``
    Total play 2δ in the gear stage ahead of each screw (HT/LS: each bevel gear; LT/HS: the
    first bevel gear, ahead of both stations), δ referred to the screw [rad]. One state per
    play: the drive-side travel b inside the play (motor-shaft radians). While the drive
    crosses the play after a motion reversal the load side stands still and no load torque
    reaches the motor (kinematic play operator, the load held by its friction). The play is
    a tanh-smoothed clamp of width 0.05 δ; b relaxes onto the contact flank with a 2 ms time
    constant so the equations stay non-stiff for the fixed-step RK4.
``stribeck``
    Every Coulomb term C sgn(v) becomes C (1 + ρ exp(-(v/v_s)²)) sgn(v), i.e.
    C_s = (1 + ρ) C, with v the speed of that shaft referred to the screw; parameters
    ρ = C_s/C - 1 [1] and v_s [rad/s].
``shaft_compliance``
    A torsional spring and damper between the motor (+ magnetic gear) and the rest of the
    drive train (HT/LS: motor shaft; LT/HS: the input shaft, where eq. 22 puts D_IS - here
    acting on the shaft's twist, the printed D_IS θ_MG term stays a zero design constant).
    J splits into motor and load inertia by the load fraction f [1] (J_load = f J), a parameter
    because a rig's split is not known (on an LT/HS two-mass drive of load share 0.57, the refit
    with the fraction held at 0.3 closed 46 % of the held-out gap, held at 0.57 73 %).
    Parameters: the period T of the torsional mode [s] (k = J_red (2π/T)², rigid at T = 0),
    its damping ratio ζ [1] (d = 2 ζ (2π/T) J_red) and f. Two states: twist q and twist rate
    (modal form; the original Ω state becomes the centre-of-inertia speed, so the rigid
    model is recovered exactly). Periods shorter than the integrator can resolve
    (T < 2π h) keep the mode at 2π h and scale its participation by T / (2π h).
``ujoint_kinematics``
    Exact U-joint speed factor of eq. 8, g = cosβ / (1 - sin²β cos²(θ_TP + φ)), with the
    design angles β1, β2 and θ_TP = the screw-shaft angle: Ω_U = g_U Ω_TP and the U-joint
    passes g_U M_TSER / cosβ back (ideal joint: torque ratio = speed ratio). Ripple at twice
    the shaft rotation. Parameters: ripple scale a with g_U = 1 + a (g - 1) [1] (a = 1: the
    design angles; a > 1: a rig joint working at a larger angle than designed) and the yoke
    phase φ at θ = 0 [rad].
``load_dependent_friction``
    Ball-screw Coulomb friction grows with the carried load: C_TS + μ r |F_ER| [μ: 1].
``sensor_delay``
    Every measured channel lags the true signal by τ [s] (linear interpolation in time,
    samples before τ hold the initial value); applied after the kernel.
``torque_ripple``
    Motor cogging/ripple torque k_n A sin(n_p θ + φ) added to the motor torque (the current
    command does not contain it), A as the equivalent armature current [A], n_p fixed per
    concept (HT/LS 6, LT/HS 4 periods per motor revolution), phase φ [rad].

Further forms of these families (``Effect.family``; the gap diagnosis names the family):

``backlash_compliant`` (family ``backlash``)
    The play sits in a compliant coupling between motor (+ magnetic gear) and drive train, where
    ``shaft_compliance`` puts its spring: the modal twist states, period T and damping ratio ζ of
    ``shaft_compliance`` (its load fraction held, HT/LS 0.5, LT/HS 0.3: on an LT/HS two-mass play
    of load share 0.63, holding it there closed no more of the gap), but spring and damper act on
    the twist beyond a dead band ±δ only
    (δ referred to the screw, the band in motor radians δ i_TP (HT/LS) or δ i_MG i_BG1 (LT/HS)):
    inside the band motor and drive train move freely, the load side held by its friction.
    The band's corners are smoothed over 0.05 δ (spring force ½(a + √(a² + s²)) + ½(b - √(b² + s²))
    with a = q - band, b = q + band; the damper weighted by its slope). Off at T = 0.
``backlash_output`` (family ``backlash``)
    Play of half width δ [screw rad] between each screw's nut and its carriage (the play operator
    of ``backlash`` on the screw-to-carriage motion): after a reversal the screw turns while the
    carriage (the measured position, on which the position loop closes) stands, and the load
    force reaches the screw only at a flank. Two states, the nut travel inside each play.

``ujoint_stations`` (family ``ujoint_kinematics``)
    The U-joint factor of ``ujoint_kinematics`` with each station's own ripple scale a_k and yoke
    phase φ_k, g_Uk = 1 + a_k (g_k - 1): the two joints of a rig are separate parts, each at its
    own working angle and assembled at its own phase (one a and φ for both assumes them alike).
    Parameters a1, φ1, a2, φ2; off at a1 = a2 = 0.
``torque_ripple_harmonics`` (family ``torque_ripple``)
    The ripple of ``torque_ripple`` with its 2nd and 3rd harmonic, k_n A (sin(n_p θ + φ1)
    + h2 sin(2 n_p θ + φ2) + h3 sin(3 n_p θ + φ3)); the harmonics as ratios h2, h3 to the
    fundamental, so that A = 0 switches the whole ripple off.

Forms with the freedom the mechanism has (method version 3 of the gap diagnosis; each nests its
family's first form, which it equals at a = 0 or d = 0):

``stribeck_directional`` (family ``stribeck``)
    The Stribeck rise with its breakaway excess per direction of motion, ρ (1 + a) moving out
    (screw speed > 0) and ρ (1 - a) moving in. A drive whose load presses one way works its
    balls, seals and lubricant film differently in the two directions, so a rig's static
    friction is not symmetric in general; ``stribeck`` is the case a = 0.
``load_friction_directional`` (family ``load_dependent_friction``)
    The ball screw's load-dependent friction μ (1 + a) r |F| while the load opposes the motion
    (the screw drives it: M_ER along Ω) and μ (1 - a) r |F| while the load aids it (the screw is
    back-driven). A screw's efficiencies differ with the direction of the power flow
    (η = tan γ / tan(γ + φ) driving, η' = tan(γ - φ) / tan γ back-driven, φ the friction
    angle), so the load's share of the friction does too; ``load_dependent_friction`` is a = 0.
``sensor_delay_dispersed`` (family ``sensor_delay``)
    A delay of τ in all made of a pure delay (1 - d) τ and a first-order lag of time constant
    d τ, equal at low frequency: a real sensor chain filters (anti-aliasing, averaging,
    sample-and-hold), so its delay falls with frequency; ``sensor_delay`` is d = 0.

Nominal magnitudes (one value serves both concepts) are typical rig values chosen so that,
with 2 % noise, each effect stays visible on deploy-retract at nominal and at half
magnitude: the noise-normalised excess chi-square N Σ (NRMSE_ch / 0.02)² over the rig
channels is >= 140 at half magnitude (tests/unit/test_effects.py). Play 2 x 0.02 rad at the
screw (45 µm of carriage lost motion); C_s = 1.5 C below v_s = 1 rad/s of screw speed
(1.1 mm/s); a 33 Hz torsional mode with ζ = 0.05; U-joint ripple a = 6, i.e. joints at
about 2.4 x the design angles (7°, 12°) - at the design angles (a = 1) the ripple changes I_A
by only 0.14 % NRMSE, below what 2 % noise shows; μ = 0.005 (a ball screw of ~93 %
efficiency at the rig loads); 12 ms delay; 0.5 A equivalent ripple (~2.5 % of the running
current).

Caveats for fitting: on deploy-retract much of the shaft-compliance signature is ringing
excited by the 10 ms reference staircase and sampled in step with it, so the cost is
multimodal in T (periods dividing 10 ms barely show in steady motion; the start value
4.4 ms avoids that). Linear interpolation makes the outputs piecewise linear in τ with kinks
at multiples of the sample time.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING, Callable, Mapping, Sequence

import numpy as np

from ..params import Parameter, ParameterError, ParameterSet
from .base import KERNEL_IDS

if TYPE_CHECKING:  # pragma: no cover
    from .base import Model

#: Regimes in which an effect shows in the residuals (for the gap diagnosis).
SIGNATURES = ("reversal", "low_speed", "high_acceleration", "high_load", "direction", "saturation",
              "periodic", "delay")


class EffectError(ParameterError):
    """An unknown effect or effect parameter, a duplicate, or an effect a concept lacks."""


@dataclass(frozen=True)
class Effect:
    """One unmodelled effect: its physics, parameters and how to switch it off.

    ``parameters`` are named ``<effect>_<short>`` (e.g. ``backlash_delta``); ``start`` is
    where an ML refit of the augmented model starts them; ``off`` makes the effect vanish
    (an augmented model at ``off`` reproduces the nominal outputs). ``signature`` lists the
    regimes (:data:`SIGNATURES`) where its residuals show.

    How the effect enters the compiled kernels of ``effect_kernels.py`` is declared here too,
    so that a new effect needs only its definition and its physics: ``extra_states`` (concept
    -> names of the states it adds, in kernel order), ``state_scales`` (each extra state's
    typical magnitude in its units, the adaptive integrator's error scale), ``magnitude`` (the
    parameter that sets the effect's size: at its zero the effect vanishes and its extra
    states feed nothing, so the adaptive integrator leaves them out of its error norm),
    ``constants`` (concept -> fixed kernel constants, short name -> value, the same names for
    every concept; :data:`LAYOUT` gives their kernel positions) and ``postprocess`` (an
    output-side step ``f(model, thetas, time, out) -> out`` run by ``simulate_batch`` after
    the kernel). ``family`` (default: the effect's own name) groups alternative forms of one
    piece of physics (e.g. play in a rigid or in a compliant drive train): the gap diagnosis
    names the family and reports the form. ``combines`` names other families whose mechanism
    the effect carries beside its own (a play inside a compliant coupling carries the coupling's
    spring, ``shaft_compliance``): such a compound is simulated like any effect, but the gap
    diagnosis does not offer it as a candidate, since a candidate is one mechanism and a
    compound would explain its parts' faults under its own family's name. ``fast_dynamics``: the
    effect brings a time scale faster than the nominal dynamics (a torsional mode, a play's
    relaxation, a forcing at motor-angle order); a model with it runs at the concept's fine
    ``integration_step`` even where the contract's coarser converged step is asked for
    (:attr:`ema_uq.models.base.Model.rk4_step`), since that step was verified on the nominal
    dynamics only. ``nests``: forms of the same family this form contains exactly at a value of its
    extra parameters (e.g. ``stribeck_directional`` at zero asymmetry is ``stribeck`` bit for bit):
    a diagnosis that offers a form can leave out the forms it nests. ``reduces_to``: the forms
    this one computes exactly at some values of its parameters, each as {own parameter: the
    other form's parameter whose value it takes, or a fixed number} (e.g. ``torque_ripple_harmonics``
    at zero harmonic ratios is ``torque_ripple`` with the fundamental's amplitude and phase): a
    fit of this form that ends below the other form's fit is refitted from the point where it
    computes that fit (method versions 8 and 9 of the gap diagnosis). Unlike ``nests`` it does
    not let a diagnosis leave the other form out.
    """

    name: str
    description: str
    parameters: tuple[Parameter, ...]
    start: dict[str, float]
    off: dict[str, float]
    signature: tuple[str, ...]
    extra_states: Mapping[str, tuple[str, ...]] = field(default_factory=dict)
    state_scales: Mapping[str, float] = field(default_factory=dict)
    magnitude: str | None = None
    constants: Mapping[str, Mapping[str, float]] = field(default_factory=dict)
    postprocess: Callable | None = None
    family: str = ""
    combines: tuple[str, ...] = ()
    fast_dynamics: bool = False
    nests: tuple[str, ...] = ()
    reduces_to: Mapping[str, Mapping[str, str | float]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.family:  # a form of its own: the family is the effect itself
            object.__setattr__(self, "family", self.name)
        names = [p.name for p in self.parameters]
        for p in self.parameters:
            if not p.name.startswith(self.name + "_"):
                raise EffectError(f"effect {self.name}: parameter {p.name} must start with '{self.name}_'")
        for what, values in (("start", self.start), ("off", self.off)):
            for key, value in values.items():
                if key not in names:
                    raise EffectError(f"effect {self.name}: {what} names unknown parameter {key!r}")
                p = self.parameters[names.index(key)]
                if not p.lower <= value <= p.upper:
                    raise EffectError(f"effect {self.name}: {what} value of {key} = {value:g} lies outside "
                                      f"[{p.lower:g}, {p.upper:g}]")
        unknown = [s for s in self.signature if s not in SIGNATURES]
        if unknown:
            raise EffectError(f"effect {self.name}: unknown signature regime(s) {', '.join(unknown)}; "
                              f"use {', '.join(SIGNATURES)}")
        self._check_kernel_facts(names)
        self._check_reductions(names)

    def _check_reductions(self, names: list[str]) -> None:
        """Each reduction gives every parameter of this form a value: a parameter of the other
        form (by its full name) or a number inside this parameter's bounds."""
        for other, mapping in self.reduces_to.items():
            if sorted(mapping) != sorted(names):
                raise EffectError(f"effect {self.name}: its reduction to {other} must map each of its parameters "
                                  f"({', '.join(names)}), got {', '.join(mapping) or 'none'}")
            for key, value in mapping.items():
                if isinstance(value, str):
                    if not value.startswith(other + "_"):
                        raise EffectError(f"effect {self.name}: reduction to {other} maps {key} to {value!r}, "
                                          f"which is not a parameter of {other}")
                    continue
                p = self.parameters[names.index(key)]
                if not p.lower <= float(value) <= p.upper:
                    raise EffectError(f"effect {self.name}: reduction to {other} sets {key} = {value:g} outside "
                                      f"[{p.lower:g}, {p.upper:g}]")

    def reduced_values(self, other: str, values: Mapping[str, float]) -> dict[str, float]:
        """This form's parameter values at which it computes ``other`` with ``values`` (the
        other form's parameters by full name): :attr:`reduces_to`."""
        try:
            mapping = self.reduces_to[other]
        except KeyError:
            raise EffectError(f"effect {self.name} does not reduce to {other}; it reduces to "
                              f"{', '.join(self.reduces_to) or 'no other form'}") from None
        return {key: float(values[value]) if isinstance(value, str) else float(value)
                for key, value in mapping.items()}

    def _check_kernel_facts(self, names: list[str]) -> None:
        """Every extra state has an error scale, ``magnitude`` is a parameter that is zero at
        ``off``, and every concept gives the same kernel constants."""
        for concept, states in self.extra_states.items():
            unscaled = [s for s in states if not self.state_scales.get(s, 0.0) > 0.0]
            if unscaled:
                raise EffectError(f"effect {self.name}: extra state {unscaled[0]} of concept {concept} has no "
                                  "positive error scale; give it in state_scales")
        if self.magnitude is not None and self.off.get(self.magnitude, None) != 0.0:
            raise EffectError(f"effect {self.name}: magnitude {self.magnitude!r} must be a parameter that is 0 "
                              f"at off; parameters: {', '.join(names)}")
        for concept, values in self.constants.items():
            if tuple(values) != self.constant_names:
                raise EffectError(f"effect {self.name}: concept {concept} gives kernel constants "
                                  f"{', '.join(values)}; every concept must give {', '.join(self.constant_names)}")

    @property
    def constant_names(self) -> tuple[str, ...]:
        """Short names of the effect's kernel constants (``relaxation`` -> ``backlash_relaxation``
        in :data:`LAYOUT`)."""
        return tuple(next(iter(self.constants.values()), ()))

    @property
    def parameter_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.parameters)

    @property
    def short_names(self) -> tuple[str, ...]:
        """Parameter names without the ``<effect>_`` prefix (``delta`` for ``backlash_delta``)."""
        return tuple(p.name[len(self.name) + 1:] for p in self.parameters)

    @property
    def nominal(self) -> dict[str, float]:
        return {p.name: p.nominal for p in self.parameters}

    def full_name(self, key: str) -> str:
        """``delta`` or ``backlash_delta`` -> ``backlash_delta``; anything else is an EffectError."""
        if key in self.parameter_names:
            return key
        if key in self.short_names:
            return self.parameter_names[self.short_names.index(key)]
        raise EffectError(f"effect {self.name} has no parameter {key!r}; its parameters are "
                          f"{', '.join(self.short_names)} (or {', '.join(self.parameter_names)})")


def _delayed(values: np.ndarray, tau: float, dt: float) -> np.ndarray:
    """``values`` (n_samples, n_outputs) delayed by ``tau`` >= 0 [s]: linear interpolation
    between samples, samples with t < tau holding the first value."""
    n = values.shape[0]
    k = np.arange(n)
    lag = tau / dt
    whole = int(math.floor(lag))
    frac = lag - whole
    src = k - lag  # fractional sample index of t_k - tau
    i0 = np.clip(k - whole, 0, n - 1)      # sample at or after t_k - tau
    i1 = np.clip(k - whole - 1, 0, n - 1)  # sample before it
    delayed = (1.0 - frac) * values[i0] + frac * values[i1]
    delayed[src <= 0.0] = values[0]
    return delayed


def first_order_lag(values: np.ndarray, tau: float, dt: float) -> np.ndarray:
    """``values`` (n, ...) along axis 0 through a first-order lag of time constant ``tau`` > 0
    [s], exact for an input linear between samples, started at rest on the first value:
    y_k = a y_(k-1) + b0 u_k + b1 u_(k-1), a = exp(-dt/tau), b0 = 1 - (tau/dt)(1 - a),
    b1 = (tau/dt)(1 - a) - a (unit static gain; tau -> 0 tends to a delay of tau)."""
    from scipy.signal import lfilter  # scipy.signal costs start-up time; only lags need it

    a = math.exp(-dt / tau)
    c = tau / dt * (1.0 - a)
    return lfilter([1.0 - c, c - a], [1.0, -a], values - values[0], axis=0) + values[0]


def delay_outputs(model: "Model", thetas: np.ndarray, time: np.ndarray, out: np.ndarray) -> np.ndarray:
    """``sensor_delay``: every channel of set s lags by tau_s (linear interpolation between
    samples; samples with t < tau hold the first value). thetas (n_sets, n_params), out
    (n_sets, n_samples, n_outputs), modified in place and returned. tau = 0 leaves a set untouched."""
    taus = thetas[:, model.parameters.index("sensor_delay_tau")]
    dt = float(time[1] - time[0])
    for s, tau in enumerate(taus):
        if tau != 0.0:
            out[s] = _delayed(out[s], tau, dt)
    return out


def delay_dispersed_outputs(model: "Model", thetas: np.ndarray, time: np.ndarray, out: np.ndarray) -> np.ndarray:
    """``sensor_delay_dispersed``: every channel of set s lags by tau_s in all, (1 - d_s) tau_s
    as a pure delay (as ``sensor_delay``) followed by a first-order lag of time constant
    d_s tau_s. In place as :func:`delay_outputs`; d = 0 is ``sensor_delay``, tau = 0 no change."""
    index = model.parameters.index
    taus = thetas[:, index("sensor_delay_dispersed_tau")]
    shares = thetas[:, index("sensor_delay_dispersed_dispersion")]
    dt = float(time[1] - time[0])
    for s, (tau, share) in enumerate(zip(taus, shares)):
        pure, lag = (1.0 - share) * tau, share * tau
        if pure > 0.0:
            out[s] = _delayed(out[s], pure, dt)
        if lag > 0.0:
            out[s] = first_order_lag(out[s], lag, dt)
    return out


def _p(name, unit, nominal, lower, upper, description) -> Parameter:
    return Parameter(name, unit, nominal, lower, upper, free=True, description=description)


TWO_PI = 2.0 * math.pi


def _torsional_mode(effect: str, condition: str = "") -> tuple[Parameter, ...]:
    """Period, damping ratio and load-side inertia share of a two-inertia torsional mode, the
    parameters of ``effect`` (``condition``: where the mode has that period, e.g. "unloaded")."""
    at = f" {condition}" if condition else ""
    return (_p(f"{effect}_period", "s", 0.03, 0.0, 1.0,
               f"period 2π/ω_n of the torsional mode{at} (stiffness k = J_red ω_n², rigid at 0)"),
            _p(f"{effect}_zeta", "1", 0.05, 1e-3, 5.0, f"damping ratio of the torsional mode{at}"),
            _p(f"{effect}_load_fraction", "1", 0.5, 0.05, 0.95,
               "load-side share of the inertia J (the rest turns with the motor)"))

#: The seven effects of MODEL_SPEC.md for the EMA concepts (htls, lths), then further forms of
#: their families, in kernel order.
CATALOGUE: dict[str, Effect] = {e.name: e for e in (
    Effect(
        "backlash",
        "dead band of total play 2δ in the gear ahead of the screw(s): after a motion reversal the "
        "drive crosses the play with the carriage standing and no load torque transmitted",
        (_p("backlash_delta", "rad", 0.02, 0.0, 1.0,
            "half play of the gear stage, referred to the screw shaft (carriage lost motion 2δ r tanγ)"),),
        start={"backlash_delta": 0.002}, off={"backlash_delta": 0.0},
        signature=("reversal", "direction", "low_speed"), magnitude="backlash_delta",
        # one play per bevel gear on HT/LS, one ahead of both stations on LT/HS (travel b [rad])
        extra_states={"htls": ("backlash_b1", "backlash_b2"), "lths": ("backlash_b",)},
        state_scales={"backlash_b1": 0.1, "backlash_b2": 0.1, "backlash_b": 0.1},
        # play relaxation [s] and clamp softness [1]
        constants={"htls": {"relaxation": 2e-3, "softness": 0.05}, "lths": {"relaxation": 1e-3, "softness": 0.05}},
        fast_dynamics=True),
    Effect(
        "stribeck",
        "Coulomb friction rising near zero speed: C(v) = C (1 + ρ exp(-(v/v_s)²)) on every Coulomb term",
        (_p("stribeck_ratio", "1", 0.5, 0.0, 20.0, "breakaway excess C_s/C - 1 of every Coulomb term"),
         _p("stribeck_speed", "rad/s", 1.0, 1e-3, 100.0, "Stribeck speed v_s, referred to the screw shaft")),
        start={"stribeck_ratio": 0.05, "stribeck_speed": 1.0},
        off={"stribeck_ratio": 0.0, "stribeck_speed": 1.0},
        signature=("low_speed", "reversal"), magnitude="stribeck_ratio"),
    Effect(
        "shaft_compliance",
        "torsional spring and damper between motor and drive train (two-inertia mode of period T, "
        "damping ratio ζ)",
        _torsional_mode("shaft_compliance"),
        start={"shaft_compliance_period": 0.0044, "shaft_compliance_zeta": 0.05, "shaft_compliance_load_fraction": 0.5},
        off={"shaft_compliance_period": 0.0, "shaft_compliance_zeta": 0.05, "shaft_compliance_load_fraction": 0.5},
        signature=("high_acceleration", "reversal", "periodic"), magnitude="shaft_compliance_period",
        extra_states={"htls": ("shaft_twist", "shaft_twist_rate"), "lths": ("shaft_twist", "shaft_twist_rate")},
        state_scales={"shaft_twist": 0.01, "shaft_twist_rate": 1.0},  # [rad], [rad/s]
        # fastest resolved torsional mode (1 / the concept's RK4 step) [rad/s]
        constants={"htls": {"mode_omega_max": 1.0 / 5e-4}, "lths": {"mode_omega_max": 1.0 / 2e-4}},
        fast_dynamics=True),
    Effect(
        "ujoint_kinematics",
        "exact U-joint speed factor g_U(θ) of eq. 8: speed and torque ripple at twice the shaft rotation",
        (_p("ujoint_kinematics_scale", "1", 6.0, 0.0, 100.0,
            "ripple scale a: g_U = 1 + a (g_eq8 - 1); 1 = the design joint angles"),
         _p("ujoint_kinematics_phase", "rad", 0.0, -TWO_PI, TWO_PI, "yoke phase of the U-joints at θ = 0")),
        start={"ujoint_kinematics_scale": 0.1, "ujoint_kinematics_phase": 0.0},
        off={"ujoint_kinematics_scale": 0.0, "ujoint_kinematics_phase": 0.0},
        signature=("periodic", "high_load"), magnitude="ujoint_kinematics_scale"),
    Effect(
        "load_dependent_friction",
        "ball-screw Coulomb friction growing with the carried load: C_TS + μ r |F_ER|",
        (_p("load_dependent_friction_mu", "1", 0.005, 0.0, 0.5, "load coefficient μ of the ball-screw friction"),),
        start={"load_dependent_friction_mu": 2.5e-4}, off={"load_dependent_friction_mu": 0.0},
        signature=("high_load", "direction"), magnitude="load_dependent_friction_mu"),
    Effect(
        "sensor_delay",
        "every measured channel lags the true signal by τ",
        (_p("sensor_delay_tau", "s", 0.012, 0.0, 0.5, "delay of the measured channels"),),
        start={"sensor_delay_tau": 0.001}, off={"sensor_delay_tau": 0.0},
        signature=("delay", "high_acceleration"), magnitude="sensor_delay_tau", postprocess=delay_outputs),
    Effect(
        "torque_ripple",
        "motor cogging / torque ripple k_n A sin(n_p θ + φ), periodic in the motor angle",
        (_p("torque_ripple_amplitude", "A", 0.5, 0.0, 100.0,
            "ripple torque amplitude as an equivalent armature current (torque k_n A)"),
         _p("torque_ripple_phase", "rad", 0.0, -TWO_PI, TWO_PI, "ripple phase at θ = 0")),
        start={"torque_ripple_amplitude": 0.05, "torque_ripple_phase": 0.0},
        off={"torque_ripple_amplitude": 0.0, "torque_ripple_phase": 0.0},
        signature=("periodic", "low_speed"), magnitude="torque_ripple_amplitude",
        constants={"htls": {"periods": 6.0}, "lths": {"periods": 4.0}},  # ripple periods per motor revolution
        fast_dynamics=True),
    # further forms of the families above (the diagnosis names the family)
    Effect(
        "backlash_compliant",
        "dead band ±δ inside a compliant coupling between motor and drive train: spring and damper "
        "act on the twist beyond the play only (two-inertia mode of period T, damping ratio ζ)",
        (_p("backlash_compliant_delta", "rad", 0.1, 0.0, 1.0,
            "half play of the coupling, referred to the screw shaft (carriage lost motion 2δ r tanγ)"),
         _p("backlash_compliant_period", "s", 0.03, 0.0, 1.0,
            "period 2π/ω_n of the torsional mode in contact (stiffness k = J_red ω_n², rigid at 0)"),
         _p("backlash_compliant_zeta", "1", 0.1, 1e-3, 5.0, "damping ratio of the torsional mode in contact")),
        # a play that carries the load shows only where the coupling's torque changes sign
        # (the flap load keeps one flank in contact): visible plays are large, the start grid
        # (x0.3 ... x10) spans 0.01-0.3 rad (0.01-0.3 mm of carriage). A 40 Hz start: drive-train
        # modes of rigs sit at 20-60 Hz, and the grid's periods then span 13-130 Hz
        start={"backlash_compliant_delta": 0.03, "backlash_compliant_period": 0.025, "backlash_compliant_zeta": 0.1},
        off={"backlash_compliant_delta": 0.0, "backlash_compliant_period": 0.0, "backlash_compliant_zeta": 0.1},
        # the play shows at reversals, the coupling rings under acceleration (as shaft_compliance,
        # which it contains at δ = 0: its signature match must not favour the form with play)
        signature=("high_acceleration", "reversal", "periodic"), magnitude="backlash_compliant_period",
        combines=("shaft_compliance",),
        extra_states={"htls": ("coupling_twist", "coupling_twist_rate"),
                      "lths": ("coupling_twist", "coupling_twist_rate")},
        state_scales={"coupling_twist": 0.01, "coupling_twist_rate": 1.0},  # [rad], [rad/s]
        # as shaft_compliance, and the dead band's corner softness [1]
        constants={"htls": {"load_fraction": 0.5, "mode_omega_max": 1.0 / 5e-4, "softness": 0.05},
                   "lths": {"load_fraction": 0.3, "mode_omega_max": 1.0 / 2e-4, "softness": 0.05}},
        family="backlash", fast_dynamics=True),
    Effect(
        "backlash_output",
        "play of total 2δ between each screw's nut and its carriage: after a reversal the screw turns "
        "while the measured carriage stands, and the load reaches the screw only at a flank",
        (_p("backlash_output_delta", "rad", 0.02, 0.0, 1.0,
            "half play between nut and carriage, in screw-shaft radians (carriage lost motion 2δ r tanγ)"),),
        # plays between nut and carriage are tens of µm (0.01 rad = 11 µm): the start grid
        # (x0.3 ... x10) spans 0.003-0.1 rad
        start={"backlash_output_delta": 0.01}, off={"backlash_output_delta": 0.0},
        signature=("reversal", "direction", "low_speed"), magnitude="backlash_output_delta",
        extra_states={"htls": ("nut_play_b1", "nut_play_b2"), "lths": ("nut_play_b1", "nut_play_b2")},
        state_scales={"nut_play_b1": 0.1, "nut_play_b2": 0.1},  # travel inside the play [screw rad]
        constants={"htls": {"relaxation": 2e-3, "softness": 0.05}, "lths": {"relaxation": 1e-3, "softness": 0.05}},
        family="backlash", fast_dynamics=True),
    Effect(
        "torque_ripple_harmonics",
        "motor torque ripple with its 2nd and 3rd harmonic: k_n A (sin(n_p θ + φ1) + h2 sin(2 n_p θ + φ2) "
        "+ h3 sin(3 n_p θ + φ3))",
        (_p("torque_ripple_harmonics_amplitude", "A", 0.5, 0.0, 100.0,
            "fundamental's amplitude as an equivalent armature current (torque k_n A)"),
         _p("torque_ripple_harmonics_phase", "rad", 0.0, -TWO_PI, TWO_PI, "fundamental's phase at θ = 0"),
         _p("torque_ripple_harmonics_ratio2", "1", 0.5, 0.0, 10.0, "2nd harmonic's amplitude over the fundamental's"),
         _p("torque_ripple_harmonics_phase2", "rad", 0.0, -TWO_PI, TWO_PI, "2nd harmonic's phase at θ = 0"),
         _p("torque_ripple_harmonics_ratio3", "1", 0.3, 0.0, 10.0, "3rd harmonic's amplitude over the fundamental's"),
         _p("torque_ripple_harmonics_phase3", "rad", 0.0, -TWO_PI, TWO_PI, "3rd harmonic's phase at θ = 0")),
        start={"torque_ripple_harmonics_amplitude": 0.05, "torque_ripple_harmonics_phase": 0.0,
               "torque_ripple_harmonics_ratio2": 0.3, "torque_ripple_harmonics_phase2": 0.0,
               "torque_ripple_harmonics_ratio3": 0.3, "torque_ripple_harmonics_phase3": 0.0},
        off={"torque_ripple_harmonics_amplitude": 0.0, "torque_ripple_harmonics_phase": 0.0,
             "torque_ripple_harmonics_ratio2": 0.0, "torque_ripple_harmonics_phase2": 0.0,
             "torque_ripple_harmonics_ratio3": 0.0, "torque_ripple_harmonics_phase3": 0.0},
        signature=("periodic", "low_speed"), magnitude="torque_ripple_harmonics_amplitude",
        constants={"htls": {"periods": 6.0}, "lths": {"periods": 4.0}},  # fundamental periods per motor revolution
        family="torque_ripple", fast_dynamics=True,
        reduces_to={"torque_ripple": {"torque_ripple_harmonics_amplitude": "torque_ripple_amplitude",
                                      "torque_ripple_harmonics_phase": "torque_ripple_phase",
                                      "torque_ripple_harmonics_ratio2": 0.0, "torque_ripple_harmonics_phase2": 0.0,
                                      "torque_ripple_harmonics_ratio3": 0.0, "torque_ripple_harmonics_phase3": 0.0}}),
    Effect(
        "ujoint_stations",
        "exact U-joint speed factor of eq. 8 with a ripple scale and a yoke phase per station: two "
        "joints of a rig, each at its own angle and assembled at its own phase",
        (_p("ujoint_stations_scale1", "1", 6.0, 0.0, 100.0, "ripple scale a1 of station 1's joint (1 = design angle)"),
         _p("ujoint_stations_phase1", "rad", 0.0, -TWO_PI, TWO_PI, "yoke phase of station 1's joint at θ = 0"),
         _p("ujoint_stations_scale2", "1", 6.0, 0.0, 100.0, "ripple scale a2 of station 2's joint (1 = design angle)"),
         _p("ujoint_stations_phase2", "rad", 0.0, -TWO_PI, TWO_PI, "yoke phase of station 2's joint at θ = 0")),
        start={"ujoint_stations_scale1": 0.1, "ujoint_stations_phase1": 0.0,
               "ujoint_stations_scale2": 0.1, "ujoint_stations_phase2": 0.0},
        off={"ujoint_stations_scale1": 0.0, "ujoint_stations_phase1": 0.0,
             "ujoint_stations_scale2": 0.0, "ujoint_stations_phase2": 0.0},
        signature=("periodic", "high_load"), magnitude="ujoint_stations_scale1",
        family="ujoint_kinematics",
        reduces_to={"ujoint_kinematics": {"ujoint_stations_scale1": "ujoint_kinematics_scale",
                                          "ujoint_stations_phase1": "ujoint_kinematics_phase",
                                          "ujoint_stations_scale2": "ujoint_kinematics_scale",
                                          "ujoint_stations_phase2": "ujoint_kinematics_phase"}}),
    # forms that give a family the freedom its mechanism has on a drive with a one-sided load or a
    # filtering sensor (method version 4 of the gap diagnosis; each nests the family's first form)
    Effect(
        "stribeck_directional",
        "Coulomb friction rising near zero speed, by a breakaway excess that differs with the direction of "
        "motion: C(v) = C (1 + ρ (1 ± a) exp(-(v/v_s)²)), + for v > 0",
        (_p("stribeck_directional_ratio", "1", 0.5, 0.0, 20.0, "mean breakaway excess C_s/C - 1 of both directions"),
         _p("stribeck_directional_asymmetry", "1", 0.0, -1.0, 1.0,
            "a: the excess is ρ (1 + a) moving out (v > 0), ρ (1 - a) moving in"),
         _p("stribeck_directional_speed", "rad/s", 1.0, 1e-3, 100.0,
            "Stribeck speed v_s, referred to the screw shaft")),
        start={"stribeck_directional_ratio": 0.05, "stribeck_directional_asymmetry": 0.0,
               "stribeck_directional_speed": 1.0},
        off={"stribeck_directional_ratio": 0.0, "stribeck_directional_asymmetry": 0.0,
             "stribeck_directional_speed": 1.0},
        signature=("low_speed", "reversal", "direction"), magnitude="stribeck_directional_ratio",
        family="stribeck", nests=("stribeck",),
        reduces_to={"stribeck": {"stribeck_directional_ratio": "stribeck_ratio",
                                 "stribeck_directional_asymmetry": 0.0,
                                 "stribeck_directional_speed": "stribeck_speed"}}),
    Effect(
        "load_friction_directional",
        "ball-screw Coulomb friction growing with the carried load, more against a load that opposes the "
        "motion than with one that aids it: C_TS + μ (1 ± a) r |F_ER|",
        (_p("load_friction_directional_mu", "1", 0.005, 0.0, 0.5, "mean load coefficient μ of the ball-screw friction"),
         _p("load_friction_directional_asymmetry", "1", 0.0, -1.0, 1.0,
            "a: μ (1 + a) while the load opposes the motion (driving), μ (1 - a) while it aids it (back-driven)")),
        start={"load_friction_directional_mu": 2.5e-4, "load_friction_directional_asymmetry": 0.0},
        off={"load_friction_directional_mu": 0.0, "load_friction_directional_asymmetry": 0.0},
        signature=("high_load", "direction"), magnitude="load_friction_directional_mu",
        family="load_dependent_friction", nests=("load_dependent_friction",),
        reduces_to={"load_dependent_friction": {"load_friction_directional_mu": "load_dependent_friction_mu",
                                                "load_friction_directional_asymmetry": 0.0}}),
    Effect(
        "sensor_delay_dispersed",
        "every measured channel lags the true signal by τ in all: a pure delay (1 - d) τ and a first-order "
        "lag of time constant d τ (the sensor's filter)",
        (_p("sensor_delay_dispersed_tau", "s", 0.012, 0.0, 0.5, "delay of the measured channels at low frequency"),
         _p("sensor_delay_dispersed_dispersion", "1", 0.5, 0.0, 1.0,
            "d: share of the delay that is a first-order lag rather than a pure delay")),
        start={"sensor_delay_dispersed_tau": 0.001, "sensor_delay_dispersed_dispersion": 0.5},
        off={"sensor_delay_dispersed_tau": 0.0, "sensor_delay_dispersed_dispersion": 0.5},
        signature=("delay", "high_acceleration"), magnitude="sensor_delay_dispersed_tau",
        postprocess=delay_dispersed_outputs, family="sensor_delay", nests=("sensor_delay",),
        reduces_to={"sensor_delay": {"sensor_delay_dispersed_tau": "sensor_delay_tau",
                                     "sensor_delay_dispersed_dispersion": 0.0}}),
    # forms whose magnitude follows the operating point it physically depends on (method version 5
    # of the gap diagnosis; each nests the family's first form)
    Effect(
        "torque_ripple_loaded",
        "motor torque ripple with a share of fixed amplitude (cogging) and a share proportional to the "
        "motor torque (the current acting on the flux harmonics): (k_n A + r M) sin(n_p θ + φ)",
        (_p("torque_ripple_loaded_amplitude", "A", 0.5, 0.0, 100.0,
            "fixed share's amplitude as an equivalent armature current (torque k_n A)"),
         _p("torque_ripple_loaded_phase", "rad", 0.0, -TWO_PI, TWO_PI, "ripple phase at θ = 0"),
         _p("torque_ripple_loaded_share", "1", 0.02, 0.0, 1.0,
            "r: ripple amplitude per unit of the motor's electromagnetic torque M")),
        start={"torque_ripple_loaded_amplitude": 0.05, "torque_ripple_loaded_phase": 0.0,
               "torque_ripple_loaded_share": 0.005},
        off={"torque_ripple_loaded_amplitude": 0.0, "torque_ripple_loaded_phase": 0.0,
             "torque_ripple_loaded_share": 0.0},
        signature=("periodic", "low_speed", "high_load"), magnitude="torque_ripple_loaded_amplitude",
        constants={"htls": {"periods": 6.0}, "lths": {"periods": 4.0}},  # ripple periods per motor revolution
        family="torque_ripple", fast_dynamics=True, nests=("torque_ripple",),
        reduces_to={"torque_ripple": {"torque_ripple_loaded_amplitude": "torque_ripple_amplitude",
                                      "torque_ripple_loaded_phase": "torque_ripple_phase",
                                      "torque_ripple_loaded_share": 0.0}}),
    Effect(
        "ujoint_stroke",
        "exact U-joint speed factor of eq. 8 with a ripple scale that changes along the stroke (a joint "
        "whose bend angle follows the flap, and so the carriage): a (1 + s ξ_k), ξ_k = (y_k - y_mid) / y_half",
        (_p("ujoint_stroke_scale", "1", 6.0, 0.0, 100.0, "ripple scale a at mid-stroke (1 = the design angles)"),
         _p("ujoint_stroke_phase", "rad", 0.0, -TWO_PI, TWO_PI, "yoke phase of the U-joints at θ = 0"),
         _p("ujoint_stroke_slope", "1", 0.0, -1.0, 1.0,
            "s: relative change of the scale from mid-stroke to either end (the scale stays >= 0)")),
        start={"ujoint_stroke_scale": 0.1, "ujoint_stroke_phase": 0.0, "ujoint_stroke_slope": 0.0},
        off={"ujoint_stroke_scale": 0.0, "ujoint_stroke_phase": 0.0, "ujoint_stroke_slope": 0.0},
        signature=("periodic", "high_load"), magnitude="ujoint_stroke_scale",
        # the carriage travel of the reference runs' 0-35° deflections: 0 to 0.26 m on both concepts [m]
        constants={"htls": {"mid": 0.13, "half": 0.13}, "lths": {"mid": 0.13, "half": 0.13}},
        family="ujoint_kinematics", nests=("ujoint_kinematics",),
        reduces_to={"ujoint_kinematics": {"ujoint_stroke_scale": "ujoint_kinematics_scale",
                                          "ujoint_stroke_phase": "ujoint_kinematics_phase",
                                          "ujoint_stroke_slope": 0.0}}),
    Effect(
        "shaft_compliance_loaded",
        "torsional spring and damper between motor and drive train whose stiffness grows with the torque "
        "it carries (gear teeth and bearings stiffen under contact load): k = k_0 (1 + h |M| / M_ref)",
        (*_torsional_mode("shaft_compliance_loaded", "unloaded"),
         _p("shaft_compliance_loaded_hardening", "1", 0.0, 0.0, 3.0,
            "h: relative stiffness gain at the reference torque M_ref")),
        start={"shaft_compliance_loaded_period": 0.0044, "shaft_compliance_loaded_zeta": 0.05,
               "shaft_compliance_loaded_load_fraction": 0.5, "shaft_compliance_loaded_hardening": 0.0},
        off={"shaft_compliance_loaded_period": 0.0, "shaft_compliance_loaded_zeta": 0.05,
             "shaft_compliance_loaded_load_fraction": 0.5, "shaft_compliance_loaded_hardening": 0.0},
        signature=("high_acceleration", "reversal", "periodic", "high_load"),
        magnitude="shaft_compliance_loaded_period",
        extra_states={"htls": ("shaft_twist", "shaft_twist_rate"), "lths": ("shaft_twist", "shaft_twist_rate")},
        state_scales={"shaft_twist": 0.01, "shaft_twist_rate": 1.0},  # [rad], [rad/s]
        # as shaft_compliance, and M_ref [N m]: about the largest torque the coupling carries on the
        # reference runs (HT/LS 36 N m, LT/HS 2.3 N m at the motor)
        constants={"htls": {"mode_omega_max": 1.0 / 5e-4, "torque_ref": 30.0},
                   "lths": {"mode_omega_max": 1.0 / 2e-4, "torque_ref": 2.0}},
        family="shaft_compliance", fast_dynamics=True, nests=("shaft_compliance",),
        reduces_to={"shaft_compliance": {"shaft_compliance_loaded_period": "shaft_compliance_period",
                                         "shaft_compliance_loaded_zeta": "shaft_compliance_zeta",
                                         "shaft_compliance_loaded_load_fraction": "shaft_compliance_load_fraction",
                                         "shaft_compliance_loaded_hardening": 0.0}}),
)}

#: Effects that cannot share one model: each group models the same coupling (its twist states), or
#: the same joints.
EXCLUSIVE: tuple[frozenset[str], ...] = (
    frozenset({"shaft_compliance", "backlash_compliant", "shaft_compliance_loaded"}),
    frozenset({"ujoint_kinematics", "ujoint_stations", "ujoint_stroke"}))

#: Kernel order of the catalogue effects (the layout table of the augmented kernels).
EFFECT_ORDER: tuple[str, ...] = tuple(CATALOGUE)


def parse_effect(text: str, catalogue: Mapping[str, Effect] | None = None) -> tuple[str, dict[str, float]]:
    """``"NAME[:param=value,...]"`` -> (name, {full parameter name: value}).

    Parameters may be given by short (``delta``) or full (``backlash_delta``) name. An unknown
    effect or parameter, a malformed item or a non-number is a one-line :class:`EffectError`
    naming the valid choices. ``catalogue`` defaults to :data:`CATALOGUE`.
    """
    catalogue = CATALOGUE if catalogue is None else catalogue
    name, _, rest = str(text).partition(":")
    name = name.strip()
    if not name:
        raise EffectError(f"cannot read effect {text!r}: write NAME[:param=value,...], e.g. backlash:delta=0.02")
    if name not in catalogue:
        raise EffectError(f"unknown effect {name!r}; the catalogue has: {', '.join(catalogue)}")
    effect = catalogue[name]
    values: dict[str, float] = {}
    for item in filter(None, (s.strip() for s in rest.split(","))):
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise EffectError(f"cannot read effect {text!r} at {item!r}: write NAME[:param=value,...], "
                              f"e.g. {name}:{effect.short_names[0]}={effect.parameters[0].nominal:g}")
        full = effect.full_name(key.strip())
        try:
            number = float(value)
        except ValueError:
            raise EffectError(f"cannot read effect {text!r} at {item!r}: {value.strip()!r} is not a number") from None
        if not math.isfinite(number):
            raise EffectError(f"effect {name}: {full} = {value.strip()} is not finite; give a finite number")
        values[full] = number
    return name, values


def effect_parameters(names: Sequence[str], catalogue: Mapping[str, Effect] | None = None) -> ParameterSet:
    """The parameters of the named effects, in that order."""
    catalogue = CATALOGUE if catalogue is None else catalogue
    return ParameterSet(tuple(p for n in names for p in catalogue[n].parameters))


# --------------------------------------------------------------------------------------
# augmentation of the EMA concepts (htls, lths); EMPS brings its own augment function
# --------------------------------------------------------------------------------------
def _layout(order: Sequence[str]) -> dict[str, int]:
    """Positions inside the layout table: one block per effect of ``order``, at
    ``positions[effect]`` the position of its first parameter in theta, one further its first
    extra state in x (-1 when absent), then its kernel constants (``positions[f"{effect}_{short}"]``)."""
    positions: dict[str, int] = {}
    k = 0
    for name in order:
        positions[name] = k
        k += 2
        for short in CATALOGUE[name].constant_names:
            positions[f"{name}_{short}"] = k
            k += 1
    return positions


#: Kernel layout appended to the augmented model's derived constants (see :func:`_layout`);
#: effect_kernels.py reads its offsets from here at import, as compile-time constants.
LAYOUT: dict[str, int] = _layout(EFFECT_ORDER)
LAYOUT_SIZE = 2 * len(EFFECT_ORDER) + sum(len(CATALOGUE[n].constant_names) for n in EFFECT_ORDER)


def augment_ema(model: "Model", names: tuple[str, ...], values: dict[str, float]) -> "Model":
    """The augmented HT/LS or LT/HS model (``Model.augment`` of those concepts): the kernel id
    of ``KERNEL_IDS[concept]``, each effect's extra states, error scales and kernel constants
    as its :class:`Effect` declares them for the concept.

    ``names`` are catalogue effects (checked by ``Model.with_effects``); ``values`` override
    effect nominal values (full names). The kernel reads the layout from the derived constants.
    """
    for group in EXCLUSIVE:
        both = sorted(group & set(names))
        if len(both) > 1:
            raise EffectError(f"effects {' and '.join(both)} model the same coupling; switch in one of them")
    kernel_id = KERNEL_IDS.get(model.name, (None, None))[1]
    if kernel_id is None:
        raise EffectError(f"concept {model.name} has no compiled kernel with effects; give it one in "
                          "models.base.KERNEL_IDS and effect_kernels.py")
    table = np.full(LAYOUT_SIZE, -1.0)
    n_params = len(model.parameters)
    states, scales = list(model.states), list(model.state_scales)
    for name in names:
        effect = CATALOGUE[name]
        table[LAYOUT[name]] = n_params
        n_params += len(effect.parameters)
        extra = effect.extra_states.get(model.name, ())
        if extra:
            table[LAYOUT[name] + 1] = len(states)
            states.extend(extra)
            scales.extend(effect.state_scales[s] for s in extra)
        if effect.constant_names and model.name not in effect.constants:
            raise EffectError(f"effect {name} gives no kernel constants for concept {model.name}; "
                              "add them to its Effect.constants")
        for short, value in effect.constants.get(model.name, {}).items():
            table[LAYOUT[f"{name}_{short}"]] = float(value)
    derive = _DeriveWithLayout(model.derive, tuple(table))
    parameters = model.parameters + effect_parameters(names)
    if values:
        given = parameters.vector(values)  # unknown names raise here
        parameters.check_within_bounds(given, what="effect value")
        parameters = parameters.with_nominal(values)
    steps = tuple(CATALOGUE[n].postprocess for n in names if CATALOGUE[n].postprocess is not None)
    return replace(model, model_id=kernel_id, title=f"{model.title} + {' + '.join(names)}",
                   states=tuple(states), state_scales=tuple(scales), parameters=parameters, derive=derive,
                   effects=tuple(names), postprocess=_OutputSteps(steps) if steps else None, built_from=model)


def augment_own_kernel(model: "Model", names: Sequence[str], values: Mapping[str, float] | None, *,
                       catalogue: Mapping[str, Effect], rig: str, simulator: Callable, **changes) -> "Model":
    """``Model.augment`` of a concept whose own batch simulator runs its effects (EMPS,
    Cranfield): the nominal parameters followed by each effect's of ``catalogue``, at the
    effect's nominal values overridden by ``values`` (full names), run by ``simulator`` (the
    concept's batch simulator bound to ``names``); ``changes`` are further fields that follow
    the effects (e.g. the states). ``rig`` names the concept in errors.

    An effect at its ``off`` values reproduces the nominal outputs bit for bit.
    """
    base = model.base_model
    names = tuple(names)
    unknown = [n for n in names if n not in catalogue]
    if unknown:
        raise EffectError(f"unknown {rig} effect(s) {', '.join(unknown)}; choose from {', '.join(catalogue)}")
    parameters = base.parameters + ParameterSet(tuple(p for n in names for p in catalogue[n].parameters))
    if values:
        parameters = parameters.with_nominal(values)
        parameters.check_within_bounds(parameters.nominal, what="effect value")
    return replace(base, title=f"{base.title} + {' + '.join(names)}", parameters=parameters, effects=names,
                   batch_simulator=simulator, built_from=base, **changes)


def off_vector(catalogue: Mapping[str, Effect], kernel_index: Mapping[str, int], size: int) -> np.ndarray:
    """A flagged kernel's full parameter vector (``size``,) with every effect of ``catalogue``
    at its ``off`` values (zeros elsewhere: the base entries are overwritten per call)."""
    off = np.zeros(size)
    for effect in catalogue.values():
        for name, value in effect.off.items():
            off[kernel_index[name]] = value
    return off


@dataclass(frozen=True)
class FlaggedSimulator:
    """Base of the batch simulators whose own kernel switches effects by bit flags (EMPS,
    Cranfield), bound to the switched-on ``effects``. A subclass sets the class attributes
    RIG (name in errors), FLAGS (effect -> kernel bit), KERNEL_INDEX (parameter name ->
    position in the kernel's full vector) and OFF_VALUES (:func:`off_vector`)."""

    effects: tuple[str, ...] = ()

    @property
    def flags(self) -> int:
        return int(sum(self.FLAGS[name] for name in self.effects))

    def full_vectors(self, model: "Model", thetas: np.ndarray) -> np.ndarray:
        """(n_sets, n_full) kernel vectors: OFF_VALUES with ``thetas`` (n_sets, n_params) in place."""
        try:
            index = np.array([self.KERNEL_INDEX[name] for name in model.parameters.names], dtype=np.int64)
        except KeyError as exc:
            raise EffectError(f"parameter {exc.args[0]!r} has no place in the {self.RIG} kernel") from None
        full = np.repeat(self.OFF_VALUES[None, :], thetas.shape[0], axis=0)
        full[:, index] = thetas
        return full


@dataclass(frozen=True)
class _OutputSteps:
    """``Model.postprocess`` of an augmented model: the output-side steps of its effects in
    order (a picklable object rather than a closure)."""

    steps: tuple[Callable, ...]

    def __call__(self, model: "Model", thetas: np.ndarray, time: np.ndarray, out: np.ndarray) -> np.ndarray:
        for step in self.steps:
            out = step(model, thetas, time, out)
        return out


@dataclass(frozen=True)
class _DeriveWithLayout:
    """``Model.derive`` of an augmented model: the concept's derived constants followed by the
    effect layout table (a picklable, comparable object rather than a closure)."""

    base: object
    tail: tuple[float, ...]

    def __call__(self, c: np.ndarray) -> np.ndarray:
        return np.concatenate([self.base(c), np.asarray(self.tail, dtype=np.float64)])


__all__ = ["CATALOGUE", "EFFECT_ORDER", "EXCLUSIVE", "Effect", "EffectError", "FlaggedSimulator", "LAYOUT", "LAYOUT_SIZE",
           "SIGNATURES", "augment_ema", "augment_own_kernel", "delay_dispersed_outputs", "delay_outputs",
           "effect_parameters", "first_order_lag", "off_vector", "parse_effect"]
