"""Ordered parameter sets: the single source of truth for parameter-vector layout.

A :class:`ParameterSet` is an immutable, ordered collection of :class:`Parameter`.
Every numerical routine in the package works on plain vectors; the set says which
position holds which named quantity, its unit, nominal value, bounds and whether it is
estimated (free) or held fixed.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Iterable, Iterator, Mapping, Sequence

import numpy as np

from .errors import EmaUqError


class ParameterError(EmaUqError):
    """An unknown parameter name, an impossible bound or a value outside its bounds."""


@dataclass(frozen=True)
class Parameter:
    """One named model parameter.

    ``lower``/``upper`` bound the admissible values (inclusive); ``free`` says whether
    estimators may move it. ``prior_std`` is an optional measured uncertainty that turns
    the nominal value into a pseudo-measurement (used for the rig-tuned gains).
    """

    name: str
    unit: str
    nominal: float
    lower: float = 0.0
    upper: float = np.inf
    free: bool = True
    description: str = ""
    prior_std: float | None = None

    def __post_init__(self) -> None:
        if not np.isfinite(self.nominal):
            raise ParameterError(f"parameter {self.name}: nominal value {self.nominal} is not finite")
        if not self.lower < self.upper:
            raise ParameterError(
                f"parameter {self.name}: lower bound {self.lower} is not below upper bound {self.upper}; "
                "give bounds with lower < upper"
            )
        if not self.lower <= self.nominal <= self.upper:
            raise ParameterError(
                f"parameter {self.name}: nominal {self.nominal} lies outside its bounds "
                f"[{self.lower}, {self.upper}]"
            )
        if self.prior_std is not None and not self.prior_std > 0:
            raise ParameterError(f"parameter {self.name}: prior_std must be positive, got {self.prior_std}")


@dataclass(frozen=True)
class ParameterSet:
    """An ordered, immutable collection of parameters.

    Index a set by name (``ps["J"]``) for the :class:`Parameter`; use :meth:`index`
    for its position in full vectors and :attr:`free_index` for the estimated subset.
    """

    parameters: tuple[Parameter, ...]
    _positions: Mapping[str, int] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        params = tuple(self.parameters)
        names = [p.name for p in params]
        duplicated = sorted({n for n in names if names.count(n) > 1})
        if duplicated:
            raise ParameterError(f"duplicate parameter names: {', '.join(duplicated)}")
        object.__setattr__(self, "parameters", params)
        object.__setattr__(self, "_positions", {n: i for i, n in enumerate(names)})

    # --- layout -----------------------------------------------------------------
    def __len__(self) -> int:
        return len(self.parameters)

    def __iter__(self) -> Iterator[Parameter]:
        return iter(self.parameters)

    def __contains__(self, name: object) -> bool:
        return name in self._positions

    def __getitem__(self, name: str) -> Parameter:
        return self.parameters[self.index(name)]

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.parameters)

    def index(self, name: str) -> int:
        try:
            return self._positions[name]
        except KeyError:
            raise ParameterError(
                f"unknown parameter {name!r}; known parameters: {', '.join(self.names)}"
            ) from None

    @property
    def nominal(self) -> np.ndarray:
        return np.array([p.nominal for p in self.parameters], dtype=float)

    @property
    def lower(self) -> np.ndarray:
        return np.array([p.lower for p in self.parameters], dtype=float)

    @property
    def upper(self) -> np.ndarray:
        return np.array([p.upper for p in self.parameters], dtype=float)

    @property
    def units(self) -> tuple[str, ...]:
        return tuple(p.unit for p in self.parameters)

    @property
    def free_mask(self) -> np.ndarray:
        return np.array([p.free for p in self.parameters], dtype=bool)

    @property
    def free_index(self) -> np.ndarray:
        return np.flatnonzero(self.free_mask)

    @property
    def free_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.parameters if p.free)

    # --- derived sets -------------------------------------------------------------
    def with_updates(self, **changes: Mapping[str, object]) -> "ParameterSet":
        """A copy with per-parameter field changes, e.g. ``with_updates(J={"free": False})``."""
        updated = list(self.parameters)
        for name, fields in changes.items():
            i = self.index(name)
            try:
                updated[i] = replace(updated[i], **fields)
            except TypeError as exc:
                raise ParameterError(f"parameter {name}: {exc}") from None
        return ParameterSet(tuple(updated))

    def with_nominal(self, values: Mapping[str, float]) -> "ParameterSet":
        return self.with_updates(**{k: {"nominal": float(v)} for k, v in values.items()})

    def fixing(self, names: Iterable[str]) -> "ParameterSet":
        return self.with_updates(**{n: {"free": False} for n in names})

    def freeing_only(self, names: Iterable[str]) -> "ParameterSet":
        keep = set(names)
        for n in keep:
            self.index(n)
        return ParameterSet(tuple(replace(p, free=p.name in keep) for p in self.parameters))

    def __add__(self, other: "ParameterSet") -> "ParameterSet":
        return ParameterSet(self.parameters + other.parameters)

    # --- vectors ----------------------------------------------------------------
    def vector(self, values: Mapping[str, float] | None = None) -> np.ndarray:
        """Full vector at nominal values, overridden by ``values`` (unknown names are an error)."""
        vec = self.nominal
        for name, value in (values or {}).items():
            vec[self.index(name)] = float(value)
        return vec

    def as_dict(self, vector: Sequence[float]) -> dict[str, float]:
        vector = np.asarray(vector, dtype=float)
        if vector.shape != (len(self),):
            raise ParameterError(f"expected a vector of {len(self)} values, got shape {vector.shape}")
        return {n: float(v) for n, v in zip(self.names, vector)}

    def check_within_bounds(self, vector: Sequence[float], what: str = "value") -> None:
        """Raise :class:`ParameterError` naming the first entry outside its bounds or not finite."""
        vector = np.asarray(vector, dtype=float)
        for p, v in zip(self.parameters, vector):
            if not np.isfinite(v):
                raise ParameterError(f"{what} of {p.name} is {v}; give a finite number")
            if not p.lower <= v <= p.upper:
                raise ParameterError(
                    f"{what} of {p.name} = {v:g} lies outside its bounds [{p.lower:g}, {p.upper:g}]; "
                    "choose a value inside or widen the bounds"
                )

    def table(self, vector: Sequence[float] | None = None) -> str:
        vector = self.nominal if vector is None else np.asarray(vector, dtype=float)
        rows = [f"{'name':<10} {'value':>12} {'unit':<12} {'free':<5} bounds"]
        for p, v in zip(self.parameters, vector):
            rows.append(f"{p.name:<10} {v:>12.6g} {p.unit:<12} {str(p.free):<5} [{p.lower:g}, {p.upper:g}]")
        return "\n".join(rows)


def parse_assignments(items: Iterable[str]) -> dict[str, float]:
    """Parse ``NAME=VALUE`` strings (command-line ``--set``) into a dict."""
    out: dict[str, float] = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name.strip():
            raise ParameterError(f"cannot read {item!r}: write NAME=VALUE, e.g. J=0.05")
        try:
            out[name.strip()] = float(value)
        except ValueError:
            raise ParameterError(f"cannot read {item!r}: {value!r} is not a number") from None
    return out
