"""Building blocks shared by the EMA concepts: loss torques, brake, smoothed sign and the
parameter definitions common to both drive trains."""
from __future__ import annotations

import math

import numpy as np
from numba import njit

from ..params import Parameter

DEG = math.pi / 180.0

_BTS = "B in N m s/rad as seen at that point of the torque sum"
_CTS = "C in N m as seen at that point of the torque sum"


def _loss(name: str, nominal: float, where: str) -> Parameter:
    viscous = name.startswith("B")
    return Parameter(name, "N m s/rad" if viscous else "N m", nominal, 0.0, np.inf,
                     description=f"{'viscous' if viscous else 'Coulomb'} loss of the {where} ({_BTS if viscous else _CTS})")


def loss_parameters(values: dict[str, float]) -> tuple[Parameter, ...]:
    """The 12 station loss parameters common to both concepts, in eq. 44 order."""
    where = {"TS": "ball screw", "U": "U-joint", "TP": "bevel gear"}
    out = []
    for k in (1, 2):
        for part in ("TS", "U", "TP"):
            for kind in ("B", "C"):
                name = f"{kind}_{part}{k}"
                out.append(_loss(name, values[name], f"{where[part]} of station {k}"))
    return tuple(out)


def rig_gain(name: str, nominal: float, unit: str, what: str) -> Parameter:
    """A controller gain with its rig-tuned value as a 2 % pseudo-measurement (ambiguity 4)."""
    return Parameter(name, unit, nominal, nominal * 1e-3, nominal * 1e3,
                     description=f"{what}, measured on the rig (prior/pseudo-measurement)",
                     prior_std=0.02 * nominal)


def const(name, unit, value, description):
    return Parameter(name, unit, value, -np.inf, np.inf, free=False, description=description)


BRAKE_AND_SETTINGS = (
    const("M_Bmax", "N m", 100.0, "brake torque at standstill (eq. 3)"),
    const("K_b", "1", 1.0, "electromagnetic brake constant (eq. 3)"),
    const("Omega_half", "rad/s", 1.0, "speed of half the maximum brake torque (eq. 3)"),
    Parameter("omega_eps", "rad/s", 0.05, 1e-9, np.inf, free=False,
              description="speed scale of the smoothed sign tanh(v/omega_eps)"),
)

@njit(cache=True, inline="always", error_model="numpy")
def smooth_sign(v, eps):
    return math.tanh(v / eps)


@njit(cache=True, inline="always", error_model="numpy")
def brake_torque(engaged, speed, m_bmax, k_b, omega_half, eps):
    """Eq. 3, acting against the motion; zero when the brake is released (engaged = 0)."""
    if engaged == 0.0:
        return 0.0
    magnitude = m_bmax - 0.5 * m_bmax * (1.0 - math.exp(-k_b * abs(speed) / omega_half))
    return engaged * magnitude * smooth_sign(speed, eps)


def screw_constants(r: float, gamma: float, beta1: float, beta2: float) -> list[float]:
    """[r sinγ cosγ, r tanγ, 1/cosβ1, 1/cosβ2]: the trigonometric constants of both stations."""
    return [r * math.sin(gamma) * math.cos(gamma), r * math.tan(gamma), 1.0 / math.cos(beta1), 1.0 / math.cos(beta2)]


#: |v / omega_eps| from which tanh(v / omega_eps) is exactly ±1 in double precision
#: (19.0615...): beyond it a smoothed sign is a constant and the friction terms are affine.
SIGN_SATURATED_ARGUMENT = 19.07
#: the linear regime of the "hybrid" integrator keeps every smoothed-sign argument above
#: this multiple of SIGN_SATURATED_ARGUMENT, a margin for the checks between sample points
LINEAR_REGIME_MARGIN = 2.0


@njit(cache=True, inline="always", error_model="numpy")
def stays_above(value, rate, delta, bound):
    """``value - delta |rate| > bound``: the tangent at a checked point keeps ``value`` above
    ``bound`` for ``delta`` seconds (the linear regime's test between checked points)."""
    return value - delta * abs(rate) > bound


@njit(cache=True, inline="always", error_model="numpy")
def stays_below(value, rate, delta, bound):
    """``value + delta |rate| < bound`` (see :func:`stays_above`)."""
    return value + delta * abs(rate) < bound


@njit(cache=True, inline="always", error_model="numpy")
def in_linear_regime(brake, omega, omega_rate, eps, slowest_ratio, gain, p_ace, y_r, y1, y2, y1_rate, y2_rate,
                     lower, upper, delta):
    """The linear regime of a cascaded-P EMA over the next ``delta`` seconds: brake released,
    the motor fast enough that the slowest signed shaft (motor speed / ``slowest_ratio``) has
    its smoothed sign saturated with margin, and the controller command
    ``gain (p_ace (y_r - (y1 + y2) / 2) - omega)`` (torque or voltage) inside its limits."""
    if brake != 0.0:
        return False
    omega_min = LINEAR_REGIME_MARGIN * SIGN_SATURATED_ARGUMENT * eps * slowest_ratio
    if not stays_above(abs(omega), omega_rate, delta, omega_min):
        return False
    command = gain * (p_ace * (y_r - 0.5 * (y1 + y2)) - omega)
    rate = -gain * (p_ace * 0.5 * (y1_rate + y2_rate) + omega_rate)
    return stays_above(command, rate, delta, lower) and stays_below(command, rate, delta, upper)
