"""Assemble one self-contained HTML report per study from the workflow's result files.

Each stage contributes a section when its result file exists; a missing stage is listed
as not run, never silently dropped.
"""
from __future__ import annotations

import html
from importlib import resources
from pathlib import Path
from string import Template
from typing import Any

import numpy as np

from .. import io
from ..models import get_model
from ..provenance import file_sha256, settings_hash
from ..rigs import is_measured, rig_of
from . import figures
from .outputs import fit_outputs_path, read_fit_outputs

TEMPLATE = "report/templates/report.html"


def _table(header: list[str], rows: list[list[Any]], name_cols: int = 1) -> str:
    head = "".join(f'<th class="{"name" if i < name_cols else ""}">{html.escape(h)}</th>' for i, h in enumerate(header))
    body = []
    for row in rows:
        cells = "".join(f'<td class="{"name" if i < name_cols else ""}">{c}</td>' for i, c in enumerate(row))
        body.append(f"<tr>{cells}</tr>")
    return f"<table><tr>{head}</tr>{''.join(body)}</table>"


def _fmt(x: float | None, digits: int = 5) -> str:
    if isinstance(x, str):
        return html.escape(x)
    if x is None or not np.isfinite(x):
        return '<span class="muted">–</span>'
    return f"{x:.{digits}g}"


def _decimals(sigma: float) -> int:
    """Decimal places that keep two significant digits of ``sigma`` (negative: round to tens...)."""
    return 1 - int(np.floor(np.log10(abs(sigma))))


def _uncertain(x: float, sigma: float) -> tuple[str, str, str]:
    """(x, sigma, power suffix) as text: two significant digits of sigma and x to the same
    place; very large or small magnitudes share one power of ten (suffix ``·10<sup>k</sup>``)."""
    big = max(abs(x), sigma)
    power = int(np.floor(np.log10(big))) if big > 0 else 0
    if -3 <= power < 5:
        d = _decimals(sigma)
        return _round(x, d), _round(sigma, d), ""
    scale = 10.0 ** power
    d = _decimals(sigma / scale)
    return _round(x / scale, d), _round(sigma / scale, d), f"·10<sup>{power}</sup>"


def _known(sigma: float | None) -> bool:
    return sigma is not None and bool(np.isfinite(sigma)) and sigma > 0


def _pm(x: float | None, sigma: float | None, fallback: int = 4) -> str:
    """``x ± sigma`` so that a number shows no digit its uncertainty does not support
    (:func:`_uncertain`). Without a finite positive sigma, x has ``fallback`` significant
    digits and the sigma shows as –."""
    if x is None or not np.isfinite(x):
        return _fmt(None)
    if not _known(sigma):
        return f"{_fmt(x, fallback)} ± {_fmt(None)}"
    xs, ss, power = _uncertain(x, sigma)
    return f"({xs} ± {ss}){power}" if power else f"{xs} ± {ss}"


def _at(x: float | None, sigma: float | None, fallback: int = 4) -> str:
    """``x`` alone to the place two significant digits of ``sigma`` give (interval ends, truths)."""
    if x is None or not np.isfinite(x):
        return _fmt(None)
    if not _known(sigma):
        return _fmt(x, fallback)
    xs, _, power = _uncertain(x, sigma)
    return xs + power


def _round(x: float, decimals: int) -> str:
    if decimals > 0:
        return f"{x:.{decimals}f}"
    return f"{round(x, decimals):.0f}"


#: called with a line after every figure drawn (the report stage's progress; None: silent)
PROGRESS = None


def _img(fig, alt: str) -> str:
    text = f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{figures.to_png_base64(fig)}">'
    if PROGRESS is not None:
        PROGRESS(f"drew {alt}")
    return text


def _held_parameters(fits: dict) -> list[str]:
    """Parameters a fit held because its channels cannot determine them, and the identifiable
    combinations it reports instead (FIT.json ``fixed``, ``combinations``)."""
    parts = []
    for k, f in fits.items():
        if not f.get("fixed"):
            continue
        rule = (f.get("unidentifiable") or {}).get("rule") or ""
        parts.append(f"<h3>{k}: parameters held (the channels cannot determine them)</h3>"
                     f"<p>Rule: {html.escape(rule)}. Held values carry no bound; the member left free in a "
                     "lumped group carries the group, so its value is the group's combination less the held "
                     "values and its σ holds only given them: the combination's σ is the bound.</p>")
        parts.append(_table(["parameter", "held at", "reason"],
                            [[n, _fmt(r["value"], 4), html.escape(r["reason"])] for n, r in f["fixed"].items()]))
        parts.append(_table(["identifiable combination", "value ± CRB σ", "95 % interval"],
                            [[html.escape(c["expression"]), _pm(c["value"], c["std"]),
                              f"[{_at(c['ci95'][0], c['std'])}, {_at(c['ci95'][1], c['std'])}]"]
                             for c in f["combinations"]]))
    return parts


def _identification_section(study: dict, results: Path) -> tuple[str, dict]:
    model = get_model(study["concept"])
    synthetic = not is_measured(model.name)
    fits = {}
    for method in study["identify"]["methods"]:
        path = results / f"fit_{method}.json"
        if path.exists():
            fits[method.upper()] = io.read_json(path)
    if not fits:
        return '<p class="muted">Identification not run.</p>', {}
    truth = model.parameters.vector(study["data"].get("set", {}))
    names = model.parameters.names
    header = ["parameter", "unit"] + (["truth"] if synthetic else []) + [f"{k} estimate ± CRB σ" for k in fits] \
        + ([f"{k} (est−truth)/σ" for k in fits] if synthetic else [])
    rows = []
    for i, n in enumerate(names):
        est = [fits[k]["parameters"][n]["estimate"] for k in fits]
        std = [fits[k]["parameters"][n]["std"] for k in fits]
        # the member that carries a lumped group: its σ holds only given the held members
        kept = [fits[k]["parameters"][n].get("role") == "kept" for k in fits]
        z = [((e - truth[i]) / s) if s and not c else None for e, s, c in zip(est, std, kept)]
        rows.append([n, model.parameters[n].unit] + ([_fmt(truth[i], 4)] if synthetic else [])
                    + [f"{_pm(e, s)} (σ given the held)" if c else _pm(e, s) for e, s, c in zip(est, std, kept)]
                    + ([_fmt(v, 2) for v in z] if synthetic else []))
    summary_rows = [[k, "yes" if f["converged"] else '<span class="flag">no</span>', f["iterations"],
                     f["n_simulations"], f"{f['wall_time_s']:.2f}", _fmt(f["log_det_R"], 8),
                     html.escape(f.get("message", ""))] for k, f in fits.items()]
    parts = ["<h3>Fits</h3>", _table(["method", "converged", "iterations", "simulations", "wall time [s]",
                                      "log det R", "stop"], summary_rows)]
    parts += ["<h3>Parameters</h3>",
              "<p>Truth is the value that generated the synthetic data; σ is the Cramér-Rao bound.</p>" if synthetic
              else "<p>Real measured data: no truth; σ is the Cramér-Rao bound (white-residual assumption).</p>",
              _table(header, rows, name_cols=2)]
    for k, f in fits.items():
        if f.get("high_correlations"):
            pairs = ", ".join(f"{p['a']}–{p['b']} ({p['rho']:+.2f})" for p in f["high_correlations"])
            parts.append(f'<p class="flag">{k}: |ρ| &gt; 0.9 for {html.escape(pairs)}</p>')
        for w in f.get("warnings", []):
            parts.append(f'<p class="flag">{k}: {html.escape(w)}</p>')
    parts += _held_parameters(fits)

    parts.append("<h3>Measured vs identified model (paper Fig. 2/3)</h3>")
    outputs = {k: read_fit_outputs(fit_outputs_path(results / f"fit_{k.lower()}.json")) for k in fits
               if fit_outputs_path(results / f"fit_{k.lower()}.json").exists()}
    if not outputs:
        parts.append('<p class="muted">No predicted outputs beside the fits (FIT.outputs.npz); rerun identify.</p>')
    first = next(iter(outputs.values()), [])
    seen = set()
    for i, record in enumerate(first):
        if record["role"] in seen:  # one figure per role, as the workflow has one record of each
            continue
        seen.add(record["role"])
        channels = record["channels"][:8]
        preds = {k: recs[i]["predicted"][:, :len(channels)] for k, recs in outputs.items()}
        fig = figures.fit_comparison(record["time"], record["measured"][:, :len(channels)], preds, channels,
                                     record["units"][:8],
                                     title=f"{model.title}: {record['role']} data ({record['experiment']})")
        parts.append(_img(fig, f"{record['role']} comparison"))
    parts.append("<h3>Convergence</h3>")
    parts.append(_img(figures.convergence({k: f["history"] for k, f in fits.items()}), "convergence"))

    val_rows = []
    for k, f in fits.items():
        for v in f.get("validation", []):
            for ch, c in v["channels"].items():
                val_rows.append([k, ch, f"{c['fit_percent']:.1f}", _fmt(c["nrmse"], 2),
                                 _fmt(c["ljung_box_p"], 2), "yes" if c["white"] else '<span class="flag">no</span>',
                                 "yes" if c["independent_of_inputs"] else '<span class="flag">no</span>'])
    if val_rows:
        parts += ["<h3>Validation on data not used for estimation</h3>",
                  "<p>fit % = 100 (1 − ‖z − y‖/‖z − mean z‖); residual whiteness by Ljung-Box (25 lags) and "
                  "input cross-correlation (Bonferroni over lags and inputs), both at 1 %.</p>",
                  _table(["method", "channel", "fit %", "NRMSE", "Ljung-Box p", "white", "indep. of inputs"],
                         val_rows, name_cols=2)]
    return "\n".join(parts), fits


def _posterior_section(study: dict, results: Path) -> str:
    """Posterior table (truth, ML ± CRB, mean ± sd, 90 % HDI, R-hat, ESS, MCSE), trace,
    corner and predictive-band figures from ``posterior.nc``."""
    from ..bayes import PosteriorResult
    from . import bayes_figures

    path = results / "posterior.nc"
    if not path.exists():
        return '<p class="muted">Posterior not sampled.</p>'
    post = PosteriorResult.from_netcdf(path)
    model = get_model(study["concept"])
    synthetic = not is_measured(model.name)  # measured data have no truth
    truth = dict(zip(model.parameters.names, model.parameters.vector(study["data"].get("set", {}))))
    table = post.summary()
    hdi_lo, hdi_hi = [c for c in table.columns if c.startswith("hdi_")][:2]
    rows, flagged = [], []
    for name in post.names:
        r = table.loc[name]
        ok = r["r_hat"] < 1.01 and r["ess_bulk"] >= 400
        if not ok:
            flagged.append(name)
        ratio = r["sd"] / r["crb_sd"] if r["crb_sd"] > 0 else np.nan
        rows.append([name] + ([_fmt(truth.get(name), 4)] if synthetic else []) + [
                     _pm(r["ml"], r["crb_sd"]), _pm(r["mean"], r["sd"]),
                     f"[{_at(r[hdi_lo], r['sd'])}, {_at(r[hdi_hi], r['sd'])}]",
                     _fmt(ratio, 2), f"{r['r_hat']:.3f}", f"{r['ess_bulk']:.0f}", f"{r['ess_tail']:.0f}",
                     _fmt(r["mcse_mean"], 2)])
    a = post.attrs
    state = "converged" if post.converged else '<span class="flag">not converged</span>'
    facts = (f"{a['n_ensembles']} ensembles × {a['n_walkers']} walkers × {post.n_steps} steps "
             f"({state}: "
             f"{html.escape(str(a['stop_reason']))}); burn-in {post.burn_in}, thin {post.thin}, "
             f"max τ {float(np.max(post.tau)):.1f} steps, {post.n_simulations} simulations in "
             f"{post.wall_time_s:.0f} s, seed {post.seed}; moves: {html.escape(str(a.get('move_mix', a.get('moves', ''))))}; "
             f"likelihood: {html.escape(str(a.get('likelihood', '')))}, simulated with "
             f"{html.escape(str(a.get('integrator', 'the model integrator')))}.")
    diagnostics = (" R-hat and ESS compare the ensembles (one chain per ensemble: its walkers' kept draws "
                   "concatenated); emcee's τ ESS (steps after burn-in × walkers / τ) is at least "
                   f"{float(np.min(post.ess_tau)):.0f}." if "ess_tau" in a else "")
    parts = [f"<p>emcee started from the ML estimate (N(ML, {float(a['spread']):g} × Cramér-Rao covariance)). "
             f"{facts}{diagnostics}</p>",
             _table(["parameter"] + (["truth"] if synthetic else []) + [
                 "ML ± CRB σ", "posterior mean ± sd", "90 % HDI", "sd / CRB σ", "R-hat", "bulk ESS", "tail ESS",
                 "MCSE mean"], rows)]
    if flagged:
        parts.append(f'<p class="flag">R-hat ≥ 1.01 or bulk ESS &lt; 400: {html.escape(", ".join(flagged))}</p>')
    shown, left_out = bayes_figures.corner_parameters(post)
    corner_note = ("" if not left_out else
                   f"<p>The {len(shown)} parameters in the strongest posterior correlations (pairs taken from the "
                   f"largest |ρ| down); not shown: {html.escape(', '.join(left_out))} (their marginals are in the "
                   "table and the traces). Black crosses: the ML estimate.</p>")
    parts += ["<h3>Traces</h3>",
              "<p>Per parameter: the marginal density of each ensemble (left) and its kept draws (right); ArviZ calls "
              "the ensembles chains 0, 1, ….</p>",
              _img(bayes_figures.trace(post), "trace plots"),
              "<h3>Corner plot</h3>", corner_note, _img(bayes_figures.pair(post, names=shown), "corner plot")]
    parts.append("<h3>Posterior predictive check</h3>")
    try:
        channels, rest = bayes_figures.predictive_channels(post)
        parts += ["<p>Measured data minus the model's posterior median, with the central 90 % band of new data "
                  "(blue: model and noise) and of the model output alone (orange). About 10 % of the points "
                  "should fall outside the blue band. "
                  + (f"Shown: the {len(channels)} channels with the most points outside it; the other "
                     f"{len(rest)} ({html.escape(', '.join(rest))}) have fewer." if rest else "") + "</p>",
                  _img(bayes_figures.predictive_bands(post, channels=channels), "posterior predictive check")]
    except ValueError as exc:
        parts.append(f'<p class="muted">Not drawn: {html.escape(str(exc))}.</p>')
    return "\n".join(parts)


def _sobol_section(results: Path) -> str:
    from . import sensitivity_figures

    path = results / "sobol.json"
    if not path.exists():
        return '<p class="muted">Sobol analysis not run.</p>'
    sobol = io.read_json(path)
    state = "converged" if sobol["converged"] else '<span class="flag">not converged</span>'
    parts = [f"<p>SALib Saltelli design, N = {sobol['n_base']} base samples over {len(sobol['parameters'])} "
             f"parameters ({sobol['n_evaluations']} runs in {sobol['n_chunks']} independent chunks, "
             f"{sobol['evaluations_per_s']:.0f} runs/s); {int(100 * sobol.get('conf_level', 0.95))} % bootstrap "
             f"intervals; N/2 vs N check: {state}.</p>"]
    main = ("cost", "rms_Omega", "rms_y1", "rms_I_A", "rms_U_A", "tracking_error", "peak_torque", "peak_current",
            "energy")
    qoi = [q for q in main if q in sobol["qoi"]] or list(sobol["qoi"])[:8]
    names = list(sobol["parameters"])
    rows = []
    for n in names:
        row = [html.escape(n)]
        for q in qoi:
            st, conf = sobol["qoi"][q]["ST"][n], sobol["qoi"][q]["ST_conf"][n]
            row.append(_pm(st, conf, 2))
        rows.append(row)
    parts += ["<h3>Total indices S<sub>T</sub> ± 95 % interval, main quantities of interest (all in SOBOL.json)</h3>",
              _table(["parameter"] + [html.escape(q) for q in qoi], rows),
              _img(sensitivity_figures.sobol_bars(sobol), "Sobol indices"),
              "<h3>Time-resolved indices with the flap command</h3>",
              _img(sensitivity_figures.time_resolved(sobol), "time-resolved Sobol indices")]
    return "\n".join(parts)


def _identifiability_section(study: dict, results: Path) -> str:
    """Sensor-set verdicts, profiles, combinations and one dossier line per friction/damping
    parameter joining every piece of evidence the workflow produced."""
    from . import sensitivity_figures

    path = results / "ident.json"
    if not path.exists():
        return '<p class="muted">Identifiability analysis not run.</p>'
    ident = io.read_json(path)
    sobol = io.read_json(results / "sobol.json") if (results / "sobol.json").exists() else None
    posterior = None
    if (results / "posterior.nc").exists():
        from ..bayes import PosteriorResult

        posterior = PosteriorResult.from_netcdf(results / "posterior.nc").summary()
    sets = ident["sensor_sets"]
    parts = [f'<p class="muted">Sensor set {html.escape(name)} not assessed: {html.escape(why)}.</p>'
             for name, why in (ident.get("skipped_sensor_sets") or {}).items()]
    for name, r in sets.items():
        fim = r["fim"]
        if fim.get("condition") is not None:
            condition = f"condition number {_fmt(fim['condition'], 2)}"
        else:  # singular: the number that means something is the one on the identifiable subspace
            condition = ("singular (no condition number); condition on the identifiable subspace "
                         f"{_fmt(fim.get('condition_identifiable'), 2)}")
        parts.append(f"<p><b>{html.escape(name)}</b> sensors ({html.escape(', '.join(r['channels']))}): information "
                     f"rank {fim['rank']} of {fim['n_parameters']}, {condition}.</p>")
        if r["combinations"]:
            items = "".join(f"<li>{html.escape(c['expression'])} = {_pm(c.get('value'), c.get('std'))}</li>"
                            for c in r["combinations"])
            parts.append(f"<p>Identifiable combinations:</p><ul>{items}</ul>")
    parts += [_img(sensitivity_figures.sensor_set_verdicts(ident), "verdicts per sensor set"),
              _img(sensitivity_figures.profile_likelihoods(ident), "profile likelihoods")]
    header = ["parameter"]
    for name in sets:
        header += [f"{name}: CRB σ", f"{name}: profile 95 %", f"{name}: γ max (with)", f"{name}: verdict"]
    header += ["Sobol S_T (cost)", "posterior sd / CRB σ"]
    rows = []
    for n in ident["comparison"]:
        row = [html.escape(n)]
        for name, r in sets.items():
            t = r["parameters"].get(n)
            if t is None:
                row += ["–"] * 4
                continue
            ci = t.get("profile_ci")
            ci_text = "–" if not ci else "[" + ", ".join("open" if x is None else _at(x, t["crb_std"], 3)
                                                         for x in ci) + "]"
            verdict = t["verdict"].replace("_", " ")
            if t["verdict"] != "identifiable":
                verdict = f'<span class="flag">{verdict}</span>'
            row += [_fmt(t["crb_std"], 2), ci_text,
                    f"{_gamma(t['collinearity'])} ({html.escape(str(t.get('most_collinear_with') or '–'))})", verdict]
        cost = sobol["qoi"].get("cost", {}) if sobol else {}
        st, st_conf = cost.get("ST", {}).get(n), cost.get("ST_conf", {}).get(n)
        ratio = None
        if posterior is not None and n in posterior.index and posterior.loc[n, "crb_sd"] > 0:
            ratio = posterior.loc[n, "sd"] / posterior.loc[n, "crb_sd"]
        row += [_pm(st, st_conf, 2) if st is not None else _fmt(None), _fmt(ratio, 2)]
        rows.append(row)
    parts += ["<h3>Dossier per friction/damping parameter</h3>",
              "<p>Cramér-Rao σ, 95 % profile-likelihood interval, largest pairwise Brun collinearity index and its "
              "partner, and the verdict for each sensor set; the Sobol total index of the det R cost and the posterior "
              "width relative to the Cramér-Rao σ (fit channels of the study).</p>",
              _table(header, rows)]
    return "\n".join(parts)


def _gamma(value: float | None) -> str:
    """A Brun collinearity index; the analysis caps an exactly collinear pair at GAMMA_CAP."""
    from ..identifiability import GAMMA_CAP

    if value is not None and np.isfinite(value) and value >= GAMMA_CAP:
        return "≥ 10<sup>12</sup> (exactly collinear)"
    return _fmt(value, 2)


def _png_file(path: Path, alt: str) -> str:
    import base64

    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{base64.b64encode(path.read_bytes()).decode()}">'


def _effect_name(gap: dict) -> str:
    """"family (form)" when the winning form is not the family's own effect, else the effect."""
    effect, family = str(gap.get("effect")), gap.get("family")
    return f"{family} ({effect})" if family and family != effect else effect


def _honest_shrink(summary: dict) -> str:
    """The shrink of an ``effect`` verdict, scored on held-out data not used to choose the effect."""
    if summary.get("shrink") is None:
        return "No shrink is reported: the verdict names no effect."
    return (f"Shrink {_pm(summary['shrink'], summary.get('shrink_se'), 2)} (signed, ± block-bootstrap "
            f"standard error), scored on {html.escape(str(summary.get('shrink_record', 'held-out data')))}, "
            "which did not take part in choosing the effect.")


def _open_set_parts(gap: dict) -> list[str]:
    """Family probabilities and, when a candidate leaves structure, where (the open-set verdict)."""
    probabilities = gap.get("family_probabilities") or {}
    if not probabilities:
        return []
    tempering = gap.get("evidence_tempering")
    rows = [[html.escape(f), f"{p:.3g}"] for f, p in probabilities.items()]
    parts = ["<h3>Family probabilities</h3>",
             f"<p>From each family's evidence ΔBIC + held-out gain (the nominal model is <i>none</i>), tempered by "
             f"the effective-sample fraction {_fmt(tempering, 2)} of the best model's residual; a family is named "
             f"only when it beats every other by 2 ln B ≥ {_fmt(gap.get('margin_evidence'), 3)} and leaves no "
             "structure.</p>", _table(["family", "probability"], rows)]
    if gap.get("verdict_reason"):
        parts.append(f"<p>Not named: {html.escape(str(gap['verdict_reason']))}.</p>")
    where = gap.get("where_left") or {}
    if where:
        items = "".join(f"<li><b>{html.escape(group)}</b>: {html.escape('; '.join(cells[:3]))}</li>"
                        for group, cells in where.items())
        parts.append("<p>Structure the best candidate leaves on the held-out data (cells it did not halve, "
                     f"holding a material part of the gap):</p><ul>{items}</ul>")
    return parts


def _scored_gap(summary: dict) -> tuple[float | None, float | None]:
    """(before, after) of the gap on the held-out part that scores the shrink: the one pair of
    numbers the report prints for the held-out gap, so text, table and ledger agree
    (``shrink = 1 - after / before``). Older GAP.json files have only before/after."""
    if summary.get("shrink_gap_before") is not None:
        return summary["shrink_gap_before"], summary.get("shrink_gap_after")
    return summary.get("before", summary.get("gap_before")), summary.get("after", summary.get("gap_after"))


def _gap_section(study: dict, results: Path) -> str:
    """The gap ledger: verdict, where the nominal model departs, each candidate's refit scores,
    the winner's parameters and the before/after figure."""
    path = results / "gap.json"
    if not path.exists():
        return '<p class="muted">Gap diagnosis not run.</p>'
    gap = io.read_json(path)
    hidden = study.get("gap", {}).get("rig_effects") or []
    verdict = html.escape(str(gap["verdict"])) + (f": <b>{html.escape(_effect_name(gap))}</b>" if gap.get("effect") else "")
    parts = [f"<p>Verdict <b>{verdict}</b>"
             + (f" (confidence {html.escape(str(gap['confidence']))})" if gap.get("confidence") else "") + ". "
             + f"The gap lies in channels {html.escape(', '.join(gap['where'].get('channels', [])) or '–')} and "
               f"regimes {html.escape(', '.join(gap['where'].get('regimes', [])) or '–')}.</p>"]
    if not is_measured(study["concept"]):
        truth = ", ".join(hidden) if hidden else "none (the rig-like records are nominal-model data)"
        parts.append(f"<p>Check of this study: the rig-like records were generated with the hidden effect(s) "
                     f"<b>{html.escape(truth)}</b>; the diagnosis did not see them.</p>")
    summary = gap.get("gap") or {}
    before, after = _scored_gap(summary)
    if before is not None:
        metric = summary.get("metric", "held-out systematic NRMSE")
        # the numbers the shrink is computed from, as in the candidate table and the ledger figure
        parts.append(f"<p>Gap metric ({html.escape(str(metric))}) on the scoring part of the held-out data: "
                     f"{_fmt(before, 3)} before, {_fmt(after, 3)} after the winning candidate. "
                     f"{_honest_shrink(summary)}</p>")
    parts += _open_set_parts(gap)
    extra = [k for k in ("delta_bic", "likelihood_ratio", "held_out_gain", "signature_match") if gap["ranking"]
             and k in gap["ranking"][0]]
    rows = [[html.escape(str(c["effect"])), html.escape(str(c.get("family", c["effect"]))), _fmt(c["score"], 4),
             _fmt(c["gap_before"], 3), _fmt(c["gap_after"], 3),
             _pm(c["shrink"], c.get("shrink_se"), 2)] + [_fmt(c.get(k), 3) for k in extra]
            for c in gap["ranking"]]
    parts += ["<h3>Candidates (best first; gap and shrink on the scoring part of the held-out data)</h3>",
              _table(["effect", "family", "score", "gap before", "gap after", "shrink ± se"]
                     + [k.replace("_", " ") for k in extra], rows, name_cols=2)]
    params = gap.get("effect_parameters") or {}
    if params:
        prow = [[html.escape(k), _pm(v.get("estimate"), v.get("std")),
                 html.escape(str(v.get("unit", "")))] for k, v in params.items()]
        parts += ["<h3>Estimated effect parameters</h3>", _table(["parameter", "estimate ± CRB σ", "unit"], prow)]
    if gap.get("selected"):
        parts.append(f"<p>Effects kept by forward selection: {html.escape(' + '.join(gap['selected']))}.</p>")
    ledger = results / "gap_ledger.png"
    parts.append("<h3>Gap ledger</h3>")
    if ledger.exists():
        parts.append(_png_file(ledger, "gap ledger"))
    else:
        parts.append('<p class="muted">No ledger figure: the gap stage wrote none (ema-uq gap --figure '
                     'gap_ledger.png draws it).</p>')
    return "\n".join(parts)


def _left_out_table(matrix: dict) -> str:
    """The left-out-family confusion matrix as a table (rows: family left out; right: a flag)."""
    if not matrix:
        return ""
    columns = sorted({c for row in matrix.values() for c in row},
                     key=lambda c: ({"ambiguous": 1, "unexplained": 1, "none": 2}.get(c, 0), c))
    rows = [[html.escape(r)] + [str(matrix[r].get(c, 0) or "·") for c in columns] for r in sorted(matrix)]
    return ("<h3>Left-out families</h3><p>Each in-catalogue variant diagnosed with its family's forms removed "
            "from the catalogue; the right verdict is a flag (“unexplained” or “ambiguous”).</p>"
            + _table(["family left out", *map(html.escape, columns)], rows))


def _selfcheck_section(results: Path) -> str:
    from . import gap_figures

    path = results / "selfcheck.json"
    if not path.exists():
        return '<p class="muted">Blind self-check not run for this study.</p>'
    sc = io.read_json(path)
    if "top1" not in sc:
        return '<p class="muted">Self-check file of an older format; rerun ema-uq gap-selfcheck.</p>'
    targets = sc["targets"]
    # the self-check's own one-sided judgement; files without it are judged on the two-sided interval
    status = sc.get("status") or {}

    def rate(name, key, score, cmp):
        r = sc.get(score)
        if r is None or key not in targets:
            return [name, "–", "", "", ""]
        if not r.get("n"):
            return [name, "no case", "–", f"{cmp} {targets[key]}", '<span class="muted">not shown: no case</span>']
        low, high = r["interval95"]
        if key in status:
            mark = status[key]
            mark = mark if mark == "met" else f'<span class="flag">{html.escape(mark)}</span>'
        else:
            mark = _judged(low, high, targets[key], cmp)
        return [name, f"{_fmt(r['value'], 3)} ({r['count']}/{r['n']})", f"{_fmt(low, 2)}–{_fmt(high, 2)}",
                f"{cmp} {targets[key]}", mark]

    s = sc["shrink"]
    rows = [rate("top-1 accuracy (right family named)", "top1_accuracy", "top1", "≥"),
            rate("false-alarm rate (no-effect cases)", "false_alarm_rate", "false_alarms", "≤"),
            rate("outside the catalogue flagged (“unexplained” or “ambiguous”)", "out_of_catalogue_flagged",
                 "out_of_catalogue_flagged", "≥"),
            rate("left-out family flagged (its forms removed from the catalogue)", "left_out_flagged",
                 "left_out_flagged", "≥"),
            rate("wrong family named with high confidence", "wrong_family_confident", "wrong_family_confident", "≤"),
            ["honest shrink where the right family was named (median, quartiles)",
             (f"{_fmt(s['median'], 2)} ({_fmt(s['q25'], 2)}–{_fmt(s['q75'], 2)}), n = {s['n']}" if s.get("n", 0) >= 4
              else f"n = {s.get('n', 0)}: " + (", ".join(_fmt(c["shrink"], 2) for c in sc["cases"]
                                                          if c.get("shrink") is not None and c["correct"]) or "–")),
             f"median se {_fmt(s['median_se'], 2)}" if s.get("n") else "–", "", ""]]
    cases = []
    for c in sc["cases"]:
        shrink = "" if c.get("shrink") is None else _pm(c["shrink"], c.get("shrink_se"), 2)
        ok = "yes" if c["correct"] else '<span class="flag">no</span>'
        cases.append([html.escape(str(c["case_id"]).split("/")[-1]), html.escape(str(c["truth_family"] or c["expected"])),
                      html.escape(c["sensors"]), html.escape(c["verdict"]),
                      html.escape(str(c["family"]) if c["verdict"] == "effect"
                                  else " | ".join(c.get("ambiguous_families") or []) or "–"),
                      html.escape(c["confidence"]), shrink, f"{c['wall_time_s']:.0f}", ok])
    settings = sc.get("settings", {})
    return ("<p>Rig-like records of an independent simulator with effect variants written apart from the "
            "catalogue's kernels (magnitudes log-uniform, phases uniform, base parameters ±10 % off nominal, "
            "2 % noise), diagnosed without their labels; the honest shrink is scored on a second validation "
            f"record that did not select the winner. Concepts {html.escape(', '.join(settings.get('concepts', [])))}, "
            f"sensor sets {html.escape(', '.join(settings.get('sensors', [])))}, seed {sc['seed']}"
            f"{', quick subset' if sc.get('quick') else ''}; {sc['n_cases']} cases in {sc['wall_time_s']:.0f} s.</p>"
            + _table(["score", "value", "95 % interval", "target", ""], rows)
            + "<p>A target is met or not met only where the one-sided 95 % Clopper-Pearson bound shows it; "
            "“n too small” otherwise. False alarms: a named effect on a no-effect case (half of them with "
            "model-form stress); a low-confidence “unexplained” is a soft alarm "
            f"({_fmt((sc.get('soft_alarms') or {}).get('value'), 3)}), a high-confidence one a hard alarm "
            f"({_fmt((sc.get('hard_alarms') or {}).get('value'), 3)}).</p>"
            + "<h3>Confusion matrix</h3>" + _img(gap_figures.selfcheck_confusion(sc), "self-check confusion matrix")
            + _left_out_table(sc.get("confusion_left_out") or {})
            + "<h3>Cases</h3>"
            + _table(["case", "truth family", "sensors", "verdict", "family found", "confidence",
                      "shrink ± se", "time [s]", "right"], cases))


def _judged(low: float, high: float, target: float, cmp: str) -> str:
    """A target judged by the 95 % interval of its rate, not by the point estimate: met when the
    whole interval is on the right side, not met when it is wholly on the wrong side, and not
    shown either way when it straddles the target (too few cases for this target)."""
    good, bad = (low >= target, high < target) if cmp == "≥" else (high <= target, low > target)
    if good:
        return '<span class="ok">met</span>'
    if bad:
        return '<span class="flag">NOT met</span>'
    return '<span class="muted">not shown: n too small for the target</span>'


def _read(results: Path, name: str) -> dict | None:
    return io.read_json(results / name) if (results / name).exists() else None


def _estimate_findings(study: dict, results: Path, fits: dict) -> list[str]:
    """Per fit: the largest |estimate - truth| / CRB σ (synthetic data) or |ML - published| / σ
    (EMPS, the published IDIM-LS values)."""
    model = get_model(study["concept"])
    items = []
    if not is_measured(model.name):
        truth = dict(zip(model.parameters.names, model.parameters.vector(study["data"].get("set", {}))))
        for k, f in fits.items():
            z = {n: abs(p["estimate"] - truth[n]) / p["std"] for n, p in f["parameters"].items()
                 if n in truth and p.get("std") and np.isfinite(p["std"]) and p["std"] > 0 and p.get("role") != "kept"}
            if z:
                worst = max(z, key=z.get)
                state = "converged" if f["converged"] else '<span class="flag">not converged</span>'
                items.append(f"{k} estimates vs truth: max |error|/CRB σ = {_fmt(z[worst], 3)} "
                             f"({html.escape(worst)}), {state}.")
        return items
    comp = (fits.get("GN") or {}).get("published_comparison")
    if comp:
        z = {r["parameter"]: abs(r["z"]) for r in comp["parameters"] if r["z"] is not None and np.isfinite(r["z"])}
        diff = {r["parameter"]: abs(r["difference_percent"]) for r in comp["parameters"]}
        worst = max(diff, key=diff.get)
        items.append(f"GN estimates vs published {html.escape(comp['reference'])}: max |difference| "
                     f"{_fmt(diff[worst], 3)} % ({html.escape(worst)})"
                     + (f", max |difference|/σ = {_fmt(max(z.values()), 3)} ({html.escape(max(z, key=z.get))})"
                        if z else ""))
    return items


def _summary_section(study: dict, results: Path, fits: dict) -> str:
    """The findings of every stage in a few lines: verdicts, estimates, convergence, Sobol."""
    items = []
    gap = _read(results, "gap.json")
    if gap:
        what = {"effect": f"effect <b>{html.escape(_effect_name(gap))}</b>", "none": "no significant gap",
                "unexplained": "unexplained gap",
                "ambiguous": "ambiguous between " + html.escape(" / ".join(
                    c["family"] for c in gap.get("contenders") or []))}.get(gap["verdict"],
                                                                           html.escape(str(gap["verdict"])))
        conf = f", {html.escape(str(gap['confidence']))} confidence" if gap.get("confidence") else ""
        params = "; ".join(f"{html.escape(n)} = {_pm(v.get('estimate'), v.get('std'))} "
                           f"{html.escape(str(v.get('unit', '')))}" for n, v in (gap.get("effect_parameters") or {}).items())
        items.append(f"Sim-to-real gap: {what}{conf}" + (f" ({params})" if params else "") + ".")
    faults = _read(results, "faults.json")
    if faults:
        rows = faults["diagnoses"]
        right = sum(_fault_label(r) == faults["expected"].get(r["record_set"]) for r in rows)
        items.append(f"Fault diagnosis of measured records against the healthy fit: {right} of {len(rows)} record "
                     "sets as expected (" + ", ".join(f"{html.escape(r['record_set'])} → "
                                                      f"{html.escape(_fault_label(r))}" for r in rows) + ").")
    ident = _read(results, "ident.json")
    if ident:
        from ..identifiability import VERDICTS

        for name, r in ident["sensor_sets"].items():
            counts = [sum(t["verdict"] == v for t in r["parameters"].values()) for v in VERDICTS]
            items.append(f"Identifiability, {html.escape(name)} sensors: {counts[0]} identifiable, {counts[1]} "
                         f"practically and {counts[2]} structurally non-identifiable.")
    items += _estimate_findings(study, results, fits)
    if (results / "posterior.nc").exists():
        from ..bayes import PosteriorResult

        post = PosteriorResult.from_netcdf(results / "posterior.nc")
        table = post.summary()
        items.append(f"Posterior: max R-hat {_fmt(float(table['r_hat'].max()), 4)}, min bulk ESS "
                     f"{float(table['ess_bulk'].min()):.0f}, converged "
                     + ("yes" if post.converged else '<span class="flag">no</span> ('
                        + html.escape(str(post.attrs.get("stop_reason", "step cap reached"))) + ")") + ".")
    sobol = _read(results, "sobol.json")
    if sobol and "cost" in sobol["qoi"]:
        st, conf = sobol["qoi"]["cost"]["ST"], sobol["qoi"]["cost"].get("ST_conf", {})
        top = sorted(st, key=lambda n: -st[n])[:3]
        items.append("Sobol, largest total indices of the det R cost (± 95 % interval): "
                     + ", ".join(f"{html.escape(n)} {_pm(st[n], conf.get(n), 2)}" for n in top) + ".")
    if not items:
        return '<p class="muted">No stage has written results yet.</p>'
    return "<ul>" + "".join(f"<li>{i}</li>" for i in items) + "</ul>"


def _published_section(study: dict, results: Path) -> str:
    """EMPS: ML beside the published IDIM-LS values and simulation errors next to the published
    figures, as ``ema-uq identify`` wrote them into FIT.json (``published_comparison``)."""
    path = results / "fit_gn.json"
    comp = io.read_json(path).get("published_comparison") if path.exists() else None
    if not comp:
        return '<p class="muted">EMPS fit (with its comparison to the published values) not available.</p>'
    rows = [[html.escape(r["parameter"]), html.escape(r["unit"]), _pm(r["ml"], r["ml_std"]),
             _pm(r["published"], r["published_std"]), _fmt(r["difference_percent"], 2),
             _fmt(r["z"], 2)] for r in comp["parameters"]]
    err_rows = []
    for role, kinds in comp["errors"].items():
        for kind, e in kinds.items():
            err_rows.append([role, kind.replace("_", " ")] + [_fmt(e.get(k), 4) for k in
                                                              ("position", "velocity", "acceleration", "force")])
    notes = "".join(f"<li>{html.escape(n)}</li>" for n in comp["notes"])
    return (f"<p>ML output error ({comp['method'].upper()}, channels {html.escape(', '.join(comp['channels']))}) "
            f"beside the published {html.escape(comp['reference'])} estimates (inverse dynamics, Janot, Gautier, Brunot 2019).</p>"
            + _table(["parameter", "unit", "ML ± CRB σ", "published ± σ", "difference %", "z"], rows, name_cols=2)
            + "<h3>Simulation errors [%] (benchmark definition: 100‖z − y‖/‖z‖)</h3>"
            + _table(["record", "model", "position", "velocity", "acceleration", "force"], err_rows, name_cols=2)
            + f"<h3>Why the estimates differ</h3><ul>{notes}</ul>")


def _fault_label(row: dict) -> str:
    return str(row["effect"] if row["verdict"] == "effect" else row["verdict"])


def _faults_section(results: Path) -> str:
    """Measured seeded-fault records (``ema-uq fault-diagnosis``): the healthy fit, then every
    record set's verdict against it, the expected verdict, shrink ± se and the effect's parameters."""
    faults = _read(results, "faults.json")
    if not faults:
        return '<p class="muted">Fault diagnosis not run.</p>'
    ref = faults["reference"]
    nrmse = ", ".join(f"{html.escape(c)} {_fmt(v, 3)}" for c, v in (ref.get("nrmse_held_out") or {}).items())
    parts = [f"<p>Rig model fitted on the healthy runs; NRMSE on held-out healthy runs: {nrmse}. Each record set "
             "is diagnosed against that fit: the base parameters are held, only the candidate effect's parameters "
             "are fitted (on the record set's estimation runs, thinned by a stride of "
             f"{html.escape(str(ref.get('thinning_stride', ref.get('stride', '?'))))} samples, the residual's "
             "correlation time), and the shrink is scored on a held-out block not used to choose the effect. The "
             "runs repeat one cycle, so the gap splits into a reproducible part, which the mean of the estimation "
             "runs' residual at the same load and phase of the cycle closes, and a part that changes from run to "
             "run (the rig drifts within a test session), which no fixed effect can explain: <i>reproducible</i> is "
             "the share of the selection blocks' gap in the first part, <i>closed</i> the share of it the best "
             "candidate closes, which the verdict requires to be at least one half.</p>"]
    rows = []
    for r in faults["diagnoses"]:
        label, expected = _fault_label(r), faults["expected"].get(r["record_set"], "?")
        mark = "" if label == expected else ' <span class="flag">≠ expected</span>'
        shrink = "–" if r.get("shrink") is None else _pm(r["shrink"], r.get("shrink_se"), 2)
        params = "; ".join(f"{html.escape(n)} = {_pm(p.get('estimate'), p.get('std'))} "
                           f"{html.escape(str(p.get('unit', '')))}" for n, p in
                           ((r.get("effect_parameters") or {}).items() if r["verdict"] == "effect" else ()))
        rows.append([html.escape(r["record_set"]), html.escape(expected), html.escape(label) + mark,
                     html.escape(str(r.get("confidence") or "–")), html.escape(str(r.get("runner_up") or "–")),
                     _fmt(r.get("gap_before"), 4), _fmt(r.get("gap_after"), 4)]
                    # the split of a gap that is not there (insignificant: noise) says nothing
                    + ([_fmt(r.get("reproducible_share"), 2), _fmt(r.get("reproducible_shrink"), 2)]
                       if r.get("significant_selection", True) else ["no gap", "–"])
                    + [shrink, params or "–", _fault_why(r)])
    parts.append(_table(["record set", "expected", "verdict", "confidence", "runner-up", "gap before", "gap after",
                         "reproducible", "closed", "shrink ± se", "effect parameters (± CRB σ)",
                         "family probability; why not named; where left"], rows))
    return "\n".join(parts)


def _fault_why(r: dict) -> str:
    """Family probabilities (top 3), contenders, the reason no family was named and the first
    cell left per group, of one fault-diagnosis row."""
    probabilities = r.get("family_probabilities") or {}
    parts = ([", ".join(f"{html.escape(f)} {_fmt(p, 3)}" for f, p in probabilities.items())] if probabilities else [])
    if r.get("contenders"):
        parts.append("contenders " + " / ".join(map(html.escape, r["contenders"])))
    if r.get("verdict_reason"):
        parts.append(html.escape(str(r["verdict_reason"])))
    parts += [f"{html.escape(g)}: {html.escape(str(c))}" for g, c in (r.get("where_left") or {}).items()]
    return "<br>".join(parts) or "–"


def _stage_cost_section(results: Path) -> str:
    """Wall time and peak memory of every workflow job, from Snakemake's benchmark files."""
    rows, total = [], 0.0
    for path in sorted((results / "benchmarks").glob("*.tsv")):
        lines = [line.split("\t") for line in path.read_text().splitlines() if line.strip()]
        if len(lines) < 2:
            continue
        record = dict(zip(lines[0], lines[-1]))
        try:
            seconds, rss = float(record["s"]), float(record["max_rss"])
        except (KeyError, ValueError):
            continue  # a benchmark still being written, or from another Snakemake version
        total += seconds
        cpu = record.get("cpu_time", "")
        rows.append([html.escape(path.stem), f"{seconds:.1f}", _fmt(float(cpu), 3) if cpu not in ("", "NA") else _fmt(None),
                     f"{rss:.0f}"])
    if not rows:
        return '<p class="muted">No benchmark files (the stages were not run by the workflow).</p>'
    rows.append(["<b>total</b>", f"<b>{total:.1f}</b>", "", ""])
    return ("<p>From the workflow's benchmark files (one per job; the report's own job is listed from its "
            "previous run). Peak memory is the maximum resident set size.</p>"
            + _table(["job", "wall time [s]", "CPU time [s]", "peak memory [MB]"], rows))


#: the dependencies whose versions can change a number of the report
DEPENDENCIES = ("numpy", "scipy", "numba", "xarray", "pandas", "emcee", "arviz", "SALib", "matplotlib", "snakemake")


def _source_state() -> tuple[str, str]:
    """(commit, state) of the git checkout the package is imported from: state is "clean",
    "dirty (n files changed)" or why there is no commit (an installed wheel, no git)."""
    import subprocess

    root = Path(__file__).resolve().parents[2]
    try:
        commit = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"], capture_output=True, text=True,
                                timeout=20)
        if commit.returncode != 0:
            return "–", "not a git checkout (an installed copy)"
        status = subprocess.run(["git", "-C", str(root), "status", "--porcelain", "--untracked-files=no"],
                                capture_output=True, text=True, timeout=20)
    except (OSError, subprocess.SubprocessError):
        return "–", "git not available"
    changed = [line for line in status.stdout.splitlines() if line.strip()]
    return commit.stdout.strip(), f"dirty ({len(changed)} tracked files changed)" if changed else "clean"


def _versions() -> str:
    from importlib import metadata

    out = []
    for name in DEPENDENCIES:
        try:
            out.append(f"{name} {metadata.version(name)}")
        except metadata.PackageNotFoundError:
            out.append(f"{name} not installed")
    return ", ".join(out)


def _provenance_section(study: dict, study_path: Path, results: Path, fits: dict) -> str:
    import platform

    from .. import __version__

    commit, state = _source_state()
    rows = [["package version", __version__], ["git commit", commit],
            ["working tree", f'<span class="flag">{state}</span>' if state.startswith("dirty") else state],
            ["Python", platform.python_version()], ["dependencies", html.escape(_versions())],
            ["study file", html.escape(str(study_path.name))],
            ["study hash", settings_hash(study)], ["seed", study.get("seed")]]
    for f in sorted(results.rglob("*")):
        if f.is_file() and f.suffix in (".nc", ".csv", ".mat") and "logs" not in f.parts:
            rows.append([f"sha256 {html.escape(str(f.relative_to(results)))}", file_sha256(f)[:32] + "…"])
    rig = rig_of(study["concept"])
    for label, f in rig.data_files(study) if rig is not None else ():
        rows.append([f"sha256 {html.escape(label)}", file_sha256(f)[:32] + "…" if f.is_file() else "not found"])
    for k, fit in fits.items():
        rows.append([f"{k} fit created", html.escape(str(fit.get("provenance", {}).get("created", "")))])
    return _table(["item", "value"], [[html.escape(str(a)), str(b)] for a, b in rows], name_cols=2)


def build_report(study: dict, study_path: str | Path, results: str | Path) -> str:
    """HTML text of the report for ``study`` from the result files in ``results``."""
    results, study_path = Path(results), Path(study_path)
    rig = rig_of(study["concept"])
    if rig is not None and rig.fault_diagnosis:  # measured fault records: one stage, healthy fit and diagnoses
        return _render(study, [("summary", "Summary of findings", _summary_section(study, results, {})),
                               ("faults", "Fault diagnosis of measured records", _faults_section(results)),
                               ("cost", "Time and memory per stage", _stage_cost_section(results)),
                               ("provenance", "Provenance", _provenance_section(study, study_path, results, {}))])
    ident, fits = _identification_section(study, results)
    sections = [("summary", "Summary of findings", _summary_section(study, results, fits)),
                ("identification", "Maximum-likelihood identification", ident)]
    if rig is not None and rig.published_comparison is not None:
        sections.append((rig.concept, f"{rig.title}: ML vs the published identification", _published_section(study, results)))
    sections.append(("posterior", "Bayesian posterior", _posterior_section(study, results)))
    if rig is None:  # synthetic data of an EMA concept: Sobol and identifiability of its friction terms
        sections.append(("sobol", "Sobol sensitivity", _sobol_section(results)))
        sections.append(("identifiability", "Identifiability of the friction and damping parameters",
                         _identifiability_section(study, results)))
    if (results / "gap.json").exists():
        sections.append(("gap", "Sim-to-real gap", _gap_section(study, results)))
    if (results / "selfcheck.json").exists():
        sections.append(("selfcheck", "Blind self-check of the gap diagnosis", _selfcheck_section(results)))
    stages = {"posterior": "Bayesian posterior", "sobol": "Sobol sensitivity",
              "ident": "Identifiability", "gap": "Sim-to-real gap"}
    if rig is not None:  # Sobol and identifiability concern the EMA friction terms
        stages = {k: v for k, v in stages.items() if k in ("posterior", "gap")}
    pending = [title for key, title in stages.items() if not any(results.glob(f"{key}*"))]
    if pending:
        sections.append(("pending", "Stages not run", "<p class=\"muted\">" + ", ".join(pending) + "</p>"))
    sections.append(("cost", "Time and memory per stage", _stage_cost_section(results)))
    sections.append(("provenance", "Provenance", _provenance_section(study, study_path, results, fits)))
    return _render(study, sections)


def _render(study: dict, sections: list[tuple[str, str, str]]) -> str:
    body = "\n".join(f'<h2 id="{key}">{title}</h2>\n{content}' for key, title, content in sections)
    nav = " ".join(f'<a href="#{key}">{title}</a>' for key, title, _ in sections)
    template = Template(resources.files("ema_uq").joinpath(TEMPLATE).read_text())
    model = get_model(study["concept"])
    return template.substitute(title=html.escape(f"{study['name']} — {model.title}"),
                               description=html.escape(study.get("description", "")),
                               nav=nav, sections=body)
