"""Model registry: ``get_model("htls")`` returns a concept's :class:`Model` description.

A concept's module (and with it numba and its kernels) is imported on the first
``get_model`` of that concept; ``concepts()`` needs only the kernel-id table."""
from __future__ import annotations

from importlib import import_module

from .base import INPUTS, KERNEL_IDS, REQUIRED_INPUTS, Model
from ..errors import EmaUqError

#: concepts loaded so far, by name: the module ``models/<name>.py`` and its ``MODEL``; every
#: concept of the kernel-id table can be loaded
_REGISTRY: dict[str, Model] = {}


class UnknownConceptError(EmaUqError):
    pass


def get_model(name: str) -> Model:
    model = _REGISTRY.get(name)
    if model is None:
        if name not in KERNEL_IDS:
            raise UnknownConceptError(
                f"unknown concept {name!r}; choose one of: {', '.join(concepts())}"
            )
        model = _REGISTRY[name] = import_module(f"{__name__}.{name}").MODEL
    return model


def concepts() -> tuple[str, ...]:
    return tuple(sorted(KERNEL_IDS))


__all__ = ["INPUTS", "KERNEL_IDS", "REQUIRED_INPUTS", "Model", "get_model", "concepts", "UnknownConceptError"]
