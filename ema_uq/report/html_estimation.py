"""Report sections of the estimation stages: the maximum-likelihood fits (parameters, measured
vs predicted outputs, convergence, validation), a rig's comparison with its published
identification, the Bayesian posterior, the Sobol sensitivity and the identifiability of the
friction and damping parameters; and the findings of the fits for the summary.
"""
from __future__ import annotations

import html
from pathlib import Path

import numpy as np

from .. import io
from ..models import get_model
from ..rigs import is_measured
from . import figures
from .html_format import _at, _fmt, _img, _pm, _table
from .outputs import fit_outputs_path, read_fit_outputs


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
