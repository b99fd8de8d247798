"""Model registry: ``get_model("htls")`` returns a concept's :class:`Model` description."""
from __future__ import annotations

from importlib import import_module

from .base import INPUTS, KERNEL_IDS, REQUIRED_INPUTS, Model
from ..errors import EmaUqError

#: every concept of the kernel-id table, by name: the module ``models/<name>.py`` and its ``MODEL``
_REGISTRY: dict[str, Model] = {name: import_module(f"{__name__}.{name}").MODEL for name in KERNEL_IDS}


class UnknownConceptError(EmaUqError):
    pass


def get_model(name: str) -> Model:
    try:
        return _REGISTRY[name]
    except KeyError:
        raise UnknownConceptError(
            f"unknown concept {name!r}; choose one of: {', '.join(sorted(_REGISTRY))}"
        ) from None


def concepts() -> tuple[str, ...]:
    return tuple(sorted(_REGISTRY))


__all__ = ["INPUTS", "KERNEL_IDS", "REQUIRED_INPUTS", "Model", "get_model", "concepts", "UnknownConceptError"]
