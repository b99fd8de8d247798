"""The independent simulator's own kernel: parameter, constant, state and output layouts of the
HT/LS and LT/HS models, the variants' parameters in kernel units, and the right-hand sides and
fixed-step RK4 loop compiled by numba. Written from MODEL_SPEC.md apart from the package's
equation modules (see :mod:`ema_uq.gap.variants` for why); :func:`ema_uq.gap.variants.simulate_variant`
drives it.
"""
from __future__ import annotations

import math
from typing import Mapping

import numpy as np
from numba import njit

from ..models import get_model
from .variant_catalogue import (TWO_PI, V_BACKLASH_TWO_MASS, V_BACKLASH_WORN, V_CARDAN, V_COUPLING_PROGRESSIVE,
                                V_DEADZONE, V_LOAD_EFFICIENCY, V_LOAD_FOLLOW, V_LOAD_LINEAR, V_LOAD_OFFSET,
                                V_LOAD_POWER, V_NONE, V_POSITION_DEADBAND, V_POSITION_SENSOR, V_RIPPLE,
                                V_RIPPLE_PROPORTIONAL, V_SCREW_BINDING, V_SHAFT_TWO_MASS, V_SPEED_FEEDFORWARD,
                                V_SPEED_INTEGRAL, V_SPEED_SENSOR, V_SPOT, V_STRIBECK_ASYMMETRIC, V_STRIBECK_EXP,
                                V_STRIBECK_GAUSS, V_STRIBECK_DWELL, V_STRIBECK_RATIONAL, V_TORQUE_LAG,
                                V_TORQUE_SATURATION, V_UJOINT_SWIVEL, V_WARM_UP, Variant, VariantError)

#: ripple periods per motor revolution (as the catalogue's torque_ripple)
RIPPLE_PERIODS = {"htls": 6.0, "lths": 4.0}
LOAD_SMOOTHING = 200.0      # N, F0 of the smoothed |F| of the load-friction variants
LOAD_REFERENCE = 10e3       # N, F_ref of the power-law load friction
LOAD_EXPONENT = 1.2
CONTACT_RAMP = 0.1          # fraction of the output play over which the load is taken up
EFFICIENCY_POWER = 5.0      # W, P0 of the smoothed switch between opposing and aiding load
STROKE_REFERENCE = 0.25     # m, carriage stroke at which the swivelling joints reach their stated angle
#: A, current at which the saturating torque constant has fallen by s / (1 + s): about the
#: peak motor current of deploy-retract, so s reads as the fall where the drive works hardest
SATURATION_CURRENT = {"htls": 30.0, "lths": 25.0}
#: play of the least worn screw section over that at the retracted end (the nut's own clearance)
WORN_PLAY_FLOOR = 0.25
#: m, elastic approach of a ball nut's balls under the rigs' loads (Hertzian contact)
BALL_APPROACH = 1e-5
#: rad of screw rotation (0.56 mm of carriage travel) in which sliding wipes out the breakaway
#: friction built up at rest
DWELL_SLIDE = 0.5
#: N m, reference torque of the progressive coupling: at the twist where its small-twist spring would
#: carry it, the stiffness has grown by 1 + s. About the peak motor torque of deploy-retract, so s
#: reads as the stiffening over the run
COUPLING_TORQUE = {"htls": 40.0, "lths": 2.0}


# ------------------------------------------------------------------------------------------
# the independent simulator: layouts
# ------------------------------------------------------------------------------------------
#: base parameters in this kernel's own order (absent ones of a concept are 0 and never read)
PARAMETER_LAYOUT = ("J", "B_TS1", "C_TS1", "B_U1", "C_U1", "B_TP1", "C_TP1",
                    "B_TS2", "C_TS2", "B_U2", "C_U2", "B_TP2", "C_TP2",
                    "k_n", "p_ACE", "p_PCE", "B_MG", "C_MG", "R_A", "L_A", "k_s")
(T_J, T_BTS1, T_CTS1, T_BU1, T_CU1, T_BTP1, T_CTP1, T_BTS2, T_CTS2, T_BU2, T_CU2, T_BTP2, T_CTP2,
 T_KN, T_PACE, T_PPCE, T_BMG, T_CMG, T_RA, T_LA, T_KS) = range(21)
#: the loss coefficients (viscous and Coulomb) that the friction warm-up scales
LOSS_COEFFICIENTS = np.array([T_BTS1, T_CTS1, T_BU1, T_CU1, T_BTP1, T_CTP1, T_BTS2, T_CTS2, T_BU2, T_CU2, T_BTP2,
                              T_CTP2, T_BMG, T_CMG])
STATION_STRIDE = 6  # station-2 losses follow station 1's in the same order
#: design constants in this kernel's own order, then the values derived from them
CONSTANT_LAYOUT = ("omega_eps", "r", "gamma", "beta1", "beta2", "k_y", "M_Bmax", "K_b", "Omega_half",
                   "i_TP1", "i_TP2", "i_MG", "i_BG1", "i_BG2", "D_IS", "M_min", "M_max", "U_max")
(K_EPS, K_R, K_GAMMA, K_BETA1, K_BETA2, K_KY, K_MBMAX, K_KB, K_OHALF, K_ITP1, K_ITP2, K_IMG, K_IBG1, K_IBG2,
 K_DIS, K_MMIN, K_MMAX, K_UMAX, K_LEAD, K_RSC, K_INVCB1, K_INVCB2) = range(22)

#: state layout after the concept offset o (LT/HS: x[0] = I_A, o = 1; HT/LS: o = 0)
(S_OMEGA, S_Y1, S_Y2, S_THETA, S_LOAD_SPEED, S_LOAD_ANGLE, S_LAG, S_CARRIAGE1, S_CARRIAGE2,
 S_SPEED_INTEGRAL) = range(10)
S_BREAKAWAY = S_LAG    # the breakaway memory's state (no variant has a torque lag and a memory)
N_STATE = 11

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
    elif kid in (V_CARDAN, V_UJOINT_SWIVEL):
        v[:4] = (p["beta1"], p["beta2"], p["phase1"], p["phase2"])
    elif kid == V_SPOT:
        v[:3] = (p["friction"], p["position"], p["width"])
    elif kid == V_LOAD_FOLLOW:
        v[0] = p["stiffness"]
    elif kid == V_LOAD_EFFICIENCY:
        v[:2] = (p["mu"], p["aid"])
    elif kid == V_STRIBECK_ASYMMETRIC:
        v[:3] = (p["ratio"], p["speed"], p["asymmetry"])
    elif kid == V_WARM_UP:
        v[:2] = (p["drop"], p["tau"])
    elif kid == V_POSITION_SENSOR:
        v[:4] = (p["amplitude"], p["wavelength"], p["phase1"], p["phase2"])
    elif kid == V_LOAD_OFFSET:
        v[0] = math.copysign(p["offset"], p["direction"])
    elif kid == V_RIPPLE_PROPORTIONAL:
        v[:3] = (p["ratio"], p["phase"], RIPPLE_PERIODS[concept])
    elif kid == V_TORQUE_SATURATION:
        v[:2] = (p["saturation"], SATURATION_CURRENT[concept])
    elif kid == V_SPEED_INTEGRAL:
        v[0] = p["rate"]
    elif kid == V_SPEED_FEEDFORWARD:  # motor radians per radian of phi_r on a rigid train
        v[:2] = (p["fraction"], c[K_KY] / _carriage_per_motor_radian(concept, c))
    elif kid == V_BACKLASH_WORN:
        v[:2] = (p["delta"], p["extent"])
    elif kid == V_COUPLING_PROGRESSIVE:   # the two-mass layout (no play), then the stiffening
        v[:6] = (p["load_share"], TWO_PI * p["frequency"], p["damping"], 0.0, p["stiffening"],
                 COUPLING_TORQUE[concept])
    elif kid == V_STRIBECK_DWELL:
        v[:3] = (p["ratio"], p["speed"], p["rest_time"])
    elif kid == V_SCREW_BINDING:
        v[:2] = (p["binding"], p["phase"])
    elif kid == V_SPEED_SENSOR:
        v[:2] = (p["amplitude"], p["phase"])
    elif kid == V_POSITION_DEADBAND:
        v[0] = p["width"]
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
    if vid == V_STRIBECK_ASYMMETRIC:
        q = v / vv[1]
        sign = math.tanh(v / eps)
        share = vv[2] + (1.0 - vv[2]) * 0.5 * (1.0 + sign)
        return level * (1.0 + vv[0] * share * math.exp(-q * q)) * sign
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
def _flank_contact(gap, half_play):
    """How far a flank carries (0..1) when the drive side stands ``gap`` off the load side's
    centre in a play of ``half_play``: taken up smoothly over the last CONTACT_RAMP of the play."""
    ramp = min(max((gap / half_play - 1.0 + CONTACT_RAMP) / CONTACT_RAMP, 0.0), 1.0)
    return ramp * ramp * (3.0 - 2.0 * ramp)


@njit(cache=True, error_model="numpy")
def _ball_contact(gap, half_play):
    """How far a worn nut's flank carries (0..1) when the screw stands ``gap`` off the nut's centre
    in a play of ``half_play``: the balls take the load up over their elastic approach
    BALL_APPROACH, so a play narrower than that never unloads them fully."""
    ramp = min(max((gap - half_play + BALL_APPROACH) / BALL_APPROACH, 0.0), 1.0)
    return ramp * ramp * (3.0 - 2.0 * ramp)


@njit(cache=True, error_model="numpy")
def _worn_half_play(nut, vv):
    """Half play of a worn screw where its nut stands: vv[0] at the retracted end, falling over
    the extent vv[1] to the unworn floor (the section travelled most wears most)."""
    worn = math.exp(-max(nut, 0.0) / vv[1])
    return vv[0] * (WORN_PLAY_FLOOR + (1.0 - WORN_PLAY_FLOOR) * worn)


@njit(cache=True, error_model="numpy")
def _breakaway_excess(vid, x, o, vv):
    """Factor on every Coulomb level: 1 + rho m with the breakaway memory m, else 1."""
    if vid == V_STRIBECK_DWELL:
        return 1.0 + vv[0] * x[o + S_BREAKAWAY]
    return 1.0


@njit(cache=True, error_model="numpy")
def _station(k, vid, w_tp, a_tp, x, u, th, c, vv, o):
    """Station k (0, 1): U-joint and ball screw driven at bevel-output speed w_tp, angle a_tp.

    Returns (Omega_U, M_ER, M_TSER, M_UER, carriage position)."""
    eps = c[K_EPS]
    s = STATION_STRIDE * k
    nut = x[o + S_Y1 + k]
    ratio = 1.0
    if vid == V_CARDAN or vid == V_UJOINT_SWIVEL:  # d phi_out / d phi_in of tan(phi_out) = tan(phi_in) / cos(beta)
        beta = vv[k] if vid == V_CARDAN else vv[k] * nut / STROKE_REFERENCE
        cb = math.cos(beta)
        phi = a_tp + vv[2 + k]
        ratio = cb / (cb * cb * math.cos(phi) ** 2 + math.sin(phi) ** 2)
    w_u = ratio * w_tp
    force = u[1 + k]
    contact = 1.0
    carriage = nut
    if vid == V_LOAD_FOLLOW:
        force -= 0.5 * vv[0] * (nut - c[K_KY] * u[0])
    elif vid == V_LOAD_OFFSET:
        force += vv[0]
    elif vid == V_DEADZONE and vv[0] > 0.0:
        carriage = min(max(x[o + S_CARRIAGE1 + k], nut - vv[0]), nut + vv[0])
        contact = _flank_contact(abs(nut - carriage), vv[0])
    elif vid == V_BACKLASH_WORN and vv[0] > 0.0:
        half = _worn_half_play(nut, vv)
        carriage = min(max(x[o + S_CARRIAGE1 + k], nut - half), nut + half)
        contact = _ball_contact(abs(nut - carriage), half)
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
    elif vid == V_SCREW_BINDING and k == 0:   # a lead of nut travel per screw radian: nut / lead is its angle
        c_ts += vv[0] * 0.5 * (1.0 + math.cos(nut / c[K_LEAD] + vv[1]))
    m_er = -c[K_RSC] * force * contact
    if vid == V_LOAD_EFFICIENCY:
        opposing = 0.5 * (1.0 + math.tanh(m_er * w_u / EFFICIENCY_POWER))
        c_ts += (vv[0] * c[K_R] * (math.sqrt(force * force + LOAD_SMOOTHING ** 2) - LOAD_SMOOTHING)
                 * (vv[1] + (1.0 - vv[1]) * opposing))
    elif vid == V_POSITION_SENSOR:   # the loops and the record see the sensor's reading
        carriage += vv[0] * math.sin(TWO_PI * carriage / vv[1] + vv[2 + k])
    excess = _breakaway_excess(vid, x, o, vv)
    # a worn nut's balls roll under load only against a flank: inside the play the screw turns free
    rolling = contact if vid == V_BACKLASH_WORN else 1.0
    m_tser = rolling * (th[T_BTS1 + s] * w_u + _coulomb(excess * c_ts, w_u, eps, vid, vv)) + m_er
    m_uer = (ratio * m_tser * c[K_INVCB1 + k] + th[T_BU1 + s] * w_u
             + _coulomb(excess * th[T_CU1 + s], w_u, eps, vid, vv))
    return w_u, m_er, m_tser, m_uer, carriage


@njit(cache=True, error_model="numpy")
def _coupling_torque(twist, twist_rate, stiffness, damping, half_play, hardening):
    """Torque through a spring-damper with a dead band of +-half_play (no torque inside it, and
    no pulling torque while the flanks separate); half_play = 0 is a plain shaft, whose spring
    stiffens as stiffness (1 + hardening twist^2) (an elastomer coupling; hardening 0: linear)."""
    if half_play <= 0.0:
        return stiffness * twist * (1.0 + hardening * twist * twist) + damping * twist_rate
    if twist > half_play:
        return max(stiffness * (twist - half_play) + damping * twist_rate, 0.0)
    if twist < -half_play:
        return min(stiffness * (twist + half_play) + damping * twist_rate, 0.0)
    return 0.0


@njit(cache=True, error_model="numpy")
def _two_mass(drive, load, omega, theta, w_load, a_load, inertia, vv, dx, o):
    """Motor inertia (1 - share) J under ``drive``, load inertia share J under ``load`` [N m],
    joined by the coupling of mode vv[1] [rad/s] (at small twist), damping ratio vv[2], half play
    vv[3] [rad]; a progressive coupling's stiffness has grown by the factor 1 + vv[4] at the
    twist where its small-twist spring would carry vv[5] [N m]."""
    share, wn, zeta = vv[0], vv[1], vv[2]
    j_motor, j_load = (1.0 - share) * inertia, share * inertia
    j_red = j_motor * j_load / inertia
    stiffness = j_red * wn * wn
    hardening = 0.0
    if vv[4] > 0.0:
        hardening = vv[4] * (stiffness / vv[5]) ** 2
    torque = _coupling_torque(theta - a_load, omega - w_load, stiffness, 2.0 * zeta * wn * j_red, vv[3], hardening)
    dx[o + S_OMEGA] = (drive - torque) / j_motor
    dx[o + S_LOAD_SPEED] = (torque - load) / j_load
    dx[o + S_LOAD_ANGLE] = w_load


@njit(cache=True, error_model="numpy")
def _ripple(vid, theta, torque, vv):
    """Ripple torque at motor angle theta; the proportional form scales with the motor torque."""
    if vid == V_RIPPLE_PROPORTIONAL:
        return vv[0] * torque * math.sin(vv[2] * theta + vv[1])
    if vid != V_RIPPLE:
        return 0.0
    total = 0.0
    for j in range(3):
        total += vv[j] * math.sin((j + 1) * vv[6] * theta + vv[3 + j])
    return total


@njit(cache=True, error_model="numpy")
def _speed_command(vid, command, u, vv):
    """The position loop's speed command; with feed-forward, plus k_ff x the motor speed that
    follows the command's rate u[4]."""
    if vid == V_SPEED_FEEDFORWARD:
        return command + vv[0] * vv[1] * u[4]
    return command


@njit(cache=True, error_model="numpy")
def _position_error(vid, error, vv):
    """The position error the loop acts on: with a dead band, what lies beyond +-vv[0]."""
    if vid == V_POSITION_DEADBAND:
        return error - min(max(error, -vv[0]), vv[0])
    return error


@njit(cache=True, error_model="numpy")
def _speed_reading(vid, omega, theta, vv):
    """The motor speed the drive reads: an eccentric angle sensor reads theta + A sin(theta + phi),
    so its speed omega (1 + A cos(theta + phi))."""
    if vid == V_SPEED_SENSOR:
        return omega * (1.0 + vv[0] * math.cos(theta + vv[1]))
    return omega


@njit(cache=True, error_model="numpy")
def _breakaway_rate(vid, x, o, screw_speed, vv):
    """d/dt of the breakaway memory m: it goes to exp(-(v/v_s)^2) of the screw speed v, slowly at
    rest (time constant vv[2], the rest time) and within DWELL_SLIDE of screw rotation in motion."""
    if vid != V_STRIBECK_DWELL:
        return 0.0
    q = screw_speed / vv[1]
    return (math.exp(-q * q) - x[o + S_BREAKAWAY]) * (1.0 / vv[2] + abs(screw_speed) / DWELL_SLIDE)


@njit(cache=True, error_model="numpy")
def _speed_loop_input(vid, speed_error, integral, vv):
    """What the speed loop's gain multiplies: the error, plus k_i times its integral in a PI loop."""
    if vid == V_SPEED_INTEGRAL:
        return speed_error + vv[0] * integral
    return speed_error


@njit(cache=True, error_model="numpy")
def _integrand(speed_error, command, limited):
    """d/dt of the PI loop's integral: held while the output is clipped and the error would push it
    further (anti-windup by conditional integration, as drives do)."""
    if command != limited and speed_error * command > 0.0:
        return 0.0
    return speed_error


@njit(cache=True, error_model="numpy")
def _saturation(current, vv):
    """Torque constant over its nominal value at ``current``: 1 / (1 + s (I / I_ref)^2)."""
    q = current / vv[1]
    return 1.0 / (1.0 + vv[0] * q * q)


@njit(cache=True, error_model="numpy")
def _htls_rhs(vid, x, u, th, c, vv, dx, y, outputs):
    """HT/LS: dx (N_STATE,) and, if ``outputs``, y in HTLS_OUTPUTS order."""
    dx[:] = 0.0
    eps = c[K_EPS]
    omega, theta = x[S_OMEGA], x[S_THETA]
    two_mass = vid == V_BACKLASH_TWO_MASS or vid == V_SHAFT_TWO_MASS or vid == V_COUPLING_PROGRESSIVE
    w_d = x[S_LOAD_SPEED] if two_mass else omega
    a_d = x[S_LOAD_ANGLE] if two_mass else theta
    i1, i2 = c[K_ITP1], c[K_ITP2]
    w_tp1, w_tp2 = w_d / i1, w_d / i2
    w_u1, m_er1, m_tser1, m_uer1, y1 = _station(0, vid, w_tp1, a_d / i1, x, u, th, c, vv, 0)
    w_u2, m_er2, m_tser2, m_uer2, y2 = _station(1, vid, w_tp2, a_d / i2, x, u, th, c, vv, 0)
    brake = u[3]
    excess = _breakaway_excess(vid, x, 0, vv)
    m_tper1 = (m_uer1 / i1 + th[T_BTP1] * w_tp1 + _coulomb(excess * th[T_CTP1], w_tp1, eps, vid, vv)
               + _brake(brake, w_tp1, c))
    m_tper2 = (m_uer2 / i2 + th[T_BTP2] * w_tp2 + _coulomb(excess * th[T_CTP2], w_tp2, eps, vid, vv)
               + _brake(brake, w_tp2, c))
    omega_read = _speed_reading(vid, omega, theta, vv)
    position_error = _position_error(vid, c[K_KY] * u[0] - 0.5 * (y1 + y2), vv)
    speed_error = _speed_command(vid, th[T_PACE] * position_error, u, vv) - omega_read
    command = th[T_PPCE] * _speed_loop_input(vid, speed_error, x[S_SPEED_INTEGRAL], vv)
    m_n = min(max(command, c[K_MMIN]), c[K_MMAX])
    if vid == V_SPEED_INTEGRAL:
        dx[S_SPEED_INTEGRAL] = _integrand(speed_error, command, m_n)
    m_motor = m_n
    if vid == V_TORQUE_LAG:  # the lagged torque is what the current sensor sees
        m_motor = x[S_LAG]
        dx[S_LAG] = (m_n - m_motor) / vv[0]
    elif vid == V_STRIBECK_DWELL:
        dx[S_BREAKAWAY] = _breakaway_rate(vid, x, 0, w_tp1, vv)
    i_a = m_motor / th[T_KN]
    if vid == V_TORQUE_SATURATION:  # the drive sets the current for the nominal constant
        m_motor = m_motor * _saturation(i_a, vv)
    drive = m_motor + _ripple(vid, theta, m_motor, vv) - _brake(brake, omega, c)
    if two_mass:
        _two_mass(drive, m_tper1 + m_tper2, omega, theta, w_d, a_d, th[T_J], vv, dx, 0)
    else:
        dx[S_OMEGA] = (drive - m_tper1 - m_tper2) / th[T_J]
    dx[S_Y1] = c[K_LEAD] * w_u1
    dx[S_Y2] = c[K_LEAD] * w_u2
    dx[S_THETA] = omega
    if outputs:   # the drive's speed reading is the recorded motor speed
        values = (omega_read, y1, y2, i_a, w_tp1, w_tp2, w_u1, w_u2, m_er1, m_er2, m_tser1, m_tser2,
                  m_uer1, m_uer2, m_tper1, m_tper2)
        for j in range(16):
            y[j] = values[j]


@njit(cache=True, error_model="numpy")
def _lths_rhs(vid, x, u, th, c, vv, dx, y, outputs):
    """LT/HS: dx (N_STATE,) and, if ``outputs``, y in LTHS_OUTPUTS order (x[0] = I_A)."""
    dx[:] = 0.0
    eps = c[K_EPS]
    i_a, omega, theta = x[0], x[1 + S_OMEGA], x[1 + S_THETA]
    two_mass = vid == V_BACKLASH_TWO_MASS or vid == V_SHAFT_TWO_MASS or vid == V_COUPLING_PROGRESSIVE
    w_d = x[1 + S_LOAD_SPEED] if two_mass else omega   # drive side of the magnetic gear, motor-referred
    a_d = x[1 + S_LOAD_ANGLE] if two_mass else theta
    i_mg, i_bg1, i_bg2, i_tp2 = c[K_IMG], c[K_IBG1], c[K_IBG2], c[K_ITP2]
    w_tp1 = w_d / (i_mg * i_bg1)
    w_mg2 = w_d / (i_mg * i_bg2)
    w_tp2 = w_mg2 / i_tp2
    w_u1, m_er1, m_tser1, m_uer1, y1 = _station(0, vid, w_tp1, a_d / (i_mg * i_bg1), x, u, th, c, vv, 1)
    w_u2, m_er2, m_tser2, m_uer2, y2 = _station(1, vid, w_tp2, a_d / (i_mg * i_bg2 * i_tp2), x, u, th, c, vv, 1)
    brake = u[3]
    excess = _breakaway_excess(vid, x, 1, vv)
    m_mg2 = (m_uer2 / i_tp2 + th[T_BTP2] * w_tp2 + _coulomb(excess * th[T_CTP2], w_tp2, eps, vid, vv)
             + _brake(brake, w_tp2, c))
    m_tper = (m_uer1 / i_bg1 + m_mg2 / i_bg2 + th[T_BTP1] * w_tp1
              + _coulomb(excess * th[T_CTP1], w_tp1, eps, vid, vv) + _brake(brake, w_tp1, c))
    m_iser = m_tper + c[K_DIS] * a_d / i_mg
    w_mg = omega / i_mg   # the magnetic gear turns with the motor (a compliance sits behind it)
    mg_loss = th[T_BMG] * w_mg + _coulomb(excess * th[T_CMG], w_mg, eps, vid, vv)
    m_mger = m_iser / i_mg + mg_loss
    omega_read = _speed_reading(vid, omega, theta, vv)
    position_error = _position_error(vid, c[K_KY] * u[0] - 0.5 * (y1 + y2), vv)
    speed_error = _speed_command(vid, th[T_PACE] * position_error, u, vv) - omega_read
    command = th[T_PPCE] / th[T_KN] * _speed_loop_input(vid, speed_error, x[1 + S_SPEED_INTEGRAL], vv)
    u_a = min(max(command, -c[K_UMAX]), c[K_UMAX])
    if vid == V_SPEED_INTEGRAL:
        dx[1 + S_SPEED_INTEGRAL] = _integrand(speed_error, command, u_a)
    dx[0] = (-th[T_RA] * i_a - th[T_KS] * omega + u_a) / th[T_LA]
    m_motor = th[T_KN] * i_a
    if vid == V_TORQUE_SATURATION:
        m_motor = m_motor * _saturation(i_a, vv)
    if vid == V_TORQUE_LAG:
        dx[1 + S_LAG] = (m_motor - x[1 + S_LAG]) / vv[0]
        m_motor = x[1 + S_LAG]
    elif vid == V_STRIBECK_DWELL:
        dx[1 + S_BREAKAWAY] = _breakaway_rate(vid, x, 1, w_tp1, vv)
    drive = m_motor + _ripple(vid, theta, m_motor, vv)
    if two_mass:
        _two_mass(drive - mg_loss, m_iser / i_mg, omega, theta, w_d, a_d, th[T_J], vv, dx, 1)
    else:
        dx[1 + S_OMEGA] = (drive - m_mger) / th[T_J]
    dx[1 + S_Y1] = c[K_LEAD] * w_u1
    dx[1 + S_Y2] = c[K_LEAD] * w_u2
    dx[1 + S_THETA] = omega
    if outputs:   # the drive's speed reading is the recorded motor speed
        values = (omega_read, y1, y2, i_a, u_a, w_mg, w_tp1, w_mg2, w_tp2, w_u1, w_u2, m_er1, m_er2,
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
    """Fixed-step RK4 from rest over held inputs (n_samples, 5: phi_r, F_ER1, F_ER2, brake and
    phi_r's rate); outputs (n_samples, n_outputs) at t_k from x(t_k) and u_k. The output plays
    (constant or worn) are projected after every step; the friction warm-up's loss factor is held
    over each sample interval, as the inputs are."""
    o = concept_id  # LT/HS carries I_A ahead of the common states
    x = np.zeros(N_STATE)
    xt = np.empty(N_STATE)
    k1, k2, k3, k4 = np.empty(N_STATE), np.empty(N_STATE), np.empty(N_STATE), np.empty(N_STATE)
    scratch = np.empty(out.shape[1])
    n = inputs.shape[0]
    if vid == V_BACKLASH_WORN:   # each carriage starts on the flank its load presses it against
        for j in range(2):
            x[o + S_CARRIAGE1 + j] = math.copysign(_worn_half_play(0.0, vv), inputs[0, 1 + j])
    elif vid == V_STRIBECK_DWELL:   # the drive stood long before the record: its breakaway is full
        x[o + S_BREAKAWAY] = 1.0
    cold = th
    th = cold.copy()
    for k in range(n):
        u = inputs[k]
        if vid == V_WARM_UP:
            factor = 1.0 - vv[0] * (1.0 - math.exp(-k * n_sub * h / vv[1]))
            for i in LOSS_COEFFICIENTS:
                th[i] = cold[i] * factor
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
            elif vid == V_BACKLASH_WORN:
                for j in range(2):
                    nut = x[o + S_Y1 + j]
                    half = _worn_half_play(nut, vv)
                    x[o + S_CARRIAGE1 + j] = min(max(x[o + S_CARRIAGE1 + j], nut - half), nut + half)
