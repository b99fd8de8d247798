"""What a localisation says: per-channel figures (:class:`ChannelLocalization`), regimes
(:class:`RegimeLocalization`), shaft-order peaks (:class:`OrderPeak`), and the whole
:class:`Localization` with the views the verdict reads (where the gap is, how well an effect's
signature matches) and its text and JSON forms; :class:`RegimeRms`, the coarser form for rigs
whose records support no residual tests. :func:`ema_uq.gap.localize.localize` computes them.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar, Mapping, Sequence

import numpy as np
from scipy import stats

ALPHA = 1e-3              # family-wise level of every residual test (Bonferroni inside a test)
MIN_ENRICHMENT = 1.5


@dataclass
class ChannelLocalization:
    """Per-channel figures: systematic NRMSE and its share of the gap, z of its systematic energy,
    Ljung-Box p, bias z (mean residual in σ/sqrt(n), σ the record's own noise; the largest over
    records, Bonferroni-adjusted), the largest normalised cross-correlation
    with an input, and the least-squares delay τ [s] of the residual on the output derivative."""

    channel: str
    systematic_nrmse: float
    share: float
    z: float
    ljung_box_p: float
    bias_z: float
    max_input_xcorr: float
    delay_s: float


@dataclass
class RegimeLocalization:
    """One regime: its sample ``fraction``, ``share`` of the gap, ``enrichment`` = share /
    fraction, ``z``, whether it ``holds_gap``, and ``systematic_nrmse`` — the systematic NRMSE
    of every channel over the regime's samples (comparable between models on the same data;
    NaN for the spectral regimes ``periodic`` and ``delay``)."""

    name: str
    fraction: float
    share: float
    enrichment: float
    z: float
    holds_gap: bool
    detail: str = ""
    systematic_nrmse: float = float("nan")


@dataclass
class OrderPeak:
    """Residual power at harmonic ``harmonic`` of shaft ``shaft`` (motor order ``order``), in
    units of the noise power (``power_ratio``) and of the neighbouring orders (``neighbour_ratio``)."""

    channel: str
    shaft: str
    harmonic: int
    order: float
    power_ratio: float
    neighbour_ratio: float
    share: float


@dataclass
class Localization:
    """Where a fitted model departs from the data (see the module docstring for every figure).

    ``windows`` maps a record name to {"time": centres [s], "systematic_nrmse": per window,
    "z": per window, "phi_r_deg": mean command per window}.
    """

    channels: list[ChannelLocalization]
    regimes: list[RegimeLocalization]
    peaks: list[OrderPeak]
    windows: dict[str, dict[str, list[float]]]
    systematic_nrmse: float
    z: float
    tests: dict[str, Any]
    structured: bool
    reasons: list[str] = field(default_factory=list)

    # --- the verdict-facing views ---------------------------------------------------------
    @property
    def where_regimes(self) -> list[str]:
        """Regimes that hold the gap, largest share first."""
        held = [r for r in self.regimes if r.holds_gap]
        return [r.name for r in sorted(held, key=lambda r: -r.share)]

    def where_channels(self, relative: float = 0.25) -> list[str]:
        """Channels with significant systematic energy and at least ``relative`` of the largest
        channel's systematic NRMSE, largest first."""
        z_thr = stats.norm.isf(ALPHA / max(len(self.channels), 1))
        sig = [c for c in self.channels if c.z >= z_thr]
        if not sig:
            return []
        top = max(c.systematic_nrmse for c in sig)
        keep = [c for c in sig if c.systematic_nrmse >= relative * top]
        return [c.channel for c in sorted(keep, key=lambda c: -c.systematic_nrmse)]

    def regime(self, name: str) -> RegimeLocalization:
        for r in self.regimes:
            if r.name == name:
                return r
        raise KeyError(name)

    def signature_match(self, signature: Sequence[str]) -> float:
        """Fraction (0..1) of an effect's signature regimes that hold the gap, graded by enrichment
        for mask regimes (enrichment 1 -> 0, ``MIN_ENRICHMENT`` or more with significance -> 1)."""
        if not signature:
            return 0.0
        grades = []
        for name in signature:
            try:
                r = self.regime(name)
            except KeyError:
                grades.append(0.0)
                continue
            if r.holds_gap:
                grades.append(1.0)
            elif r.z > 0 and np.isfinite(r.enrichment):
                grades.append(float(np.clip((r.enrichment - 1.0) / (MIN_ENRICHMENT - 1.0), 0.0, 1.0)) * 0.5)
            else:
                grades.append(0.0)
        return float(np.mean(grades))

    # --- reporting -----------------------------------------------------------------------
    def summary(self) -> str:
        rows = [f"Residual localisation: systematic NRMSE {self.systematic_nrmse:.4g} (z = {self.z:.1f}), "
                f"{'structured' if self.structured else 'consistent with white noise'}"
                + (f" ({'; '.join(self.reasons)})" if self.reasons else ""),
                f"  {'channel':<10} {'sys.NRMSE':>10} {'share':>7} {'z':>8} {'LB p':>8} {'bias z':>7} "
                f"{'xcorr':>6} {'tau [ms]':>8}"]
        for c in sorted(self.channels, key=lambda c: -c.systematic_nrmse):
            rows.append(f"  {c.channel:<10} {c.systematic_nrmse:>10.4g} {c.share:>7.3f} {c.z:>8.1f} "
                        f"{c.ljung_box_p:>8.2g} {c.bias_z:>7.1f} {c.max_input_xcorr:>6.3f} {1e3 * c.delay_s:>8.2f}")
        rows.append(f"  {'regime':<18} {'fraction':>8} {'share':>7} {'enrich':>7} {'z':>8}  holds gap")
        for r in sorted(self.regimes, key=lambda r: -r.share):
            rows.append(f"  {r.name:<18} {r.fraction:>8.3f} {r.share:>7.3f} {r.enrichment:>7.2f} {r.z:>8.1f}  "
                        f"{'yes' if r.holds_gap else 'no'} {r.detail}")
        for p in self.peaks[:5]:
            rows.append(f"  peak: {p.channel} at harmonic {p.harmonic} of {p.shaft} (motor order {p.order:.3g}), "
                        f"{p.power_ratio:.0f}x noise, {p.neighbour_ratio:.0f}x neighbours")
        return "\n".join(rows)

    def to_json(self) -> dict[str, Any]:
        return {
            "systematic_nrmse": self.systematic_nrmse, "z": self.z, "structured": self.structured,
            "reasons": list(self.reasons), "tests": self.tests,
            "channels": [vars(c).copy() for c in self.channels],
            "regimes": [vars(r).copy() for r in self.regimes],
            "peaks": [vars(p).copy() for p in self.peaks],
            "windows": self.windows,
        }

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> "Localization":
        def numbers(row):  # JSON null is a NaN figure
            return {k: float("nan") if v is None else v for k, v in row.items()}

        return cls(
            channels=[ChannelLocalization(**numbers(c)) for c in data["channels"]],
            regimes=[RegimeLocalization(**numbers(r)) for r in data["regimes"]],
            peaks=[OrderPeak(**numbers(p)) for p in data.get("peaks", [])],
            windows={k: dict(v) for k, v in data.get("windows", {}).items()},
            systematic_nrmse=float(data["systematic_nrmse"]), z=float(data["z"]),
            tests=dict(data.get("tests", {})), structured=bool(data["structured"]),
            reasons=list(data.get("reasons", [])),
        )


@dataclass
class RegimeRms:
    """A coarser localisation for rigs whose records support no residual tests of the
    actuator kind (e.g. EMPS): the RMS of one residual signal (``channel``, in its unit)
    overall and per operating regime. ``regimes`` maps a regime to {"rms", "ratio" (to the
    overall RMS), "share_of_samples"}; a regime holds the gap when its ratio exceeds
    ``hold_ratio``. No residual test is run (``structured`` False, ``z`` NaN)."""

    KIND: ClassVar[str] = "regime_rms"
    channel: str
    rms: float
    regimes: dict[str, dict[str, float]]
    hold_ratio: float = 1.2
    z: float = float("nan")
    structured: bool = False

    @classmethod
    def of(cls, channel: str, residual: np.ndarray, masks: Mapping[str, np.ndarray],
           hold_ratio: float = 1.2) -> "RegimeRms":
        """From a residual (n,) and regime masks (n,) over the same samples (regimes without a sample are left out)."""
        overall = float(np.sqrt(np.mean(residual ** 2)))
        regimes = {}
        for name, mask in masks.items():
            if mask.any():
                rms = float(np.sqrt(np.mean(residual[mask] ** 2)))
                regimes[name] = {"rms": rms, "ratio": rms / overall, "share_of_samples": float(mask.mean())}
        return cls(channel, overall, regimes, hold_ratio)

    @property
    def where_regimes(self) -> list[str]:
        """Regimes whose RMS ratio exceeds ``hold_ratio``, largest first."""
        ranked = sorted(self.regimes.items(), key=lambda kv: -kv[1]["ratio"])
        return [name for name, r in ranked if r["ratio"] > self.hold_ratio]

    def where_channels(self) -> list[str]:
        return [self.channel]

    def signature_match(self, signature: Sequence[str]) -> float:
        """Fraction of the signature regimes that hold the gap."""
        return float(np.mean([name in self.where_regimes for name in signature])) if signature else 0.0

    def summary(self) -> str:
        rows = [f"Residual {self.channel} by regime: RMS {self.rms:.4g} overall"]
        rows += [f"  {name:<18} RMS {r['rms']:>9.4g}  ratio {r['ratio']:>5.2f}  samples {r['share_of_samples']:.3f}"
                 for name, r in self.regimes.items()]
        return "\n".join(rows)

    def to_json(self) -> dict[str, Any]:
        return {"kind": self.KIND, "channel": self.channel, "rms": self.rms, "regimes": self.regimes,
                "hold_ratio": self.hold_ratio, "where_regimes": self.where_regimes}

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> "RegimeRms":
        return cls(data["channel"], float(data["rms"]), {k: dict(v) for k, v in data["regimes"].items()},
                   float(data.get("hold_ratio", 1.2)))
