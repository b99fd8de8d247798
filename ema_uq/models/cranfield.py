"""Cranfield concept: the linear ball-screw actuator rig of Ruiz-Carcel and Starr (Cranfield
University, 2018) with seeded faults, measured at 25 Hz. Measured data, not hypothetical: see
``ema_uq.io.read_cranfield``.

The rig: a stepper motor turns a 5 mm-lead ball screw with a preloaded (anti-backlash) nut; a
second, force-controlled actuator loads the carriage with 20, 40 or -40 kgf; a linear
potentiometer measures the carriage, a Hall sensor the drive current. The set point is a
trapezoid (120 mm in 5 s, 3 s dwell at the top, immediate reversal at the bottom).

Position loop (discrete, sample time dt = 40 ms; what the records show: the carriage
overshoots the stopping set point by about 4 mm and creeps back, so the loop has integral
action and no feed-forward, yet it starts every up stroke from rest, so the integrator
restarts when the set point reverses)::

    e(k)   = x_sp(k) - x_n(k)                                  potentiometer error [m]
    I(k)   = I(k-1) + e(k) dt,   I = 0 when sgn(x_sp(k+1) - x_sp(k)) reverses
    u(k)   = kp e(k) + ki I(k)                                 speed command [m/s]

Drive and carriage (continuous, the command held over [t_k, t_k+1), exact steps)::

    tau v̇_m = u - v_m,   ẋ_m = v_m                             motor side, referred to the carriage
    x_n = x_m                                                   nut = motor side (no play)

Drive current (a stepper driver draws a standstill current, a running current while it
steps and a share that grows with the mechanical power it delivers; the current follows the
commanded step rate u at once, the carriage follows it with the lag tau)::

    i = i_rest + i_run tanh(|u| / v_run) + k_w g ((C + mu |F_load|) |u| + B u² - F_load u)

with |u| smoothed as u tanh(u / v_eps) and g = 1 (the share of the sample interval in which
the nut is driven; below 1 only with ``backlash``). A current sample is the current of the
interval its command u(k) acts over. ``F_load`` [N] is positive when it pushes the carriage
towards larger set point (the records show it: a positive load lowers the current of the up
stroke and raises that of the down stroke). ``k_w`` [A/W] converts power into current (the
inverse of an effective supply voltage), so the loss terms are forces: C [N] is the
speed-proportional loss as an equivalent Coulomb friction (screw, nut, guides and the
driver's own speed-dependent losses, which one speed profile cannot tell apart), mu [1]
its growth with the load, B [N s/m] the quadratic term (negative on this rig: the current
falls at higher step rates, as a stepper's back-EMF limits it).

Outputs per sample: ``position`` x_n [m], ``position_error`` x_sp - x_n [m], ``current``
[A] and ``velocity`` v_n [m/s] (the nut speed, for regime masks). Each record starts at rest
on the set point (``x_n = x_m = x_sp(0)``, v = 0, I = 0).

Unmodelled effects (:data:`EFFECTS`) switch into the same kernel by flags; at their ``off``
values the kernel reproduces the nominal outputs bit for bit.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import Mapping, Sequence

import numpy as np
from numba import njit, prange

from ..params import Parameter, ParameterError, ParameterSet
from .base import KERNEL_IDS, Model
from .effects import Effect, EffectError

#: standard gravity [m/s²]: the records give the load in kgf
G0 = 9.80665

# --- estimated parameters Θ of the nominal model, kernel positions ----------------------
(P_KP, P_KI, P_TAU, P_I_REST, P_I_RUN, P_K_W, P_C, P_MU, P_B) = range(9)

# --- effect parameters, positions in the kernel's full parameter vector -----------------
(E_PLAY, E_DC, E_DB, E_MU, E_GAIN) = range(9, 14)
N_FULL = 14

# --- effect flags (bits of the kernel's ``flags`` argument) -----------------------------
F_BACKLASH = 1
F_FRICTION = 2
F_LOAD_FRICTION = 4
F_CURRENT_GAIN = 8

# --- design constants and settings, kernel positions ------------------------------------
(C_V_RUN, C_V_EPS) = range(2)

INPUTS = ("x_sp", "F_load")
REQUIRED_INPUTS = ("x_sp", "F_load")
INPUT_UNITS = {"x_sp": "m", "F_load": "N"}
OUTPUTS = ("position", "position_error", "current", "velocity")
OUTPUT_UNITS = ("m", "m", "A", "m/s")
STATES = ("x_m", "v_m", "integral", "x_n")
#: sample time of the records [s]
SAMPLE_TIME = 0.04

PARAMETERS = ParameterSet((
    Parameter("kp", "1/s", 3.9, 0.0, 50.0, description="position-loop proportional gain (speed command per metre of error)"),
    Parameter("ki", "1/s²", 9.6, 0.0, 200.0, description="position-loop integral gain"),
    Parameter("tau", "s", 0.016, 1e-3, 1.0, description="time constant of the carriage speed following the command"),
    Parameter("i_rest", "A", 0.35, -5.0, 5.0, description="drive current at standstill"),
    Parameter("i_run", "A", -0.16, -5.0, 5.0, description="extra drive current while the motor steps"),
    Parameter("k_w", "A/W", 0.023, 1e-4, 1.0, description="drive current per watt of mechanical power (1 / effective supply voltage)"),
    Parameter("C", "N", 2900.0, 0.0, 1e4, description="speed-proportional loss as an equivalent Coulomb friction"),
    Parameter("mu", "1", 0.4, -5.0, 5.0, description="growth of that loss with the load, C + mu |F_load|"),
    Parameter("B", "N s/m", -7e4, -1e6, 1e6,
              description="quadratic speed term as an equivalent viscous friction (negative: the stepper current falls at high step rates)"),
))


def _const(name, unit, value, description):
    return Parameter(name, unit, value, -np.inf, np.inf, free=False, description=description)


CONSTANTS = ParameterSet((
    _const("v_run", "m/s", 2e-3, "speed scale of the running-current switch tanh(|v| / v_run) (a model setting)"),
    _const("v_eps", "m/s", 1e-4, "speed scale of the smoothed |v| = v tanh(v / v_eps) (a model setting)"),
))


def derived_constants(c: np.ndarray) -> np.ndarray:
    """The concept derives nothing from its constants."""
    return np.zeros(0)


# --------------------------------------------------------------------------------------
# the compiled kernel
# --------------------------------------------------------------------------------------
@njit(cache=True, inline="always", error_model="numpy")
def _current(u, driven, load, th, c, flags):
    """Drive current [A] at commanded speed u [m/s] under load [N]; ``driven`` in [0, 1] is the
    share of the interval in which the nut is driven (friction and load draw power only then)."""
    abs_u = u * math.tanh(u / c[C_V_EPS])
    coulomb = th[P_C] + th[P_MU] * abs(load)
    viscous = th[P_B]
    if flags & F_FRICTION:
        coulomb += th[E_DC]
        viscous += th[E_DB]
    if flags & F_LOAD_FRICTION:
        coulomb += th[E_MU] * abs(load)
    power = coulomb * abs_u + viscous * u * u - load * u
    i = th[P_I_REST] + th[P_I_RUN] * math.tanh(abs_u / c[C_V_RUN]) + th[P_K_W] * driven * power
    if flags & F_CURRENT_GAIN:
        i *= 1.0 + th[E_GAIN]
    return i


@njit(cache=True, error_model="numpy")
def _simulate_one(th, c, flags, x_sp, load, dt, n_sub, out):
    """Closed-loop run of one full parameter vector ``th`` (N_FULL,); writes (n_samples, 4) outputs."""
    n = x_sp.shape[0]
    half_play = 0.5 * th[E_PLAY] if flags & F_BACKLASH else 0.0
    x_m = x_sp[0]
    x_n = x_sp[0]
    v_m = 0.0
    v_n = 0.0
    integral = 0.0
    last_direction = 0.0
    driven = 1.0
    h = dt / n_sub
    tau = th[P_TAU]
    decay = math.exp(-h / tau)
    for k in range(n):
        e = x_sp[k] - x_n
        # the loop restarts its integrator when the set point reverses (a new stroke)
        step = x_sp[k + 1] - x_sp[k] if k < n - 1 else 0.0
        direction = 1.0 if step > 0.0 else (-1.0 if step < 0.0 else 0.0)
        if direction != 0.0:
            if last_direction != 0.0 and direction != last_direction:
                integral = 0.0
            last_direction = direction
        integral += e * dt
        u = th[P_KP] * e + th[P_KI] * integral
        out[k, 0] = x_n
        out[k, 1] = e
        out[k, 3] = v_n
        if k == n - 1:
            out[k, 2] = _current(u, driven, load[k], th, c, flags)
            break
        pushed = 0
        for _ in range(n_sub):
            x_m += u * h + (v_m - u) * tau * (1.0 - decay)
            v_m = u + (v_m - u) * decay
            if half_play > 0.0:
                # play operator: the nut moves only when a flank of the play pushes it
                previous = x_n
                x_n = min(max(x_n, x_m - half_play), x_m + half_play)
                if x_n != previous:
                    v_n = v_m
                    pushed += 1
                else:
                    v_n = 0.0
            else:
                x_n = x_m
                v_n = v_m
        driven = pushed / n_sub if half_play > 0.0 else 1.0
        out[k, 2] = _current(u, driven, load[k], th, c, flags)


@njit(cache=True, parallel=True, error_model="numpy")
def _simulate_batch(thetas, c, flags, x_sp, load, dt, n_sub, out):
    """Kernel entry: full parameter vectors (n_sets, N_FULL) -> out (n_sets, n_samples, 4)."""
    for s in prange(thetas.shape[0]):
        _simulate_one(thetas[s], c, flags, x_sp, load, dt, n_sub, out[s])


# --------------------------------------------------------------------------------------
# effects
# --------------------------------------------------------------------------------------
#: The unmodelled effects of this rig (``Model.with_effects`` / ``available_effects``), the
#: seeded faults and plausible alternatives a diagnosis must tell them from. Parameters are
#: named ``<effect>_<short>``; ``off`` makes the effect vanish exactly.
EFFECTS: dict[str, Effect] = {e.name: e for e in (
    Effect(
        "backlash",
        "lost motion in the nut (balls smaller than the groove): the nut follows the screw through a play "
        "of total width b, so after a reversal the motor travels b before the carriage moves, the "
        "potentiometer loop lags by up to b and no friction or load power is drawn while the play is crossed",
        (Parameter("backlash_play", "m", 5e-4, 0.0, 5e-3, description="total axial play (lost motion) of the nut"),),
        start={"backlash_play": 1e-4}, off={"backlash_play": 0.0},
        signature=("reversal", "direction", "low_speed")),
    Effect(
        "friction_increase",
        "more Coulomb and viscous friction in screw and nut (lost lubrication, a tightened seal): "
        "C + dC, B + dB; it raises the current while moving and leaves the position loop alone",
        (Parameter("friction_increase_dC", "N", 100.0, -5e3, 5e3, description="added Coulomb friction"),
         Parameter("friction_increase_dB", "N s/m", 0.0, -1e5, 1e5, description="added viscous friction")),
        start={"friction_increase_dC": 20.0, "friction_increase_dB": 0.0},
        off={"friction_increase_dC": 0.0, "friction_increase_dB": 0.0},
        signature=("high_load", "direction")),
    Effect(
        "load_dependent_friction",
        "Coulomb friction growing with the carried load (ball-contact friction): C + mu |F_load|",
        (Parameter("load_dependent_friction_mu", "1", 0.05, 0.0, 2.0, description="load coefficient of the Coulomb friction"),),
        start={"load_dependent_friction_mu": 0.005}, off={"load_dependent_friction_mu": 0.0},
        signature=("high_load", "direction")),
    Effect(
        "current_gain",
        "drift of the Hall current sensor: every current sample scaled by 1 + g (standstill current included)",
        (Parameter("current_gain_error", "1", 0.05, -0.5, 0.5, description="relative gain error of the current sensor"),),
        start={"current_gain_error": 0.01}, off={"current_gain_error": 0.0},
        signature=("high_load",)),
)}

#: kernel flag of each effect
_FLAGS = {"backlash": F_BACKLASH, "friction_increase": F_FRICTION, "load_dependent_friction": F_LOAD_FRICTION,
          "current_gain": F_CURRENT_GAIN}
#: Kernel position of every parameter name a Cranfield model may carry.
_KERNEL_INDEX = {"kp": P_KP, "ki": P_KI, "tau": P_TAU, "i_rest": P_I_REST, "i_run": P_I_RUN, "k_w": P_K_W,
                 "C": P_C, "mu": P_MU, "B": P_B, "backlash_play": E_PLAY, "friction_increase_dC": E_DC,
                 "friction_increase_dB": E_DB, "load_dependent_friction_mu": E_MU, "current_gain_error": E_GAIN}
#: The kernel's full parameter vector with every effect off (base entries overwritten per call).
_OFF_VALUES = np.zeros(N_FULL)
for _effect in EFFECTS.values():
    for _name, _value in _effect.off.items():
        _OFF_VALUES[_KERNEL_INDEX[_name]] = _value


@dataclass(frozen=True)
class BatchSimulator:
    """The Cranfield simulator bound to a set of switched-on effects (``Model.batch_simulator``).

    Called by :func:`ema_uq.simulate.simulate_batch` as
    ``simulator(model, thetas, inputs, kernel_constants, x0, dt, n_sub)`` with thetas
    (n_sets, n_params) in ``model.parameters`` order and inputs (n_samples, 2) = [x_sp [m],
    F_load [N]]; returns (n_sets, n_samples, 4) outputs. Every record starts at rest on its
    set point, so ``x0`` must be None.
    """

    effects: tuple[str, ...] = ()

    @property
    def flags(self) -> int:
        return int(sum(_FLAGS[name] for name in self.effects))

    def full_vectors(self, model: Model, thetas: np.ndarray) -> np.ndarray:
        try:
            index = np.array([_KERNEL_INDEX[name] for name in model.parameters.names], dtype=np.int64)
        except KeyError as exc:
            raise EffectError(f"parameter {exc.args[0]!r} has no place in the Cranfield kernel") from None
        full = np.repeat(_OFF_VALUES[None, :], thetas.shape[0], axis=0)
        full[:, index] = thetas
        return full

    def __call__(self, model: Model, thetas: np.ndarray, inputs: np.ndarray, constants: np.ndarray,
                 x0: np.ndarray | None, dt: float, n_sub: int) -> np.ndarray:
        if x0 is not None:
            raise ParameterError("the Cranfield model starts every record at rest on its set point; give no x0")
        full = self.full_vectors(model, np.atleast_2d(thetas))
        c = np.ascontiguousarray(constants, dtype=np.float64)
        x_sp = np.ascontiguousarray(inputs[:, 0])
        load = np.ascontiguousarray(inputs[:, 1])
        out = np.empty((full.shape[0], x_sp.size, len(OUTPUTS)))
        _simulate_batch(full, c, np.int64(self.flags), x_sp, load, float(dt), int(n_sub), out)
        return out


def augment(model: Model, names: Sequence[str], values: Mapping[str, float] | None = None) -> Model:
    """The Cranfield model with the named effects switched on (``Model.augment`` of this concept,
    called by ``Model.with_effects``, which checks the names): the nominal parameters followed
    by each effect's, at the effect's nominal values overridden by ``values`` (full names).

    An effect at its ``off`` values reproduces the nominal outputs bit for bit.
    """
    base = model.base_model
    names = tuple(names)
    unknown = [n for n in names if n not in EFFECTS]
    if unknown:
        raise EffectError(f"unknown Cranfield effect(s) {', '.join(unknown)}; choose from {', '.join(EFFECTS)}")
    parameters = base.parameters + ParameterSet(tuple(p for n in names for p in EFFECTS[n].parameters))
    if values:
        parameters = parameters.with_nominal(values)
        parameters.check_within_bounds(parameters.nominal, what="effect value")
    return replace(base, title=f"{base.title} + {' + '.join(names)}", parameters=parameters, effects=names,
                   batch_simulator=BatchSimulator(names), built_from=base)


MODEL = Model(
    name="cranfield", model_id=KERNEL_IDS["cranfield"][0], title="Cranfield linear actuator (stepper ball screw, measured)",
    states=STATES, outputs=OUTPUTS, output_units=OUTPUT_UNITS,
    parameters=PARAMETERS, constants=CONSTANTS, derive=derived_constants, integration_step=SAMPLE_TIME / 8,
    inputs=INPUTS, required_inputs=REQUIRED_INPUTS, batch_simulator=BatchSimulator(),
    sensor_sets={"full": OUTPUTS, "rig": ("position_error", "current")}, effect_catalogue=EFFECTS, augment=augment,
)
