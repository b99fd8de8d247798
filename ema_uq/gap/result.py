"""Results of the gap diagnosis: one candidate's refit and scores (:class:`CandidateScore`)
and the diagnosis (:class:`GapResult`, GAP.json of INTERFACES.md plus details)."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Mapping

import numpy as np

from .localize import Localization, RegimeRms


#: GAP.json keys of the open-set verdict (:mod:`ema_uq.gap.verdict`)
OPEN_SET_KEYS = ("family_probabilities", "evidence_tempering", "margin_evidence", "contenders", "structure_left",
                 "where_left", "verdict_reason", "state_predictable")

#: a reported shrink counts as resolved when it lies at least this many of its standard errors
#: above zero. The verdict is read on the selection part; the shrink is scored on a shorter
#: part that did not select, so a named effect can close a gap there that its noise hides.
SHRINK_RESOLVED_SE = 2.0


def shrink_resolved(shrink: float | None, shrink_se: float | None) -> bool:
    """Whether the honest shrink is resolved: finite, with a finite standard error, and at
    least :data:`SHRINK_RESOLVED_SE` standard errors above zero."""
    if shrink is None or shrink_se is None or not (np.isfinite(shrink) and np.isfinite(shrink_se)):
        return False
    return bool(shrink >= SHRINK_RESOLVED_SE * shrink_se)


# ----------------------------------------------------------------------------------------
# results
# ----------------------------------------------------------------------------------------
@dataclass
class CandidateScore:
    """One candidate effect's refit and scores (see the module docstring for each figure).

    ``parameters`` maps each effect parameter to {"estimate", "std" (Cramér-Rao), "unit"};
    gaps are the strategy's held-out gap metric (default: systematic NRMSE). ``gap_before``,
    ``gap_after`` and ``shrink`` = 1 - after / before (signed, unclipped) are scored on the
    held-out part that did not select the winner, ``shrink_se`` is its block-bootstrap standard
    error; ``selection_gap_*``, ``selection_shrink``, ``held_out_gain``, ``held_out_log_det_r``,
    ``nrmse_after`` (plain NRMSE, channel mean) and ``gap_z_after`` are on the selection part,
    the one the verdict reads. ``reproducible_shrink`` is the share of the selection part's
    reproducible gap (the nominal gap less the ceiling a replicate mean of the estimation
    residual leaves: :attr:`DiagnosisStrategy.replicate_prediction`) that the candidate closes,
    NaN when nothing is reproducible; without replicates it equals ``selection_shrink``.
    ``family`` is the effect's family (``Effect.family``; the effect itself when its catalogue
    has none).
    """

    effect: str
    score: float
    gap_before: float
    gap_after: float
    shrink: float
    likelihood_ratio: float
    delta_bic: float
    held_out_gain: float
    signature_match: float
    n_parameters: int
    parameters: dict[str, dict[str, float]] = field(default_factory=dict)
    log_det_r: float = float("nan")
    held_out_log_det_r: float = float("nan")
    nrmse_after: float = float("nan")
    gap_z_after: float = float("nan")
    converged: bool = False
    iterations: int = 0
    n_simulations: int = 0
    wall_time_s: float = 0.0
    message: str = ""
    estimate: dict[str, float] = field(default_factory=dict, repr=False)
    stage: str = ""
    free_parameters: list[str] = field(default_factory=list, repr=False)
    shrink_se: float = float("nan")
    selection_gap_before: float = float("nan")
    selection_gap_after: float = float("nan")
    selection_shrink: float = float("nan")
    family: str = ""
    reproducible_shrink: float | None = None

    def __post_init__(self) -> None:
        if not self.family:  # a catalogue without families: every effect is its own
            self.family = self.effect
        if self.reproducible_shrink is None:  # no replicates: the whole gap is reproducible
            self.reproducible_shrink = self.selection_shrink

    def to_json(self) -> dict[str, Any]:
        out = {k: _finite(v) for k, v in vars(self).items()}
        return out


def _finite(value):
    if isinstance(value, float) and not np.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite(v) for v in value]
    return value


def _unfinite(value):
    if value is None:
        return float("nan")
    return value


@dataclass
class GapResult:
    """Outcome of a sim-to-real gap diagnosis (GAP.json of INTERFACES.md plus details).

    ``verdict`` is ``"effect"``, ``"ambiguous"``, ``"none"`` or ``"unexplained"``; ``effect`` the winning
    catalogue name, the form (None unless the verdict is ``effect``); ``family`` its family
    (``Effect.family``: what the diagnosis names; None unless the verdict is ``effect``); ``ranking`` every candidate,
    best score first; ``where`` the channels and regimes holding the nominal model's gap;
    ``localization``/``localization_held_out`` the nominal model's residual localisation on the
    estimation and the held-out data, ``localization_after``/``localization_after_held_out``
    the best candidate's; ``where_source`` says which of the two nominal localisations
    (by default the one with the larger systematic z) gave ``where`` and the signature matches.
    ``selected`` lists the effects kept by forward selection (the winner, and with more than
    one round the effects added after it); ``further_rounds`` ranks the candidates of each
    round after the first (added to the effects selected before it). ``open_set`` holds the
    open-set verdict's figures (:data:`OPEN_SET_KEYS`: family probabilities, the tempering of
    the evidence, the margin, the contenders of an ``ambiguous`` verdict, the cells the best
    candidate leaves and why no family was named).
    """

    concept: str
    verdict: str
    effect: str | None
    confidence: str
    ranking: list[CandidateScore]
    where: dict[str, list[str]]
    gap: dict[str, Any]
    localization: Localization | RegimeRms
    localization_held_out: Localization | RegimeRms
    localization_after: Localization | RegimeRms | None
    localization_after_held_out: Localization | RegimeRms | None
    where_source: str
    held_out: str
    channels: list[str]
    held_out_channels: list[str]
    nominal: dict[str, Any]
    effect_parameters: dict[str, dict[str, float]]
    thresholds: dict[str, float]
    wall_time_s: float
    n_simulations: int
    seed: int | None = None
    provenance: dict[str, Any] = field(default_factory=dict)
    selected: list[str] = field(default_factory=list)
    further_rounds: list[list[CandidateScore]] = field(default_factory=list)
    family: str | None = None
    open_set: dict[str, Any] = field(default_factory=dict)
    #: the model-form allowance fitted in every model (:mod:`ema_uq.gap.allowance`), None when off
    model_form_allowance: dict[str, Any] | None = None

    def __post_init__(self) -> None:
        if self.family is None and self.effect is not None:
            row = next((c for c in self.ranking if c.effect == self.effect), None)
            self.family = row.family if row is not None else self.effect

    @property
    def family_probabilities(self) -> dict[str, float]:
        """{family: probability} of the open-set verdict (``none``: the nominal model), largest first."""
        return dict(self.open_set.get("family_probabilities") or {})

    @property
    def ambiguous_families(self) -> list[str]:
        """The families an ``ambiguous`` verdict cannot tell apart (empty otherwise)."""
        return [c["family"] for c in self.open_set.get("contenders") or []]

    @property
    def best(self) -> CandidateScore | None:
        return self.ranking[0] if self.ranking else None

    @property
    def after_effects(self) -> list[str]:
        """Effects of the model the gap is measured after (``gap["after"]``): the selected ones,
        else round 1's best candidate."""
        name = self.gap.get("effect_of_after")
        return list(self.selected) if self.selected else ([name] if name else [])

    @property
    def after(self) -> CandidateScore | None:
        """The refit of the model the gap is measured after (its ``estimate`` is the full vector)."""
        name = self.gap.get("effect_of_after")
        rounds = [self.ranking] + list(self.further_rounds)
        r = max(len(self.selected) - 1, 0)
        return next((c for c in rounds[r] if c.effect == name), None) if r < len(rounds) else None

    def headline(self) -> str:
        """The verdict in a few words, for one-line summaries and figure titles."""
        contenders = " / ".join(c["family"] for c in self.open_set.get("contenders", []))
        return {"effect": f"effect {self.effect} ({self.confidence} confidence)", "none": "no significant gap",
                "ambiguous": f"ambiguous ({contenders})" if contenders else "ambiguous",
                "unexplained": "unexplained gap"}[self.verdict]

    def summary(self) -> str:
        named = self.family if self.family == self.effect else f"{self.family} ({self.effect})"
        contenders = ", ".join(f"{c['family']} {c['probability']:.2f}" for c in self.open_set.get("contenders", []))
        head = {"effect": f"effect {named} ({self.confidence} confidence)",
                "none": "no significant gap: the noise explains the residual",
                "ambiguous": f"ambiguous: the data cannot tell these families apart ({contenders})",
                "unexplained": f"a significant gap that no candidate effect closes ({self.confidence} confidence)"
                }[self.verdict]
        lines = [f"[[Gap diagnosis: {self.concept}]] verdict: {head}",
                 f"    held-out data      = {self.held_out}",
                 f"    where (channels)   = {', '.join(self.where['channels']) or '-'}  ({self.where_source} data)",
                 f"    where (regimes)    = {', '.join(self.where['regimes']) or '-'}",
                 f"    where (stroke)     = {'; '.join(self.where.get('stroke', [])) or '-'}",
                 f"    gap ({self.gap['metric'].split(':')[0]}) {self.gap['before']:.4g} -> {self.gap['after']:.4g}"
                 f"; plain NRMSE {self.gap['nrmse_before']:.4g} -> {self.gap['nrmse_after']:.4g}",
                 *self._shrink_line(),
                 *self._open_set_lines(),
                 *self._allowance_lines(),
                 f"    wall time          = {self.wall_time_s:.1f} s, {self.n_simulations} simulations",
                 "[[Ranking]] (gaps and shrink on the scoring part, the held-out gain on the selection part)",
                 f"    {'effect':<24} {'family':<18} {'score':>10} {'dBIC':>10} {'held-out':>10} {'sig':>5} "
                 f"{'gap before':>10} {'after':>9} {'shrink':>7} {'+/-':>5}"]
        for c in self.ranking:
            lines.append(f"    {c.effect:<24} {c.family:<18} {c.score:>10.1f} {c.delta_bic:>10.1f} {c.held_out_gain:>10.1f} "
                         f"{c.signature_match:>5.2f} {c.gap_before:>10.4g} {c.gap_after:>9.4g} {c.shrink:>7.2f} "
                         f"{c.shrink_se:>5.2f}"
                         + ("" if not c.message or c.converged else f"  ({c.message[:60]})"))
        for r, rnd in enumerate(self.further_rounds, 2):
            lines.append(f"[[Round {r}]] added to {' + '.join(self.selected[:r - 1])}")
            lines += [f"    {c.effect:<24} {c.score:>10.1f} {c.delta_bic:>10.1f} {c.gap_before:>10.4g} "
                      f"{c.gap_after:>9.4g} {c.shrink:>7.2f}" for c in rnd]
        if self.selected:
            lines.append(f"    selected           = {' + '.join(self.selected)}")
        if self.effect_parameters:
            lines.append("[[Effect parameters]] (std = Cramér-Rao bound)")
            for name, p in self.effect_parameters.items():
                lines.append(f"    {name:<24} = {p['estimate']:.6g} +/- {p['std']:.3g} {p.get('unit', '')}")
        return "\n".join(lines)

    def _allowance_lines(self) -> list[str]:
        """The model-form allowance fitted in the nominal model (relative offsets in %, the lag in ms)."""
        fitted = (self.model_form_allowance or {}).get("fitted_nominal") or {}
        if not fitted:
            return []
        shown = [f"{n[3:]} {p['estimate'] * 1e3:.0f} ms" if p["unit"] == "s" else f"{n[3:]} {p['estimate']:+.2%}"
                 for n, p in fitted.items()]
        return [f"    model-form allow.  = {', '.join(shown)} (nominal fit; in every model, never named)"]

    def _open_set_lines(self) -> list[str]:
        """Family probabilities, and what the best candidate leaves where (open-set verdict)."""
        o = self.open_set
        if not o.get("family_probabilities"):
            return []
        shown = [f"{f} {p:.3g}" for f, p in list(o["family_probabilities"].items())[:4]]
        lines = [f"    family probability = {', '.join(shown)} (evidence x {o.get('evidence_tempering', 1.0):.3g}"
                 f" for autocorrelated residuals; named only beyond 2 ln B = {o.get('margin_evidence', 10):g})"]
        p = o.get("state_predictable") or {}
        if p.get("z") is not None and p.get("share") is not None:
            lines.append(f"    state predicts     = {p['share']:.0%} of the held-out gap (z {p['z']:.1f}): "
                         + ("a model error" if p.get("deterministic") else "not shown to be a function of the state"))
        if o.get("verdict_reason"):
            lines.append(f"    why not named      = {o['verdict_reason']}")
        for group, cells in o.get("where_left", {}).items():
            lines.append(f"    left ({group}){' ' * max(12 - len(group), 0)}= {'; '.join(cells[:3])}")
        return lines

    def _shrink_line(self) -> list[str]:
        """The honest shrink, shown for an ``effect`` verdict only."""
        shrink = self.gap.get("shrink")
        if self.verdict != "effect" or shrink is None:
            return []
        se = self.gap.get("shrink_se")
        lines = [f"    shrink             = {shrink:.3f} +/- {se if se is not None else float('nan'):.3f} "
                 f"(scored on the {self.gap.get('shrink_record', 'held-out data')}, not used to select the winner)"]
        if not shrink_resolved(shrink, se):
            # the verdict stands on the selection part; say plainly that this record cannot confirm it
            selection = self.gap.get("reproducible_shrink")
            read = "" if selection is None or not np.isfinite(selection) else f" ({selection:.2f} there)"
            lines.append(f"    shrink not resolved: less than {SHRINK_RESOLVED_SE:g} standard errors above zero on "
                         f"this record; the effect is named on the selection part's shrink{read} alone")
        return lines

    def to_json(self) -> dict[str, Any]:
        return _finite({
            "verdict": self.verdict,
            "effect": self.effect,
            "family": self.family,
            "confidence": self.confidence,
            "ranking": [c.to_json() for c in self.ranking],
            "where": {"channels": list(self.where["channels"]), "regimes": list(self.where["regimes"]),
                      "stroke": list(self.where.get("stroke", []))},
            "concept": self.concept,
            "gap": self.gap,
            "effect_parameters": self.effect_parameters,
            "held_out": self.held_out,
            "channels": list(self.channels),
            "held_out_channels": list(self.held_out_channels),
            "nominal": self.nominal,
            "where_source": self.where_source,
            "selected": list(self.selected),
            "further_rounds": [[c.to_json() for c in rnd] for rnd in self.further_rounds],
            "localization": self.localization.to_json(),
            "localization_held_out": self.localization_held_out.to_json(),
            "localization_after": None if self.localization_after is None else self.localization_after.to_json(),
            "localization_after_held_out": (None if self.localization_after_held_out is None
                                            else self.localization_after_held_out.to_json()),
            "thresholds": self.thresholds,
            "wall_time_s": self.wall_time_s,
            "n_simulations": self.n_simulations,
            "seed": self.seed,
            "provenance": self.provenance,
            # the open-set verdict: family probabilities, contenders of an ambiguous verdict, and the
            # cells where the best candidate leaves structure
            **{k: self.open_set.get(k) for k in OPEN_SET_KEYS if k in self.open_set},
            **({} if self.model_form_allowance is None else {"model_form_allowance": self.model_form_allowance}),
        })

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> "GapResult":
        def optional(key):
            return None if data.get(key) is None else _localization_from_json(data[key])

        gap = {k: _unfinite(v) for k, v in data["gap"].items()}
        return cls(
            concept=data["concept"], verdict=data["verdict"], effect=data["effect"],
            confidence=data.get("confidence", ""), ranking=[_candidate_from_json(c) for c in data["ranking"]],
            where=dict(data["where"]), gap=gap,
            localization=_localization_from_json(data["localization"]),
            localization_held_out=_localization_from_json(data["localization_held_out"]),
            localization_after=optional("localization_after"),
            localization_after_held_out=optional("localization_after_held_out"),
            where_source=data.get("where_source", "estimation"),
            held_out=data.get("held_out", ""), channels=list(data.get("channels", [])),
            held_out_channels=list(data.get("held_out_channels", [])), nominal=dict(data.get("nominal", {})),
            effect_parameters=dict(data.get("effect_parameters", {})),
            thresholds=dict(data.get("thresholds", {})),
            wall_time_s=float(data.get("wall_time_s", 0.0)), n_simulations=int(data.get("n_simulations", 0)),
            seed=data.get("seed"), provenance=dict(data.get("provenance", {})),
            selected=list(data.get("selected", [])),
            further_rounds=[[_candidate_from_json(c) for c in rnd] for rnd in data.get("further_rounds", [])],
            family=data.get("family"),
            open_set={k: data[k] for k in OPEN_SET_KEYS if k in data},
            model_form_allowance=data.get("model_form_allowance"),
        )


def _candidate_from_json(data: Mapping[str, Any]) -> CandidateScore:
    c = dict(data)
    for key in ("score", "gap_before", "gap_after", "shrink", "likelihood_ratio", "delta_bic",
                "held_out_gain", "signature_match", "log_det_r", "held_out_log_det_r", "nrmse_after",
                "gap_z_after", "shrink_se", "selection_gap_before", "selection_gap_after", "selection_shrink",
                "reproducible_shrink"):
        if key in c:
            c[key] = float(_unfinite(c[key]))
    return CandidateScore(**c)


def _localization_from_json(data: Mapping[str, Any]) -> Localization | RegimeRms:
    return RegimeRms.from_json(data) if data.get("kind") == RegimeRms.KIND else Localization.from_json(data)
