"""Model registry: ``get_model("htls")`` returns a concept's :class:`Model` description."""
from __future__ import annotations

from .base import INPUTS, REQUIRED_INPUTS, Model
from . import emps, htls, lths

_REGISTRY: dict[str, Model] = {htls.MODEL.name: htls.MODEL, lths.MODEL.name: lths.MODEL,
                               emps.MODEL.name: emps.MODEL}


class UnknownConceptError(ValueError):
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


__all__ = ["INPUTS", "REQUIRED_INPUTS", "Model", "get_model", "concepts", "UnknownConceptError"]
