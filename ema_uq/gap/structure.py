"""Where does a fitted model still leave structure? The open-set half of the gap verdict.

A candidate effect that is the cause of a gap explains it wherever the gap shows; one that
only fits the largest part of it (a wrong mechanism bent to the data, or the right family when
a second, uncatalogued cause is present) leaves the rest where it was. So the verdict does not
stop at the aggregate shrink: the held-out residual of the model after the candidate is cut
into *cells* and each cell is held against the nominal model's residual there and against the
healthy level (:func:`structure_left`).

Cells (every one a sample mask over the held-out records, or a frequency band):

- ``channel:<name>``: every sample of one channel;
- ``stroke:<k>/<K>``: the k-th of ``STROKE_BINS`` equally populated bins of the position along
  the stroke (the model's stroke output, ``STROKE_OUTPUTS``; a position-localised error — a
  damaged stretch of the screw, a stroke-dependent stiffness — shows here);
- ``direction:extend``/``direction:retract``/``direction:rest``: sign of the stroke speed;
- ``regime:<name>``: the actuator regimes of :func:`ema_uq.gap.localize.regime_masks`
  (reversal, low speed, high acceleration, high load) where the model has them;
- ``band:<lo>-<hi>`` per channel: residual power in a band of ``BANDS`` (fractions of the
  sample rate) above the channel's white-noise floor (a position-periodic error — ripple,
  a U-joint, a lead error of the screw — shows as a band while it hardly moves a mask cell).

Energy of a mask cell: the sum over its samples of the systematic products
(:func:`ema_uq.gap.localize.systematic_products`: unbiased under white noise) over every
channel's mean square, with its white-noise standard deviation. Energy of a band: the sum of
periodogram ordinates in the band less the noise floor (median ordinate / ln 2: the median of
an exponential), with the chi-square standard deviation of white noise.

A cell is *left* when, after the candidate, (1) its energy stands out of the noise (z >
``Z_CELL``), (2) it holds at least ``MIN_SHARE`` of the nominal model's total excess energy of
its kind (mask cells against the whole residual, band cells against every channel's bands), and
(3) the candidate closed less than ``closed_min`` of the cell on the metric's square-root scale
(energy after > (1 - closed_min)² of before), every energy counted above the healthy level:
the gap the replicate prediction leaves where the records repeat one experiment (a rig that
drifts from run to run leaves that much whatever the model), else zero (white noise). A cell
the candidate made worse counts likewise. Generic reason: a mechanism is the cause when it
closes the gap in every region that carried a material part of it; what it leaves in such a
region is a mechanism it does not contain. ``closed_min`` (a quarter) is below the aggregate
shrink test's half on purpose: a candidate's form only approximates the rig's (a dead zone at
the output where the catalogue has one in the drive, an exponential Stribeck curve where it has
another), and an approximate form closes its own mechanism's cells partly, while a missing
mechanism leaves its cells untouched (the development cases: a wrong family's cells closed 0-2 %,
a form mismatch's worst cell 37 %). The thresholds live in :class:`StructureSettings` (the
protocol file records them).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any, Mapping, Sequence

import numpy as np

from .localize import LAG_NORM, LocalizationError, ResidualRecord, _runs, regime_masks, systematic_products

#: outputs that measure the position along the stroke, the first one the model has is used
STROKE_OUTPUTS = ("y1", "position", "qm")
STROKE_BINS = 4
#: frequency bands of the band cells, fractions of the sample rate
BANDS = ((0.0, 0.02), (0.02, 0.1), (0.1, 0.5))
#: least complete stretch [samples] whose periodogram enters the band cells
MIN_BAND_SAMPLES = 64
MASK_REGIME_CELLS = ("reversal", "low_speed", "high_acceleration", "high_load")


@dataclass(frozen=True)
class StructureSettings:
    """Thresholds of :func:`structure_left` (see the module docstring)."""

    z_cell: float = 5.0
    min_share: float = 0.10
    closed_min: float = 0.25

    def to_json(self) -> dict[str, float]:
        return asdict(self)


@dataclass(frozen=True)
class CellEnergy:
    """Excess energy of one cell of one model's held-out residual: ``energy`` (sum, channel
    mean squares as unit), its white-noise standard deviation ``sd`` and ``samples``."""

    name: str
    kind: str
    energy: float
    sd: float
    samples: int

    @property
    def z(self) -> float:
        return self.energy / self.sd if self.sd > 0 else float("nan")


@dataclass(frozen=True)
class LeftCell:
    """A cell where structure is left after a candidate (:func:`structure_left`)."""

    name: str
    kind: str
    before: float
    after: float
    floor: float
    z_after: float
    share: float

    def to_json(self) -> dict[str, Any]:
        return {k: (None if isinstance(v, float) and not np.isfinite(v) else v) for k, v in asdict(self).items()}

    def describe(self) -> str:
        of = "of the excess power" if self.kind.startswith("band:") else "of the gap"
        if self.before <= self.floor:
            # nothing stood above the healthy level here before: the candidate put it there
            return f"{self.name} (holds {self.share:.0%} {of}, made by the candidate, z {self.z_after:.1f})"
        closed = 1.0 - np.sqrt(max(self.after - self.floor, 0.0) / (self.before - self.floor))
        return f"{self.name} (holds {self.share:.0%} {of}, closed {closed:.0%}, z {self.z_after:.1f})"


def _stroke(model, outputs: np.ndarray) -> np.ndarray | None:
    for name in STROKE_OUTPUTS:
        if name in model.outputs:
            return outputs[:, model.outputs.index(name)]
    return None


def _stroke_edges(strokes: Sequence[np.ndarray]) -> np.ndarray:
    return np.quantile(np.concatenate(strokes), np.linspace(0.0, 1.0, STROKE_BINS + 1))


def stroke_bins(records: Sequence[ResidualRecord], model) -> tuple[str, np.ndarray] | None:
    """(stroke output, the ``STROKE_BINS`` + 1 edges of the stroke bins of :func:`cell_masks`)
    of the same records, or None when the model has no stroke output."""
    strokes = [_stroke(model, r.outputs) for r in records]
    if not strokes or any(s is None for s in strokes):
        return None
    return next(n for n in STROKE_OUTPUTS if n in model.outputs), _stroke_edges(strokes)


def cell_masks(records: Sequence[ResidualRecord], model, theta: np.ndarray | None = None,
               constants: np.ndarray | None = None) -> dict[str, list[np.ndarray]]:
    """Sample masks of the mask cells, per record: {cell name: [(n_i,) bool]}. The stroke bins
    are quantiles of the stroke output over every record, from the noise-free outputs of the
    model the records belong to (the nominal model's records define the cells, and the same
    cells are then read on every model's residual)."""
    masks: dict[str, list[np.ndarray]] = {}
    strokes = [_stroke(model, r.outputs) for r in records]
    if all(s is not None for s in strokes):
        edges = _stroke_edges(strokes)
        if edges[-1] > edges[0]:
            for k in range(STROKE_BINS):
                upper = edges[k + 1] if k < STROKE_BINS - 1 else np.inf
                masks[f"stroke:{k + 1}/{STROKE_BINS}"] = [(s >= edges[k]) & (s < upper) for s in strokes]
        for name in ("extend", "retract", "rest"):
            masks[f"direction:{name}"] = []
        for r, s in zip(records, strokes):
            v = np.gradient(s, r.time)
            moving = np.abs(v) > 0.1 * max(float(np.max(np.abs(v))), 1e-300)
            masks["direction:extend"].append(moving & (v > 0))
            masks["direction:retract"].append(moving & (v < 0))
            masks["direction:rest"].append(~moving)
    if "Omega" in model.outputs and theta is not None:
        try:
            per_record = [regime_masks(model, theta, constants, r.time, r.inputs, r.outputs) for r in records]
        except (KeyError, ValueError, IndexError):
            per_record = []
        for name in MASK_REGIME_CELLS:
            if per_record and all(name in m for m in per_record):
                masks[f"regime:{name}"] = [m[name] for m in per_record]
    return masks


def _mask_energies(records: Sequence[ResidualRecord], channels: Sequence[str], spread: np.ndarray,
                   masks: Mapping[str, list[np.ndarray]]) -> dict[str, CellEnergy]:
    parts, sigma, _ = systematic_products([r.residual for r in records])
    unit = 1.0 / np.asarray(spread, dtype=float) ** 2
    noise_var = LAG_NORM * (sigma ** 2 * unit) ** 2                 # per sample and channel
    out: dict[str, CellEnergy] = {}

    def add(name: str, kind: str, selected: list[np.ndarray], channel: int | None) -> None:
        energy, var, count = 0.0, 0.0, 0
        for p, keep in zip(parts, selected):
            rows = keep & np.all(np.isfinite(p), axis=1)
            if channel is None:
                energy += float(np.sum(p[rows] * unit))
                var += float(rows.sum() * np.sum(noise_var))
            else:
                energy += float(np.sum(p[rows, channel] * unit[channel]))
                var += float(rows.sum() * noise_var[channel])
            count += int(rows.sum())
        out[name] = CellEnergy(name, kind, energy, float(np.sqrt(var)), count)

    everywhere = [np.ones(r.residual.shape[0], dtype=bool) for r in records]
    add("all", "all", everywhere, None)
    for c, channel in enumerate(channels):
        add(f"channel:{channel}", "mask", everywhere, c)
    for name, selected in masks.items():
        add(name, "mask", selected, None)
    return out


def _band_energies(records: Sequence[ResidualRecord], channels: Sequence[str],
                   spread: np.ndarray) -> dict[str, CellEnergy]:
    """Band cells per channel: periodogram power above the white-noise floor, in channel mean squares."""
    m = len(channels)
    energy = np.zeros((m, len(BANDS)))
    var = np.zeros((m, len(BANDS)))
    count = np.zeros(len(BANDS), dtype=int)
    for r in records:
        e = r.residual
        for a, b in _runs(np.all(np.isfinite(e), axis=1)):
            if b - a < MIN_BAND_SAMPLES:
                continue
            seg = e[a:b] - e[a:b].mean(axis=0)
            n = seg.shape[0]
            # one-sided periodogram, Σ power = Σ e² (Parseval): every ordinate but DC and Nyquist doubled
            power = np.abs(np.fft.rfft(seg, axis=0)) ** 2 / n
            power[1:] *= 2.0
            if n % 2 == 0:
                power[-1] /= 2.0
            freq = np.fft.rfftfreq(n)                               # fraction of the sample rate
            usable = freq > 0
            floor = np.median(power[usable], axis=0) / np.log(2.0)   # white noise: exponential ordinates
            for j, (lo, hi) in enumerate(BANDS):
                inside = usable & (freq >= lo) & (freq < hi)
                k = int(inside.sum())
                if k == 0:
                    continue
                energy[:, j] += (power[inside].sum(axis=0) - k * floor) / spread ** 2
                var[:, j] += k * (floor / spread ** 2) ** 2
                count[j] += k
    out: dict[str, CellEnergy] = {}
    for c, channel in enumerate(channels):
        for j, (lo, hi) in enumerate(BANDS):
            name = f"band:{channel}:{lo:g}-{hi:g}fs"
            out[name] = CellEnergy(name, f"band:{channel}", float(energy[c, j]), float(np.sqrt(var[c, j])),
                                   int(count[j]))
    return out


def cell_energies(records: Sequence[ResidualRecord], channels: Sequence[str], spread: np.ndarray,
                  masks: Mapping[str, list[np.ndarray]]) -> dict[str, CellEnergy]:
    """Every cell's excess energy of one model's held-out residual records (same records and
    order as ``masks``)."""
    try:
        out = _mask_energies(records, channels, spread, masks)
    except LocalizationError:
        return {}
    out.update(_band_energies(records, channels, spread))
    return out


def structure_left(before: Mapping[str, CellEnergy], after: Mapping[str, CellEnergy],
                   floor: Mapping[str, CellEnergy] | None = None,
                   settings: StructureSettings = StructureSettings()) -> list[LeftCell]:
    """Cells where the model ``after`` leaves structure the nominal model ``before`` had (or
    that ``after`` made), above the healthy level ``floor`` (None: white noise), largest share
    first (module docstring)."""
    if not before or not after:
        return []

    def level(cells, name):
        return max(cells[name].energy, 0.0) if cells is not None and name in cells else 0.0

    totals: dict[str, float] = {}
    for name, cell in before.items():
        if cell.kind == "all":
            totals["mask"] = max(cell.energy - level(floor, name), 0.0)
        elif cell.kind.startswith("band:"):
            totals["band"] = totals.get("band", 0.0) + max(cell.energy - level(floor, name), 0.0)
    left: list[LeftCell] = []
    keep = (1.0 - settings.closed_min) ** 2
    for name, cell in after.items():
        if cell.kind == "all" or name not in before:
            continue
        base = level(floor, name)
        excess_after = cell.energy - base
        excess_before = max(before[name].energy - base, 0.0)
        total = totals.get("band" if cell.kind.startswith("band:") else cell.kind, 0.0)
        if total <= 0:
            continue
        share = excess_after / total
        if (cell.z > settings.z_cell and share >= settings.min_share and excess_after > keep * excess_before):
            left.append(LeftCell(name, cell.kind, before[name].energy, cell.energy, base, cell.z, float(share)))
    return sorted(left, key=lambda c: -c.share)


def where_along_stroke(cells: Mapping[str, CellEnergy], floor: Mapping[str, CellEnergy] | None = None,
                       bins: tuple[str, np.ndarray] | None = None, unit: str = "",
                       settings: StructureSettings = StructureSettings()) -> list[str]:
    """Where along the stroke the nominal model's held-out gap lies, for a reader: the stroke
    bins whose energy above the healthy level ``floor`` stands out of the noise (z >
    ``z_cell``) and holds at least twice the share of the gap that the bin's share of the
    samples would carry (the bins are equally populated, so a gap spread along the stroke
    names none), largest share first, each with its span of the stroke output (``bins``, from
    :func:`stroke_bins`, in ``unit``). Only read out, never part of the verdict."""
    if not cells or "all" not in cells:
        return []

    def level(name):
        return max(floor[name].energy, 0.0) if floor is not None and name in floor else 0.0

    total = cells["all"].energy - level("all")
    if total <= 0:
        return []
    found = []
    for name, cell in cells.items():
        if not name.startswith("stroke:") or cell.sd <= 0:
            continue
        excess = cell.energy - level(name)
        share = excess / total
        if excess / cell.sd > settings.z_cell and share >= 2.0 / STROKE_BINS:
            k = int(name.split(":")[1].split("/")[0])
            span = "" if bins is None else f"{bins[0]} {bins[1][k - 1]:.4g}-{bins[1][k]:.4g} {unit}".rstrip() + ", "
            found.append((share, f"{name} ({span}holds {share:.0%} of the gap, z {excess / cell.sd:.1f})"))
    return [text for _, text in sorted(found, key=lambda f: -f[0])]


def where_left(cells: Sequence[LeftCell]) -> dict[str, list[str]]:
    """The left cells grouped for a reader: {"channel": [...], "stroke": [...], "direction": [...],
    "regime": [...], "band": [...]}, each a list of cell descriptions, largest share first."""
    out: dict[str, list[str]] = {}
    for cell in cells:
        group = cell.name.split(":")[0]
        out.setdefault(group, []).append(cell.describe())
    return out
