"""The output-error estimation problem: data, channel selection, parameter layout and the
det R likelihood, all evaluated through one batched simulator call.

Objective minimised by both optimisers (negative log-likelihood, concentrated over R):

    V(Θ) = (N/2) log det R(Θ) + ½ Σ_j ((Θ_j - Θ_j,rig) / σ_j,rig)²

where R = (1/N) Σ_k e_k e_kᵀ over every complete sample of every experiment (eqs. 48-49)
and the second sum runs over parameters with a rig pseudo-measurement (docs/MODEL_SPEC.md,
resolved ambiguity 4). Minimising V is minimising det R when no pseudo-measurement is free.
V, R and log det R are computed by :mod:`ema_uq.statistics`.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Sequence

import numpy as np

from ..experiments import Measurement
from ..models import Model, get_model
from ..params import ParameterSet
from ..simulate import simulate_batch
from .. import statistics
from ..statistics import covariance, log_det_r, rig_terms
from ..errors import EmaUqError


class IdentificationError(EmaUqError):
    """Bad estimation input (wrong concept, no usable channel, start outside bounds) or
    a problem the data cannot answer (singular information matrix)."""


def _as_slice(index: np.ndarray) -> slice | np.ndarray:
    """A basic slice equal to an increasing, evenly spaced integer ``index`` (indexing with it is
    a view), else the index itself."""
    index = np.asarray(index, dtype=int)
    if index.size == 0:
        return index
    if index.size == 1:
        return slice(int(index[0]), int(index[0]) + 1)
    step = int(index[1] - index[0])
    if step > 0 and np.all(np.diff(index) == step):
        return slice(int(index[0]), int(index[-1]) + 1, step)
    return index


#: bytes of predictions one :class:`PredictionMemo` keeps (the most recently stored first): the
#: repeats come within a few batches, and on an HT/LS gap diagnosis 16 MB served 97 % of what
#: 64 MB did (172 against 190 runs saved of 1769) for 20 MB of resident memory instead of 90
PREDICTION_MEMO_BYTES = 16 * 2 ** 20


class PredictionMemo:
    """The predicted channels of parameter vectors already simulated for one set of prediction
    inputs (model, measurements, channels, constants), so that a vector asked for again is
    copied instead of run again: a fit repeats vectors when it computes the sensitivities
    at a point it has already differenced (the point a failed step left unchanged, the start
    a reduced or narrower refit of the same model begins from). Each vector's run is
    independent of the batch it was run in, so the copy carries the same numbers.

    Bounded by :data:`PREDICTION_MEMO_BYTES` (least recently stored dropped first). ``runs``
    counts the parameter vectors actually simulated through it.
    """

    def __init__(self, owner: "FitProblem", capacity_bytes: int | None = None) -> None:
        self._signature = _prediction_inputs(owner)
        self._rows: dict[bytes, np.ndarray] = {}
        self._bytes = 0
        self.capacity_bytes = PREDICTION_MEMO_BYTES if capacity_bytes is None else int(capacity_bytes)
        self.runs = 0

    def serves(self, problem: "FitProblem") -> bool:
        """Whether ``problem`` predicts from the same inputs (so the same vectors give the same outputs)."""
        theirs = _prediction_inputs(problem)
        mine = self._signature
        return (theirs[0] is mine[0] and len(theirs[1]) == len(mine[1])
                and all(a is b for a, b in zip(theirs[1], mine[1])) and theirs[2:] == mine[2:])

    def __contains__(self, key: bytes) -> bool:
        return key in self._rows

    def get(self, key: bytes) -> np.ndarray:
        return self._rows[key]

    def store(self, keys, predicted: np.ndarray) -> None:
        for key, row in zip(keys, predicted):
            if row.nbytes > self.capacity_bytes:
                return
            self._rows[key] = np.array(row)      # a copy: the caller may write into its result
            self._bytes += row.nbytes
        while self._bytes > self.capacity_bytes:
            oldest = next(iter(self._rows))
            self._bytes -= self._rows.pop(oldest).nbytes


def _prediction_inputs(problem: "FitProblem") -> tuple:
    """What a prediction depends on besides the parameter vector: model and measurements (by
    identity), channels and constants (by value)."""
    return (problem.model, tuple(problem.measurements), tuple(problem.channels),
            np.asarray(problem.constants, dtype=np.float64).tobytes())


@dataclass(frozen=True)
class _Block:
    """One experiment's data restricted to the fitted channels and complete samples."""

    time: np.ndarray          # (n_samples,)
    inputs: np.ndarray        # (n_samples, n_inputs)
    rows: np.ndarray          # indices of complete samples, (n_valid,)
    observed: np.ndarray      # (n_valid, n_channels)


@dataclass(frozen=True)
class FitProblem:
    """Measurements of one concept joined for a joint fit.

    Parameters
    ----------
    measurements : one or more :class:`Measurement` of the same concept.
    parameters : layout, bounds, free flags and rig pseudo-measurements (nominal + prior_std);
        default: the concept's own set.
    channels : fitted output channels (default: every channel present in all measurements).
    constants : design constants vector (default: nominal).
    model : the model to fit (default: the measurements' concept). An augmented model
        (``Model.with_effects``) is allowed when it is built on the measurements' concept;
        its parameter layout (base + effect parameters) then sets ``parameters``.
    predictions : the :class:`PredictionMemo` of another problem with the same model,
        measurements, channels and constants (its free parameters may differ), to reuse the
        vectors it simulated; default, or when the inputs differ: a memo of its own.
        :func:`dataclasses.replace` passes it on, and it is replaced when the inputs change.
    """

    measurements: Sequence[Measurement]
    parameters: ParameterSet | None = None
    channels: Sequence[str] | None = None
    constants: np.ndarray | None = None
    model: Model | None = None
    predictions: PredictionMemo | None = field(default=None, repr=False, compare=False)
    blocks: tuple[_Block, ...] = field(init=False, repr=False)
    channel_index: np.ndarray = field(init=False, repr=False)
    _observed: np.ndarray = field(init=False, repr=False, compare=False)
    _channel_take: slice | np.ndarray = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        measurements = tuple(self.measurements)
        if not measurements:
            raise IdentificationError("no measurement given; pass at least one data file")
        concepts = {m.concept for m in measurements}
        if len(concepts) != 1:
            raise IdentificationError(
                f"measurements mix concepts {sorted(concepts)}; fit one concept at a time"
            )
        concept = measurements[0].concept
        model = get_model(concept) if self.model is None else self.model
        base = getattr(model, "base_model", None) or model
        if base.name != concept:
            raise IdentificationError(
                f"model {model.name} is built on concept {base.name}, but the measurements are of concept "
                f"{concept}; use a model of the data's concept"
            )
        parameters = model.parameters if self.parameters is None else self.parameters
        if parameters.names != model.parameters.names:
            raise IdentificationError(
                f"parameter layout {parameters.names} does not match concept {model.name}"
            )
        if not parameters.free_names:
            raise IdentificationError("every parameter is fixed; free at least one to estimate")
        common = [c for c in measurements[0].channels if all(c in m.channels for m in measurements)]
        channels = tuple(common if self.channels is None else self.channels)
        if not channels:
            raise IdentificationError(
                "no usable channel: the measurements share no output channel; give data with at least one common channel"
            )
        model.output_index(channels)
        for m in measurements:
            missing = [c for c in channels if c not in m.channels]
            if missing:
                raise IdentificationError(
                    f"channel(s) {', '.join(missing)} missing from measurement {m.experiment.name!r}; "
                    "choose channels every data set has"
                )
        blocks = []
        for m in measurements:
            z = m.select(channels).values
            for j, ch in enumerate(channels):
                if not np.any(np.isfinite(z[:, j])):
                    raise IdentificationError(
                        f"channel {ch} of {m.experiment.name!r} has no valid sample (all NaN); drop it from the channels"
                    )
            rows = np.flatnonzero(np.all(np.isfinite(z), axis=1))
            blocks.append(_Block(m.time, m.experiment.input_matrix(model), rows, z[rows]))
        n_valid = sum(b.rows.size for b in blocks)
        if n_valid <= len(channels) + len(parameters.free_names):
            raise IdentificationError(
                f"only {n_valid} complete samples for {len(channels)} channels and "
                f"{len(parameters.free_names)} free parameters; give more data or fewer channels"
            )
        consts = model.constants_vector() if self.constants is None else np.asarray(self.constants, float)
        object.__setattr__(self, "measurements", measurements)
        object.__setattr__(self, "model", model)
        object.__setattr__(self, "parameters", parameters)
        object.__setattr__(self, "channels", channels)
        object.__setattr__(self, "constants", consts)
        object.__setattr__(self, "blocks", tuple(blocks))
        object.__setattr__(self, "channel_index", model.output_index(channels))
        observed = np.concatenate([b.observed for b in blocks])
        observed.flags.writeable = False
        object.__setattr__(self, "_observed", observed)
        object.__setattr__(self, "_channel_take", _as_slice(self.channel_index))
        if self.predictions is None or not self.predictions.serves(self):
            object.__setattr__(self, "predictions", PredictionMemo(self))

    # --- sizes -------------------------------------------------------------------
    @property
    def n_samples(self) -> int:
        """N: complete samples over all experiments."""
        return sum(b.rows.size for b in self.blocks)

    @property
    def free_index(self) -> np.ndarray:
        return self.parameters.free_index

    @property
    def observed(self) -> np.ndarray:
        """(N, n_channels) measured values of every complete sample (read-only, built once)."""
        return self._observed

    # --- model evaluation ----------------------------------------------------------
    def full_vectors(self, free_values: np.ndarray, base: np.ndarray) -> np.ndarray:
        """Embed (n_sets, n_free) free values into full parameter vectors around ``base``."""
        free_values = np.atleast_2d(free_values)
        full = np.repeat(base[None, :], free_values.shape[0], axis=0)
        full[:, self.free_index] = free_values
        return full

    def predict(self, thetas: np.ndarray, *, share_steps: bool = False) -> np.ndarray:
        """Predicted channels (n_sets, N, n_channels) for full parameter vectors (n_sets, n_params).

        Every experiment is one batched simulator call over the sets not already in
        :attr:`predictions` (a set simulated before is copied from there: the same numbers,
        without the run). ``share_steps``: every set follows the adaptive step sequence of the
        first (finite differences around it); such a batch of an adaptive integrator is run
        whole, since its sets' outputs depend on the first.
        """
        thetas = np.atleast_2d(np.asarray(thetas, dtype=np.float64))
        memo = self.predictions
        if share_steps and self.model.integrator != "rk4":
            memo.runs += thetas.shape[0]
            return self._simulate(thetas, share_steps=True)
        keys = [row.tobytes() for row in thetas]
        known = {k: memo.get(k) for k in keys if k in memo}     # taken before storing can drop them
        missing = [k for k in dict.fromkeys(keys) if k not in known]
        if missing:
            order = {k: i for i, k in enumerate(keys)}
            fresh = self._simulate(thetas[[order[k] for k in missing]])
            memo.runs += len(missing)
            memo.store(missing, fresh)
            if len(missing) == len(keys):       # nothing known, nothing repeated: no assembly
                return fresh
            known.update(zip(missing, fresh))
        return np.stack([known[k] for k in keys])

    def _simulate(self, thetas: np.ndarray, share_steps: bool = False) -> np.ndarray:
        """The simulator's predicted channels (n_sets, N, n_channels), every set run."""
        cols = self._channel_take
        if len(self.blocks) == 1 and self.blocks[0].rows.size == self.blocks[0].time.size and isinstance(cols, slice):
            b = self.blocks[0]            # every sample complete, channels contiguous: a view, no copy
            return simulate_batch(self.model, thetas, b.time, b.inputs, constants=self.constants,
                                  share_steps=share_steps)[:, :, cols]
        result = np.empty((thetas.shape[0], self.n_samples, len(self.channels)))
        start = 0
        for b in self.blocks:
            out = simulate_batch(self.model, thetas, b.time, b.inputs, constants=self.constants,
                                 share_steps=share_steps)
            stop = start + b.rows.size
            if b.rows.size == b.time.size:
                rows = slice(None)
            else:
                rows = b.rows if isinstance(cols, slice) else b.rows[:, None]
            result[:, start:stop] = out[:, rows, cols]      # one indexing step, written in place
            start = stop
        return result

    def residuals(self, thetas: np.ndarray) -> np.ndarray:
        """z - y, (n_sets, N, n_channels)."""
        return self.observed[None] - self.predict(thetas)

    # --- likelihood ------------------------------------------------------------------
    def prior_terms(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Free-parameter positions (in the free vector), rig values and rig σ of pseudo-measurements."""
        return rig_terms(self.parameters, self.free_index)

    def objective(self, residuals: np.ndarray, free_values: np.ndarray) -> tuple[float, float]:
        """(V, log det R) for one residual array (N, n_channels) at free parameter values."""
        logdet = log_det_r(covariance(residuals))
        return statistics.objective(self.n_samples, logdet, free_values, self.parameters, self.free_index), logdet
