"""How much of a residual is model error rather than white measurement noise, and the gap
metric built on it (:func:`systematic_nrmse`).

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
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import numpy as np

from ..errors import EmaUqError

LAG_WEIGHTS = (0.2,) * 5
LAGS = len(LAG_WEIGHTS)
LAG_NORM = float(sum(w * w for w in LAG_WEIGHTS))   # Σ w², variance factor of Σ p under white noise
MAX_FACTORS = 8
PSI_FLOOR = 1e-4          # least uniqueness (share of a channel's mean square) of the factor model


class LocalizationError(EmaUqError):
    """Residual records that cannot be localised (shapes, no valid sample)."""


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


# here, beside complete_runs, as the lowest room that needs it: the regime masks and the
# residual tests (ema_uq.gap.localize, ema_uq.gap.structure) use it too
def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """Maximal runs [start, stop) of True."""
    edges = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)))


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
