"""Independent plain-Python reference of the two EMA concepts of docs/MODEL_SPEC.md.

Written from the specification only (not from ``ema_uq.models``) so that it can check the
compiled simulator. States carry the motor angle theta as last entry, as the package does:
``[Omega, y1, y2, theta]`` (htls) and ``[I_A, Omega, y1, y2, theta]`` (lths).

Brakes (eq. 3): each brake torque is ``b * M_B(|v|) * sgn_eps(v)`` with ``b`` the brake
input in [0, 1] and ``v`` the speed of the shaft the brake torque is added on:
HT/LS ``M_B1`` on the motor (Omega), ``M_B2k`` in ``M_TPERk`` (Omega_TPk); LT/HS ``M_B2``
in ``M_TPER`` (Omega_TP1), ``M_B22`` in ``M_MG2`` (Omega_TP2). The LT/HS mechanical
equation (eq. 18/39) has no primary motor brake.

Integration: ``solve_ivp`` sample interval by sample interval with the inputs held
(zero-order hold); the output at t_k is computed from x(t_k) and u_k.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.integrate import solve_ivp

HTLS_OUTPUTS = (
    "Omega", "y1", "y2", "I_A", "Omega_TP1", "Omega_TP2", "Omega_U1", "Omega_U2",
    "M_ER1", "M_ER2", "M_TSER1", "M_TSER2", "M_UER1", "M_UER2", "M_TPER1", "M_TPER2",
)
LTHS_OUTPUTS = (
    "Omega", "y1", "y2", "I_A", "U_A", "Omega_MG", "Omega_TP1", "Omega_MG2", "Omega_TP2",
    "Omega_U1", "Omega_U2", "M_ER1", "M_ER2", "M_TSER1", "M_TSER2", "M_UER1", "M_UER2",
    "M_MG2", "M_TPER", "M_MGER",
)
N_STATES = {"htls": 4, "lths": 5}
OUTPUTS = {"htls": HTLS_OUTPUTS, "lths": LTHS_OUTPUTS}

#: Settings of the performance peer: adaptive RK45 (Dormand-Prince 5(4)) at scipy's default
#: rtol, an absolute tolerance that is meaningful for carriage positions of ~0.1 m.
PEER_SETTINGS = {"method": "RK45", "rtol": 1e-6, "atol": 1e-9}


def sgn(v: float, eps: float) -> float:
    """Smoothed sign tanh(v / eps)."""
    return math.tanh(v / eps)


def clip(v: float, lo: float, hi: float) -> float:
    return lo if v < lo else hi if v > hi else v


def brake_torque(v: float, b: float, c: dict) -> float:
    """Brake torque [N m] at shaft speed v [rad/s] for brake input b in [0, 1] (eq. 3)."""
    if b == 0.0:
        return 0.0
    m_bmax = c["M_Bmax"]
    magnitude = m_bmax - 0.5 * m_bmax * (1.0 - math.exp(-c["K_b"] * abs(v) / c["Omega_half"]))
    return b * magnitude * sgn(v, c["omega_eps"])


def station(omega_u: float, f_er: float, b_ts: float, c_ts: float, b_u: float, c_u: float,
            beta: float, c: dict) -> tuple[float, float, float]:
    """Ball-screw and U-joint of one station: (M_ER, M_TSER, M_UER) [N m] (eqs. 10-15)."""
    eps, r, gamma = c["omega_eps"], c["r"], c["gamma"]
    m_er = -r * f_er * math.sin(gamma) * math.cos(gamma)
    m_tser = b_ts * omega_u + c_ts * sgn(omega_u, eps) + m_er
    m_uer = m_tser / math.cos(beta) + b_u * omega_u + c_u * sgn(omega_u, eps)
    return m_er, m_tser, m_uer


def htls_rhs(x, u, th: dict, c: dict) -> tuple[list, list]:
    """HT/LS: state x [Omega, y1, y2, theta], inputs u [phi_r, F_ER1, F_ER2, brake]
    -> (dx/dt (4,), outputs (16,) in HTLS_OUTPUTS order)."""
    omega, y1, y2 = x[0], x[1], x[2]
    phi_r, f1, f2, b = u[0], u[1], u[2], u[3]
    eps = c["omega_eps"]
    w_tp1 = omega / c["i_TP1"]
    w_tp2 = omega / c["i_TP2"]
    w_u1, w_u2 = w_tp1, w_tp2  # g_U = 1
    m_er1, m_tser1, m_uer1 = station(w_u1, f1, th["B_TS1"], th["C_TS1"], th["B_U1"], th["C_U1"], c["beta1"], c)
    m_er2, m_tser2, m_uer2 = station(w_u2, f2, th["B_TS2"], th["C_TS2"], th["B_U2"], th["C_U2"], c["beta2"], c)
    m_tper1 = (m_uer1 / c["i_TP1"] + th["B_TP1"] * w_tp1 + th["C_TP1"] * sgn(w_tp1, eps)
               + brake_torque(w_tp1, b, c))
    m_tper2 = (m_uer2 / c["i_TP2"] + th["B_TP2"] * w_tp2 + th["C_TP2"] * sgn(w_tp2, eps)
               + brake_torque(w_tp2, b, c))
    y_r = c["k_y"] * phi_r
    y_s = 0.5 * (y1 + y2)
    omega_r = th["p_ACE"] * (y_r - y_s)
    m_n = clip(th["p_PCE"] * (omega_r - omega), c["M_min"], c["M_max"])
    i_a = m_n / th["k_n"]
    lead = c["r"] * math.tan(c["gamma"])
    dx = [
        (m_n - (brake_torque(omega, b, c) + m_tper1 + m_tper2)) / th["J"],
        lead * w_u1,
        lead * w_u2,
        omega,
    ]
    y = [omega, y1, y2, i_a, w_tp1, w_tp2, w_u1, w_u2, m_er1, m_er2, m_tser1, m_tser2,
         m_uer1, m_uer2, m_tper1, m_tper2]
    return dx, y


def lths_rhs(x, u, th: dict, c: dict) -> tuple[list, list]:
    """LT/HS: state x [I_A, Omega, y1, y2, theta], inputs u [phi_r, F_ER1, F_ER2, brake]
    -> (dx/dt (5,), outputs (20,) in LTHS_OUTPUTS order)."""
    i_a, omega, y1, y2, theta = x[0], x[1], x[2], x[3], x[4]
    phi_r, f1, f2, b = u[0], u[1], u[2], u[3]
    eps = c["omega_eps"]
    w_mg = omega / c["i_MG"]
    w_tp1 = w_mg / c["i_BG1"]
    w_mg2 = w_mg / c["i_BG2"]
    w_tp2 = w_mg2 / c["i_TP2"]
    w_u1, w_u2 = w_tp1, w_tp2  # g_U = 1
    m_er1, m_tser1, m_uer1 = station(w_u1, f1, th["B_TS1"], th["C_TS1"], th["B_U1"], th["C_U1"], c["beta1"], c)
    m_er2, m_tser2, m_uer2 = station(w_u2, f2, th["B_TS2"], th["C_TS2"], th["B_U2"], th["C_U2"], c["beta2"], c)
    m_mg2 = (m_uer2 / c["i_TP2"] + th["B_TP2"] * w_tp2 + th["C_TP2"] * sgn(w_tp2, eps)
             + brake_torque(w_tp2, b, c))
    m_tper = (m_uer1 / c["i_BG1"] + m_mg2 / c["i_BG2"] + th["B_TP1"] * w_tp1
              + th["C_TP1"] * sgn(w_tp1, eps) + brake_torque(w_tp1, b, c))
    m_iser = m_tper + c["D_IS"] * theta / c["i_MG"]
    m_mger = m_iser / c["i_MG"] + th["B_MG"] * w_mg + th["C_MG"] * sgn(w_mg, eps)
    y_r = c["k_y"] * phi_r
    y_s = 0.5 * (y1 + y2)
    u_a = clip(th["p_PCE"] / th["k_n"] * (th["p_ACE"] * (y_r - y_s) - omega), -c["U_max"], c["U_max"])
    lead = c["r"] * math.tan(c["gamma"])
    dx = [
        (-th["R_A"] * i_a - th["k_s"] * omega + u_a) / th["L_A"],
        (th["k_n"] * i_a - m_mger) / th["J"],
        lead * w_u1,
        lead * w_u2,
        omega,
    ]
    y = [omega, y1, y2, i_a, u_a, w_mg, w_tp1, w_mg2, w_tp2, w_u1, w_u2, m_er1, m_er2,
         m_tser1, m_tser2, m_uer1, m_uer2, m_mg2, m_tper, m_mger]
    return dx, y


RHS = {"htls": htls_rhs, "lths": lths_rhs}


def reference_simulate(concept: str, theta: dict, constants: dict, time: np.ndarray,
                       inputs: np.ndarray, rtol: float = 1e-10, atol: float = 1e-12,
                       method: str = "DOP853", x0=None) -> np.ndarray:
    """Simulate one parameter set with ``solve_ivp``, one held sample interval at a time.

    Parameters
    ----------
    concept : "htls" or "lths".
    theta, constants : parameter and design-constant values by name (SI units).
    time : (n,) sample times [s].
    inputs : (n, 4) held inputs [phi_r rad, F_ER1 N, F_ER2 N, brake 1].
    rtol, atol, method : passed to ``solve_ivp`` for every interval.
    x0 : initial state (default zeros, at rest).

    Returns
    -------
    (n, n_outputs) outputs in ``OUTPUTS[concept]`` order (= the package's order).
    """
    rhs = RHS[concept]
    th, c = dict(theta), dict(constants)
    time = np.asarray(time, dtype=float)
    inputs = np.asarray(inputs, dtype=float)
    x = np.zeros(N_STATES[concept]) if x0 is None else np.array(x0, dtype=float)
    out = np.empty((time.size, len(OUTPUTS[concept])))

    def fun(t, xs, u):
        return rhs(xs, u, th, c)[0]

    first_step = None
    for k in range(time.size):
        u = tuple(float(v) for v in inputs[k])
        out[k] = rhs(x, u, th, c)[1]
        if k == time.size - 1:
            break
        span = (time[k], time[k + 1])
        # reuse the last accepted step so each interval does not restart its step search
        sol = solve_ivp(fun, span, x, method=method, rtol=rtol, atol=atol, args=(u,),
                        first_step=first_step)
        if not sol.success:
            raise RuntimeError(f"solve_ivp failed in [{span[0]:g}, {span[1]:g}] s: {sol.message}")
        x = sol.y[:, -1]
        last_full = sol.t[-2] - sol.t[-3] if sol.t.size > 2 else span[1] - span[0]
        first_step = min(float(last_full), span[1] - span[0])
    return out


def peer_simulate(concept: str, theta: dict, constants: dict, time: np.ndarray,
                  inputs: np.ndarray) -> np.ndarray:
    """The performance peer: a Python rhs under ``solve_ivp`` with ``PEER_SETTINGS``
    (RK45, rtol=1e-6, atol=1e-9), same interval-by-interval zero-order hold. Shapes as
    :func:`reference_simulate`."""
    return reference_simulate(concept, theta, constants, time, inputs, **PEER_SETTINGS)
