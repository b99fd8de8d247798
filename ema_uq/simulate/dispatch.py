"""Kernel dispatch: from a model to its compiled right-hand side.

The ids come from models.base.KERNEL_IDS (module constants: numba compiles them in). numba
needs a static branch per right-hand side, so a new concept adds its branch to each helper
below and its id to NOMINAL_KERNELS / EFFECT_KERNELS; an id without a branch is refused by
``kernel_family`` before any kernel runs, and raises inside a kernel rather than running
another concept's equations. A model with unmodelled effects runs its concept's right-hand
side with the effects' bit set ``flags`` (``models.effect_kernels``): the nominal entries of
``integrators.py`` compile the set 0 in, the entries with effects take the set at run time.
"""
from __future__ import annotations

from numba import njit

from ..models import KERNEL_IDS, Model
from ..models import htls, lths
from ..models.effect_kernels import effect_flags
from ..errors import EmaUqError


class SimulationError(EmaUqError):
    """Inputs or parameter arrays of the wrong shape, an unknown kernel id, or a non-finite trajectory."""


HTLS_KERNEL, HTLS_EFFECTS_KERNEL = KERNEL_IDS["htls"]
LTHS_KERNEL, LTHS_EFFECTS_KERNEL = KERNEL_IDS["lths"]
#: ids of the nominal models and of the models with unmodelled effects (models/effects.py)
NOMINAL_KERNELS = (HTLS_KERNEL, LTHS_KERNEL)
EFFECT_KERNELS = (HTLS_EFFECTS_KERNEL, LTHS_EFFECTS_KERNEL)


def kernel_family(model: Model) -> str:
    """``"nominal"`` or ``"effects"``: the compiled entry that runs ``model.model_id``; any
    other id is a one-line :class:`SimulationError`."""
    if model.model_id in NOMINAL_KERNELS:
        return "nominal"
    if model.model_id in EFFECT_KERNELS:
        return "effects"
    raise SimulationError(f"model {model.name!r} has kernel id {model.model_id}, which no compiled kernel knows "
                          f"(known: {', '.join(map(str, NOMINAL_KERNELS + EFFECT_KERNELS))}); take the model "
                          "from get_model or with_effects, or register its kernel in models.base.KERNEL_IDS")


def kernel_key(model: Model) -> tuple[int, int]:
    """(concept kernel id, effect flags) of the compiled kernel that runs ``model``: an augmented
    model runs its concept's right-hand side with its effects' bits (none for effects that act
    on the outputs only, as ``sensor_delay``: those models run the nominal kernel)."""
    if kernel_family(model) == "nominal":
        return model.model_id, 0
    return model.base_model.model_id, effect_flags(model.effects)


@njit(cache=True, inline="always", error_model="numpy")
def _evaluate(model_id, flags, x, u, th, c, dx, y, outputs=True):
    if model_id == HTLS_KERNEL:
        htls.evaluate(x, u, th, c, dx, y, outputs, flags)
    elif model_id == LTHS_KERNEL:
        lths.evaluate(x, u, th, c, dx, y, outputs, flags)
    else:
        raise ValueError("unknown kernel id")


@njit(cache=True, inline="always", error_model="numpy")
def _linear_state_matrix(model_id, th, c, a):
    if model_id == HTLS_KERNEL:
        htls.linear_state_matrix(th, c, a)
    elif model_id == LTHS_KERNEL:
        lths.linear_state_matrix(th, c, a)
    else:
        raise ValueError("unknown kernel id")


@njit(cache=True, inline="always", error_model="numpy")
def _linear_regime(model_id, x, dx, u, th, c, delta):
    if model_id == HTLS_KERNEL:
        return htls.linear_regime(x, dx, u, th, c, delta)
    if model_id == LTHS_KERNEL:
        return lths.linear_regime(x, dx, u, th, c, delta)
    raise ValueError("unknown kernel id")
