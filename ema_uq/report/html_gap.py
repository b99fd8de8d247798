"""Report sections of the sim-to-real gap: the gap diagnosis of a study's records (verdict,
candidates, open-set evidence, ledger), the blind self-check of that diagnosis (scores against
their targets, confusion matrices, cases) and the fault diagnosis of a rig's measured records.
"""
from __future__ import annotations

import html
from pathlib import Path

from .. import io
from ..rigs import is_measured
from .html_format import _fmt, _img, _pm, _png_file, _read, _table


def _effect_name(gap: dict) -> str:
    """"family (form)" when the winning form is not the family's own effect, else the effect."""
    effect, family = str(gap.get("effect")), gap.get("family")
    return f"{family} ({effect})" if family and family != effect else effect


def _honest_shrink(summary: dict) -> str:
    """The shrink of an ``effect`` verdict, scored on held-out data not used to choose the effect."""
    if summary.get("shrink") is None:
        return "No shrink is reported: the verdict names no effect."
    from ..gap.result import SHRINK_RESOLVED_SE, shrink_resolved    # the gap package is heavy; only here
    text = (f"Shrink {_pm(summary['shrink'], summary.get('shrink_se'), 2)} (signed, ± block-bootstrap "
            f"standard error), scored on {html.escape(str(summary.get('shrink_record', 'held-out data')))}, "
            "which did not take part in choosing the effect.")
    if not shrink_resolved(summary["shrink"], summary.get("shrink_se")):
        text += (f' <span class="flag">Not resolved: less than {SHRINK_RESOLVED_SE:g} standard errors above zero, '
                 "so this record does not confirm the effect; it is named on the selection part alone.</span>")
    return text


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
               f"regimes {html.escape(', '.join(gap['where'].get('regimes', [])) or '–')}"
             + (f"; along the stroke in {html.escape('; '.join(gap['where']['stroke']))}"
                if gap["where"].get("stroke") else "") + ".</p>"]
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


def _score_rows(sc: dict) -> list[list[str]]:
    """Score rows (score, value, 95 % interval, target, judgement) of a self-check (SELFCHECK.json)."""
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

    return [rate("top-1 accuracy (right family named)", "top1_accuracy", "top1", "≥"),
            rate("false-alarm rate (no-effect cases)", "false_alarm_rate", "false_alarms", "≤"),
            rate("outside the catalogue flagged (“unexplained” or “ambiguous”)", "out_of_catalogue_flagged",
                 "out_of_catalogue_flagged", "≥"),
            rate("left-out family flagged (its forms removed from the catalogue)", "left_out_flagged",
                 "left_out_flagged", "≥"),
            rate("wrong family named with high confidence", "wrong_family_confident", "wrong_family_confident", "≤")]


def _evaluation_part(evaluation: dict | None) -> str:
    """The out-of-sample figures of the default method: its frozen protocol's evaluation block,
    run once on frozen sources (``benchmarks/gap.py --protocol``), beside this run's self-check,
    whose seed the method may have been built on."""
    if evaluation is None:
        return ""
    settings = evaluation.get("settings") or {}
    seeds = ", ".join(str(seed) for seed in settings.get("seeds") or [evaluation.get("seed")])
    return ("<h3>Out of sample: the default method's evaluation block</h3>"
            "<p>The figures above are on this run's seed, which may have been looked at while the method was "
            "built. These are the evaluation block of the default method's frozen protocol: seeds "
            f"{html.escape(seeds)}, {evaluation['n_cases']} cases, run once on frozen sources "
            f"(sources {html.escape(str(settings.get('sources_sha256', '?'))[:12])}), nothing changed because of "
            "them.</p>"
            + _table(["score", "value", "95 % interval", "target", ""], _score_rows(evaluation)))


def _selfcheck_section(results: Path, evaluation: dict | None = None) -> str:
    """The blind self-check of a study (``results/selfcheck.json``) and, when given, the evaluation
    block of the default method's frozen protocol (a SELFCHECK.json of the same form)."""
    from . import gap_figures

    path = results / "selfcheck.json"
    if not path.exists():
        return '<p class="muted">Blind self-check not run for this study.</p>'
    sc = io.read_json(path)
    if "top1" not in sc:
        return '<p class="muted">Self-check file of an older format; rerun ema-uq gap-selfcheck.</p>'
    s = sc["shrink"]
    rows = _score_rows(sc) + [
        ["honest shrink where the right family was named (median, quartiles)",
         (f"{_fmt(s['median'], 2)} ({_fmt(s['q25'], 2)}–{_fmt(s['q75'], 2)}), n = {s['n']}" if s.get("n", 0) >= 4
          else f"n = {s.get('n', 0)}: " + (", ".join(_fmt(c["shrink"], 2) for c in sc["cases"]
                                                      if c.get("shrink") is not None and c["correct"]) or "–")),
         f"median se {_fmt(s['median_se'], 2)}" + (f"; {s['not_resolved']} not resolved" if "not_resolved" in s else "")
         if s.get("n") else "–", "", ""]]
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
            + _evaluation_part(evaluation)
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
        label, expected = _fault_label(r), faults["expected"].get(r["record_set"])
        mark = "" if expected is None or label == expected else ' <span class="flag">≠ expected</span>'
        expected = "no known fault" if expected is None else expected
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
    splits = faults.get("splits")
    if splits:
        parts.append(f"<p>The same study under each of {int(splits['n_splits'])} splits of the ten runs into a fitted "
                     "and a held-out half (the ten arcs of consecutive runs and odd | even both ways: the rig drifts "
                     "within a test session, so which runs are held out matters): the verdicts per record set."
                     + (" Not split (they lack some of the ten runs): "
                        + ", ".join(html.escape(n) for n in splits["not_split"]) + "." if splits.get("not_split")
                        else "") + "</p>")
        count_rows = []
        for name, counts in splits["counts"].items():
            expected = splits["expected"].get(name)
            right = counts.get(expected, 0) if expected is not None else None
            count_rows.append([html.escape(name), html.escape(expected or "no known fault"),
                               html.escape(", ".join(f"{v} {n}" for v, n in sorted(counts.items(),
                                                                                  key=lambda kv: -kv[1]))),
                               "–" if right is None else f"{right} of {sum(counts.values())}"])
        parts.append(_table(["record set", "expected", "verdicts over the splits", "as expected"], count_rows))
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
    parts += [f"gap along the stroke: {html.escape(str(c))}" for c in r.get("where_stroke") or []]
    parts += [f"{html.escape(g)}: {html.escape(str(c))}" for g, c in (r.get("where_left") or {}).items()]
    return "<br>".join(parts) or "–"
