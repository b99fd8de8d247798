"""EMPS concept: the Electro-Mechanical Positioning System benchmark (Janot, Gautier, Brunot
2019), a DC motor driving a ball screw and a load on one prismatic axis, run in closed loop
at 1 kHz. Measured data, not hypothetical: see ``ema_uq.io.read_emps``.

Plant (load side, continuous; the published rigid model)::

    M q̈ = gτ·u(t) - Fv q̇ - Fc sgn(q̇) - offset            sgn = tanh(q̇ / v_eps)

Controller (discrete, sample time dt = 1 ms, the published loop; a P position loop around a
P velocity loop on a backward-difference velocity estimate)::

    qm(k)     = q(t_k)                                       encoder, load side [m]
    qf(k)     = ½ qm(k) + ½ qm(k-1)
    qd_hat(k) = (qf(k) - qf(k-1)) / dt                       [m/s]
    vir(k)    = clip(kv (kp (qg(k) - qm(k)) - qd_hat(k)), ±u_max) + pulse_gain·pulse(k)   [V]
    u(t)      = vir(k-1)  for t in [t_k, t_k+1)              one-sample unit delay

``vir`` is the logged drive command: recomputing it from the measured qm and qg with this
law reproduces the logged value at the same sample k (``tests/unit/test_emps.py``). The
validation record's pulses (``pulse`` input, volts) are part of that logged command, so they
enter the volt channel before the gain gτ and pass through the same delay.

Outputs per sample: ``qm`` [m], ``vir`` [V], ``force`` = gτ·vir [N] (the drive force
command), ``qd_hat`` [m/s] (the controller's velocity estimate) and ``qd`` [m/s] (the true
load velocity at t_k, for comparison with the differentiated measurement).

Between samples the plant is advanced by ``n_sub`` classical RK4 steps with the command
held. The record starts in motion (16 ms into the first stroke), so the initial state is a
set of constants (``q0``, ``qd0``, ``u0``) that :func:`ema_uq.io.read_emps` estimates from
the first samples of each file; their defaults are those of ``DATA_EMPS.mat``.

Unmodelled effects (:data:`EFFECTS`) switch into the same kernel by flags; each has an
``off`` value at which its term vanishes, and the nominal model is the flags-zero path of
the kernel, so an augmented model with every effect at ``off`` reproduces the nominal
outputs bit for bit.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
from numba import njit, prange

from ..params import Parameter, ParameterError, ParameterSet
from .base import KERNEL_IDS, Model
from .effects import Effect, FlaggedSimulator, augment_own_kernel, off_vector

# --- estimated parameters Θ of the nominal model, kernel positions ----------------------
(P_M, P_FV, P_FC, P_OFFSET) = range(4)

# --- effect parameters, positions in the kernel's full parameter vector -----------------
(E_DFV, E_FS, E_VS, E_TAU_A, E_TAU_S, E_LOAD_FRACTION, E_F_RES, E_ZETA_RES) = range(4, 12)
N_FULL = 12

# --- effect flags (bits of the kernel's ``flags`` argument) -----------------------------
F_ASYMMETRIC = 1
F_STRIBECK = 2
F_ACTUATION_DELAY = 4
F_SENSOR_DELAY = 8
F_COMPLIANCE = 16

# --- design constants and settings, kernel positions ------------------------------------
(C_KP, C_KV, C_GTAU, C_U_MAX, C_V_EPS, C_Q0, C_QD0, C_U0, C_PULSE_GAIN) = range(9)

INPUTS = ("qg", "pulse")
REQUIRED_INPUTS = ("qg",)
INPUT_UNITS = {"qg": "m", "pulse": "V"}
OUTPUTS = ("qm", "vir", "force", "qd_hat", "qd")
OUTPUT_UNITS = ("m", "V", "N", "m/s", "m/s")
STATES = ("q", "qd")
COMPLIANCE_STATES = ("q", "qd", "q_load", "qd_load")

#: Published IDIM-LS estimates (value, standard deviation) of the benchmark description,
#: ``Script_IDIM_LS.m`` on ``DATA_EMPS.mat``; also the nominal values below.
PUBLISHED_IDIM_LS = {
    "M": (95.1089, 0.1085),
    "Fv": (203.5034, 1.1460),
    "Fc": (20.3935, 0.1012),
    "offset": (-3.1648, 0.0444),
}
#: Published closed-loop simulation errors with those values, percent (relative 2-norm,
#: samples 50..N, measured position Butterworth-filtered).
PUBLISHED_SIMULATION_ERROR = {
    "estimation": {"position": 0.0138, "velocity": 0.229, "acceleration": 8.60, "force": 5.85},
    "validation": {"position": 0.0080, "velocity": 0.479, "acceleration": 19.8, "force": 8.94},
}

PARAMETERS = ParameterSet((
    Parameter("M", "kg", 95.1089, 1.0, 1000.0, description="moving mass reduced to the load side"),
    Parameter("Fv", "N s/m", 203.5034, 0.0, 2000.0, description="viscous friction coefficient"),
    Parameter("Fc", "N", 20.3935, 0.0, 500.0, description="Coulomb friction force"),
    Parameter("offset", "N", -3.1648, -500.0, 500.0,
              description="constant force offset (drive offset, gravity component, friction asymmetry)"),
))


def _const(name, unit, value, description):
    return Parameter(name, unit, value, -np.inf, np.inf, free=False, description=description)


CONSTANTS = ParameterSet((
    _const("kp", "1/s", 160.18, "position-loop gain (stored in the data files)"),
    _const("kv", "V/(m/s)", 243.45, "velocity-loop gain (stored in the data files)"),
    _const("gtau", "N/V", 35.15065188248547, "drive gain, force per volt (stored in the data files)"),
    _const("u_max", "V", 10.0, "controller output saturation"),
    _const("v_eps", "m/s", 1e-5, "velocity scale of the smoothed sign tanh(v / v_eps) (a model setting)"),
    _const("q0", "m", 7.45e-6, "load position at t = 0 (the record starts in motion)"),
    _const("qd0", "m/s", 6.5e-3, "load velocity at t = 0"),
    _const("u0", "V", 2.5386280888756465, "drive command applied before the first sample (delay memory)"),
    _const("pulse_gain", "1", 1.0, "volts of drive command per volt of the pulse input (the pulse record logs 1.014)"),
))


def derived_constants(c: np.ndarray) -> np.ndarray:
    """EMPS derives nothing from its constants."""
    return np.zeros(0)


# --------------------------------------------------------------------------------------
# the compiled kernel
# --------------------------------------------------------------------------------------
@njit(cache=True, inline="always", error_model="numpy")
def _friction(v, th, c, flags):
    """Friction force [N] at load velocity v [m/s], including the switched-on friction effects."""
    s = math.tanh(v / c[C_V_EPS])
    f = th[P_FV] * v + th[P_FC] * s + th[P_OFFSET]
    if flags & F_ASYMMETRIC:
        # Fv+ = Fv + dFv/2 moving forward, Fv- = Fv - dFv/2 backward; v·s is a smooth |v|
        f += 0.5 * th[E_DFV] * v * s
    if flags & F_STRIBECK:
        r = v / th[E_VS]
        f += th[E_FS] * math.exp(-r * r) * s
    return f


@njit(cache=True, inline="always", error_model="numpy")
def _rigid_segment(x, force, h, n, th, c, flags):
    """Advance the rigid plant x = [q, qd] by n RK4 steps of h [s] under a held drive force [N]."""
    m = th[P_M]
    q = x[0]
    v = x[1]
    for _ in range(n):
        a1 = (force - _friction(v, th, c, flags)) / m
        v2 = v + 0.5 * h * a1
        a2 = (force - _friction(v2, th, c, flags)) / m
        v3 = v + 0.5 * h * a2
        a3 = (force - _friction(v3, th, c, flags)) / m
        v4 = v + h * a3
        a4 = (force - _friction(v4, th, c, flags)) / m
        q += h / 6.0 * (v + 2.0 * v2 + 2.0 * v3 + v4)
        v += h / 6.0 * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
    x[0] = q
    x[1] = v


@njit(cache=True, inline="always", error_model="numpy")
def _compliant_rhs(x, force, th, c, flags, dx):
    """Two-mass plant: motor side (encoder, friction, drive) and load joined by a spring-damper."""
    m_total = th[P_M]
    r = th[E_LOAD_FRACTION]
    m_load = r * m_total
    m_motor = m_total - m_load
    w = 2.0 * math.pi * th[E_F_RES]
    k = m_load * w * w
    d = 2.0 * th[E_ZETA_RES] * m_load * w
    link = k * (x[0] - x[2]) + d * (x[1] - x[3])
    dx[0] = x[1]
    dx[1] = (force - _friction(x[1], th, c, flags) - link) / m_motor
    dx[2] = x[3]
    dx[3] = link / m_load


@njit(cache=True, inline="always", error_model="numpy")
def _compliant_segment(x, force, h, n, th, c, flags, k1, k2, k3, k4, xt):
    for _ in range(n):
        _compliant_rhs(x, force, th, c, flags, k1)
        for i in range(4):
            xt[i] = x[i] + 0.5 * h * k1[i]
        _compliant_rhs(xt, force, th, c, flags, k2)
        for i in range(4):
            xt[i] = x[i] + 0.5 * h * k2[i]
        _compliant_rhs(xt, force, th, c, flags, k3)
        for i in range(4):
            xt[i] = x[i] + h * k3[i]
        _compliant_rhs(xt, force, th, c, flags, k4)
        for i in range(4):
            x[i] += h / 6.0 * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])


@njit(cache=True, error_model="numpy")
def _simulate_one(th, c, flags, qg, pulse, x0, dt, n_sub, out):
    """Closed-loop run of one full parameter vector ``th`` (N_FULL,); writes (n_samples, 5) outputs."""
    n = qg.shape[0]
    compliant = (flags & F_COMPLIANCE) != 0 and th[E_LOAD_FRACTION] > 0.0
    x = np.zeros(4)
    x[0] = x0[0]
    x[1] = x0[1]
    x[2] = x0[0]
    x[3] = x0[1]
    k1 = np.empty(4)
    k2 = np.empty(4)
    k3 = np.empty(4)
    k4 = np.empty(4)
    xt = np.empty(4)
    # controller memory: the record starts in motion, so the past is extrapolated at qd0
    qm_prev = x0[0] - x0[1] * dt
    qf_prev = 0.5 * qm_prev + 0.5 * (x0[0] - 2.0 * x0[1] * dt)
    cmd_prev = c[C_U0]        # vir(k-1)
    cmd_prev2 = c[C_U0]       # vir(k-2)
    q_last = x0[0] - x0[1] * dt
    v_last = x0[1]
    # total command delay in samples: 1 nominal, 1 + tau_a/dt with the actuation-delay effect
    delay = 1.0
    if flags & F_ACTUATION_DELAY:
        delay = 1.0 + th[E_TAU_A] / dt
        delay = min(max(delay, 0.0), 2.0)
    whole = int(math.floor(delay))
    frac = delay - whole
    if whole == 2:
        frac = 0.0
    gtau = c[C_GTAU]
    u_max = c[C_U_MAX]
    h = dt / n_sub
    for k in range(n):
        qm = x[0]
        if (flags & F_SENSOR_DELAY) and th[E_TAU_S] > 0.0:
            # encoder reading taken tau_s before t_k: cubic Hermite between the last two samples
            s = 1.0 - th[E_TAU_S] / dt
            s2 = s * s
            s3 = s2 * s
            qm = ((2.0 * s3 - 3.0 * s2 + 1.0) * q_last + (s3 - 2.0 * s2 + s) * dt * v_last
                  + (-2.0 * s3 + 3.0 * s2) * x[0] + (s3 - s2) * dt * x[1])
        qf = 0.5 * qm + 0.5 * qm_prev
        qd_hat = (qf - qf_prev) / dt
        ctrl = c[C_KV] * (c[C_KP] * (qg[k] - qm) - qd_hat)
        ctrl = min(max(ctrl, -u_max), u_max)
        cmd = ctrl + c[C_PULSE_GAIN] * pulse[k]
        out[k, 0] = qm
        out[k, 1] = cmd
        out[k, 2] = gtau * cmd
        out[k, 3] = qd_hat
        out[k, 4] = x[1]
        qm_prev = qm
        qf_prev = qf
        q_last = x[0]
        v_last = x[1]
        if k == n - 1:
            break
        # command applied over [t_k, t_k+1): vir(k - whole - 1) until t_k + frac·dt, then vir(k - whole)
        if whole == 0:
            first, second = cmd_prev, cmd
        elif whole == 1:
            first, second = cmd_prev2, cmd_prev
        else:
            first, second = cmd_prev2, cmd_prev2
        if compliant:
            if frac > 0.0:
                _compliant_segment(x, gtau * first, frac * h, n_sub, th, c, flags, k1, k2, k3, k4, xt)
                _compliant_segment(x, gtau * second, (1.0 - frac) * h, n_sub, th, c, flags, k1, k2, k3, k4, xt)
            else:
                _compliant_segment(x, gtau * second, h, n_sub, th, c, flags, k1, k2, k3, k4, xt)
        else:
            if frac > 0.0:
                _rigid_segment(x, gtau * first, frac * h, n_sub, th, c, flags)
                _rigid_segment(x, gtau * second, (1.0 - frac) * h, n_sub, th, c, flags)
            else:
                _rigid_segment(x, gtau * second, h, n_sub, th, c, flags)
        cmd_prev2 = cmd_prev
        cmd_prev = cmd


@njit(cache=True, parallel=True, error_model="numpy")
def _simulate_batch(thetas, c, flags, qg, pulse, x0, dt, n_sub, out):
    """Kernel entry: full parameter vectors (n_sets, N_FULL) -> out (n_sets, n_samples, 5)."""
    for s in prange(thetas.shape[0]):
        _simulate_one(thetas[s], c, flags, qg, pulse, x0, dt, n_sub, out[s])


# --------------------------------------------------------------------------------------
# effects
# --------------------------------------------------------------------------------------
#: The unmodelled effects of this rig (``Model.with_effects`` / ``available_effects``).
#: Parameters are named ``<effect>_<short>``; ``off`` makes the effect vanish exactly.
EFFECTS: dict[str, Effect] = {e.name: e for e in (
    Effect(
        "asymmetric_friction",
        "viscous friction different per direction, Fv± = Fv ± dFv/2 (a Coulomb asymmetry acts like the "
        "offset while moving, and the offset is already in the nominal model)",
        (Parameter("asymmetric_friction_dFv", "N s/m", -50.0, -1000.0, 1000.0,
                   description="viscous coefficient forward minus backward"),),
        start={"asymmetric_friction_dFv": -20.0}, off={"asymmetric_friction_dFv": 0.0},
        signature=("direction",)),
    Effect(
        "stribeck",
        "friction above Coulomb near zero speed: Fc + Fs exp(-(v/v_s)²)",
        (Parameter("stribeck_Fs", "N", 5.0, 0.0, 500.0, description="static friction above Coulomb"),
         Parameter("stribeck_v_s", "m/s", 5e-3, 1e-4, 0.1, description="Stribeck velocity")),
        start={"stribeck_Fs": 2.0, "stribeck_v_s": 5e-3}, off={"stribeck_Fs": 0.0, "stribeck_v_s": 5e-3},
        signature=("low_speed", "reversal")),
    Effect(
        "actuation_delay",
        "drive command delay other than the published one-sample unit delay: total delay dt + tau, "
        "between 0 (the command acts in the sample it is computed) and two samples",
        (Parameter("actuation_delay_tau", "s", -5e-4, -1e-3, 1e-3,
                   description="command delay beyond one sample (negative: shorter than one sample)"),),
        start={"actuation_delay_tau": -2e-4}, off={"actuation_delay_tau": 0.0},
        signature=("delay", "high_acceleration")),
    Effect(
        "sensor_delay",
        "the encoder reading lags the load position by tau (cubic Hermite interpolation of the state)",
        (Parameter("sensor_delay_tau", "s", 2e-4, 0.0, 1e-3, description="encoder delay"),),
        start={"sensor_delay_tau": 2e-4}, off={"sensor_delay_tau": 0.0},
        signature=("delay", "high_acceleration")),
    Effect(
        "compliance",
        "part of the mass sits behind a spring-damper (screw, nut, coupling flexibility); encoder, drive "
        "and friction on the motor side; two extra states",
        (Parameter("compliance_load_fraction", "1", 0.3, 0.0, 0.95, description="mass behind the spring / M"),
         Parameter("compliance_f_res", "Hz", 30.0, 2.0, 500.0,
                   description="resonance of that mass on the locked motor side"),
         Parameter("compliance_zeta", "1", 0.1, 1e-3, 2.0, description="damping ratio of that resonance")),
        start={"compliance_load_fraction": 0.2, "compliance_f_res": 30.0, "compliance_zeta": 0.1},
        off={"compliance_load_fraction": 0.0, "compliance_f_res": 30.0, "compliance_zeta": 0.1},
        signature=("high_acceleration", "reversal", "periodic")),
)}

#: kernel flag of each effect
_FLAGS = {"asymmetric_friction": F_ASYMMETRIC, "stribeck": F_STRIBECK, "actuation_delay": F_ACTUATION_DELAY,
          "sensor_delay": F_SENSOR_DELAY, "compliance": F_COMPLIANCE}
#: Kernel position of every parameter name an EMPS model may carry.
_KERNEL_INDEX = {"M": P_M, "Fv": P_FV, "Fc": P_FC, "offset": P_OFFSET,
                 "asymmetric_friction_dFv": E_DFV, "stribeck_Fs": E_FS, "stribeck_v_s": E_VS,
                 "actuation_delay_tau": E_TAU_A, "sensor_delay_tau": E_TAU_S,
                 "compliance_load_fraction": E_LOAD_FRACTION, "compliance_f_res": E_F_RES,
                 "compliance_zeta": E_ZETA_RES}
#: The kernel's full parameter vector with every effect off (base entries overwritten per call).
_OFF_VALUES = off_vector(EFFECTS, _KERNEL_INDEX, N_FULL)


@dataclass(frozen=True)
class BatchSimulator(FlaggedSimulator):
    """The EMPS simulator bound to a set of switched-on effects (``Model.batch_simulator``).

    Called by :func:`ema_uq.simulate.simulate_batch` as
    ``simulator(model, thetas, inputs, kernel_constants, x0, dt, n_sub)`` with thetas
    (n_sets, n_params) in ``model.parameters`` order and inputs (n_samples, 2) = [qg [m],
    pulse [V]]; returns (n_sets, n_samples, 5) outputs. ``x0`` = [q, qd] overrides the
    constants ``q0``, ``qd0`` when given.
    """

    RIG = "EMPS"
    FLAGS = _FLAGS
    KERNEL_INDEX = _KERNEL_INDEX
    OFF_VALUES = _OFF_VALUES

    def __call__(self, model: Model, thetas: np.ndarray, inputs: np.ndarray, constants: np.ndarray,
                 x0: np.ndarray | None, dt: float, n_sub: int) -> np.ndarray:
        full = self.full_vectors(model, np.atleast_2d(thetas))
        c = np.ascontiguousarray(constants, dtype=np.float64)
        if x0 is None:
            start = np.array([c[C_Q0], c[C_QD0]])
        else:
            start = np.asarray(x0, dtype=np.float64).ravel()[:2]
            if start.size != 2:
                raise ParameterError(f"EMPS initial state needs [q, qd], got {np.asarray(x0).shape}")
        qg = np.ascontiguousarray(inputs[:, 0])
        pulse = np.ascontiguousarray(inputs[:, 1])
        out = np.empty((full.shape[0], qg.size, len(OUTPUTS)))
        _simulate_batch(full, c, np.int64(self.flags), qg, pulse, start, float(dt), int(n_sub), out)
        return out


def augment(model: Model, names: Sequence[str], values: Mapping[str, float] | None = None) -> Model:
    """The EMPS model with the named effects switched on (``Model.augment`` of this concept,
    called by ``Model.with_effects``; :func:`~ema_uq.models.effects.augment_own_kernel`)."""
    names = tuple(names)
    return augment_own_kernel(model, names, values, catalogue=EFFECTS, rig="EMPS", simulator=BatchSimulator(names),
                              states=COMPLIANCE_STATES if "compliance" in names else STATES)

MODEL = Model(
    name="emps", model_id=KERNEL_IDS["emps"][0], title="EMPS (ball-screw positioning benchmark, measured)",
    states=STATES, outputs=OUTPUTS, output_units=OUTPUT_UNITS,
    parameters=PARAMETERS, constants=CONSTANTS, derive=derived_constants, integration_step=1e-4,
    inputs=INPUTS, required_inputs=REQUIRED_INPUTS, batch_simulator=BatchSimulator(),
    sensor_sets={"full": OUTPUTS}, effect_catalogue=EFFECTS, augment=augment,
)


def constants_for(measurement, overrides: Mapping[str, float] | None = None) -> np.ndarray:
    """Constants vector for one EMPS record: the gains and initial state the reader stored in
    ``measurement.attrs`` (kp, kv, gtau, q0, qd0, u0), then ``overrides``."""
    values = {k: float(measurement.attrs[k]) for k in ("kp", "kv", "gtau", "q0", "qd0", "u0")
              if k in measurement.attrs}
    values.update(overrides or {})
    return CONSTANTS.vector(values)


def reference_trajectory(strokes: int = 2, *, distance: float = 0.2, v_max: float = 0.1247,
                         a_max: float = 0.842, dwell: float = 0.3, dt: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """An EMPS-like reference (time (n,) [s], qg (n,) [m]): ``strokes`` back-and-forth moves of
    ``distance`` [m] with bang-bang acceleration ±a_max [m/s²] capped at ±v_max [m/s] (the
    benchmark's trapezoidal velocity profile), separated by ``dwell`` [s] at rest."""
    t_acc = v_max / a_max
    d_acc = 0.5 * a_max * t_acc ** 2
    if distance <= 2 * d_acc:  # triangular profile: never reaches v_max
        t_acc = math.sqrt(distance / a_max)
        v_max = a_max * t_acc
        d_acc = 0.5 * distance
    t_move = 2 * t_acc + (distance - 2 * d_acc) / v_max
    period = t_move + dwell
    n = int(round((dwell + strokes * period) / dt)) + 1
    time = np.arange(n) * dt
    qg = np.zeros(n)
    for i, t in enumerate(time):
        k = int((t - dwell) // period) if t >= dwell else -1
        if k < 0:
            continue
        k = min(k, strokes - 1)
        tau = min(t - dwell - k * period, t_move)
        if tau < t_acc:
            s = 0.5 * a_max * tau ** 2
        elif tau < t_move - t_acc:
            s = d_acc + v_max * (tau - t_acc)
        else:
            s = distance - 0.5 * a_max * (t_move - tau) ** 2
        qg[i] = s if k % 2 == 0 else distance - s
    return time, qg


def controller_output(qm: np.ndarray, qg: np.ndarray, kp: float, kv: float, dt: float,
                      pulse: np.ndarray | None = None, u_max: float = 10.0) -> tuple[np.ndarray, np.ndarray]:
    """The published control law applied to measured signals: (vir [V], qd_hat [m/s]), each (n,).

    ``qm``, ``qg`` (n,) [m]; the first two samples use qm(-1) = qm(-2) = qm(0) (unknown past).
    """
    qm = np.asarray(qm, dtype=float)
    past = np.concatenate([[qm[0]], qm[:-1]])
    qf = 0.5 * qm + 0.5 * past
    qf_past = np.concatenate([[qf[0]], qf[:-1]])
    qd_hat = (qf - qf_past) / dt
    vir = np.clip(kv * (kp * (np.asarray(qg, dtype=float) - qm) - qd_hat), -u_max, u_max)
    if pulse is not None:
        vir = vir + np.asarray(pulse, dtype=float)
    return vir, qd_hat
