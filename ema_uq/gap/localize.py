"""Where does the model depart from the data? Localisation of a fitted model's residual by
channel, time window, operating regime and shaft order, with residual tests.

The systematic part of the residual (model error, as opposed to white measurement noise) is
measured without knowing the noise level by short-lag products and a factor model of the
errors the channels share (:mod:`ema_uq.gap.systematic`); these figures localise the gap
(channels, regimes, time windows). The result types are in :mod:`ema_uq.gap.localization_result`.

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

from dataclasses import dataclass
from typing import Any, Sequence

import numpy as np
from scipy import stats

from ..statistics import LJUNG_BOX_LAGS, ljung_box, max_cross_correlation, speed_regimes
from .localization_result import (ALPHA, MIN_ENRICHMENT, ChannelLocalization, Localization, OrderPeak,
                                  RegimeLocalization)
from .systematic import LAG_NORM, LAGS, LocalizationError, _runs, noise_std, systematic_products

# The estimators of the systematic part and the result types stay importable from here, where
# they were defined before they had rooms of their own (the diagnosis, the rigs and the tests
# reach them so).
from .localization_result import RegimeRms  # noqa: F401
from .systematic import (LAG_WEIGHTS, MAX_FACTORS, PSI_FLOOR, FactorModel, complete_runs,  # noqa: F401
                         factor_model, lag_products, nrmse_of_products, systematic_nrmse)

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
Z_REGIME = 4.0
DIRECTION_RATIO = 2.0
MIN_SHARE = 0.10          # periodic/delay: least share of the gap to be named
MAX_LAG = LJUNG_BOX_LAGS

MASK_REGIMES = ("reversal", "low_speed", "high_acceleration", "high_load", "saturation")
REGIMES = ("reversal", "low_speed", "high_acceleration", "high_load", "direction", "saturation",
           "periodic", "delay")


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
# regimes
# ----------------------------------------------------------------------------------------
def _output(model, outputs: np.ndarray, name: str) -> np.ndarray:
    return outputs[:, model.outputs.index(name)]

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
