"""HT/LS concept (high torque / low speed, symmetric): MODEL_SPEC.md, eqs. 1-15, 32-38.

One motor drives two stations, each bevel gear -> U-joint -> ball screw. The motor torque is
commanded by cascaded P control; ``k_n`` only converts it to the measured current.
The integer layouts below are the kernel's contract and must match the ParameterSets.
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

# --- estimated parameters Θ (eq. 44), kernel positions ----------------------------------
(P_J, P_B_TS1, P_C_TS1, P_B_U1, P_C_U1, P_B_TP1, P_C_TP1,
 P_B_TS2, P_C_TS2, P_B_U2, P_C_U2, P_B_TP2, P_C_TP2, P_K_N, P_P_ACE, P_P_PCE) = range(16)

# --- design constants and settings, kernel positions ------------------------------------
(C_I_TP1, C_I_TP2, C_R, C_GAMMA, C_BETA1, C_BETA2, C_M_MIN, C_M_MAX, C_K_Y,
 C_M_BMAX, C_K_B, C_OMEGA_HALF, C_OMEGA_EPS) = range(13)

# --- outputs (eq. 42 without the two gains) ---------------------------------------------
# --- derived constants appended by ``derived_constants`` (kernel positions) --------------
(D_R_SCG, D_LEAD, D_INV_COS_B1, D_INV_COS_B2) = range(13, 13 + 4)

OUTPUTS = ("Omega", "y1", "y2", "I_A", "Omega_TP1", "Omega_TP2", "Omega_U1", "Omega_U2",
           "M_ER1", "M_ER2", "M_TSER1", "M_TSER2", "M_UER1", "M_UER2", "M_TPER1", "M_TPER2")
OUTPUT_UNITS = ("rad/s", "m", "m", "A") + ("rad/s",) * 4 + ("N m",) * 8
# theta (motor angle) is an auxiliary state: it feeds nothing in the nominal model and is
# there for the angle-dependent unmodelled effects (U-joint kinematics, torque ripple).
STATES = ("Omega", "y1", "y2", "theta")
(X_OMEGA, X_Y1, X_Y2, X_THETA) = range(4)

PARAMETERS = ParameterSet(
    (Parameter("J", "kg m^2", 0.05, 1e-6, np.inf, description="inertia of rotating parts reduced to the motor shaft"),)
    + loss_parameters({
        "B_TS1": 0.40, "C_TS1": 1.20, "B_U1": 0.10, "C_U1": 0.30, "B_TP1": 0.20, "C_TP1": 0.60,
        "B_TS2": 0.44, "C_TS2": 1.35, "B_U2": 0.09, "C_U2": 0.33, "B_TP2": 0.22, "C_TP2": 0.55,
    })
    + (
        Parameter("k_n", "N m/A", 1.2, 1e-4, np.inf, description="motor torque constant"),
        rig_gain("p_ACE", 2000.0, "(rad/s)/m", "position-loop gain of the ACE module"),
        rig_gain("p_PCE", 10.0, "N m/(rad/s)", "speed-loop gain of the PCE module"),
    )
)


CONSTANTS = ParameterSet((
    const("i_TP1", "1", 2.0, "bevel-gear ratio, station 1"),
    const("i_TP2", "1", 2.0, "bevel-gear ratio, station 2"),
    const("r", "m", 0.016, "screw rolling radius"),
    const("gamma", "rad", 4.0 * DEG, "screw lead angle"),
    const("beta1", "rad", 3.0 * DEG, "U-joint angle, station 1"),
    const("beta2", "rad", 5.0 * DEG, "U-joint angle, station 2"),
    const("M_min", "N m", -80.0, "motor torque lower limit"),
    const("M_max", "N m", 80.0, "motor torque upper limit"),
    const("k_y", "m/rad", 0.3 / (40.0 * DEG), "flap command to carriage position"),
) + BRAKE_AND_SETTINGS)

def derived_constants(c: np.ndarray) -> np.ndarray:
    """Constants computed once per simulation from the design constants (kernel layout D_*)."""
    return np.array(screw_constants(c[C_R], c[C_GAMMA], c[C_BETA1], c[C_BETA2]))


def loss_factors(c) -> dict[str, float]:
    """``Model.loss_referral``: each station loss referred to the motor shaft through its bevel
    gear (1/i) and, for the screw, the U-joint (1/cos β); viscous terms once more by the speed."""
    f = {}
    for k in (1, 2):
        i, cb = c[f"i_TP{k}"], math.cos(c[f"beta{k}"])
        f.update({f"B_TS{k}": 1 / (cb * i * i), f"B_U{k}": 1 / (i * i), f"B_TP{k}": 1 / i,
                  f"C_TS{k}": 1 / (cb * i), f"C_U{k}": 1 / i, f"C_TP{k}": 1.0})
    return f


MODEL = Model(
    name="htls", model_id=KERNEL_IDS["htls"][0], title="HT/LS (high torque / low speed)",
    states=STATES, outputs=OUTPUTS, output_units=OUTPUT_UNITS,
    parameters=PARAMETERS, constants=CONSTANTS, derive=derived_constants, integration_step=5e-4, converged_step=1e-3,
    integrator="rk4", rtol=5e-8, state_scales=(30.0, 0.3, 0.3, 500.0),  # Omega, y1, y2, theta
    sensor_sets={"full": OUTPUTS, "realistic": ("Omega", "y1", "y2", "I_A")}, loss_referral=loss_factors,
    effect_catalogue=CATALOGUE, augment=augment_ema,  # effects: the hooks of effect_kernels in evaluate
)


#: position of the effects' layout table in the kernel constants of an augmented model
FX_TABLE = D_INV_COS_B2 + 1


@njit(cache=True, inline="always", error_model="numpy")
def evaluate(x, u, th, c, dx, y, outputs=True, flags=None):
    """State derivative ``dx`` and all outputs ``y``; ``c`` is ``MODEL.kernel_constants(...)``;
    x = [Omega, y1, y2, theta] followed by the extra states of the effects in ``flags``
    (``effect_kernels.effect_flags``; None: the nominal model of MODEL_SPEC.md, its effect
    branches pruned at compile time), which enter through the hooks of ``effect_kernels``."""
    t = FX_TABLE
    eps = c[C_OMEGA_EPS]
    i_tp1 = c[C_I_TP1]
    i_tp2 = c[C_I_TP2]
    omega = x[X_OMEGA]
    theta = x[X_THETA]
    # motor side and shaft end (rigid: both the state Omega)
    omega_m, omega_s, theta_m, coupling = ek.coupling(flags, x, th, c, t, omega, theta, i_tp1, 1.0)
    # bevel-gear plays (one per station)
    omega_l1, e1 = ek.gear_play(flags, x, th, c, t, 0, i_tp1, 1.0, omega_s, dx)
    omega_l2, e2 = ek.gear_play(flags, x, th, c, t, 1, i_tp2, 1.0, omega_s, dx)

    omega_tp1 = omega_l1 / i_tp1  # eq. 4
    omega_tp2 = omega_l2 / i_tp2
    brake = u[3]
    m_b21 = brake_torque(brake, omega_tp1, c[C_M_BMAX], c[C_K_B], c[C_OMEGA_HALF], eps)
    m_b22 = brake_torque(brake, omega_tp2, c[C_M_BMAX], c[C_K_B], c[C_OMEGA_HALF], eps)
    m_b1 = brake_torque(brake, omega_m, c[C_M_BMAX], c[C_K_B], c[C_OMEGA_HALF], eps)
    contact = ek.nut_contact(flags, x, th, c, t, u[1], u[2])  # the load forces at the screws
    # the stations' shafts turn alike at equal ratios: tanh is the costliest operation of a step
    terms = ek.station_terms(flags, th, c, t, omega_tp1, omega_tp2, theta / i_tp1, theta / i_tp2, eps)
    sign_tp1, sign_tp2, _, _, f_tp1, f_tp2 = terms
    # ball screws and U-joints (eqs. 10-15): their loads on the bevel gears, the carriages' speeds
    m_uer1, m_uer2, carriage1, carriage2, stations = ek.stations(
        flags, x, th, c, t, omega_tp1, omega_tp2, terms, contact, P_B_TS1, P_B_TS2, c[D_R_SCG], c[D_INV_COS_B1],
        c[D_INV_COS_B2], c[C_R], x[X_Y1], x[X_Y2], dx)
    m_tper1 = ek.transmit(flags, e1, m_uer1 / i_tp1 + th[P_B_TP1] * omega_tp1
                          + ek.coulomb(flags, th[P_C_TP1], f_tp1) * sign_tp1 + m_b21)
    m_tper2 = ek.transmit(flags, e2, m_uer2 / i_tp2 + th[P_B_TP2] * omega_tp2
                          + ek.coulomb(flags, th[P_C_TP2], f_tp2) * sign_tp2 + m_b22)

    # cascaded P control (eqs. 32-35, 38) on the motor speed and the carriage positions
    y_r = c[C_K_Y] * u[0]
    y_s = 0.5 * (x[X_Y1] + x[X_Y2])
    omega_r = th[P_P_ACE] * (y_r - y_s)
    m_n = min(max(th[P_P_PCE] * (omega_r - omega_m), c[C_M_MIN]), c[C_M_MAX])

    lead = c[D_LEAD]
    net = ek.motor_torque(flags, th, c, t, theta_m, th[P_K_N], m_n) - (m_b1 + m_tper1 + m_tper2)
    dx[X_OMEGA] = net / th[P_J]
    dx[X_Y1] = lead * carriage1
    dx[X_Y2] = lead * carriage2
    dx[X_THETA] = omega
    ek.coupling_rates(flags, th[P_J], coupling, net, m_tper1 + m_tper2, dx)

    if outputs:  # the RK stages between samples need only dx
        y[0] = omega_m
        y[1] = x[X_Y1]
        y[2] = x[X_Y2]
        y[3] = m_n / th[P_K_N]
        y[4] = omega_tp1
        y[5] = omega_tp2
        ek.station_outputs(y, 6, stations)  # y[6:14]: Omega_U1 ... M_UER2
        y[14] = m_tper1
        y[15] = m_tper2


# --- the linear regime (integrator "hybrid", simulate.py) ---------------------------------
# With the brake released, every smoothed sign saturated (|speed / omega_eps| beyond the
# point where tanh is exactly ±1) and the torque limit inactive, eqs. 1-15 and 32-38 are
# affine in the state: dx/dt = A x + b(u, sign), with A below. Over a held sample interval
# that stays in this regime, x(t) = x_k + Γ(t) f(x_k) exactly, Γ(t) = ∫_0^t e^{As} ds.

@njit(cache=True, inline="always", error_model="numpy")
def linear_state_matrix(th, c, a):
    """Write into ``a`` (4, 4) the state matrix ∂f/∂x, constant in the linear regime."""
    a[:, :] = 0.0
    i1 = c[C_I_TP1]
    i2 = c[C_I_TP2]
    # d M_TPERk / d Omega through the screw, the U-joint (1/cos beta) and the bevel gear (1/i)
    loss1 = ((th[P_B_TS1] * c[D_INV_COS_B1] + th[P_B_U1]) / i1 + th[P_B_TP1]) / i1
    loss2 = ((th[P_B_TS2] * c[D_INV_COS_B2] + th[P_B_U2]) / i2 + th[P_B_TP2]) / i2
    j = th[P_J]
    a[X_OMEGA, X_OMEGA] = -(th[P_P_PCE] + loss1 + loss2) / j
    a[X_OMEGA, X_Y1] = -0.5 * th[P_P_PCE] * th[P_P_ACE] / j
    a[X_OMEGA, X_Y2] = a[X_OMEGA, X_Y1]
    a[X_Y1, X_OMEGA] = c[D_LEAD] / i1
    a[X_Y2, X_OMEGA] = c[D_LEAD] / i2
    a[X_THETA, X_OMEGA] = 1.0


@njit(cache=True, inline="always", error_model="numpy")
def linear_regime(x, dx, u, th, c, delta):
    """True when the state ``x`` (derivative ``dx``) under the held input ``u`` lies in the
    linear regime and, by the tangents of speed and torque, stays there for ``delta`` seconds."""
    slowest = max(c[C_I_TP1], c[C_I_TP2])  # the bevel-gear shafts turn slowest: their signs saturate last
    return in_linear_regime(u[3], x[X_OMEGA], dx[X_OMEGA], c[C_OMEGA_EPS], slowest, th[P_P_PCE], th[P_P_ACE],
                            c[C_K_Y] * u[0], x[X_Y1], x[X_Y2], dx[X_Y1], dx[X_Y2], c[C_M_MIN], c[C_M_MAX], delta)
