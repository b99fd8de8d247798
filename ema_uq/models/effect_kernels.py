"""Compiled right-hand sides of the HT/LS and LT/HS models with unmodelled effects.

``evaluate_htls_effects`` / ``evaluate_lths_effects`` have the signature of the nominal
``evaluate(x, u, th, c, dx, y)``. Which effects are active, where their parameters sit in
``th`` and their extra states in ``x``, and the effects' kernel constants are read from the
layout table that :func:`~ema_uq.models.effects.augment_ema` appends to the kernel constants
``c``, at the offsets ``effects.LAYOUT`` computes from the effect definitions (``FX_*`` below,
module constants that numba compiles in). The physics is documented in ``effects.py``.

A new effect: its :class:`~ema_uq.models.effects.Effect` in ``effects.py`` (parameters,
extra states with their error scales, kernel constants per concept) and its physics here,
reading its offsets ``FX_<EFFECT> = LAYOUT["<effect>"]`` (state: + 1) and ``LAYOUT["<effect>_<constant>"]``.
Numba caches compiled kernels per source file: after changing an effect's parameters or
constants in ``effects.py`` alone, delete the caches (``*.nbi``, ``*.nbc``) so the kernels
compile the new offsets.

Every effect enters so that its ``off`` values give back the nominal arithmetic exactly
(factors of exactly 1.0, additions of exactly 0.0, unchanged summation order), which is
what makes an augmented model at ``off`` reproduce the nominal outputs bit for bit. The
nominal ``evaluate`` functions are not touched.
"""
from __future__ import annotations

import math

from numba import njit

from . import htls as H
from . import lths as L
from .components import brake_torque
from .effects import LAYOUT

TWO_PI = 2.0 * math.pi
#: tanh(z) rounds to exactly ±1.0 in double precision for |z| > 19.06: skipping the call there
#: changes no bit and saves most tanh calls while shafts turn
TANH_SATURATED = 19.1

#: kernel positions of the layout table (after the concept's derived constants)
HTLS_FX = H.D_INV_COS_B2 + 1
LTHS_FX = L.D_INV_COS_B2 + 1
# offsets inside the table (effects.LAYOUT): the effect's first parameter position in th (its
# first extra state in x one further, -1 when the effect is off), then its kernel constants
FX_BACKLASH = LAYOUT["backlash"]
FX_BACKLASH_RELAXATION = LAYOUT["backlash_relaxation"]      # [s]
FX_BACKLASH_SOFTNESS = LAYOUT["backlash_softness"]          # [1]
FX_STRIBECK = LAYOUT["stribeck"]
FX_COMPLIANCE = LAYOUT["shaft_compliance"]
FX_MODE_OMEGA_MAX = LAYOUT["shaft_compliance_mode_omega_max"]  # [rad/s]
FX_UJOINT = LAYOUT["ujoint_kinematics"]
FX_UJOINT_STATIONS = LAYOUT["ujoint_stations"]
FX_LOAD_FRICTION = LAYOUT["load_dependent_friction"]
FX_RIPPLE = LAYOUT["torque_ripple"]
FX_RIPPLE_PERIODS = LAYOUT["torque_ripple_periods"]         # periods per motor revolution
FX_COUPLING = LAYOUT["backlash_compliant"]
FX_COUPLING_LOAD_FRACTION = LAYOUT["backlash_compliant_load_fraction"]    # [1]
FX_COUPLING_OMEGA_MAX = LAYOUT["backlash_compliant_mode_omega_max"]       # [rad/s]
FX_COUPLING_SOFTNESS = LAYOUT["backlash_compliant_softness"]              # [1]
FX_NUT_PLAY = LAYOUT["backlash_output"]
FX_NUT_PLAY_RELAXATION = LAYOUT["backlash_output_relaxation"]  # [s]
FX_NUT_PLAY_SOFTNESS = LAYOUT["backlash_output_softness"]      # [1]
FX_HARMONICS = LAYOUT["torque_ripple_harmonics"]
FX_HARMONICS_PERIODS = LAYOUT["torque_ripple_harmonics_periods"]  # fundamental periods per motor revolution


@njit(cache=True, inline="always", error_model="numpy")
def _tanh(z):
    if z > TANH_SATURATED:
        return 1.0
    if z < -TANH_SATURATED:
        return -1.0
    return math.tanh(z)


@njit(cache=True, inline="always", error_model="numpy")
def smooth_sign(v, eps):
    """components.smooth_sign, bit for bit, without the tanh call where it saturates."""
    return _tanh(v / eps)


@njit(cache=True, inline="always", error_model="numpy")
def _play_slope(b, half_play, softness):
    """b_eff'(b) of :func:`_play`: 1 inside the play, 0 at a flank (the load carries 1 - it)."""
    w2 = 2.0 * softness * half_play
    return 0.5 * (_tanh((b + half_play) / w2) - _tanh((b - half_play) / w2))


@njit(cache=True, inline="always", error_model="numpy")
def _play_rate(b, half_play, softness, relaxation, drive):
    """db/dt of :func:`_play`."""
    stop = half_play * (1.0 + 8.0 * softness)
    if b > stop:
        return drive - (b - stop) / relaxation
    if b < -stop:
        return drive - (b + stop) / relaxation
    return drive


@njit(cache=True, inline="always", error_model="numpy")
def _dead_band(q, band, width):
    """Twist beyond a dead band ±band with corners smoothed over ``width``, and its slope
    (0 inside the band, 1 in contact): the spring's deflection and the damper's weight."""
    if width <= 0.0:
        return q, 1.0
    a = q - band
    b = q + band
    ra = math.sqrt(a * a + width * width)
    rb = math.sqrt(b * b + width * width)
    return 0.5 * (a + ra) + 0.5 * (b - rb), 0.5 * (1.0 + a / ra) + 0.5 * (1.0 - b / rb)


@njit(cache=True, inline="always", error_model="numpy")
def _coupling_rate(net, load, j_motor, j_load, omega_n, zeta, q, q_rate, band, softness):
    """d²q/dt² of the modal two-inertia coupling: a plain spring (band < 0: shaft_compliance's
    arithmetic, unchanged) or one acting beyond a dead band ±band (backlash_compliant)."""
    if band < 0.0:
        return (net + load) / j_motor + load / j_load - omega_n * omega_n * q - 2.0 * zeta * omega_n * q_rate
    deflection, contact = _dead_band(q, band, softness * band)
    return ((net + load) / j_motor + load / j_load
            - omega_n * omega_n * deflection - 2.0 * zeta * omega_n * contact * q_rate)


@njit(cache=True, inline="always", error_model="numpy")
def _play(b, half_play, softness, relaxation, drive):
    """Kinematic play of half width ``half_play`` (> 0, drive-side radians) at drive speed
    ``drive``: returns (load-side speed, torque transmission 0..1, db/dt).

    b is the drive-side travel inside the play; b_eff = a tanh-smoothed clamp of b to
    [-half_play, half_play] is the drive angle the load does not follow, so the load turns at
    drive - b_eff'(b) db/dt and carries torque with weight 1 - b_eff'(b). Beyond the contact
    flank (1 + 8 softness) half_play, b relaxes back with time constant ``relaxation``.
    """
    w2 = 2.0 * softness * half_play
    slope = 0.5 * (_tanh((b + half_play) / w2) - _tanh((b - half_play) / w2))
    stop = half_play * (1.0 + 8.0 * softness)
    if b > stop:
        over = b - stop
    elif b < -stop:
        over = b + stop
    else:
        over = 0.0
    b_rate = drive - over / relaxation
    return drive - slope * b_rate, 1.0 - slope, b_rate


@njit(cache=True, inline="always", error_model="numpy")
def _ujoint_factor(cos_angle, scale, inv_cos_beta):
    """g_U = 1 + scale (g - 1), g = cosβ / (1 - sin²β cos²(θ_TP + φ)) (eq. 8); ``cos_angle``
    is cos(θ_TP + φ)."""
    cos_b = 1.0 / inv_cos_beta
    g = cos_b / (1.0 - (1.0 - cos_b * cos_b) * cos_angle * cos_angle)
    return 1.0 + scale * (g - 1.0)


@njit(cache=True, inline="always", error_model="numpy")
def _ujoint_positions(c, t):
    """Positions in th of each station's U-joint ripple scale (its yoke phase follows it):
    ujoint_kinematics' one pair for both stations, ujoint_stations' own pair per station, or
    (-1, -1) without a U-joint effect."""
    p_uj = int(c[t + FX_UJOINT])
    if p_uj >= 0:
        return p_uj, p_uj
    p_us = int(c[t + FX_UJOINT_STATIONS])
    if p_us >= 0:
        return p_us, p_us + 2
    return -1, -1


@njit(cache=True, inline="always", error_model="numpy")
def _stribeck(speed, ratio, v_s):
    """Coulomb multiplier 1 + ρ exp(-(v/v_s)²)."""
    z = speed / v_s
    zz = z * z
    if zz > 50.0:  # ρ e^-50 < 4e-21 for ρ <= 20 (its bound): 1 + that rounds to 1 exactly
        return 1.0
    return 1.0 + ratio * math.exp(-zz)


@njit(cache=True, inline="always", error_model="numpy")
def _station(omega_tp, sign_tp, cos_angle, f_tp, f_er, b_ts, c_ts, b_u, c_u, r_scg, inv_cos_beta,
             p_uj, p_st, p_ld, r, th):
    """One station with the station effects: returns Ω_U, M_ER, M_TSER, M_UER.

    ``sign_tp`` = sgn_ε(Ω_TP), ``cos_angle`` = cos(θ_TP + φ_U) and ``f_tp`` (the Stribeck
    factor at Ω_TP) come from the caller, which shares them between stations whose shafts
    turn alike (transcendentals dominate the cost of a step). The U-joint and screw terms use
    the sign and Stribeck factor of Ω_TP: g_U > 0 never changes the direction, and the
    ripple (|g_U - 1| < 3 % at a = 6) hardly moves the Stribeck factor.
    """
    g_u = 1.0
    omega_u = omega_tp
    if p_uj >= 0:
        g_u = _ujoint_factor(cos_angle, th[p_uj], inv_cos_beta)
        omega_u = g_u * omega_tp
    if p_ld >= 0:
        c_ts = c_ts + th[p_ld] * r * abs(f_er)
    if p_st >= 0:
        c_ts = c_ts * f_tp
        c_u = c_u * f_tp
    m_er = -r_scg * f_er
    m_tser = b_ts * omega_u + c_ts * sign_tp + m_er
    m_uer = m_tser * g_u * inv_cos_beta + b_u * omega_u + c_u * sign_tp
    return omega_u, m_er, m_tser, m_uer


@njit(cache=True, inline="always", error_model="numpy")
def _shared_terms(omega_tp1, omega_tp2, angle1, angle2, eps, p_uj1, p_uj2, p_st, th):
    """sgn_ε, cos(θ_TP + φ_U) and Stribeck factor of both stations, each computed once when
    the two shafts turn alike (identical arguments give identical results)."""
    sign1 = smooth_sign(omega_tp1, eps)
    sign2 = sign1 if omega_tp2 == omega_tp1 else smooth_sign(omega_tp2, eps)
    cos1 = 1.0
    cos2 = 1.0
    if p_uj1 >= 0:
        cos1 = math.cos(angle1 + th[p_uj1 + 1])
        cos2 = cos1 if angle2 == angle1 and p_uj2 == p_uj1 else math.cos(angle2 + th[p_uj2 + 1])
    f1 = 1.0
    f2 = 1.0
    if p_st >= 0:
        f1 = _stribeck(omega_tp1, th[p_st], th[p_st + 1])
        f2 = f1 if omega_tp2 == omega_tp1 else _stribeck(omega_tp2, th[p_st], th[p_st + 1])
    return sign1, sign2, cos1, cos2, f1, f2


@njit(cache=True, inline="always", error_model="numpy")
def _compliance(x, th, p_sc, x_sc, load_fraction, omega_max):
    """Modal two-inertia shaft: (participation, ω_n, ζ, twist q, twist rate)."""
    period = th[p_sc]
    t_floor = TWO_PI / omega_max
    if period >= t_floor:
        part = 1.0
        omega_n = TWO_PI / period
    else:  # faster than the integrator resolves: keep the mode there, fade its participation
        part = period / t_floor
        omega_n = omega_max
    return part, omega_n, th[p_sc + 1], x[x_sc], x[x_sc + 1]


@njit(cache=True, inline="always", error_model="numpy")
def _harmonic_ripple(th, c, t, theta_m, k_n):
    """torque_ripple_harmonics: k_n A (sin(n θ + φ1) + h2 sin(2 n θ + φ2) + h3 sin(3 n θ + φ3))."""
    p = int(c[t + FX_HARMONICS])
    angle = c[t + FX_HARMONICS_PERIODS] * theta_m
    return k_n * th[p] * (math.sin(angle + th[p + 1]) + th[p + 2] * math.sin(2.0 * angle + th[p + 3])
                          + th[p + 4] * math.sin(3.0 * angle + th[p + 5]))


@njit(cache=True, inline="always", error_model="numpy")
def _nut_contact(x, th, c, t, p_np, x_np, force1, force2):
    """backlash_output: the load forces that reach the screws (only at a flank of the nut
    play) and the plays' slopes; (force1, force2, 0, 0) unchanged when the effect is off."""
    if p_np < 0 or not th[p_np] > 0.0:
        return force1, force2, 0.0, 0.0
    softness = c[t + FX_NUT_PLAY_SOFTNESS]
    slope1 = _play_slope(x[x_np], th[p_np], softness)
    slope2 = _play_slope(x[x_np + 1], th[p_np], softness)
    return (1.0 - slope1) * force1, (1.0 - slope2) * force2, slope1, slope2


@njit(cache=True, inline="always", error_model="numpy")
def _nut_play_rates(x, th, c, t, p_np, x_np, omega_u1, omega_u2, slope1, slope2, dx):
    """backlash_output: the carriages' speeds in screw radians (the screw's, less its travel
    inside the play), writing the plays' db/dt into ``dx``; the screws' when off."""
    if p_np < 0:
        return omega_u1, omega_u2
    if not th[p_np] > 0.0:
        dx[x_np] = 0.0
        dx[x_np + 1] = 0.0
        return omega_u1, omega_u2
    softness, relaxation = c[t + FX_NUT_PLAY_SOFTNESS], c[t + FX_NUT_PLAY_RELAXATION]
    b_rate1 = _play_rate(x[x_np], th[p_np], softness, relaxation, omega_u1)
    b_rate2 = _play_rate(x[x_np + 1], th[p_np], softness, relaxation, omega_u2)
    dx[x_np] = b_rate1
    dx[x_np + 1] = b_rate2
    return omega_u1 - slope1 * b_rate1, omega_u2 - slope2 * b_rate2


@njit(cache=True, inline="always", error_model="numpy")
def evaluate_htls_effects(x, u, th, c, dx, y):
    """HT/LS with the effects listed in the layout table of ``c``; states as ``htls.evaluate``
    followed by the effects' extra states (backlash: b1, b2; compliance: q, dq/dt)."""
    t = HTLS_FX
    p_bl = int(c[t + FX_BACKLASH])
    x_bl = int(c[t + FX_BACKLASH + 1])
    p_st = int(c[t + FX_STRIBECK])
    p_sc = int(c[t + FX_COMPLIANCE])
    x_sc = int(c[t + FX_COMPLIANCE + 1])
    p_uj1, p_uj2 = _ujoint_positions(c, t)
    p_ld = int(c[t + FX_LOAD_FRICTION])
    p_tr = int(c[t + FX_RIPPLE])
    relaxation, softness = c[t + FX_BACKLASH_RELAXATION], c[t + FX_BACKLASH_SOFTNESS]
    omega_max = c[t + FX_MODE_OMEGA_MAX]
    load_fraction = th[p_sc + 2] if p_sc >= 0 else 0.0
    periods = c[t + FX_RIPPLE_PERIODS]
    p_np = int(c[t + FX_NUT_PLAY])
    x_np = int(c[t + FX_NUT_PLAY + 1])

    eps = c[H.C_OMEGA_EPS]
    i_tp1 = c[H.C_I_TP1]
    i_tp2 = c[H.C_I_TP2]
    omega = x[H.X_OMEGA]
    theta = x[H.X_THETA]
    # one compliant coupling: shaft_compliance's spring, or backlash_compliant's beyond its band
    band = -1.0
    coupling_softness = 0.0
    p_bc = int(c[t + FX_COUPLING])
    if p_bc >= 0:
        p_sc, x_sc = p_bc + 1, int(c[t + FX_COUPLING + 1])
        load_fraction, omega_max = c[t + FX_COUPLING_LOAD_FRACTION], c[t + FX_COUPLING_OMEGA_MAX]
        coupling_softness = c[t + FX_COUPLING_SOFTNESS]
        band = th[p_bc] * i_tp1

    # motor side and shaft end (rigid: both the state Ω)
    omega_m = omega
    omega_s = omega
    theta_m = theta
    part = 0.0
    if p_sc >= 0:
        part, omega_n, zeta, q, q_rate = _compliance(x, th, p_sc, x_sc, load_fraction, omega_max)
        omega_m = omega + part * load_fraction * q_rate
        omega_s = omega - part * (1.0 - load_fraction) * q_rate
        theta_m = theta + part * load_fraction * q

    # bevel-gear plays (one per station)
    omega_l1 = omega_s
    omega_l2 = omega_s
    e1 = 1.0
    e2 = 1.0
    if p_bl >= 0:
        if th[p_bl] > 0.0:
            omega_l1, e1, b_rate1 = _play(x[x_bl], th[p_bl] * i_tp1, softness, relaxation, omega_s)
            if x[x_bl + 1] == x[x_bl] and i_tp2 == i_tp1:  # both plays in the same place
                omega_l2, e2, b_rate2 = omega_l1, e1, b_rate1
            else:
                omega_l2, e2, b_rate2 = _play(x[x_bl + 1], th[p_bl] * i_tp2, softness, relaxation, omega_s)
            dx[x_bl] = b_rate1
            dx[x_bl + 1] = b_rate2
        else:
            dx[x_bl] = 0.0
            dx[x_bl + 1] = 0.0

    omega_tp1 = omega_l1 / i_tp1
    omega_tp2 = omega_l2 / i_tp2
    r = c[H.C_R]
    f_er1, f_er2, slope1, slope2 = _nut_contact(x, th, c, t, p_np, x_np, u[1], u[2])
    sign_tp1, sign_tp2, cos1, cos2, f_tp1, f_tp2 = _shared_terms(
        omega_tp1, omega_tp2, theta / i_tp1, theta / i_tp2, eps, p_uj1, p_uj2, p_st, th)
    omega_u1, m_er1, m_tser1, m_uer1 = _station(
        omega_tp1, sign_tp1, cos1, f_tp1, f_er1, th[H.P_B_TS1], th[H.P_C_TS1], th[H.P_B_U1], th[H.P_C_U1],
        c[H.D_R_SCG], c[H.D_INV_COS_B1], p_uj1, p_st, p_ld, r, th)
    omega_u2, m_er2, m_tser2, m_uer2 = _station(
        omega_tp2, sign_tp2, cos2, f_tp2, f_er2, th[H.P_B_TS2], th[H.P_C_TS2], th[H.P_B_U2], th[H.P_C_U2],
        c[H.D_R_SCG], c[H.D_INV_COS_B2], p_uj2, p_st, p_ld, r, th)
    carriage1, carriage2 = _nut_play_rates(x, th, c, t, p_np, x_np, omega_u1, omega_u2, slope1, slope2, dx)
    brake = u[3]
    m_b21 = brake_torque(brake, omega_tp1, c[H.C_M_BMAX], c[H.C_K_B], c[H.C_OMEGA_HALF], eps)
    m_b22 = brake_torque(brake, omega_tp2, c[H.C_M_BMAX], c[H.C_K_B], c[H.C_OMEGA_HALF], eps)
    m_b1 = brake_torque(brake, omega_m, c[H.C_M_BMAX], c[H.C_K_B], c[H.C_OMEGA_HALF], eps)
    m_tper1 = e1 * (m_uer1 / i_tp1 + th[H.P_B_TP1] * omega_tp1 + th[H.P_C_TP1] * f_tp1 * sign_tp1 + m_b21)
    m_tper2 = e2 * (m_uer2 / i_tp2 + th[H.P_B_TP2] * omega_tp2 + th[H.P_C_TP2] * f_tp2 * sign_tp2 + m_b22)

    # cascaded P control on the motor speed and the carriage positions
    y_r = c[H.C_K_Y] * u[0]
    y_s = 0.5 * (x[H.X_Y1] + x[H.X_Y2])
    omega_r = th[H.P_P_ACE] * (y_r - y_s)
    m_n = min(max(th[H.P_P_PCE] * (omega_r - omega_m), c[H.C_M_MIN]), c[H.C_M_MAX])
    m_ripple = 0.0
    if p_tr >= 0:
        m_ripple = th[H.P_K_N] * th[p_tr] * math.sin(periods * theta_m + th[p_tr + 1])
    if c[t + FX_HARMONICS] >= 0.0:
        m_ripple = m_ripple + _harmonic_ripple(th, c, t, theta_m, th[H.P_K_N])

    lead = c[H.D_LEAD]
    net = m_n + m_ripple - (m_b1 + m_tper1 + m_tper2)
    dx[H.X_OMEGA] = net / th[H.P_J]
    dx[H.X_Y1] = lead * carriage1
    dx[H.X_Y2] = lead * carriage2
    dx[H.X_THETA] = omega
    if p_sc >= 0:
        load = m_tper1 + m_tper2
        j_load = load_fraction * th[H.P_J]
        j_motor = th[H.P_J] - j_load
        dx[x_sc] = q_rate
        dx[x_sc + 1] = _coupling_rate(net, load, j_motor, j_load, omega_n, zeta, q, q_rate, band, coupling_softness)

    y[0] = omega_m
    y[1] = x[H.X_Y1]
    y[2] = x[H.X_Y2]
    y[3] = m_n / th[H.P_K_N]
    y[4] = omega_tp1
    y[5] = omega_tp2
    y[6] = omega_u1
    y[7] = omega_u2
    y[8] = m_er1
    y[9] = m_er2
    y[10] = m_tser1
    y[11] = m_tser2
    y[12] = m_uer1
    y[13] = m_uer2
    y[14] = m_tper1
    y[15] = m_tper2


@njit(cache=True, inline="always", error_model="numpy")
def evaluate_lths_effects(x, u, th, c, dx, y):
    """LT/HS with the effects listed in the layout table of ``c``; states as ``lths.evaluate``
    followed by the effects' extra states (backlash: b; compliance: q, dq/dt)."""
    t = LTHS_FX
    p_bl = int(c[t + FX_BACKLASH])
    x_bl = int(c[t + FX_BACKLASH + 1])
    p_st = int(c[t + FX_STRIBECK])
    p_sc = int(c[t + FX_COMPLIANCE])
    x_sc = int(c[t + FX_COMPLIANCE + 1])
    p_uj1, p_uj2 = _ujoint_positions(c, t)
    p_ld = int(c[t + FX_LOAD_FRICTION])
    p_tr = int(c[t + FX_RIPPLE])
    relaxation, softness = c[t + FX_BACKLASH_RELAXATION], c[t + FX_BACKLASH_SOFTNESS]
    omega_max = c[t + FX_MODE_OMEGA_MAX]
    load_fraction = th[p_sc + 2] if p_sc >= 0 else 0.0
    periods = c[t + FX_RIPPLE_PERIODS]
    p_np = int(c[t + FX_NUT_PLAY])
    x_np = int(c[t + FX_NUT_PLAY + 1])

    eps = c[L.C_OMEGA_EPS]
    i_mg = c[L.C_I_MG]
    i_bg1 = c[L.C_I_BG1]
    i_bg2 = c[L.C_I_BG2]
    i_tp2 = c[L.C_I_TP2]
    i_a = x[L.X_I_A]
    omega = x[L.X_OMEGA]
    theta = x[L.X_THETA]
    # one compliant coupling: shaft_compliance's spring, or backlash_compliant's beyond its band
    band = -1.0
    coupling_softness = 0.0
    p_bc = int(c[t + FX_COUPLING])
    if p_bc >= 0:
        p_sc, x_sc = p_bc + 1, int(c[t + FX_COUPLING + 1])
        load_fraction, omega_max = c[t + FX_COUPLING_LOAD_FRACTION], c[t + FX_COUPLING_OMEGA_MAX]
        coupling_softness = c[t + FX_COUPLING_SOFTNESS]
        band = th[p_bc] * i_mg * i_bg1

    # motor (+ magnetic gear) side and the first bevel gear's end of the input shaft
    omega_m = omega
    omega_s = omega
    theta_m = theta
    if p_sc >= 0:
        part, omega_n, zeta, q, q_rate = _compliance(x, th, p_sc, x_sc, load_fraction, omega_max)
        omega_m = omega + part * load_fraction * q_rate
        omega_s = omega - part * (1.0 - load_fraction) * q_rate
        theta_m = theta + part * load_fraction * q

    # play in the first bevel gear, ahead of both stations (motor-scale radians)
    omega_l = omega_s
    e = 1.0
    if p_bl >= 0:
        if th[p_bl] > 0.0:
            omega_l, e, b_rate = _play(x[x_bl], th[p_bl] * i_mg * i_bg1, softness, relaxation, omega_s)
            dx[x_bl] = b_rate
        else:
            dx[x_bl] = 0.0

    omega_mg = omega_m / i_mg
    omega_bg = omega_l / i_mg
    omega_tp1 = omega_bg / i_bg1
    omega_mg2 = omega_bg / i_bg2
    omega_tp2 = omega_mg2 / i_tp2
    r = c[L.C_R]
    theta_bg = theta / i_mg
    f_er1, f_er2, slope1, slope2 = _nut_contact(x, th, c, t, p_np, x_np, u[1], u[2])
    sign_tp1, sign_tp2, cos1, cos2, f_tp1, f_tp2 = _shared_terms(
        omega_tp1, omega_tp2, theta_bg / i_bg1, theta_bg / i_bg2 / i_tp2, eps, p_uj1, p_uj2, p_st, th)
    omega_u1, m_er1, m_tser1, m_uer1 = _station(
        omega_tp1, sign_tp1, cos1, f_tp1, f_er1, th[L.P_B_TS1], th[L.P_C_TS1], th[L.P_B_U1], th[L.P_C_U1],
        c[L.D_R_SCG], c[L.D_INV_COS_B1], p_uj1, p_st, p_ld, r, th)
    omega_u2, m_er2, m_tser2, m_uer2 = _station(
        omega_tp2, sign_tp2, cos2, f_tp2, f_er2, th[L.P_B_TS2], th[L.P_C_TS2], th[L.P_B_U2], th[L.P_C_U2],
        c[L.D_R_SCG], c[L.D_INV_COS_B2], p_uj2, p_st, p_ld, r, th)
    carriage1, carriage2 = _nut_play_rates(x, th, c, t, p_np, x_np, omega_u1, omega_u2, slope1, slope2, dx)
    brake = u[3]
    m_b22 = brake_torque(brake, omega_tp2, c[L.C_M_BMAX], c[L.C_K_B], c[L.C_OMEGA_HALF], eps)
    m_b2 = brake_torque(brake, omega_tp1, c[L.C_M_BMAX], c[L.C_K_B], c[L.C_OMEGA_HALF], eps)
    m_mg2 = m_uer2 / i_tp2 + th[L.P_B_TP2] * omega_tp2 + th[L.P_C_TP2] * f_tp2 * sign_tp2 + m_b22
    m_tper = e * (m_uer1 / i_bg1 + m_mg2 / i_bg2 + th[L.P_B_TP1] * omega_tp1
                  + th[L.P_C_TP1] * f_tp1 * sign_tp1 + m_b2)
    m_iser = m_tper + c[L.C_D_IS] * theta_m / i_mg
    c_mg = th[L.P_C_MG]
    if p_st >= 0:
        c_mg = c_mg * _stribeck(omega_mg / i_bg1, th[p_st], th[p_st + 1])
    m_mger = m_iser / i_mg + th[L.P_B_MG] * omega_mg + c_mg * smooth_sign(omega_mg, eps)

    # cascaded P control (eq. 41), voltage-limited, on the motor speed
    y_r = c[L.C_K_Y] * u[0]
    y_s = 0.5 * (x[L.X_Y1] + x[L.X_Y2])
    u_a = th[L.P_P_PCE] / th[L.P_K_N] * (th[L.P_P_ACE] * (y_r - y_s) - omega_m)
    u_a = min(max(u_a, -c[L.C_U_MAX]), c[L.C_U_MAX])
    m_ripple = 0.0
    if p_tr >= 0:
        m_ripple = th[L.P_K_N] * th[p_tr] * math.sin(periods * theta_m + th[p_tr + 1])
    if c[t + FX_HARMONICS] >= 0.0:
        m_ripple = m_ripple + _harmonic_ripple(th, c, t, theta_m, th[L.P_K_N])

    lead = c[L.D_LEAD]
    net = th[L.P_K_N] * i_a + m_ripple - m_mger
    dx[L.X_I_A] = (-th[L.P_R_A] * i_a - th[L.P_K_S] * omega_m + u_a) / th[L.P_L_A]
    dx[L.X_OMEGA] = net / th[L.P_J]
    dx[L.X_Y1] = lead * carriage1
    dx[L.X_Y2] = lead * carriage2
    dx[L.X_THETA] = omega
    if p_sc >= 0:
        load = m_iser / i_mg
        j_load = load_fraction * th[L.P_J]
        j_motor = th[L.P_J] - j_load
        dx[x_sc] = q_rate
        dx[x_sc + 1] = _coupling_rate(net, load, j_motor, j_load, omega_n, zeta, q, q_rate, band, coupling_softness)

    y[0] = omega_m
    y[1] = x[L.X_Y1]
    y[2] = x[L.X_Y2]
    y[3] = i_a
    y[4] = u_a
    y[5] = omega_mg
    y[6] = omega_tp1
    y[7] = omega_mg2
    y[8] = omega_tp2
    y[9] = omega_u1
    y[10] = omega_u2
    y[11] = m_er1
    y[12] = m_er2
    y[13] = m_tser1
    y[14] = m_tser2
    y[15] = m_uer1
    y[16] = m_uer2
    y[17] = m_mg2
    y[18] = m_tper
    y[19] = m_mger
