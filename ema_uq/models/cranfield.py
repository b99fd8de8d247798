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

The drive is taken as rigid. A stepper lags its commanded angle by T_load / K_h and the screw
and nut are elastic, so a compliant drive, x_n = x_m - c_drive sgn(u) F_d (F_d below), would
pass every change of the delivered force into the position error. It was tested on the healthy
records and is not in the model: the ML fit (det R) of c_drive >= 0 beside the other base
parameters on runs 1-5 of normal.csv (every load, 24 300 samples) puts it on its bound 0
(ΔBIC -10, the parameter penalty alone; log-likelihood gain on runs 6-10 +0.3), and the
estimation log-likelihood falls monotonically as c_drive grows (-170 at 3e-7 m/N, -600 at
1e-6 m/N, where 400 N would deflect 0.1 and 0.4 mm). The mean position error while moving
moves by less than 0.02 mm between -40 and +40 kgf (runs 1-10), and in opposite directions on
the up and down strokes, where a spring would shift both alike. So a position-error change of
a faulted set has no path in this model from a force change.

Drive current (a stepper driver draws a standstill current, a running current while it
steps, losses of its own that grow with the step rate, and a share for the force it
delivers; the current follows the commanded step rate u at once, the carriage follows it
with the lag tau)::

    i = i_rest + i_run tanh(|u| / v_run) + k_1 |u| + k_2 u² + k_w g(u) d F_d
    g(u) = |u| (1 + |u| / v_p),      F_d = mu |F_load| - F_load sgn(u)

with |u| and sgn(u) smoothed by tanh(u / v_eps), and d = 1 (the share of the sample interval
in which the nut is driven; below 1 only with ``backlash``). ``F_d`` [N] is the force the
drive delivers beyond the unloaded rig's own losses: the load and the friction that grows
with it (and the friction changes of the effects below). An added force shows in the current as g(u): power-like at low speed and growing
faster above v_p (the records show it: the current change of a load step at 7 mm/s is 0.17
of that at 24 mm/s). The unloaded rig's friction is not separable from the driver's own
speed-dependent losses on one speed profile; both sit in k_1 and k_2. A current sample is
the current of the interval its command u(k) acts over. ``F_load`` [N] is positive when it
pushes the carriage towards larger set point (a positive load lowers the current of the up
stroke and raises that of the down stroke).

Outputs per sample: ``position`` x_n [m], ``position_error`` x_sp - x_n [m], ``current``
[A] and ``velocity`` v_n [m/s] (the nut speed, for regime masks). Each record starts at rest
on the set point (``x_n = x_m = x_sp(0)``, v = 0, I = 0).

Unmodelled effects (:data:`EFFECTS`) switch into the same kernel by flags; at their ``off``
values the kernel reproduces the nominal outputs bit for bit. One mechanism per candidate, each
its own family, no candidate carrying another's parameters, each parameter bounded by its
physics:

- ``backlash``: play of total width b >= 0 between screw and nut, nothing else (lost motion
  at a reversal, and no force delivered while the play is crossed);
- ``contact_friction``: a change of the ball-contact friction, which scales with the normal
  load on the balls, preload + |F_load|; signed (lost preload lowers it, a damaged track
  raises it), one coefficient per load sense, since the two senses bear on opposite flanks of
  the ball track;
- ``lubrication_loss``: more friction in the lubricated ball contact, only ever higher: a
  Coulomb drag >= 0 per load sense (the loaded flank carries the grease film that thins) and
  a viscous drag >= 0 growing with the speed;
- ``seal_drag``: a wiper seal rubbing on the screw: a drag >= 0 that knows neither the load
  nor its sense (one value for both, no speed term). It is a special case of
  ``lubrication_loss`` (equal Coulomb drags, no viscous part) and is kept as a candidate of
  its own because the load-sense symmetry is a physical distinction the records can test:
  where both senses change alike the one-parameter form wins on BIC, where they do not it
  fails;
- ``current_gain``, ``current_offset``: drift of the Hall current sensor's gain and zero.

The per-load-sense values rest on the flank argument above; the records are consistent with
it (in every fault set the moving current changes by 0.04-0.26 A under +20 and +40 kgf and by
at most 0.015 A under -40 kgf, per-run means), and that asymmetry is also what sets
``seal_drag`` apart from ``lubrication_loss`` on them.
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

#: standard gravity [m/s²]: the records give the load in kgf
G0 = 9.80665

# --- estimated parameters Θ of the nominal model, kernel positions ----------------------
(P_KP, P_KI, P_TAU, P_I_REST, P_I_RUN, P_K1, P_K2, P_K_W, P_V_P, P_MU) = range(10)

# --- effect parameters, positions in the kernel's full parameter vector -----------------
(E_PLAY, E_CMU_POS, E_CMU_NEG, E_DC_POS, E_DC_NEG, E_CV, E_SEAL, E_GAIN, E_OFFSET) = range(10, 19)
N_FULL = 19

# --- effect flags (bits of the kernel's ``flags`` argument) -----------------------------
F_BACKLASH = 1
F_CONTACT = 2
F_LUBRICATION = 4
F_SEAL = 8
F_CURRENT_GAIN = 16
F_CURRENT_OFFSET = 32

# --- design constants and settings, kernel positions ------------------------------------
(C_V_RUN, C_V_EPS, C_PRELOAD) = range(3)

INPUTS = ("x_sp", "F_load")
REQUIRED_INPUTS = ("x_sp", "F_load")
INPUT_UNITS = {"x_sp": "m", "F_load": "N"}
OUTPUTS = ("position", "position_error", "current", "velocity")
OUTPUT_UNITS = ("m", "m", "A", "m/s")
STATES = ("x_m", "v_m", "integral", "x_n")
#: sample time of the records [s]
SAMPLE_TIME = 0.04

#: Nominal values: the ML fit (det R, position error and current) on runs 1-5 of every load of
#: the healthy records (normal.csv), rounded to four digits.
PARAMETERS = ParameterSet((
    Parameter("kp", "1/s", 3.867, 0.0, 50.0, description="position-loop proportional gain (speed command per metre of error)"),
    Parameter("ki", "1/s²", 9.598, 0.0, 200.0, description="position-loop integral gain"),
    Parameter("tau", "s", 0.01474, 1e-3, 1.0, description="time constant of the carriage speed following the command"),
    Parameter("i_rest", "A", 0.3511, -5.0, 5.0, description="drive current at standstill"),
    Parameter("i_run", "A", -0.1577, -5.0, 5.0, description="extra drive current while the motor steps"),
    Parameter("k_1", "A s/m", 66.64, -1e4, 1e4, description="driver current per step rate (its own losses and the unloaded friction)"),
    Parameter("k_2", "A s²/m²", -1653.0, -1e6, 1e6,
              description="quadratic step-rate term (negative: the stepper current falls at high step rates)"),
    Parameter("k_w", "A/W", 0.01773, 1e-4, 1.0, description="current per watt of delivered force at low speed"),
    Parameter("v_p", "m/s", 0.08130, 1e-3, 10.0, description="speed above which a delivered force costs more than power-like"),
    Parameter("mu", "1", 0.3647, -5.0, 5.0, description="friction growing with the load, mu |F_load|"),
))


def _const(name, unit, value, description):
    return Parameter(name, unit, value, -np.inf, np.inf, free=False, description=description)


CONSTANTS = ParameterSet((
    _const("v_run", "m/s", 2e-3, "speed scale of the running-current switch tanh(|v| / v_run) (a model setting)"),
    _const("v_eps", "m/s", 1e-4, "speed scale of the smoothed |v| = v tanh(v / v_eps) (a model setting)"),
    _const("preload", "N", 230.0, "preload of the ball nut: 3 % of the dynamic load rating of an RM1605 nut (7.65 kN), "
           "the middle of the usual 2-5 % of a light preload"),
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
    share of the interval in which the nut is driven (it delivers force only then)."""
    sign = math.tanh(u / c[C_V_EPS])
    abs_u = u * sign
    force = th[P_MU] * abs(load) - load * sign
    # a change in the nut may differ with the load's sign (the two flanks of the ball track)
    side = 0 if load >= 0.0 else 1
    if flags & F_CONTACT:
        force += th[E_CMU_POS + side] * (c[C_PRELOAD] + abs(load))
    if flags & F_LUBRICATION:
        force += th[E_DC_POS + side] + th[E_CV] * abs_u
    if flags & F_SEAL:
        force += th[E_SEAL]
    shape = abs_u * (1.0 + abs_u / th[P_V_P])
    i = (th[P_I_REST] + th[P_I_RUN] * math.tanh(abs_u / c[C_V_RUN]) + th[P_K1] * abs_u + th[P_K2] * u * u
         + th[P_K_W] * driven * shape * force)
    if flags & F_CURRENT_GAIN:
        i *= 1.0 + th[E_GAIN]
    if flags & F_CURRENT_OFFSET:
        i += th[E_OFFSET]
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
        "play between screw and nut (undersized balls in the preloaded nut): the nut follows the screw through "
        "a play of total width b, so after a reversal the motor travels b before the carriage moves, the "
        "potentiometer loop lags by up to b, and no force is delivered while the play is crossed; it shows "
        "first in the position error at the reversals",
        (Parameter("backlash_play", "m", 5e-4, 0.0, 5e-3, description="total axial play (lost motion) of the nut"),),
        start={"backlash_play": 1e-4}, off={"backlash_play": 0.0},
        signature=("reversal", "direction", "low_speed")),
    Effect(
        "contact_friction",
        "a change of the ball-contact friction (lost preload lowers it, a worn or pitted track raises it): "
        "the friction coefficient of the balls changes by dmu_pos under a positive load and dmu_neg under a "
        "negative one (the two senses bear on opposite flanks of the track), acting on the normal load of the "
        "balls, preload + |F_load|; it raises or lowers the moving current and leaves the position loop alone; "
        "|dmu| <= 1, since a sliding steel-on-steel friction coefficient stays below 1 even dry",
        (Parameter("contact_friction_dmu_pos", "1", 0.0, -1.0, 1.0,
                   description="change of the ball-contact friction coefficient, positive load"),
         Parameter("contact_friction_dmu_neg", "1", 0.0, -1.0, 1.0,
                   description="change of the ball-contact friction coefficient, negative load")),
        start={"contact_friction_dmu_pos": 0.05, "contact_friction_dmu_neg": 0.05},
        off={"contact_friction_dmu_pos": 0.0, "contact_friction_dmu_neg": 0.0},
        signature=("high_load", "direction")),
    Effect(
        "lubrication_loss",
        "lost lubrication of the ball contact: a Coulomb drag dC_pos >= 0 under a positive load and dC_neg >= 0 "
        "under a negative one (the loaded flank's grease film thins) plus a viscous drag c_v |v| >= 0; only ever "
        "more friction, whatever the load; it raises the moving current and leaves the position loop alone",
        (Parameter("lubrication_loss_dC_pos", "N", 100.0, 0.0, 5e3, description="added Coulomb drag under a positive load"),
         Parameter("lubrication_loss_dC_neg", "N", 100.0, 0.0, 5e3, description="added Coulomb drag under a negative load"),
         Parameter("lubrication_loss_c_v", "N s/m", 1e3, 0.0, 1e6, description="added viscous drag per carriage speed")),
        start={"lubrication_loss_dC_pos": 20.0, "lubrication_loss_dC_neg": 20.0, "lubrication_loss_c_v": 200.0},
        off={"lubrication_loss_dC_pos": 0.0, "lubrication_loss_dC_neg": 0.0, "lubrication_loss_c_v": 0.0},
        signature=("high_load", "direction")),
    Effect(
        "seal_drag",
        "a wiper seal rubbing on the screw: a drag dC >= 0 the drive delivers while moving, the same under any "
        "load and either load sense, independent of the speed",
        (Parameter("seal_drag_dC", "N", 100.0, 0.0, 5e3, description="added drag of the seal"),),
        start={"seal_drag_dC": 20.0}, off={"seal_drag_dC": 0.0},
        signature=("direction",)),
    Effect(
        "current_gain",
        "drift of the Hall current sensor's gain: every current sample scaled by 1 + g (standstill current included)",
        (Parameter("current_gain_error", "1", 0.05, -0.5, 0.5, description="relative gain error of the current sensor"),),
        start={"current_gain_error": 0.01}, off={"current_gain_error": 0.0},
        signature=("high_load",)),
    Effect(
        "current_offset",
        "drift of the Hall current sensor's zero: every current sample shifted by di (standstill current included)",
        (Parameter("current_offset_di", "A", 0.02, -1.0, 1.0, description="offset of the current sensor"),),
        start={"current_offset_di": 0.01}, off={"current_offset_di": 0.0},
        signature=("low_speed",)),
)}

#: kernel flag of each effect
_FLAGS = {"backlash": F_BACKLASH, "contact_friction": F_CONTACT, "lubrication_loss": F_LUBRICATION,
          "seal_drag": F_SEAL, "current_gain": F_CURRENT_GAIN, "current_offset": F_CURRENT_OFFSET}
#: Kernel position of every parameter name a Cranfield model may carry.
_KERNEL_INDEX = {"kp": P_KP, "ki": P_KI, "tau": P_TAU, "i_rest": P_I_REST, "i_run": P_I_RUN, "k_1": P_K1,
                 "k_2": P_K2, "k_w": P_K_W, "v_p": P_V_P, "mu": P_MU, "backlash_play": E_PLAY,
                 "contact_friction_dmu_pos": E_CMU_POS, "contact_friction_dmu_neg": E_CMU_NEG,
                 "lubrication_loss_dC_pos": E_DC_POS, "lubrication_loss_dC_neg": E_DC_NEG,
                 "lubrication_loss_c_v": E_CV, "seal_drag_dC": E_SEAL,
                 "current_gain_error": E_GAIN, "current_offset_di": E_OFFSET}
#: The kernel's full parameter vector with every effect off (base entries overwritten per call).
_OFF_VALUES = off_vector(EFFECTS, _KERNEL_INDEX, N_FULL)


@dataclass(frozen=True)
class BatchSimulator(FlaggedSimulator):
    """The Cranfield simulator bound to a set of switched-on effects (``Model.batch_simulator``).

    Called by :func:`ema_uq.simulate.simulate_batch` as
    ``simulator(model, thetas, inputs, kernel_constants, x0, dt, n_sub)`` with thetas
    (n_sets, n_params) in ``model.parameters`` order and inputs (n_samples, 2) = [x_sp [m],
    F_load [N]]; returns (n_sets, n_samples, 4) outputs. Every record starts at rest on its
    set point, so ``x0`` must be None.
    """

    RIG = "Cranfield"
    FLAGS = _FLAGS
    KERNEL_INDEX = _KERNEL_INDEX
    OFF_VALUES = _OFF_VALUES

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
    called by ``Model.with_effects``; :func:`~ema_uq.models.effects.augment_own_kernel`)."""
    names = tuple(names)
    return augment_own_kernel(model, names, values, catalogue=EFFECTS, rig="Cranfield", simulator=BatchSimulator(names))

MODEL = Model(
    name="cranfield", model_id=KERNEL_IDS["cranfield"][0], title="Cranfield linear actuator (stepper ball screw, measured)",
    states=STATES, outputs=OUTPUTS, output_units=OUTPUT_UNITS,
    parameters=PARAMETERS, constants=CONSTANTS, derive=derived_constants, integration_step=SAMPLE_TIME / 8,
    inputs=INPUTS, required_inputs=REQUIRED_INPUTS, batch_simulator=BatchSimulator(),
    sensor_sets={"full": OUTPUTS, "rig": ("position_error", "current")}, effect_catalogue=EFFECTS, augment=augment,
)
