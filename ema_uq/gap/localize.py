"""Where does the model depart from the data? Localisation of a fitted model's residual by
channel, time window, operating regime and shaft order, with residual tests.

The systematic part of a residual e = z - y (model error, as opposed to white measurement
noise) is measured without knowing the noise level by short-lag products::

    p_kc = e_kc · Σ_l w_l e_{k-l,c},   w_l = 1/5 at lags l = 1..5

White noise contributes nothing to E[p] (its lags are uncorrelated). A systematic residual
s contributes Σ_l w_l s_k s_{k-l}: in the frequency domain, its power weighted by
W(f) = Σ_l w_l cos(2π f l Δt), 1 at low frequency, within 10 % of 1 up to 2 % of the
sample rate (2 Hz at 100 Hz sampling) and 0.5 at 5 %. Averaged over samples, p is a short-lag
autocovariance; ``systematic NRMSE`` of a channel is sqrt(mean p) / RMS(z), and of a data set
the root of the channel-mean of mean p / RMS(z)². Under white noise of standard deviation
σ_c, Σ_k p_kc has standard deviation σ_c² sqrt(n Σ w_l²) = σ_c² sqrt(n / 5) (distinct lag
products are uncorrelated), which gives every z-score below. σ_c itself is estimated from
first differences, σ_c² = mean((Δe_c)²) / 2, which a smooth systematic residual hardly changes.

Model error that looks like white noise within a channel (impulsive or broadband error, fast
dynamics, ripple aliased near the Nyquist frequency) is invisible to lag products, but it is
rarely confined to one channel, while sensor noise is independent across channels. So the
residual is first split by a factor model (:func:`factor_model`: R = L Lᵀ + diag(ψ), ML by EM,
the number of factors q chosen by BIC — q = 0 for independent white noise) into a part the
channels share and a unique part (Bartlett scores). Per sample and channel the systematic
energy is then (common part)² minus its noise variance, plus the lag products of the unique
part (:func:`systematic_products`); both terms are unbiased under white noise independent
across channels. These figures localise the gap (channels, regimes, time windows) and measure
it (:func:`systematic_nrmse`, the gap metric on held-out data). The lag products only have
to catch the error a channel does not share — offsets and slow drifts of one sensor — so
they can average over five lags, which halves their noise. The white-noise standard
deviation of the data-set figure squared is about 0.45 · 4e-4 / sqrt(n m) for n samples of m
channels with 2 % noise, i.e. a floor near 0.001 for the reference experiments.

Regimes are sample masks computed from the fitted model's noise-free outputs and the inputs:

- ``low_speed``: |Ω| < 10 % of its maximum (rest, start and stop);
- ``reversal``: from 0.3 s before to 1 s after the onset of a motion (|Ω| > 10 % of max)
  opposite to the previous motion, and ±0.3 s around a zero crossing of Ω with at least
  5 % of max |Ω| on both sides within 0.5 s;
- ``high_acceleration``: |dΩ/dt| > 30 % of its maximum;
- ``high_load``: moving with |F_ER1| + |F_ER2| > 75 % of its maximum;
- ``direction``: extension (Ω > 10 % max) against retraction (Ω < -10 % max); the regime
  holds the gap when one direction's enrichment is at least twice the other's;
- ``saturation``: the motor command within 2 % of its limit (M_min/M_max, or ±U_max);
- ``periodic``: residual power at harmonics 1-6 of every shaft's rotation (order tracking on
  the model's motor angle), tested against the noise and the neighbouring orders;
- ``delay``: the part of the residual proportional to the model output's time derivative
  (e ≈ -τ dy/dt), with the least-squares τ per channel.

For a mask regime M: ``share`` = its part of the total systematic energy, ``fraction`` = its
part of the samples, ``enrichment`` = share / fraction, ``z`` = its systematic energy in
noise standard deviations. A regime *holds* the gap when z ≥ ``Z_REGIME`` and enrichment ≥
``MIN_ENRICHMENT``; held regimes are ranked by share.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar, Mapping, Sequence

import numpy as np
from scipy import stats

from ..statistics import LJUNG_BOX_LAGS, ljung_box, max_cross_correlation, speed_regimes
from ..errors import EmaUqError


LAG_WEIGHTS = (0.2,) * 5
LAGS = len(LAG_WEIGHTS)
LAG_NORM = float(sum(w * w for w in LAG_WEIGHTS))   # Σ w², variance factor of Σ p under white noise
WINDOW_S = 1.0
LOW_SPEED_FRACTION = 0.10
REVERSAL_SWING_FRACTION = 0.05
REVERSAL_BEFORE_S, REVERSAL_AFTER_S, CROSSING_HALF_WIDTH_S = 0.3, 1.0, 0.3
ACCELERATION_FRACTION = 0.30
HIGH_LOAD_FRACTION = 0.75
SATURATION_FRACTION = 0.98
HARMONICS = 6
NEIGHBOUR_OFFSETS = (-0.30, -0.22, -0.15, 0.15, 0.22, 0.30)   # in harmonic spacing of the shaft
PEAK_TO_NEIGHBOURS = 5.0
ALPHA = 1e-3              # family-wise level of every residual test (Bonferroni inside a test)
Z_REGIME = 4.0
MIN_ENRICHMENT = 1.5
DIRECTION_RATIO = 2.0
MIN_SHARE = 0.10          # periodic/delay: least share of the gap to be named
MAX_LAG = LJUNG_BOX_LAGS
MAX_FACTORS = 8
PSI_FLOOR = 1e-4          # least uniqueness (share of a channel's mean square) of the factor model

MASK_REGIMES = ("reversal", "low_speed", "high_acceleration", "high_load", "saturation")
REGIMES = ("reversal", "low_speed", "high_acceleration", "high_load", "direction", "saturation",
           "periodic", "delay")


class LocalizationError(EmaUqError):
    """Residual records that cannot be localised (shapes, no valid sample)."""


@dataclass(frozen=True)
class ResidualRecord:
    """One experiment's residual of a fitted model.

    time (n,) [s]; inputs (n, 4) in kernel order (phi_r [rad], F_ER1 [N], F_ER2 [N], brake);
    observed and predicted (n, m) over the fitted channels, NaN where a sample is not used;
    outputs (n, n_outputs): every output of the fitted model, noise-free (defines regimes).
    """

    name: str
    time: np.ndarray
    inputs: np.ndarray
    observed: np.ndarray
    predicted: np.ndarray
    outputs: np.ndarray

    @property
    def residual(self) -> np.ndarray:
        return self.observed - self.predicted

    @property
    def valid(self) -> np.ndarray:
        """(n,) samples where every channel is observed."""
        return np.all(np.isfinite(self.observed), axis=1)


# ----------------------------------------------------------------------------------------
# estimators
# ----------------------------------------------------------------------------------------
def lag_products(residual: np.ndarray) -> np.ndarray:
    """Per-sample systematic-energy estimate p (n, m) of a residual (n, m); NaN where undefined."""
    e = np.asarray(residual, dtype=float)
    acc = np.zeros_like(e)
    for lag, weight in enumerate(LAG_WEIGHTS, start=1):
        acc[lag:] += weight * e[:-lag]
    p = e * acc
    p[:LAGS] = np.nan
    return p


def noise_std(residual: np.ndarray) -> np.ndarray:
    """Per-channel white-noise σ (m,) from first differences of a residual (n, m), NaN-aware."""
    d = np.diff(np.asarray(residual, dtype=float), axis=0)
    with np.errstate(invalid="ignore"):
        return np.sqrt(np.nanmean(d ** 2, axis=0) / 2.0)


@dataclass(frozen=True)
class FactorModel:
    """Residual covariance split as R = L Lᵀ + diag(ψ) (factor analysis, second moments about
    zero): ``loadings`` L (m, q) and ``uniqueness`` ψ (m,) in channel units, q chosen by BIC."""

    loadings: np.ndarray
    uniqueness: np.ndarray

    @property
    def n_factors(self) -> int:
        return self.loadings.shape[1]

    def split(self, e: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(common part (n, m), unique part (n, m), noise variance of the common part (m,)) of
        complete residual rows e (n, m), by Bartlett's unbiased factor scores."""
        if self.n_factors == 0:
            return np.zeros_like(e), e, np.zeros(e.shape[1])
        lw = self.loadings / self.uniqueness[:, None]                     # Ψ⁻¹ L
        inner = np.linalg.inv(self.loadings.T @ lw)                       # (Lᵀ Ψ⁻¹ L)⁻¹
        common = e @ lw @ inner @ self.loadings.T
        noise = np.einsum("cq,qr,cr->c", self.loadings, inner, self.loadings)
        return common, e - common, noise


def _factor_em(r: np.ndarray, q: int, iterations: int = 400) -> tuple[np.ndarray, np.ndarray, float]:
    """ML factor analysis of a normalised second-moment matrix r (m, m) by EM: (L, ψ, mean log-likelihood)."""
    m = r.shape[0]
    if q == 0:
        psi = np.diag(r).copy()
        loadings = np.zeros((m, 0))
    else:
        w, v = np.linalg.eigh(r)
        loadings = v[:, -q:] * np.sqrt(np.maximum(w[-q:] - 1.0, 1e-3))
        psi = np.maximum(np.diag(r) - np.sum(loadings ** 2, axis=1), PSI_FLOOR)
        for _ in range(iterations):
            beta = np.linalg.solve(np.eye(q) + (loadings.T / psi) @ loadings, loadings.T / psi)   # E[f|e] = β e
            second = np.eye(q) - beta @ loadings + beta @ r @ beta.T                            # E[f fᵀ]
            updated = r @ beta.T @ np.linalg.inv(second)
            psi = np.maximum(np.diag(r - updated @ beta @ r), PSI_FLOOR)
            converged = np.max(np.abs(updated - loadings)) < 1e-6
            loadings = updated
            if converged:
                break
    model = loadings @ loadings.T + np.diag(psi)
    sign, logdet = np.linalg.slogdet(model)
    return loadings, psi, -0.5 * (logdet + np.trace(np.linalg.solve(model, r)))


def factor_model(e: np.ndarray, max_factors: int = MAX_FACTORS) -> FactorModel:
    """Factor model of complete residual rows e (n, m): q = 0..``max_factors`` by BIC.

    Measurement noise is independent across channels, so a common factor is model error that
    several channels share; q = 0 (every channel's noise its own) is what white independent
    noise gives.
    """
    n, m = e.shape
    scale = np.sqrt(np.mean(e ** 2, axis=0))
    scale = np.where(scale > 0, scale, 1.0)
    r = (e / scale).T @ (e / scale) / n
    best, worse = None, 0
    for q in range(0, min(max_factors, m - 1) + 1):
        if (m - q) ** 2 < m + q and q > 0:      # more parameters than the covariance can identify
            break
        loadings, psi, loglik = _factor_em(r, q)
        bic = -2.0 * n * loglik + (m * q - q * (q - 1) / 2) * np.log(n)
        if best is None or bic < best[0]:
            best, worse = (bic, loadings, psi), 0
        else:
            worse += 1
            if worse == 2:                      # BIC has turned: more factors only fit noise
                break
    _, loadings, psi = best
    return FactorModel(loadings * scale[:, None], psi * scale ** 2)


def systematic_products(segments: Sequence[np.ndarray],
                        factors: FactorModel | None = None) -> tuple[list[np.ndarray], np.ndarray, FactorModel]:
    """Per-sample systematic-energy estimates of residual stretches: for each (n_i, m) stretch
    (NaN rows allowed) an (n_i, m) array, NaN where undefined; also σ (m,) of the white noise
    and the factor model used.

    Energy = common part² minus its noise variance (factors shared by channels, any frequency)
    + lag products of the unique part (each channel's own low-frequency error); both are
    unbiased under white noise independent across channels.
    """
    rows = np.concatenate([seg[np.all(np.isfinite(seg), axis=1)] for seg in segments])
    if rows.shape[0] < 10:
        raise LocalizationError(f"only {rows.shape[0]} complete samples to measure the residual; give longer records")
    factors = factor_model(rows) if factors is None else factors
    out, diffs = [], []
    for seg in segments:
        ok = np.all(np.isfinite(seg), axis=1)
        filled = np.where(ok[:, None], seg, 0.0)
        common, unique, noise = factors.split(filled)
        unique = np.where(ok[:, None], unique, np.nan)
        energy = lag_products(unique) + common ** 2 - noise
        out.append(np.where(ok[:, None], energy, np.nan))
        diffs.append(np.diff(unique, axis=0))
    d = np.concatenate(diffs)
    with np.errstate(invalid="ignore"):
        sigma = np.sqrt(np.nanmean(d ** 2, axis=0) / 2.0)
    return out, np.where(sigma > 0, sigma, 1e-300), factors


def complete_runs(residual: np.ndarray) -> list[np.ndarray]:
    """The maximal NaN-free stretches of a residual (n, m)."""
    ok = np.all(np.isfinite(residual), axis=1)
    return [residual[a:b] for a, b in _runs(ok)]


def systematic_nrmse(segments: Sequence[np.ndarray], spread: np.ndarray) -> tuple[float, np.ndarray, float, int]:
    """The gap metric of residual stretches ``segments`` [(n_i, m)]: (data-set systematic
    NRMSE, per-channel systematic NRMSE (m,), z of the data-set figure, number of common factors).

    Per channel the systematic mean square is the mean of :func:`systematic_products`; the
    data-set figure is the root of the channel-mean of that over RMS(z)² (``spread``²); z
    compares the sum of lag products with its white-noise standard deviation σ² sqrt(n Σ w²)
    (σ from first differences) — infinite when common factors were found (BIC).
    """
    parts, sigma, factors = systematic_products(segments)
    return nrmse_of_products(np.concatenate(parts), sigma, factors.n_factors, spread)


def nrmse_of_products(p: np.ndarray, sigma: np.ndarray, n_factors: int,
                      spread: np.ndarray) -> tuple[float, np.ndarray, float, int]:
    """:func:`systematic_nrmse` from the systematic products ``p`` (n, m) (NaN rows are left out)."""
    p = p[np.all(np.isfinite(p), axis=1)]
    mean_p = p.mean(axis=0)
    per_channel = np.sqrt(np.maximum(mean_p, 0.0)) / spread
    total = float(np.sqrt(max(float(np.mean(mean_p / spread ** 2)), 0.0)))
    z = float(np.sum(p / sigma ** 2) / np.sqrt(p.size * LAG_NORM))
    return total, per_channel, z, n_factors


# ----------------------------------------------------------------------------------------
# regimes
# ----------------------------------------------------------------------------------------
def _output(model, outputs: np.ndarray, name: str) -> np.ndarray:
    return outputs[:, model.outputs.index(name)]


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Maximal runs [start, stop) of True."""
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)))


def regime_masks(model, theta: np.ndarray, constants: np.ndarray, time: np.ndarray, inputs: np.ndarray,
                 outputs: np.ndarray) -> dict[str, np.ndarray]:
    """Boolean sample masks (n,) of the mask regimes plus ``extend``/``retract``/``moving``.

    ``outputs`` (n, n_outputs) are the fitted model's noise-free outputs, ``theta`` its full
    parameter vector, ``constants`` its design constants.
    """
    dt = float(time[1] - time[0])
    omega = _output(model, outputs, "Omega")
    peak = max(float(np.max(np.abs(omega))), 1e-12)
    speed = speed_regimes(omega, dt, low_fraction=LOW_SPEED_FRACTION, acceleration_fraction=ACCELERATION_FRACTION)
    moving = speed["moving"]
    masks = {"low_speed": speed["low_speed"], "moving": moving, "extend": speed["forward"],
             "retract": speed["backward"]}

    reversal = np.zeros(time.size, dtype=bool)
    before, after = int(round(REVERSAL_BEFORE_S / dt)), int(round(REVERSAL_AFTER_S / dt))
    previous = 0.0
    for start, stop in _runs(moving):
        direction = np.sign(np.mean(omega[start:stop]))
        if previous and direction != previous:
            reversal[max(start - before, 0): min(start + after, time.size)] = True
        previous = direction
    half, reach = int(round(CROSSING_HALF_WIDTH_S / dt)), int(round(0.5 / dt))
    swing = REVERSAL_SWING_FRACTION * peak
    for k in np.flatnonzero(np.sign(omega[1:]) * np.sign(omega[:-1]) < 0):
        if (np.max(np.abs(omega[max(k - reach, 0): k + 1])) > swing
                and np.max(np.abs(omega[k + 1: k + 1 + reach])) > swing):
            reversal[max(k - half, 0): k + half + 1] = True
    masks["reversal"] = reversal

    masks["high_acceleration"] = speed["accelerating"]
    load = np.abs(inputs[:, 1]) + np.abs(inputs[:, 2])
    # while moving: at rest most load-driven losses (friction) vanish with the speed
    masks["high_load"] = moving & (load > HIGH_LOAD_FRACTION * max(float(np.max(load)), 1e-12))

    names = model.constants.names
    if "U_max" in names and "U_A" in model.outputs:
        u_max = constants[names.index("U_max")]
        masks["saturation"] = np.abs(_output(model, outputs, "U_A")) >= SATURATION_FRACTION * u_max
    else:
        k_n = theta[model.parameters.index("k_n")]
        m_n = _output(model, outputs, "I_A") * k_n
        m_min, m_max = constants[names.index("M_min")], constants[names.index("M_max")]
        masks["saturation"] = (m_n >= SATURATION_FRACTION * m_max) | (m_n <= SATURATION_FRACTION * m_min)
    return masks


def shaft_ratios(model, outputs: np.ndarray, moving: np.ndarray) -> dict[str, float]:
    """Speed of every distinct shaft relative to the motor (``Omega_*`` outputs), e.g. {"Omega": 1, "Omega_TP1": 0.5}."""
    omega = _output(model, outputs, "Omega")
    ratios: dict[str, float] = {}
    if not moving.any():
        return {"Omega": 1.0}
    for name in model.outputs:
        if name == "Omega" or name.startswith("Omega_"):
            r = float(np.median(_output(model, outputs, name)[moving] / omega[moving]))
            if abs(r) > 1e-6 and not any(abs(abs(r) - v) < 1e-3 * v for v in ratios.values()):
                ratios[name] = abs(r)
    return ratios


# ----------------------------------------------------------------------------------------
# results
# ----------------------------------------------------------------------------------------
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


# ----------------------------------------------------------------------------------------
# localisation
# ----------------------------------------------------------------------------------------
def _order_power(e: np.ndarray, angle: np.ndarray, orders: np.ndarray) -> np.ndarray:
    """|Σ_k e_k exp(-i o θ_k)|² / n for each order o; e (n, m), angle (n,) -> (n_orders, m)."""
    phase = np.outer(orders, angle)                     # (n_orders, n)
    e = np.ascontiguousarray(e)
    return ((np.cos(phase) @ e) ** 2 + (np.sin(phase) @ e) ** 2) / e.shape[0]


@dataclass
class _Energy:
    """The systematic energy of a set of residual records, shared by the steps of :func:`localize`.

    ``p_ok`` marks complete samples (n,); ``energy`` (n, m) the normalised systematic energy,
    ``noise_units`` the same in noise variances; ``focus`` the channels that carry the gap,
    ``density`` (n,) the gap² density over them and ``total`` its mean."""

    records: list[ResidualRecord]
    channels: tuple[str, ...]
    spread: np.ndarray
    sigma: np.ndarray
    factors: Any
    e_parts: list[np.ndarray]
    masks_parts: list[dict[str, np.ndarray]]
    deriv_num: np.ndarray
    deriv_den: np.ndarray
    ok: np.ndarray
    n_ok: int
    energy: np.ndarray
    noise_units: np.ndarray
    z_channel: np.ndarray
    z_channel_limit: float
    focus: np.ndarray
    m_focus: int
    density: np.ndarray
    noise_focus: np.ndarray
    total: float

    @property
    def m(self) -> int:
        return len(self.channels)


def _energy(records: list[ResidualRecord], channels: tuple[str, ...], model, theta: np.ndarray,
            constants: np.ndarray, spread: np.ndarray) -> _Energy:
    """Per-record lag products, regime masks and output derivatives, concatenated (lags never
    cross a record boundary), and the systematic energy they give."""
    m = len(channels)
    e_parts, masks_parts = [], []
    deriv_num, deriv_den = np.zeros(m), np.zeros(m)
    p_parts, sigma, factors = systematic_products([rec.residual for rec in records])
    for rec in records:
        e = rec.residual
        e_parts.append(e)
        masks_parts.append(regime_masks(model, theta, constants, rec.time, rec.inputs, rec.outputs))
        dt = float(rec.time[1] - rec.time[0])
        deriv = np.gradient(rec.predicted, dt, axis=0)
        ok = rec.valid
        deriv_num += np.sum(e[ok] * deriv[ok], axis=0)
        deriv_den += np.sum(deriv[ok] ** 2, axis=0)
    p = np.concatenate(p_parts)
    ok = np.all(np.isfinite(p), axis=1)
    n_ok = int(ok.sum())
    if n_ok < 10:
        raise LocalizationError(f"only {n_ok} complete samples to localise the residual; give longer records")
    energy = np.where(ok[:, None], p, 0.0) / spread ** 2           # (n, m) normalised systematic energy
    noise_units = np.where(ok[:, None], p, 0.0) / sigma ** 2         # in noise variances
    z_channel = noise_units.sum(axis=0) / np.sqrt(n_ok * LAG_NORM)
    # regimes, windows and orders look at the channels that carry the gap, so that a gap in
    # one channel is not drowned by the noise of the others
    z_channel_limit = stats.norm.isf(ALPHA / m)
    focus = z_channel >= z_channel_limit
    if not focus.any():
        focus = np.ones(m, dtype=bool)
    density = energy[:, focus].mean(axis=1)                          # (n,) gap² density
    return _Energy(records, channels, spread, sigma, factors, e_parts, masks_parts, deriv_num, deriv_den, ok, n_ok,
                   energy, noise_units, z_channel, z_channel_limit, focus, int(focus.sum()), density,
                   noise_units[:, focus], float(density[ok].mean()))


def _combined_bias_z(biases: Sequence[float]) -> float:
    """One bias z from the records' own: the largest in size, its two-sided p multiplied by the
    number of records (Bonferroni) and turned back into a signed z; 0 without records."""
    if not biases:
        return 0.0
    worst = max(biases, key=abs)
    p = min(1.0, len(biases) * 2.0 * stats.norm.sf(abs(worst)))
    return float(np.sign(worst) * stats.norm.isf(p / 2.0))


def _channel_rows(en: _Energy) -> list[ChannelLocalization]:
    """Per-channel figures: systematic NRMSE, share, z, Ljung-Box p (Bonferroni over records),
    bias z, input cross-correlation and the delay τ."""
    m = en.m
    lb_p, bias_z, xcorr = np.ones(m), np.zeros(m), np.zeros(m)
    for j in range(m):
        pvals, biases, xcs = [], [], []
        for rec, e in zip(en.records, en.e_parts):
            valid = rec.valid
            runs = _runs(valid)
            if not runs:
                continue
            start, stop = max(runs, key=lambda r: r[1] - r[0])
            ej = e[start:stop, j]
            if ej.size > 4 * MAX_LAG and np.std(ej) > 0:
                pvals.append(ljung_box(ej, MAX_LAG))
                for col in range(3):
                    u = rec.inputs[start:stop, col]
                    if np.std(u) > 0:
                        xcs.append(max_cross_correlation(ej, u, MAX_LAG))
            ev = e[valid, j]
            # each record's own noise level: records of different amplitude carry different
            # noise, and a pooled σ understates the noisier one's (a false bias)
            sigma_record = noise_std(e[:, j:j + 1])[0]
            if ev.size > 1 and np.isfinite(sigma_record) and sigma_record > 0:
                biases.append(ev.mean() / (sigma_record / np.sqrt(ev.size)))
        lb_p[j] = min(pvals) * len(pvals) if pvals else np.nan
        bias_z[j] = _combined_bias_z(biases)
        xcorr[j] = max(xcs) if xcs else 0.0
    den = en.deriv_den
    delay = np.where(den > 0, -en.deriv_num / np.where(den > 0, den, 1.0), 0.0)
    channel_energy = en.energy[en.ok].mean(axis=0)
    share_ch = channel_energy / np.sum(channel_energy) if np.sum(channel_energy) > 0 else np.zeros(m)
    return [ChannelLocalization(ch, float(np.sqrt(max(channel_energy[j], 0.0))),
                                float(share_ch[j]), float(en.z_channel[j]), float(min(lb_p[j], 1.0)),
                                float(bias_z[j]), float(xcorr[j]), float(delay[j]))
            for j, ch in enumerate(en.channels)]


def _residual_tests(en: _Energy, channel_rows: list[ChannelLocalization], z_total: float):
    """Residual tests at family-wise level ALPHA (Bonferroni over channels): (reasons, tests)."""
    m = en.m
    lb_limit = ALPHA / m
    bias_limit = stats.norm.isf(ALPHA / (2 * m))
    xcorr_bound = stats.norm.isf(ALPHA / (2 * m * 3 * (2 * MAX_LAG + 1))) / np.sqrt(en.n_ok / len(en.records))
    z_limit = stats.norm.isf(ALPHA)
    reasons = []
    bad_lb = [c.channel for c in channel_rows if c.ljung_box_p < lb_limit]
    bad_bias = [c.channel for c in channel_rows if abs(c.bias_z) > bias_limit]
    bad_xc = [c.channel for c in channel_rows if c.max_input_xcorr > xcorr_bound]
    if bad_lb:
        reasons.append(f"non-white (Ljung-Box) in {', '.join(bad_lb)}")
    if bad_bias:
        reasons.append(f"biased in {', '.join(bad_bias)}")
    if bad_xc:
        reasons.append(f"correlated with the inputs in {', '.join(bad_xc)}")
    if z_total > z_limit:
        reasons.append(f"systematic energy z = {z_total:.1f}")
    if en.factors.n_factors:
        reasons.append(f"{en.factors.n_factors} error factor(s) common to several channels")
    bad_z = [c.channel for c in channel_rows if c.z > en.z_channel_limit]
    if bad_z and z_total <= z_limit:
        reasons.append(f"systematic energy in {', '.join(bad_z)}")
    tests = {"alpha": ALPHA, "common_factors": en.factors.n_factors, "ljung_box_limit": lb_limit,
             "bias_limit": float(bias_limit), "xcorr_bound": float(xcorr_bound), "z_limit": float(z_limit),
             "non_white": bad_lb, "biased": bad_bias, "input_correlated": bad_xc}
    return reasons, tests


def _regime_row(en: _Energy, name: str, mask: np.ndarray, detail: str = "") -> RegimeLocalization:
    ok, density, total = en.ok, en.density, en.total
    sel = mask & ok
    n_sel = int(sel.sum())
    fraction = n_sel / en.n_ok
    if n_sel == 0:
        return RegimeLocalization(name, 0.0, 0.0, float("nan"), 0.0, False, detail or "no sample")
    share = float(density[sel].sum() / density[ok].sum()) if total > 0 else 0.0
    z = float(en.noise_focus[sel].sum() / np.sqrt(n_sel * en.m_focus * LAG_NORM))
    enrichment = share / fraction
    within = float(np.sqrt(max(float(en.energy[sel].mean()), 0.0)))
    return RegimeLocalization(name, float(fraction), share, float(enrichment), z,
                              bool(z >= Z_REGIME and enrichment >= MIN_ENRICHMENT and total > 0), detail, within)


def _mask_regimes(en: _Energy) -> list[RegimeLocalization]:
    """The mask regimes and the direction regime (extension against retraction)."""
    masks = {k: np.concatenate([mp[k] for mp in en.masks_parts]) for k in en.masks_parts[0]}
    regimes = [_regime_row(en, name, masks[name]) for name in MASK_REGIMES]
    ext, ret = _regime_row(en, "extend", masks["extend"]), _regime_row(en, "retract", masks["retract"])
    hi, lo = (ext, ret) if (ext.enrichment if np.isfinite(ext.enrichment) else 0) >= \
        (ret.enrichment if np.isfinite(ret.enrichment) else 0) else (ret, ext)
    lo_enrich = lo.enrichment if np.isfinite(lo.enrichment) else 0.0
    direction_holds = bool(hi.z >= Z_REGIME and hi.share > 0
                           and hi.enrichment >= DIRECTION_RATIO * max(lo_enrich, 0.0) and en.total > 0
                           and np.isfinite(lo.enrichment))
    regimes.append(RegimeLocalization("direction", hi.fraction, hi.share, hi.enrichment, hi.z, direction_holds,
                                      f"{hi.name} {hi.enrichment:.2f} vs {lo.name} {lo_enrich:.2f}",
                                      hi.systematic_nrmse))
    return regimes


def _delay_regime(en: _Energy, channel_rows: list[ChannelLocalization]) -> RegimeLocalization:
    """The residual along the output derivative (e ≈ -τ dy/dt)."""
    num, den, total, focus = en.deriv_num, en.deriv_den, en.total, en.focus
    delay_energy = np.where(den > 0, num ** 2 / np.where(den > 0, den, 1.0), 0.0)
    delay_share = (min(float(np.sum((delay_energy / en.spread ** 2)[focus]) / en.m_focus / en.n_ok / total), 1.0)
                   if total > 0 else 0.0)
    chi2 = float(np.sum((delay_energy / en.sigma ** 2)[focus]))
    z_delay = float(stats.norm.isf(max(stats.chi2.sf(chi2, en.m_focus), 1e-300)))
    taus = ", ".join(f"{c.channel} {1e3 * c.delay_s:.1f} ms" for c in sorted(channel_rows, key=lambda c: -abs(c.z))[:3])
    return RegimeLocalization("delay", 1.0, delay_share, delay_share, z_delay,
                              bool(z_delay >= Z_REGIME and delay_share >= MIN_SHARE and total > 0), f"tau: {taus}")


def _order_candidates(en: _Energy, model) -> tuple[list[tuple], int]:
    """Residual power at harmonics of every shaft (order tracking on the model's motor angle)
    against the noise and the neighbouring orders: (candidate peaks, number of tests)."""
    n_tests, candidates = 0, []
    for rec, e, mp in zip(en.records, en.e_parts, en.masks_parts):
        dt = float(rec.time[1] - rec.time[0])
        omega = _output(model, rec.outputs, "Omega")
        angle = np.concatenate([[0.0], np.cumsum(0.5 * (omega[1:] + omega[:-1]) * dt)])
        use = mp["moving"] & rec.valid
        if use.sum() < 200:
            continue
        nyquist = np.pi / dt
        for shaft, ratio in shaft_ratios(model, rec.outputs, use).items():
            for h in range(1, HARMONICS + 1):
                order = h * ratio
                sel = use & (order * np.abs(omega) < 0.9 * nyquist)
                revolutions = np.sum(np.abs(omega[sel])) * dt * order / (2 * np.pi)
                if sel.sum() < 200 or revolutions < 10:
                    continue
                neighbours = order + np.array(NEIGHBOUR_OFFSETS) * ratio
                power = _order_power(e[sel], angle[sel], np.concatenate([[order], neighbours]))
                ratio_noise = power[0] / en.sigma ** 2
                ratio_nb = power[0] / np.maximum(np.median(power[1:], axis=0), 1e-300)
                n_tests += en.m
                candidates.append((rec.name, shaft, h, order, ratio_noise, ratio_nb, power[0], sel.sum(), rec.time.size))
    return candidates, n_tests


def _periodic_regime(en: _Energy, model) -> tuple[RegimeLocalization, list[OrderPeak]]:
    """The periodic regime: significant order peaks (above the noise and the neighbours)."""
    candidates, n_tests = _order_candidates(en, model)
    total, peaks, periodic_energy = en.total, [], 0.0
    threshold = np.log(max(n_tests, 1) / ALPHA)
    seen = set()
    for name, shaft, h, order, ratio_noise, ratio_nb, power, n_sel, n_rec in candidates:
        for j in range(en.m):
            key = (name, j, round(order, 6))
            if key in seen or not en.focus[j]:
                continue
            if ratio_noise[j] > threshold and ratio_nb[j] > PEAK_TO_NEIGHBOURS:
                seen.add(key)
                # a sinusoid of amplitude A gives power A² n/4, i.e. energy A²/2 on n samples
                e_density = 2.0 * power[j] / en.n_ok / en.spread[j] ** 2 / en.m_focus
                periodic_energy += e_density
                peaks.append(OrderPeak(en.channels[j], shaft, h, float(order), float(ratio_noise[j]),
                                       float(ratio_nb[j]), float(e_density / total) if total > 0 else 0.0))
    peaks.sort(key=lambda pk: -pk.power_ratio)
    periodic_share = min(float(periodic_energy / total), 1.0) if total > 0 else 0.0
    best = peaks[0] if peaks else None
    return RegimeLocalization(
        "periodic", 1.0, periodic_share, periodic_share,
        float(stats.norm.isf(max(np.exp(-best.power_ratio) * max(n_tests, 1), 1e-300))) if best else 0.0,
        bool(best is not None and periodic_share >= MIN_SHARE and total > 0),
        f"{best.channel}: harmonic {best.harmonic} of {best.shaft}" if best else "no peak"), peaks


def _windows(en: _Energy) -> dict[str, dict[str, list[float]]]:
    """Systematic NRMSE, z and mean flap command per ``WINDOW_S`` window of every record."""
    windows, offset = {}, 0
    for rec in en.records:
        n = rec.time.size
        dt = float(rec.time[1] - rec.time[0])
        width = max(int(round(WINDOW_S / dt)), LAGS + 2)
        centres, values, zs, phis = [], [], [], []
        for start in range(0, n, width):
            sl = slice(offset + start, offset + min(start + width, n))
            sel = en.ok[sl]
            if sel.sum() < width // 2:
                continue
            centres.append(float(rec.time[start: start + width].mean()))
            dens = en.density[sl][sel].mean()
            values.append(float(np.sqrt(max(dens, 0.0))))
            zs.append(float(en.noise_focus[sl][sel].sum() / np.sqrt(sel.sum() * en.m_focus * LAG_NORM)))
            phis.append(float(np.degrees(rec.inputs[start: start + width, 0].mean())))
        windows[rec.name] = {"time": centres, "systematic_nrmse": values, "z": zs, "phi_r_deg": phis}
        offset += n
    return windows


def localize(records: Sequence[ResidualRecord], channels: Sequence[str], model, theta: np.ndarray,
             constants: np.ndarray | None = None, spread: np.ndarray | None = None) -> Localization:
    """Localise the residual of ``model`` at full parameter vector ``theta`` over ``records``.

    ``spread`` (m,) normalises each channel (default: RMS of the observed channel over all
    records). Returns a :class:`Localization`.
    """
    records = list(records)
    if not records:
        raise LocalizationError("no residual record given")
    channels = tuple(channels)
    constants = model.constants_vector() if constants is None else np.asarray(constants, float)
    observed_all = np.concatenate([r.observed for r in records])
    if spread is None:
        spread = np.sqrt(np.nanmean(observed_all ** 2, axis=0))
    spread = np.where(np.asarray(spread) > 0, spread, 1.0)
    en = _energy(records, channels, model, theta, constants, spread)
    gap = float(np.sqrt(max(float(en.energy[en.ok].mean()), 0.0)))
    z_total = float(en.noise_units.sum() / np.sqrt(en.n_ok * en.m * LAG_NORM))
    channel_rows = _channel_rows(en)
    reasons, tests = _residual_tests(en, channel_rows, z_total)
    periodic, peaks = _periodic_regime(en, model)
    regimes = _mask_regimes(en) + [_delay_regime(en, channel_rows), periodic]
    tests["focus_channels"] = [ch for ch, f in zip(channels, en.focus) if f]
    return Localization(channel_rows, regimes, peaks, _windows(en), gap, z_total, tests, bool(reasons), reasons)
