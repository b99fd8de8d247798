"""LT/HS concept (low torque / high speed, asymmetric): MODEL_SPEC.md, eqs. 16-31, 39-41.

A fast voltage-controlled DC motor drives, through a magnetic gearbox and the input shaft,
the first bevel gear; station 1 hangs on it directly, station 2 through a second bevel gear.
"""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..params import Parameter, ParameterSet
from .base import KERNEL_IDS, Model
from .effects import CATALOGUE, augment_ema
from . import effect_kernels as ek
from .components import (BRAKE_AND_SETTINGS, DEG, brake_torque, const, in_linear_regime, loss_parameters,
                         rig_gain, screw_constants)

# --- estimated parameters Θ (eq. 47), kernel positions ----------------------------------
(P_J, P_B_TS1, P_C_TS1, P_B_U1, P_C_U1, P_B_TP1, P_C_TP1,
 P_B_TS2, P_C_TS2, P_B_U2, P_C_U2, P_B_TP2, P_C_TP2,
 P_B_MG, P_C_MG, P_K_N, P_R_A, P_L_A, P_K_S, P_P_ACE, P_P_PCE) = range(21)

# --- design constants and settings, kernel positions ------------------------------------
(C_I_MG, C_I_BG1, C_I_BG2, C_I_TP2, C_R, C_GAMMA, C_BETA1, C_BETA2, C_K_Y, C_U_MAX, C_D_IS,
 C_M_BMAX, C_K_B, C_OMEGA_HALF, C_OMEGA_EPS) = range(15)

# --- derived constants appended by ``derived_constants`` (kernel positions) --------------
(D_R_SCG, D_LEAD, D_INV_COS_B1, D_INV_COS_B2) = range(15, 15 + 4)

OUTPUTS = ("Omega", "y1", "y2", "I_A", "U_A", "Omega_MG", "Omega_TP1", "Omega_MG2", "Omega_TP2",
           "Omega_U1", "Omega_U2", "M_ER1", "M_ER2", "M_TSER1", "M_TSER2", "M_UER1", "M_UER2",
           "M_MG2", "M_TPER", "M_MGER")
OUTPUT_UNITS = ("rad/s", "m", "m", "A", "V") + ("rad/s",) * 6 + ("N m",) * 9
# theta (motor angle) is auxiliary: it drives D_IS (zero nominal) and the angle-dependent effects.
STATES = ("I_A", "Omega", "y1", "y2", "theta")
(X_I_A, X_OMEGA, X_Y1, X_Y2, X_THETA) = range(5)

PARAMETERS = ParameterSet(
    (Parameter("J", "kg m^2", 4e-4, 1e-8, np.inf, description="inertia of rotating parts reduced to the motor shaft"),)
    + loss_parameters({
        "B_TS1": 0.40, "C_TS1": 1.20, "B_U1": 0.10, "C_U1": 0.30, "B_TP1": 0.05, "C_TP1": 0.30,
        "B_TS2": 0.44, "C_TS2": 1.35, "B_U2": 0.09, "C_U2": 0.33, "B_TP2": 0.11, "C_TP2": 0.28,
    })
    + (
        Parameter("B_MG", "N m s/rad", 0.01, 0.0, np.inf, description="viscous loss of the magnetic gearbox"),
        Parameter("C_MG", "N m", 0.40, 0.0, np.inf, description="Coulomb loss of the magnetic gearbox"),
        Parameter("k_n", "N m/A", 0.08, 1e-5, np.inf, description="motor torque constant"),
        Parameter("R_A", "ohm", 0.3, 1e-5, np.inf, description="armature resistance"),
        Parameter("L_A", "H", 1e-3, 1e-7, np.inf, description="armature inductance"),
        Parameter("k_s", "V s/rad", 0.08, 1e-5, np.inf, description="back-EMF constant"),
        rig_gain("p_ACE", 35000.0, "(rad/s)/m", "position-loop gain of the ACE module"),
        rig_gain("p_PCE", 0.08, "N m/(rad/s)", "speed-loop gain of the PCE module"),
    )
)

CONSTANTS = ParameterSet((
    const("i_MG", "1", 20.0, "magnetic gearbox ratio"),
    const("i_BG1", "1", 2.0, "first bevel gear ratio to station 1"),
    const("i_BG2", "1", 1.0, "first bevel gear ratio to the station-2 shaft"),
    const("i_TP2", "1", 2.0, "second bevel gear ratio (station 2)"),
    const("r", "m", 0.016, "screw rolling radius"),
    const("gamma", "rad", 4.0 * DEG, "screw lead angle"),
    const("beta1", "rad", 3.0 * DEG, "U-joint angle, station 1"),
    const("beta2", "rad", 5.0 * DEG, "U-joint angle, station 2"),
    const("k_y", "m/rad", 0.3 / (40.0 * DEG), "flap command to carriage position"),
    const("U_max", "V", 135.0, "armature voltage limit"),
    const("D_IS", "N m/rad", 0.0, "input-shaft stiffness (eq. 22; zero nominal)"),
) + BRAKE_AND_SETTINGS)

def derived_constants(c: np.ndarray) -> np.ndarray:
    """Constants computed once per simulation from the design constants (kernel layout D_*)."""
    return np.array(screw_constants(c[C_R], c[C_GAMMA], c[C_BETA1], c[C_BETA2]))


def loss_factors(c) -> dict[str, float]:
    """``Model.loss_referral``: each loss referred to the motor shaft through the gears between
    them (magnetic gear, bevel gears) and, for a screw, its U-joint (1/cos β)."""
    i_mg, i_bg1, i_bg2, i_tp2 = c["i_MG"], c["i_BG1"], c["i_BG2"], c["i_TP2"]
    g1, g2 = i_mg * i_bg1, i_mg * i_bg2 * i_tp2          # motor to screw 1, screw 2
    cb1, cb2 = math.cos(c["beta1"]), math.cos(c["beta2"])
    return {"B_TS1": 1 / (cb1 * g1 * g1), "B_U1": 1 / (g1 * g1), "B_TP1": 1 / (i_mg * g1),
            "B_TS2": 1 / (cb2 * g2 * g2), "B_U2": 1 / (g2 * g2), "B_TP2": 1 / (i_mg * i_bg2 * g2),
            "B_MG": 1 / i_mg,
            "C_TS1": 1 / (cb1 * g1), "C_U1": 1 / g1, "C_TP1": 1 / i_mg,
            "C_TS2": 1 / (cb2 * g2), "C_U2": 1 / g2, "C_TP2": 1 / (i_mg * i_bg2), "C_MG": 1.0}


MODEL = Model(
    name="lths", model_id=KERNEL_IDS["lths"][0], title="LT/HS (low torque / high speed)",
    states=STATES, outputs=OUTPUTS, output_units=OUTPUT_UNITS,
    parameters=PARAMETERS, constants=CONSTANTS, derive=derived_constants, integration_step=2e-4, converged_step=5e-4,
    integrator="rk4", rtol=2e-8, state_scales=(30.0, 900.0, 0.3, 0.3, 1000.0),  # I_A, Omega, y1, y2, theta
    sensor_sets={"full": OUTPUTS, "realistic": ("Omega", "y1", "y2", "I_A", "U_A")}, loss_referral=loss_factors,
    effect_catalogue=CATALOGUE, augment=augment_ema,  # effects: the hooks of effect_kernels in evaluate
)


#: position of the effects' layout table in the kernel constants of an augmented model
FX_TABLE = D_INV_COS_B2 + 1


@njit(cache=True, inline="always", error_model="numpy")
def evaluate(x, u, th, c, dx, y, outputs=True, flags=None):
    """State derivative ``dx`` and all outputs ``y``; ``c`` is ``MODEL.kernel_constants(...)``;
    x = [I_A, Omega, y1, y2, theta] followed by the extra states of the effects in ``flags``
    (``effect_kernels.effect_flags``; None: the nominal model of MODEL_SPEC.md, its effect
    branches pruned at compile time), which enter through the hooks of ``effect_kernels``."""
    t = FX_TABLE
    eps = c[C_OMEGA_EPS]
    i_mg = c[C_I_MG]
    i_bg1 = c[C_I_BG1]
    i_bg2 = c[C_I_BG2]
    i_tp2 = c[C_I_TP2]
    i_a = x[X_I_A]
    omega = x[X_OMEGA]
    theta = x[X_THETA]
    # motor (+ magnetic gear) side and the first bevel gear's end of the input shaft
    omega_m, omega_s, theta_m, coupling = ek.coupling(flags, x, th, c, t, omega, theta, i_mg, i_bg1)
    # play in the first bevel gear, ahead of both stations (motor-scale radians)
    omega_l, e = ek.gear_play(flags, x, th, c, t, 0, i_mg, i_bg1, omega_s, dx)

    omega_mg = omega_m / i_mg  # eqs. 23, 24, 30
    omega_bg = omega_l / i_mg
    omega_tp1 = omega_bg / i_bg1
    omega_mg2 = omega_bg / i_bg2
    omega_tp2 = omega_mg2 / i_tp2
    theta_bg = theta / i_mg
    brake = u[3]
    m_b22 = brake_torque(brake, omega_tp2, c[C_M_BMAX], c[C_K_B], c[C_OMEGA_HALF], eps)
    m_b2 = brake_torque(brake, omega_tp1, c[C_M_BMAX], c[C_K_B], c[C_OMEGA_HALF], eps)
    contact = ek.nut_contact(flags, x, th, c, t, u[1], u[2])  # the load forces at the screws
    # the stations' shafts turn alike at equal ratios: tanh is the costliest operation of a step
    terms = ek.station_terms(flags, th, c, t, omega_tp1, omega_tp2, theta_bg / i_bg1, theta_bg / i_bg2 / i_tp2, eps)
    sign_tp1, sign_tp2, _, _, f_tp1, f_tp2 = terms
    # ball screws and U-joints (eqs. 27-29, as in HT/LS): their loads on the bevel gears, the carriages' speeds
    m_uer1, m_uer2, carriage1, carriage2, stations = ek.stations(
        flags, x, th, c, t, omega_tp1, omega_tp2, terms, contact, P_B_TS1, P_B_TS2, c[D_R_SCG], c[D_INV_COS_B1],
        c[D_INV_COS_B2], c[C_R], x[X_Y1], x[X_Y2], dx)
    m_mg2 = m_uer2 / i_tp2 + th[P_B_TP2] * omega_tp2 + ek.coulomb(flags, th[P_C_TP2], f_tp2) * sign_tp2 + m_b22
    m_tper = ek.transmit(flags, e, m_uer1 / i_bg1 + m_mg2 / i_bg2 + th[P_B_TP1] * omega_tp1
                         + ek.coulomb(flags, th[P_C_TP1], f_tp1) * sign_tp1 + m_b2)
    m_iser = m_tper + c[C_D_IS] * theta_m / i_mg  # eq. 22
    c_mg = ek.stribeck_coulomb(flags, th, c, t, th[P_C_MG], omega_mg / i_bg1)
    m_mger = m_iser / i_mg + th[P_B_MG] * omega_mg + c_mg * ek.smooth_sign(omega_mg, eps)

    # cascaded P control (eq. 41), voltage-limited, on the motor speed
    y_r = c[C_K_Y] * u[0]
    y_s = 0.5 * (x[X_Y1] + x[X_Y2])
    u_a = th[P_P_PCE] / th[P_K_N] * (th[P_P_ACE] * (y_r - y_s) - omega_m)
    u_a = min(max(u_a, -c[C_U_MAX]), c[C_U_MAX])

    lead = c[D_LEAD]
    net = ek.motor_torque(flags, th, c, t, theta_m, th[P_K_N], th[P_K_N] * i_a) - m_mger
    dx[X_I_A] = (-th[P_R_A] * i_a - th[P_K_S] * omega_m + u_a) / th[P_L_A]
    dx[X_OMEGA] = net / th[P_J]
    dx[X_Y1] = lead * carriage1
    dx[X_Y2] = lead * carriage2
    dx[X_THETA] = omega
    ek.coupling_rates(flags, th[P_J], coupling, net, m_iser / i_mg, dx)

    if outputs:  # the RK stages between samples need only dx
        y[0] = omega_m
        y[1] = x[X_Y1]
        y[2] = x[X_Y2]
        y[3] = i_a
        y[4] = u_a
        y[5] = omega_mg
        y[6] = omega_tp1
        y[7] = omega_mg2
        y[8] = omega_tp2
        ek.station_outputs(y, 9, stations)  # y[9:17]: Omega_U1 ... M_UER2
        y[17] = m_mg2
        y[18] = m_tper
        y[19] = m_mger


# --- the linear regime (integrator "hybrid", simulate.py) ---------------------------------
# As for HT/LS: brake released, every smoothed sign saturated, the voltage limit inactive,
# and eqs. 16-31, 39-41 are affine in the state (the input-shaft spring D_IS included).

@njit(cache=True, inline="always", error_model="numpy")
def linear_state_matrix(th, c, a):
    """Write into ``a`` (5, 5) the state matrix ∂f/∂x, constant in the linear regime."""
    a[:, :] = 0.0
    i_mg = c[C_I_MG]
    r_tp1 = 1.0 / (i_mg * c[C_I_BG1])                   # d Omega_TP1 / d Omega
    r_tp2 = 1.0 / (i_mg * c[C_I_BG2] * c[C_I_TP2])      # d Omega_TP2 / d Omega
    uer1 = th[P_B_TS1] * c[D_INV_COS_B1] + th[P_B_U1]   # d M_UERk / d Omega_Uk
    uer2 = th[P_B_TS2] * c[D_INV_COS_B2] + th[P_B_U2]
    mg2 = (uer2 / c[C_I_TP2] + th[P_B_TP2]) * r_tp2      # d M_MG2 / d Omega
    tper = uer1 * r_tp1 / c[C_I_BG1] + mg2 / c[C_I_BG2] + th[P_B_TP1] * r_tp1
    mger = tper / i_mg + th[P_B_MG] / i_mg               # d M_MGER / d Omega
    gain = th[P_P_PCE] / th[P_K_N]                       # voltage per speed error
    l_a = th[P_L_A]
    j = th[P_J]
    a[X_I_A, X_I_A] = -th[P_R_A] / l_a
    a[X_I_A, X_OMEGA] = -(th[P_K_S] + gain) / l_a
    a[X_I_A, X_Y1] = -0.5 * gain * th[P_P_ACE] / l_a
    a[X_I_A, X_Y2] = a[X_I_A, X_Y1]
    a[X_OMEGA, X_I_A] = th[P_K_N] / j
    a[X_OMEGA, X_OMEGA] = -mger / j
    a[X_OMEGA, X_THETA] = -c[C_D_IS] / (i_mg * i_mg * j)
    a[X_Y1, X_OMEGA] = c[D_LEAD] * r_tp1
    a[X_Y2, X_OMEGA] = c[D_LEAD] * r_tp2
    a[X_THETA, X_OMEGA] = 1.0


@njit(cache=True, inline="always", error_model="numpy")
def linear_regime(x, dx, u, th, c, delta):
    """True when the state ``x`` (derivative ``dx``) under the held input ``u`` lies in the
    linear regime and, by the tangents of speed and voltage, stays there for ``delta`` seconds."""
    i_mg = c[C_I_MG]
    slowest = max(i_mg, i_mg * c[C_I_BG1], i_mg * c[C_I_BG2] * c[C_I_TP2])  # Omega / slowest signed shaft
    return in_linear_regime(u[3], x[X_OMEGA], dx[X_OMEGA], c[C_OMEGA_EPS], slowest, th[P_P_PCE] / th[P_K_N],
                            th[P_P_ACE], c[C_K_Y] * u[0], x[X_Y1], x[X_Y2], dx[X_Y1], dx[X_Y2], -c[C_U_MAX],
                            c[C_U_MAX], delta)
