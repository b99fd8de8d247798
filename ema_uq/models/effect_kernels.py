"""The unmodelled effects' physics inside the HT/LS and LT/HS right-hand sides.

``htls.evaluate`` and ``lths.evaluate`` are the one source of each concept's equations; they
call the hooks below at fixed points of the right-hand side (drive-train coupling, gear play
and its torque transmission, station friction and kinematics, load forces at the nut, the
carriages' speeds, motor torque, the extra states' rates). Each hook takes ``flags``, the bit
set of the effects switched in (:func:`effect_flags`, bit ``FLAG[name]``), and tests it as
``flags is not None and flags & BIT``. The nominal kernels pass ``flags = None``: each hook is
compiled once for that type, numba prunes the effect branches before it types them, and what
is left (the nominal arithmetic) LLVM inlines into the right-hand side. The kernels with
effects pass the set as a run-time integer: one compiled kernel serves every effect set, each
effect's physics behind a test of its bit (``simulate.integrators``). The hooks are separate
compiled functions, not inlined at numba IR level: inlined, numba re-translates each one at
every call site before any branch is pruned, which multiplied the compile time. They are
compiled without the numba runtime (:data:`hook`): they allocate nothing and only borrow the
arrays they are given, and with the runtime every call paid atomic reference counts on those
arrays, which left a right-hand side with effects at twice and more the cost of the former
monolithic effect kernels (HT/LS, one evaluation: 325 ns against 188 ns; without it 74 ns).
Where an effect's parameters sit in ``th``, its extra states in ``x`` and its kernel constants
are read from the layout table that :func:`~ema_uq.models.effects.augment_ema` appends to the
kernel constants ``c``, at the offsets ``effects.LAYOUT`` computes from the effect definitions
(``FX_*`` below); ``t`` is the table's position in ``c`` (the concept's ``FX_TABLE``). The physics
is documented in ``effects.py``.

A new effect: its :class:`~ema_uq.models.effects.Effect` in ``effects.py`` (parameters, extra
states with their error scales, kernel constants per concept) and its physics here, inside the
hook where it enters, under ``if flags is not None and flags & <BIT>``, reading its offsets
``FX_<EFFECT> = LAYOUT["<effect>"]`` (state: + 1) and ``LAYOUT["<effect>_<constant>"]``. An
effect with only an output step (``Effect.postprocess``, e.g. ``sensor_delay``) has no bit: its
models run the kernel of their other effects. Numba caches compiled kernels per source file:
after changing an effect's parameters or constants in ``effects.py`` alone, delete the caches
(``*.nbi``, ``*.nbc``) so the kernels compile the new offsets.

Every effect enters so that its ``off`` values give back the nominal arithmetic exactly
(factors of exactly 1.0, additions of exactly 0.0, unchanged summation order), which is what
makes an augmented model at ``off`` reproduce the nominal outputs bit for bit.
"""
from __future__ import annotations

import math
from typing import Sequence

from numba import njit
from numba.core.cpu import CPUTargetOptions

from .effects import CATALOGUE, EFFECT_ORDER, LAYOUT

#: kernel bit of each effect with physics in the right-hand side (output-only effects have none)
FLAG: dict[str, int] = {name: 1 << i for i, name in enumerate(EFFECT_ORDER) if CATALOGUE[name].postprocess is None}
BACKLASH = FLAG["backlash"]
STRIBECK = FLAG["stribeck"]
COMPLIANCE = FLAG["shaft_compliance"]
UJOINT = FLAG["ujoint_kinematics"]
UJOINT_STATIONS = FLAG["ujoint_stations"]
LOAD_FRICTION = FLAG["load_dependent_friction"]
RIPPLE = FLAG["torque_ripple"]
HARMONICS = FLAG["torque_ripple_harmonics"]
COUPLING = FLAG["backlash_compliant"]
NUT_PLAY = FLAG["backlash_output"]
STRIBECK_DIRECTIONAL = FLAG["stribeck_directional"]
LOAD_FRICTION_DIRECTIONAL = FLAG["load_friction_directional"]
RIPPLE_LOADED = FLAG["torque_ripple_loaded"]
UJOINT_STROKE = FLAG["ujoint_stroke"]
COMPLIANCE_LOADED = FLAG["shaft_compliance_loaded"]
#: effects of one kind: a U-joint factor, a compliant coupling, a ripple torque
ANY_UJOINT = UJOINT | UJOINT_STATIONS | UJOINT_STROKE
ANY_COUPLING = COMPLIANCE | COUPLING | COMPLIANCE_LOADED
ANY_RIPPLE = RIPPLE | HARMONICS | RIPPLE_LOADED
ANY_STRIBECK = STRIBECK | STRIBECK_DIRECTIONAL
ANY_LOAD_FRICTION = LOAD_FRICTION | LOAD_FRICTION_DIRECTIONAL
#: effects with extra states (frozen by the adaptive integrator at their magnitude's zero)
STATEFUL = sum(FLAG[n] for n in FLAG if any(CATALOGUE[n].extra_states.values()))


def effect_flags(names: Sequence[str]) -> int:
    """The kernel's bit set of the named effects (0: the nominal right-hand side)."""
    return int(sum(FLAG.get(name, 0) for name in names))


#: decorator of the hooks: compiled on their own (see above), without the numba runtime's
#: reference counting (``_nrt=False``, an option of numba's CPU target); a hook that allocated
#: an array would fail to compile, which keeps them to scalars and borrowed arrays
hook = (njit(cache=True, error_model="numpy", _nrt=False) if hasattr(CPUTargetOptions, "_nrt")
        # a numba without the option: the same numbers, at the reference counting's cost
        else njit(cache=True, error_model="numpy"))

TWO_PI = 2.0 * math.pi
#: tanh(z) rounds to exactly ±1.0 in double precision for |z| > 19.06: skipping the call there
#: changes no bit and saves most tanh calls while shafts turn
TANH_SATURATED = 19.1

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
FX_STRIBECK_DIRECTIONAL = LAYOUT["stribeck_directional"]
FX_LOAD_FRICTION_DIRECTIONAL = LAYOUT["load_friction_directional"]
FX_RIPPLE_LOADED = LAYOUT["torque_ripple_loaded"]
FX_RIPPLE_LOADED_PERIODS = LAYOUT["torque_ripple_loaded_periods"]  # periods per motor revolution
FX_UJOINT_STROKE = LAYOUT["ujoint_stroke"]
FX_UJOINT_STROKE_MID = LAYOUT["ujoint_stroke_mid"]                # [m]
FX_UJOINT_STROKE_HALF = LAYOUT["ujoint_stroke_half"]              # [m]
FX_COMPLIANCE_LOADED = LAYOUT["shaft_compliance_loaded"]
FX_LOADED_OMEGA_MAX = LAYOUT["shaft_compliance_loaded_mode_omega_max"]  # [rad/s]
FX_LOADED_TORQUE_REF = LAYOUT["shaft_compliance_loaded_torque_ref"]     # [N m]


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
def _coupling_rate(net, load, j_motor, j_load, omega_n, zeta, q, q_rate, band, softness, stiffening):
    """d²q/dt² of the modal two-inertia coupling: a plain spring (band < 0: shaft_compliance's
    arithmetic, unchanged at ``stiffening`` 1.0, the factor of shaft_compliance_loaded's stiffness)
    or one acting beyond a dead band ±band (backlash_compliant)."""
    if band < 0.0:
        return ((net + load) / j_motor + load / j_load - omega_n * omega_n * stiffening * q
                - 2.0 * zeta * omega_n * q_rate)
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
def _stribeck(speed, ratio, v_s):
    """Coulomb multiplier 1 + ρ exp(-(v/v_s)²)."""
    z = speed / v_s
    zz = z * z
    if zz > 50.0:  # ρ e^-50 < 4e-21 for ρ <= 20 (its bound): 1 + that rounds to 1 exactly
        return 1.0
    return 1.0 + ratio * math.exp(-zz)


@njit(cache=True, inline="always", error_model="numpy")
def _stribeck_factor(flags, th, c, t, speed):
    """The Stribeck factor of a shaft at ``speed`` (referred to the screw): stribeck's one
    breakaway excess ρ, or stribeck_directional's ρ (1 ± a) by the direction of the speed."""
    if flags & STRIBECK:
        p_st = int(c[t + FX_STRIBECK])
        return _stribeck(speed, th[p_st], th[p_st + 1])
    p_sd = int(c[t + FX_STRIBECK_DIRECTIONAL])
    ratio = th[p_sd] * (1.0 + th[p_sd + 1]) if speed > 0.0 else th[p_sd] * (1.0 - th[p_sd + 1])
    return _stribeck(speed, ratio, th[p_sd + 2])


# --- hooks: called by the concepts' evaluate at fixed points of the right-hand side ---------
@hook
def coupling(flags, x, th, c, t, omega, theta, band_ratio_a, band_ratio_b):
    """A compliant coupling between motor (+ magnetic gear) and drive train (shaft_compliance's
    spring, or backlash_compliant's beyond a dead band of ±δ band_ratio_a band_ratio_b motor
    radians): (motor speed, drive-train speed, motor angle, the coupling's terms for
    :func:`coupling_rates`). Rigid (omega, omega, theta) without one."""
    if flags is not None and flags & ANY_COUPLING:
        if flags & COUPLING:
            p_bc = int(c[t + FX_COUPLING])
            p_sc, x_sc = p_bc + 1, int(c[t + FX_COUPLING + 1])
            load_fraction, omega_max = c[t + FX_COUPLING_LOAD_FRACTION], c[t + FX_COUPLING_OMEGA_MAX]
            softness = c[t + FX_COUPLING_SOFTNESS]
            band = th[p_bc] * band_ratio_a * band_ratio_b
            hardening = 0.0
        elif flags & COMPLIANCE_LOADED:
            p_sc = int(c[t + FX_COMPLIANCE_LOADED])
            x_sc = int(c[t + FX_COMPLIANCE_LOADED + 1])
            load_fraction, omega_max = th[p_sc + 2], c[t + FX_LOADED_OMEGA_MAX]
            softness = 0.0
            band = -1.0
            hardening = th[p_sc + 3] / c[t + FX_LOADED_TORQUE_REF]
        else:
            p_sc = int(c[t + FX_COMPLIANCE])
            x_sc = int(c[t + FX_COMPLIANCE + 1])
            load_fraction, omega_max = th[p_sc + 2], c[t + FX_MODE_OMEGA_MAX]
            softness = 0.0
            band = -1.0
            hardening = 0.0
        period = th[p_sc]
        t_floor = TWO_PI / omega_max
        if period >= t_floor:
            part = 1.0
            omega_n = TWO_PI / period
        else:  # faster than the integrator resolves: keep the mode there, fade its participation
            part = period / t_floor
            omega_n = omega_max
        zeta, q, q_rate = th[p_sc + 1], x[x_sc], x[x_sc + 1]
        omega_m = omega + part * load_fraction * q_rate
        omega_s = omega - part * (1.0 - load_fraction) * q_rate
        theta_m = theta + part * load_fraction * q
        return (omega_m, omega_s, theta_m,
                (load_fraction, omega_n, zeta, q, q_rate, band, softness, hardening, omega_max, x_sc))
    return omega, omega, theta, (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, -1)


@hook
def coupling_rates(flags, th_j, terms, net, load, dx):
    """The coupling's twist and twist rate derivatives into ``dx`` (nothing without one);
    ``net`` is the torque on the whole inertia ``th_j``, ``load`` the drive train's torque on
    the motor side of the coupling."""
    if flags is not None and flags & ANY_COUPLING:
        load_fraction, omega_n, zeta, q, q_rate, band, softness, hardening, omega_max, x_sc = terms
        j_load = load_fraction * th_j
        j_motor = th_j - j_load
        # shaft_compliance_loaded: k_0 (1 + h |M| / M_ref), the mode held below what the step resolves
        stiffening = 1.0
        if hardening > 0.0:
            stiffening = min(1.0 + hardening * abs(load), (omega_max / omega_n) ** 2)
        dx[x_sc] = q_rate
        dx[x_sc + 1] = _coupling_rate(net, load, j_motor, j_load, omega_n, zeta, q, q_rate, band, softness,
                                      stiffening)


@hook
def gear_play(flags, x, th, c, t, k, ratio_a, ratio_b, drive, dx):
    """backlash: play k (0, 1) of the gear stage ahead of the screw(s), of half width
    δ ratio_a ratio_b drive-side radians: (load-side speed, torque transmission); its travel's
    rate into ``dx``. (drive, 1.0) without the effect."""
    if flags is not None and flags & BACKLASH:
        p_bl = int(c[t + FX_BACKLASH])
        x_bl = int(c[t + FX_BACKLASH + 1]) + k
        if th[p_bl] > 0.0:
            omega_l, e, b_rate = _play(x[x_bl], th[p_bl] * ratio_a * ratio_b, c[t + FX_BACKLASH_SOFTNESS],
                                       c[t + FX_BACKLASH_RELAXATION], drive)
            dx[x_bl] = b_rate
            return omega_l, e
        dx[x_bl] = 0.0
    return drive, 1.0


@njit(cache=True, inline="always", error_model="numpy")
def transmit(flags, e, torque):
    """A gear-stage torque through the play's transmission ``e`` of :func:`gear_play`."""
    if flags is not None and flags & BACKLASH:
        return e * torque
    return torque


@njit(cache=True, inline="always", error_model="numpy")
def coulomb(flags, c_loss, factor):
    """A Coulomb loss with the Stribeck factor of its shaft (:func:`station_terms`)."""
    if flags is not None and flags & ANY_STRIBECK:
        return c_loss * factor
    return c_loss


@hook
def stribeck_coulomb(flags, th, c, t, c_loss, speed):
    """A Coulomb loss with the Stribeck factor at ``speed`` (referred to the screw)."""
    if flags is not None and flags & ANY_STRIBECK:
        return c_loss * _stribeck_factor(flags, th, c, t, speed)
    return c_loss


@njit(cache=True, inline="always", error_model="numpy")
def _ujoint_positions(flags, c, t):
    """Positions in th of each station's U-joint ripple scale (its yoke phase follows it):
    ujoint_kinematics' (or ujoint_stroke's) one pair for both stations, or ujoint_stations' own
    pair per station."""
    if flags & UJOINT:
        p_uj = int(c[t + FX_UJOINT])
        return p_uj, p_uj
    if flags & UJOINT_STROKE:
        p_uj = int(c[t + FX_UJOINT_STROKE])
        return p_uj, p_uj
    p_us = int(c[t + FX_UJOINT_STATIONS])
    return p_us, p_us + 2


@hook
def station_terms(flags, th, c, t, omega_tp1, omega_tp2, angle1, angle2, eps):
    """sgn_ε, cos(θ_TP + φ_U) and Stribeck factor of both stations' shafts, each computed once
    when the two shafts turn alike (identical arguments give identical results); the angles
    θ_TP are read only by a U-joint effect. Cosines and factors are 1.0 without the effects."""
    sign1 = smooth_sign(omega_tp1, eps)
    sign2 = sign1 if omega_tp2 == omega_tp1 else smooth_sign(omega_tp2, eps)
    cos1 = 1.0
    cos2 = 1.0
    if flags is not None and flags & ANY_UJOINT:
        p_uj1, p_uj2 = _ujoint_positions(flags, c, t)
        cos1 = math.cos(angle1 + th[p_uj1 + 1])
        cos2 = cos1 if angle2 == angle1 and p_uj2 == p_uj1 else math.cos(angle2 + th[p_uj2 + 1])
    f1 = 1.0
    f2 = 1.0
    if flags is not None and flags & ANY_STRIBECK:
        f1 = _stribeck_factor(flags, th, c, t, omega_tp1)
        f2 = f1 if omega_tp2 == omega_tp1 else _stribeck_factor(flags, th, c, t, omega_tp2)
    return sign1, sign2, cos1, cos2, f1, f2


@hook
def station(flags, th, c, t, k, omega_tp, sign_tp, cos_angle, f_tp, f_er, b_ts, c_ts, b_u, c_u, r_scg,
            inv_cos_beta, r, position):
    """Ball screw and U-joint of station k (1, 2), eqs. 10-15, with the station effects:
    returns Ω_U, M_ER, M_TSER, M_UER.

    ``sign_tp``, ``cos_angle`` and ``f_tp`` come from :func:`station_terms`; ``r`` is the screw
    radius (load-dependent friction), ``position`` the carriage's (ujoint_stroke). The U-joint and
    screw terms use the sign and Stribeck factor of Ω_TP: g_U > 0 never changes the direction,
    and the ripple (|g_U - 1| < 3 % at a = 6) hardly moves the Stribeck factor. Without
    effects, g_U = 1 (eq. 26) and Ω_U = Ω_TP.
    """
    g_u = 1.0
    omega_u = omega_tp
    if flags is not None and flags & ANY_UJOINT:
        p_uj1, p_uj2 = _ujoint_positions(flags, c, t)
        scale = th[p_uj1 if k == 1 else p_uj2]
        if flags & UJOINT_STROKE:  # a (1 + s ξ), ξ the carriage's offset from mid-stroke in half strokes
            xi = (position - c[t + FX_UJOINT_STROKE_MID]) / c[t + FX_UJOINT_STROKE_HALF]
            scale = scale * max(1.0 + th[p_uj1 + 2] * xi, 0.0)
        g_u = _ujoint_factor(cos_angle, scale, inv_cos_beta)
        omega_u = g_u * omega_tp
    if flags is not None and flags & ANY_LOAD_FRICTION:
        if flags & LOAD_FRICTION:
            c_ts = c_ts + th[int(c[t + FX_LOAD_FRICTION])] * r * abs(f_er)
        else:  # μ (1 + a) against a load that opposes the motion (M_ER along Ω), μ (1 - a) with one that aids it
            p_ld = int(c[t + FX_LOAD_FRICTION_DIRECTIONAL])
            opposing = sign_tp if -r_scg * f_er > 0.0 else -sign_tp   # at F = 0 the term is 0 anyway
            c_ts = c_ts + th[p_ld] * (1.0 + th[p_ld + 1] * opposing) * r * abs(f_er)
    if flags is not None and flags & ANY_STRIBECK:
        c_ts = c_ts * f_tp
        c_u = c_u * f_tp
    m_er = -r_scg * f_er
    m_tser = b_ts * omega_u + c_ts * sign_tp + m_er
    if flags is not None and flags & ANY_UJOINT:
        m_uer = m_tser * g_u * inv_cos_beta + b_u * omega_u + c_u * sign_tp
    else:
        m_uer = m_tser * inv_cos_beta + b_u * omega_u + c_u * sign_tp
    return omega_u, m_er, m_tser, m_uer


@hook
def nut_contact(flags, x, th, c, t, force1, force2):
    """backlash_output: the load forces that reach the screws (only at a flank of the nut
    play) and the plays' slopes; (force1, force2, 0, 0) unchanged without the effect."""
    if flags is not None and flags & NUT_PLAY:
        p_np = int(c[t + FX_NUT_PLAY])
        x_np = int(c[t + FX_NUT_PLAY + 1])
        if th[p_np] > 0.0:
            softness = c[t + FX_NUT_PLAY_SOFTNESS]
            slope1 = _play_slope(x[x_np], th[p_np], softness)
            slope2 = _play_slope(x[x_np + 1], th[p_np], softness)
            return (1.0 - slope1) * force1, (1.0 - slope2) * force2, slope1, slope2
    return force1, force2, 0.0, 0.0


@hook
def carriage_speeds(flags, x, th, c, t, omega_u1, omega_u2, slope1, slope2, dx):
    """backlash_output: the carriages' speeds in screw radians (the screw's, less its travel
    inside the play), writing the plays' db/dt into ``dx``; the screws' without the effect."""
    if flags is not None and flags & NUT_PLAY:
        p_np = int(c[t + FX_NUT_PLAY])
        x_np = int(c[t + FX_NUT_PLAY + 1])
        if th[p_np] > 0.0:
            softness, relaxation = c[t + FX_NUT_PLAY_SOFTNESS], c[t + FX_NUT_PLAY_RELAXATION]
            b_rate1 = _play_rate(x[x_np], th[p_np], softness, relaxation, omega_u1)
            b_rate2 = _play_rate(x[x_np + 1], th[p_np], softness, relaxation, omega_u2)
            dx[x_np] = b_rate1
            dx[x_np + 1] = b_rate2
            return omega_u1 - slope1 * b_rate1, omega_u2 - slope2 * b_rate2
        dx[x_np] = 0.0
        dx[x_np + 1] = 0.0
    return omega_u1, omega_u2


@njit(cache=True, inline="always", error_model="numpy")
def stations(flags, x, th, c, t, omega_tp1, omega_tp2, terms, contact, p_loss1, p_loss2, r_scg, inv_cos_b1,
             inv_cos_b2, r, position1, position2, dx):
    """Both stations (:func:`station`) and the carriages' speeds (:func:`carriage_speeds`):
    returns M_UER1, M_UER2, the two carriages' speeds in screw radians and the stations'
    outputs for :func:`station_outputs`.

    ``terms`` is the result of :func:`station_terms` for the shafts at ``omega_tp1`` and
    ``omega_tp2``, ``contact`` that of :func:`nut_contact`; station k's losses B_TS, C_TS, B_U,
    C_U sit in that order at ``th[p_lossk:p_lossk + 4]``, its U-joint's 1/cos β is
    ``inv_cos_bk``, its carriage at ``positionk``; ``r_scg`` and ``r`` are the screws' constants of
    :func:`station`. Inlined
    at numba IR level like :func:`transmit`: it only calls hooks, so it has no effect branch of
    its own for numba to translate again at each call site.
    """
    sign_tp1, sign_tp2, cos1, cos2, f_tp1, f_tp2 = terms
    f_er1, f_er2, slope1, slope2 = contact
    omega_u1, m_er1, m_tser1, m_uer1 = station(flags, th, c, t, 1, omega_tp1, sign_tp1, cos1, f_tp1, f_er1,
                                               th[p_loss1], th[p_loss1 + 1], th[p_loss1 + 2], th[p_loss1 + 3],
                                               r_scg, inv_cos_b1, r, position1)
    omega_u2, m_er2, m_tser2, m_uer2 = station(flags, th, c, t, 2, omega_tp2, sign_tp2, cos2, f_tp2, f_er2,
                                               th[p_loss2], th[p_loss2 + 1], th[p_loss2 + 2], th[p_loss2 + 3],
                                               r_scg, inv_cos_b2, r, position2)
    carriage1, carriage2 = carriage_speeds(flags, x, th, c, t, omega_u1, omega_u2, slope1, slope2, dx)
    return m_uer1, m_uer2, carriage1, carriage2, (omega_u1, omega_u2, m_er1, m_er2, m_tser1, m_tser2, m_uer1, m_uer2)


@njit(cache=True, inline="always", error_model="numpy")
def station_outputs(y, i, values):
    """The stations' outputs of :func:`stations` into ``y[i:i + 8]``, in the order both concepts
    list them: Ω_U1, Ω_U2, M_ER1, M_ER2, M_TSER1, M_TSER2, M_UER1, M_UER2."""
    y[i] = values[0]
    y[i + 1] = values[1]
    y[i + 2] = values[2]
    y[i + 3] = values[3]
    y[i + 4] = values[4]
    y[i + 5] = values[5]
    y[i + 6] = values[6]
    y[i + 7] = values[7]


@hook
def motor_torque(flags, th, c, t, theta_m, k_n, torque):
    """The motor torque ``torque`` with the ripple torques (torque_ripple: k_n A sin(n_p θ + φ);
    torque_ripple_harmonics: k_n A (sin(n θ + φ1) + h2 sin(2 n θ + φ2) + h3 sin(3 n θ + φ3));
    torque_ripple_loaded: (k_n A + r M) sin(n_p θ + φ), M = ``torque``)."""
    if flags is not None and flags & ANY_RIPPLE:
        m_ripple = 0.0
        if flags & RIPPLE:
            p_tr = int(c[t + FX_RIPPLE])
            m_ripple = k_n * th[p_tr] * math.sin(c[t + FX_RIPPLE_PERIODS] * theta_m + th[p_tr + 1])
        if flags & HARMONICS:
            p = int(c[t + FX_HARMONICS])
            angle = c[t + FX_HARMONICS_PERIODS] * theta_m
            m_ripple = m_ripple + k_n * th[p] * (math.sin(angle + th[p + 1]) + th[p + 2] * math.sin(2.0 * angle + th[p + 3])
                                                 + th[p + 4] * math.sin(3.0 * angle + th[p + 5]))
        if flags & RIPPLE_LOADED:
            p = int(c[t + FX_RIPPLE_LOADED])
            m_ripple = m_ripple + ((k_n * th[p] + th[p + 2] * torque)
                                   * math.sin(c[t + FX_RIPPLE_LOADED_PERIODS] * theta_m + th[p + 1]))
        return torque + m_ripple
    return torque
