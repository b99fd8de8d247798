"""The effect variants of the independent simulator (:mod:`ema_uq.gap.variants`): what each
one is, the catalogue family it belongs to (or none), its parameters with their bounds and
draw ranges, and how random parameters are drawn and checked.

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

Written after method version 2 was frozen (:data:`UNSEEN_VARIANTS`)
-------------------------------------------------------------------
Not in the self-check: records of mechanisms the frozen method was never run on, neither in
development nor in its evaluation block (``benchmarks/gap_unseen.py``). Each was chosen for
being common on real drives, not for resembling a catalogue form or a known miss.

``load_friction_efficiency`` (``load_dependent_friction``)
    A ball screw loses more when it drives against its load than when the load helps it
    (forward and backward efficiency differ): ball-screw friction + mu r (sqrt(F^2 + F0^2) - F0)
    x (a + (1 - a) s), s = (1 + tanh(P / P0)) / 2 the share of opposing load, P = M_ER Omega_U
    the power the load takes from the screw, P0 = 5 W; ``aid`` a in [0.2, 0.6].
``stribeck_asymmetric`` (``stribeck``)
    C (1 + rho g(v) exp(-(v/v_s)^2)) tanh(v/eps) with a breakaway excess that differs by
    direction: g = a + (1 - a) (1 + tanh(v/eps)) / 2, ``asymmetry`` a in [0.2, 0.6].
``sensor_delay_sample_hold`` (``sensor_delay``)
    Every channel comes from a sensor front end that samples and holds at its own period P,
    not in step with the recorder: y_m(t_k) = y(s_k), s_k the last sensor instant offset P + j P
    before t_k (cubic Hermite reading between the recorded samples): a delay that saw-tooths
    between 0 and P about its mean P/2.
``friction_warm_up`` (none)
    The grease warms during the record: every loss coefficient (viscous and Coulomb) times
    1 - drop (1 - exp(-t / tau)), t from the start of each record (a drift in time, which no
    time-invariant catalogue form has).
``position_sensor_nonlinearity`` (none)
    Each carriage sensor reads y + A sin(2 pi y / lambda + phi_k) (a potentiometer's or
    magnetostrictive scale's periodic linearity error), and the position loops close on the
    readings, so the carriages move off the command where the readings err.
``load_force_offset`` (none)
    The load rig's force loop holds each station's force off its set point by a constant
    offset (a load-cell zero error): F_ER,k + F_0 on both stations.

Written for the evaluation of method version 4 (:data:`UNSEEN_VARIANTS_2`)
-------------------------------------------------------------------------
A second unseen set, written without sight of the method version 4 changes, for that version's
evaluation (``benchmarks/gap_unseen2.yaml``); like the first, not in the self-check and chosen
for being common on real drives. Each differs from the catalogue's form and from every variant
above. Magnitude ranges from visibility alone: the least visible end of each draw range
(:meth:`Variant.weakest`) gives a chi-square excess over the nominal model at 2 % noise, on
deploy-retract and the rig channels (largest channel), of

======================================  =======  =======
variant                                  HT/LS    LT/HS
======================================  =======  =======
``torque_ripple_proportional``            1064      741
``ujoint_swivel``                          785      877
``sensor_delay_window``                    733     1341
``torque_constant_saturation``             804      795
``speed_loop_integral``                    854     1577
``speed_feedforward``                      855     1299
======================================  =======  =======

``torque_ripple_proportional`` (``torque_ripple``)
    M_m (1 + a sin(n_p theta + phi)): a ripple proportional to the motor torque M_m, n_p as the
    catalogue's, ``ratio`` a in [0.022, 0.12]. The catalogue's ripple (and the harmonics variant)
    has a fixed amplitude, a cogging torque; this one vanishes where the motor carries no torque
    and turns its sign with it. Common: the ripple a non-sinusoidal back-EMF or a current
    measurement error makes in a permanent-magnet motor grows with the current.
``ujoint_swivel`` (``ujoint_kinematics``)
    The exact Cardan speed ratio of ``ujoint_cardan`` at a joint angle that grows with the
    carriage's stroke, beta_k = beta_k,ref y_k / 0.25 m (joint k straight at the retracted end),
    ``beta1``, ``beta2`` in [13.5, 25] degrees at the reference stroke, a yoke phase per station.
    The catalogue's ripple (and ``ujoint_cardan``'s) has one amplitude over the whole stroke;
    here it grows about with the square of the stroke. Common: an actuator gimbal-mounted on the
    flap swivels as it deploys, so the joint between transmission shaft and screw bends more.
``sensor_delay_window`` (``sensor_delay``)
    Every channel is the mean of its signal over the last ``window`` W in [0.023, 0.08] s (the
    cubic Hermite curve through the samples integrated exactly): a delay W/2 spread uniformly
    over [0, W] with the boxcar's sinc attenuation, where the catalogue delays by one point in
    time (linear interpolation), the Hermite and all-pass variants by a point delay and the
    sample-and-hold by a delay that saw-tooths in time. Common: integrating converters
    (sigma-delta with a sinc filter), speeds from encoder counts over a gate time and currents
    averaged over PWM periods all report a window's mean.

Out of the catalogue (family ``None``):

``torque_constant_saturation``
    The motor's iron saturates: its torque is k_n I_A / (1 + s (I_A / I_ref)^2), I_ref = 30 A
    (HT/LS) / 25 A (LT/HS), about the peak current of deploy-retract, ``saturation`` s in
    [0.017, 0.17] (HT/LS) / [0.0085, 0.085] (LT/HS); the HT/LS drive sets its current for the
    nominal constant. No catalogue form changes the motor's torque per ampere; a refit of k_n
    can take up its mean, not its growth with the current. Common in compact high-torque motors
    driven near their peak current.
``speed_loop_integral``
    The drive's speed loop is PI, not P: p_PCE (e_Omega + k_i int e_Omega dt), the integral held
    while the output is clipped (conditional anti-windup), ``rate`` k_i in [0.45, 4.5] 1/s
    (HT/LS) / [0.3, 3] 1/s (LT/HS). It takes away the standing speed (and so position) error under
    load that the model's P loop keeps. Common: industrial servo drives ship with a PI speed loop.
``speed_feedforward``
    The drive adds k_ff times the command's rate, as motor speed on a rigid train, to the
    position loop's speed command (the rate as the drive differentiates its sampled set point),
    ``fraction`` k_ff in [0.013, 0.13]. It cuts the following error while the command moves; a
    lead, where the model-form stress's command shaping is a lag. Common: servo drives in
    position mode offer velocity feed-forward to track moving commands.

Tried and left out: a speed-command limit in the position loop. Deploy-retract holds its speed
command on a plateau for whole ramps, so the records do not change above the plateau speed and
change by a chi-square excess of 4 x 10^5 (LT/HS) at a limit 2 % below it: no range of visible
but weak limits.

Written for the evaluation of method version 5 (:data:`UNSEEN_VARIANTS_3`)
-------------------------------------------------------------------------
A third unseen set, written without sight of the method version 5 changes, for that version's
evaluation (``benchmarks/gap_unseen3.yaml``); like the first two, not in the self-check and
chosen for being common on real drives. Each differs from the catalogue's forms and from every
variant above; the in-catalogue ones take families no earlier unseen set took (backlash,
shaft_compliance) and, once more, stribeck. Magnitude ranges from visibility alone: the least
visible end of each draw range (:meth:`Variant.weakest`) gives a chi-square excess over the
nominal model at 2 % noise, on deploy-retract and the rig channels (largest channel), of

======================================  =======  =======
variant                                  HT/LS    LT/HS
======================================  =======  =======
``backlash_worn_screw``                   1156     1163
``shaft_compliance_progressive``          1121      976
``stribeck_dwell``                         926     1047
``screw_binding``                         1065      951
``speed_sensor_eccentricity``             1073     1020
``position_loop_deadband``                1069     1098
======================================  =======  =======

``backlash_worn_screw`` (``backlash``)
    Play between each ball screw and its nut that a worn screw has, widest where the nut travels
    most: half play delta (f + (1 - f) exp(-y / L)) at nut position y, f = 0.25 (the nut's own
    clearance), ``delta`` at the retracted end in [20, 200] um (HT/LS) / [15, 150] um (LT/HS),
    ``extent`` L in [0.08, 0.2] m. The carriage follows the nut through the play, held by its
    friction inside it (as the catalogue's play); the balls take the load up over their elastic
    approach of 10 um, and inside the play neither the load nor the screw's rolling friction
    reaches the drive. Each carriage starts on the flank its load presses it against. The
    catalogue's plays (and both backlash variants) have one width over the whole stroke.
    Common: a flap actuator's screw wears most in the section between stowed and the take-off
    setting, which every flight travels.
``shaft_compliance_progressive`` (``shaft_compliance``)
    An elastomer (jaw) coupling between motor and drive train, two masses as
    ``shaft_compliance_two_mass`` (load share 0.5-0.8 HT/LS, 0.4-0.7 LT/HS), whose spring
    stiffens with its twist q: k0 q (1 + s (q / q_ref)^2) + d q', q_ref the twist of the
    small-twist spring k0 at the reference torque (40 N m HT/LS, 2 N m LT/HS: about the peak
    motor torque of deploy-retract). ``frequency`` of the small-twist mode in [20, 65] Hz (HT/LS)
    / [90, 300] Hz (LT/HS), ``damping`` ratio in [0.05, 0.25], ``stiffening`` s in [1, 4]. The
    catalogue's spring (and the two-mass variant's) is linear: one mode frequency at every load;
    here the mode rises with the torque the coupling carries. Common: elastomer couplings between
    a servo motor and its gearbox are progressive by design.
``stribeck_dwell`` (``stribeck``)
    Breakaway friction that builds up while the drive stands: every Coulomb term
    C (1 + rho m) tanh(v/eps), the memory m going to exp(-(v/v_s)^2) of the screw speed v at the
    rate 1 / T_rest + |v| / D, D = 0.5 rad of screw rotation (0.56 mm of carriage travel): at
    rest it grows over the ``rest_time`` T_rest in [1, 5] s, in motion a short slide wipes it out;
    the drive stood long before the record (m = 1 at its start). ``ratio`` rho in [0.65, 3.5]
    (HT/LS) / [0.25, 1.5] (LT/HS), ``speed`` v_s in [0.5, 4] rad/s. The catalogue's excess is a
    function of the speed alone, the same after a short stop as after a long one (the limit
    T_rest -> 0 here); this one depends on how long the drive stood. Common: static friction of
    greased contacts rises with the time at rest as the lubricant film is squeezed out.

Out of the catalogue (family ``None``):

``screw_binding``
    Screw 1 binds once per revolution (bent, or mounted off its nut's axis): its drag torque is
    C_TS1 + B (1 + cos(alpha + phi)) / 2, alpha = y / (r tan gamma) the screw's angle (y: nut),
    ``binding`` B in [0.75, 3] N m at the screw. One screw only: the two screws turn in step, so
    two bindings of opposite phase would cancel at the motor (a draw that shows nothing). No
    catalogue form has a friction that varies with a screw's angle; the U-joint's ripple is a
    speed ratio at twice the shaft's rotation, the torque ripple a motor torque with 4 or 6
    periods per motor revolution. Common: screws bent in handling or misaligned in assembly.
``speed_sensor_eccentricity``
    The motor's angle sensor (resolver or encoder) is mounted off centre: it reads
    theta + A sin(theta + phi), so the drive's speed loop, and the record, see the speed
    Omega (1 + A cos(theta + phi)). ``amplitude`` A in [6, 30] mrad (HT/LS) / [0.19, 1.9] mrad
    (LT/HS: its motor turns twenty times as fast, and its speed loop drives a voltage). The loop
    turns the reading's once-per-revolution error into motor torque. Unlike
    ``position_sensor_nonlinearity`` this sensor's error acts in the speed loop, at the motor's
    rotation; unlike the torque ripple it grows with the speed, at motor order 1. Common: a
    resolver's eccentricity error is its largest, and sets the speed ripple of many servo drives.
``position_loop_deadband``
    The position loop acts only on the error beyond a dead band: speed command
    p_ACE (e - clip(e, -w, w)), ``width`` w in [0.4, 2.5] mm. Every error the loop settles at,
    following a ramp or holding against the load, grows by about w, and after a reversal of the
    command the drive waits until the error has crossed the band. No catalogue form changes the
    loops; set 2's loop variants (PI, feed-forward) are linear, this one is not.
    Common: position controllers offer an error dead band to keep a drive with play or stiction
    from hunting at rest.

Tried and left out: a Stribeck excess that follows the speed through a first-order lag (frictional
lag, 30-150 ms): at the ratio where it first shows (chi-square ~930 over the nominal model) its
records differ from those of the same curve without the lag by a chi-square of only 63 (HT/LS) /
113 (LT/HS), no form of its own. A drag variation on both screws: see ``screw_binding``. Not
written: a play whose load side the load pushes across rather than its friction holding it; under
the one-sided loads of the flap profiles such a play never opens.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Mapping

import numpy as np

from ..errors import EmaUqError

TWO_PI = 2.0 * math.pi
CONCEPTS = ("htls", "lths")
FAMILIES = ("backlash", "stribeck", "torque_ripple", "sensor_delay", "shaft_compliance",
            "load_dependent_friction", "ujoint_kinematics")
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
 V_SHAFT_TWO_MASS, V_LOAD_LINEAR, V_LOAD_POWER, V_CARDAN, V_TORQUE_LAG, V_SPOT, V_LOAD_FOLLOW,
 V_LOAD_EFFICIENCY, V_STRIBECK_ASYMMETRIC, V_WARM_UP, V_POSITION_SENSOR, V_LOAD_OFFSET) = range(19)
# those of the second unseen set (:data:`UNSEEN_VARIANTS_2`)
V_RIPPLE_PROPORTIONAL, V_UJOINT_SWIVEL, V_TORQUE_SATURATION, V_SPEED_INTEGRAL, V_SPEED_FEEDFORWARD = range(19, 24)
# those of the third unseen set (:data:`UNSEEN_VARIANTS_3`)
(V_BACKLASH_WORN, V_COUPLING_PROGRESSIVE, V_STRIBECK_DWELL, V_SCREW_BINDING, V_SPEED_SENSOR,
 V_POSITION_DEADBAND) = range(24, 30)

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


def _build_unseen_variants() -> dict[str, Variant]:
    variants = (
        Variant("load_friction_efficiency", "load_dependent_friction",
                "ball-screw friction + mu r (sqrt(F^2 + F0^2) - F0), less of it where the load aids the motion",
                (_mag("mu", "1", 1.5e-3, 1.5e-2, 0.0, 0.5, "load coefficient against an opposing load"),
                 _shape("aid", "1", 0.2, 0.6, 0.0, 1.0, "its fraction where the load aids the motion")),
                V_LOAD_EFFICIENCY),
        Variant("stribeck_asymmetric", "stribeck",
                "C (1 + rho g(v) exp(-(v/v_s)^2)) tanh(v/eps), the breakaway excess smaller in one direction",
                (*_STRIBECK,
                 _shape("asymmetry", "1", 0.2, 0.6, 0.0, 1.0, "breakaway excess of the negative direction / positive")),
                V_STRIBECK_ASYMMETRIC),
        Variant("sensor_delay_sample_hold", "sensor_delay",
                "every channel sampled and held by its sensor at period P, out of step with the recorder",
                (_mag("period", "s", 0.012, 0.07, 1e-4, 1.0, "sample-and-hold period of the sensors"),
                 _shape("offset", "1", 0.0, 1.0, 0.0, 1.0, "first sensor instant as a fraction of the period")),
                V_NONE),
        Variant("friction_warm_up", None, "every loss coefficient times 1 - drop (1 - exp(-t / tau)) over a record",
                (_mag("drop", "1", 0.02, 0.2, 0.0, 0.9, "fall of the losses once warm"),
                 _shape("tau", "s", 8.0, 30.0, 0.1, 1e4, "warm-up time constant")),
                V_WARM_UP),
        Variant("position_sensor_nonlinearity", None,
                "carriage sensors read y + A sin(2 pi y / lambda + phi_k); the position loops close on them",
                (_mag("amplitude", "m", 3e-4, 3e-3, 0.0, 0.05, "linearity error of the position sensors"),
                 _shape("wavelength", "m", 0.04, 0.12, 1e-3, 10.0, "period of the error along the stroke"),
                 _phase("phase1", "phase of sensor 1"), _phase("phase2", "phase of sensor 2")),
                V_POSITION_SENSOR),
        Variant("load_force_offset", None, "the load rig holds F_ER,k + F_0 on both stations",
                (_mag("offset", "N", 200.0, 2000.0, 0.0, 1e5, "size of the force offset"),
                 _shape("direction", "1", -1.0, 1.0, -1.0, 1.0, "its sign: that of direction")),
                V_LOAD_OFFSET),
    )
    return {v.name: v for v in variants}


#: variants written after method version 2 was frozen (module docstring); not in the self-check
UNSEEN_VARIANTS: dict[str, Variant] = _build_unseen_variants()


def _build_unseen_variants_2() -> dict[str, Variant]:
    variants = (
        Variant("torque_ripple_proportional", "torque_ripple",
                "motor torque ripple proportional to the motor torque: M_m (1 + a sin(n_p theta + phi))",
                (_mag("ratio", "1", 0.022, 0.12, 0.0, 0.5, "ripple amplitude as a fraction of the motor torque"),
                 _phase("phase", "ripple phase at theta = 0")),
                V_RIPPLE_PROPORTIONAL, step_divisor=4),
        Variant("ujoint_swivel", "ujoint_kinematics",
                "exact Cardan speed ratio at a joint angle that grows with the carriage's stroke (swivelling actuator)",
                (_mag("beta1", "rad", math.radians(13.5), math.radians(25.0), 0.0, 1.2,
                      "joint angle of station 1 at the reference stroke"),
                 _mag("beta2", "rad", math.radians(13.5), math.radians(25.0), 0.0, 1.2,
                      "joint angle of station 2 at the reference stroke"),
                 _phase("phase1", "yoke phase of station 1"), _phase("phase2", "yoke phase of station 2")),
                V_UJOINT_SWIVEL),
        Variant("sensor_delay_window", "sensor_delay",
                "every channel averaged by its sensor over the last window W (an integrating front end)",
                (_mag("window", "s", 0.023, 0.08, 0.0, 1.0, "averaging window of the sensors"),),
                V_NONE),
        Variant("torque_constant_saturation", None,
                "the motor's torque constant falls with its current: k_n / (1 + s (I_A / I_ref)^2)",
                (_mag("saturation", "1", 0.0, 0.0, 0.0, 5.0, "s: the torque falls by s / (1 + s) at I_ref",
                      per_concept={"htls": (0.017, 0.17), "lths": (0.0085, 0.085)}),),
                V_TORQUE_SATURATION),
        Variant("speed_loop_integral", None,
                "the drive's speed loop is PI: p_PCE (e_Omega + k_i integral e_Omega), the integral held at the limits",
                (_mag("rate", "1/s", 0.0, 0.0, 0.0, 1e3, "integral gain k_i of the speed loop",
                      per_concept={"htls": (0.45, 4.5), "lths": (0.3, 3.0)}),),
                V_SPEED_INTEGRAL),
        Variant("speed_feedforward", None,
                "the drive adds k_ff x the command's rate (as motor speed) to the position loop's speed command",
                (_mag("fraction", "1", 0.013, 0.13, 0.0, 2.0, "feed-forward fraction k_ff of the command's rate"),),
                V_SPEED_FEEDFORWARD),
    )
    return {v.name: v for v in variants}


#: variants written for the evaluation of method version 4 (module docstring); not in the self-check
UNSEEN_VARIANTS_2: dict[str, Variant] = _build_unseen_variants_2()


def _build_unseen_variants_3() -> dict[str, Variant]:
    variants = (
        Variant("backlash_worn_screw", "backlash",
                "play between a worn ball screw and its nut, widest where the nut travels most: "
                "delta (f + (1 - f) exp(-y / L))",
                (_mag("delta", "m", 0.0, 0.0, 0.0, 0.01, "half play at the retracted end of the stroke",
                      per_concept={"htls": (2e-5, 2e-4), "lths": (1.5e-5, 1.5e-4)}),
                 _shape("extent", "m", 0.08, 0.2, 1e-3, 10.0, "stroke over which the wear falls by 1/e")),
                V_BACKLASH_WORN),
        Variant("shaft_compliance_progressive", "shaft_compliance",
                "elastomer coupling between motor and drive train whose stiffness grows with its twist",
                (_mag("frequency", "Hz", 0.0, 0.0, 1.0, 1e3, "torsional mode at small twist", weak="high",
                      per_concept={"htls": (20.0, 65.0), "lths": (90.0, 300.0)}),
                 _mag("damping", "1", 0.05, 0.25, 1e-4, 2.0, "damping ratio at small twist", weak="high"),
                 _shape("load_share", "1", 0.0, 0.0, 0.05, 0.95, "load-side share of the inertia J",
                        per_concept={"htls": (0.5, 0.8), "lths": (0.4, 0.7)}),
                 _shape("stiffening", "1", 1.0, 4.0, 0.0, 100.0,
                        "s: the stiffness is (1 + s) k0 where k0 alone carries the reference torque")),
                V_COUPLING_PROGRESSIVE),
        Variant("stribeck_dwell", "stribeck",
                "C (1 + rho m) tanh(v/eps), the breakaway excess m built up at rest, wiped out by sliding",
                (_mag("ratio", "1", 0.0, 0.0, 0.0, 50.0, "breakaway excess C_s / C - 1 of every Coulomb term",
                      per_concept={"htls": (0.65, 3.5), "lths": (0.25, 1.5)}),
                 _mag("speed", "rad/s", 0.5, 4.0, 1e-4, 1e3, "Stribeck speed of the screw shaft"),
                 _shape("rest_time", "s", 1.0, 5.0, 1e-3, 1e3, "time constant of its growth at rest")),
                V_STRIBECK_DWELL),
        Variant("screw_binding", None,
                "screw 1 binds once per revolution: drag C_TS1 + B (1 + cos(alpha + phi)) / 2",
                (_mag("binding", "N m", 0.75, 3.0, 0.0, 100.0, "extra drag torque of screw 1 where it binds"),
                 _phase("phase", "screw angle of the binding at y1 = 0")),
                V_SCREW_BINDING),
        Variant("speed_sensor_eccentricity", None,
                "the motor's angle sensor reads theta + A sin(theta + phi); speed loop and record see its speed",
                (_mag("amplitude", "rad", 0.0, 0.0, 0.0, 0.2, "angle error of the motor's sensor",
                      per_concept={"htls": (6e-3, 3e-2), "lths": (1.9e-4, 1.9e-3)}),
                 _phase("phase", "phase of the error at theta = 0")),
                V_SPEED_SENSOR),
        Variant("position_loop_deadband", None,
                "the position loop acts on the error beyond a dead band +-w only",
                (_mag("width", "m", 4e-4, 2.5e-3, 0.0, 0.05, "half width of the dead band"),),
                V_POSITION_DEADBAND),
    )
    return {v.name: v for v in variants}


#: variants written for the evaluation of method version 5 (module docstring); not in the self-check
UNSEEN_VARIANTS_3: dict[str, Variant] = _build_unseen_variants_3()
#: the unseen sets by the name a protocol gives them (``variant_set``)
UNSEEN_SETS: dict[str, dict[str, Variant]] = {"UNSEEN_VARIANTS": UNSEEN_VARIANTS,
                                              "UNSEEN_VARIANTS_2": UNSEEN_VARIANTS_2,
                                              "UNSEEN_VARIANTS_3": UNSEEN_VARIANTS_3}
ALL_VARIANTS: dict[str, Variant] = {**VARIANTS, **UNSEEN_VARIANTS, **UNSEEN_VARIANTS_2, **UNSEEN_VARIANTS_3}


def get_variant(name: str) -> Variant:
    try:
        return ALL_VARIANTS[name]
    except (KeyError, TypeError):
        raise VariantError(f"unknown variant {name!r}; choose one of: {', '.join(ALL_VARIANTS)}") from None


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
        if "tau" not in values or variant.family != "sensor_delay":
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
