"""Gap diagnosis: the blind self-check on records of the independent simulator
(``ema_uq.gap.selfcheck`` on ``ema_uq.gap.variants``), scored against its targets, with the
confusion matrix and the per-case table.

Cases per concept and sensor set (full outputs; the rig's sensors): every in-catalogue effect
variant once with log-uniform magnitudes and uniform phases, ``--none-per-set`` no-effect
cases (every second one with model-form stress), every out-of-catalogue variant once and
every in-catalogue variant with its family's forms left out of the catalogue; base parameters
U(+-10 %) off nominal, 2 % noise, each case from its own seed derived from ``--seed``. Scores
(:mod:`ema_uq.gap.selfcheck`): top-1 accuracy (the right family named), false alarms (a
named effect on a no-effect case) and soft alarms, out-of-catalogue and left-out flagged
(``unexplained`` or ``ambiguous``), a wrong family named with high confidence, each with its
95 % Clopper-Pearson interval and target status, and the honest shrink (signed, scored on
the second validation record, with its standard error) where the right family was found.

Peer (``--peer``, off by default: it costs about a quarter of the main run): the former
circular self-check, whose records came from the diagnosis's own catalogue kernels at the
catalogue's nominal magnitudes from nominal base parameters (one case per effect plus one
no-effect case, full outputs), scored by the same rules.

Frozen protocol (``--protocol benchmarks/gap_protocol.yaml``): the file fixes the catalogue
(per concept, family -> forms), the thresholds and strategy knobs, the self-check settings and
targets, a SHA-256 hash of the diagnosis sources (:data:`SOURCE_PACKAGES`, :data:`SOURCE_FILES`)
and two seed blocks: ``development`` (run and look at as often as wanted) and ``evaluation``
(run once on the final method). ``--block development|evaluation`` runs every self-check
seed of the block, one outcome JSON per case under ``<results>/<block>/<sources hash>/``
(``--results``, default ``benchmarks/protocol_outcomes``, kept in the repository; a rerun
resumes; ``--chunk I/N`` runs one part of every seed, for a scheduler's array job), writes
``<block>.json`` there and prints the targets of both blocks side by side when both exist. The
evaluation block refuses to run when the sources' hash differs from the frozen one: re-freeze
with ``--freeze`` (new hash and a NEW evaluation block; the old block is recorded as spent,
never to be reused). ``--freeze`` on a protocol whose hash still holds keeps its blocks
(``--new-evaluation`` draws a fresh evaluation block anyway). A change meant to move code
without changing a number (a module split) is attested instead with ``--attest-equivalent N``:
N outcomes of the evaluation block already computed on the frozen sources are re-run on the
current ones, and only if every stored value comes out identical is the current hash recorded
under ``sources.equivalent`` (with the cases re-run), after which the block continues into the
same outcome folder; any differing value refuses the attestation. Stored values reproduce exactly
only on the setup (libraries, processor) that computed them: ``--reference REVISION`` compares
instead with the same cases diagnosed by an accepted revision's sources, checked out and run in
turn on this machine. The diagnosis settings come
from the protocol's ``settings``; a protocol frozen before the model-form allowance (method
version 1, no ``model_form_allowance`` there) runs without it.

Usage: python benchmarks/gap.py [--concept htls|lths|both] [--sensors full realistic] [--jobs N]
                                [--quick] [--none-per-set N] [--kinds ...] [--none-from K] [--seed N]
                                [--peer] [--out JSON] [--cache DIR] [--method-version 1-8]
       python benchmarks/gap.py --protocol benchmarks/gap_protocol.yaml --block development|evaluation
                                [--jobs N] [--chunk I/N] [--results DIR]
       python benchmarks/gap.py --protocol benchmarks/gap_protocol.yaml --freeze [--new-evaluation]
       python benchmarks/gap.py --protocol benchmarks/gap_protocol.yaml --attest-equivalent N [--results DIR]
                                [--reference REVISION]
"""
from __future__ import annotations

import argparse
import contextlib
import dataclasses
import datetime
import hashlib
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import yaml

from ema_uq.experiments import Measurement, add_noise, deploy_retract, validation
from ema_uq.gap import diagnose
from ema_uq.gap import attribute, predictable, structure, verdict
from ema_uq.gap.selfcheck import (CALIBRATION_SEEDS, CaseOutcome, run_case, DEFAULT_SEED, KINDS, NONE_PER_SET, SENSOR_SETS, TARGET_FALSE_ALARM,
                                  TARGET_NAMES, TARGET_TOP1, TARGETS, SelfCheckResult, catalogue_families, family_of,
                                  self_check)
from ema_uq.gap.strategy import (DEFAULT_METHOD_VERSION, METHOD_VERSIONS, DiagnosisSettings, Thresholds,
                                  method_switches, strategy_for)
from ema_uq.gap.variants import record_channels, validation_scaled
from ema_uq.models import get_model
from ema_uq.simulate import simulate_batch

PEER_NOISE = 0.02
ROOT = Path(__file__).resolve().parents[1]
#: packages whose every module the protocol hashes: the diagnosis, the estimator it fits with, the
#: simulator and the models (a change in any of them can move a verdict)
SOURCE_PACKAGES = ["ema_uq/gap", "ema_uq/identify", "ema_uq/simulate", "ema_uq/models"]
#: single modules the diagnosis computes with, hashed beside the packages
SOURCE_FILES = ["ema_uq/experiments.py", "ema_uq/params.py", "ema_uq/statistics.py"]
#: modules a diagnosis imports that hold no number it computes (messages, thread counts, lazy
#: imports): not hashed, so that mending a message needs no attestation
UNHASHED_MODULES = frozenset({"ema_uq/__init__.py", "ema_uq/errors.py", "ema_uq/threads.py"})
#: self-check seeds in use before the protocol (reported figures, defaults, calibration): never evaluation seeds
USED_SEEDS = frozenset({1, 2, 3, 5, DEFAULT_SEED, *CALIBRATION_SEEDS})
#: per-case outcomes of the protocol's blocks, committed: the evidence behind the reported
#: figures, and what lets a block scattered over several machines or days resume
PROTOCOL_OUTCOMES = ROOT / "benchmarks" / "protocol_outcomes"
DEVELOPMENT_SEEDS = [11, 12, 13]
EVALUATION_SEEDS = [5201, 5202, 5203]
#: self-check settings of a protocol block: every case kind, >= 60 none cases (half stressed)
PROTOCOL_SELFCHECK = {"concepts": ["htls", "lths"], "sensors": list(SENSOR_SETS), "kinds": list(KINDS),
                      "none_per_set": 16}


def circular_records(concept: str, effect: str | None, seed: int) -> list[Measurement]:
    """The former generator: catalogue kernel at its nominal magnitude, nominal base parameters."""
    base = get_model(concept)
    model = base if effect is None else base.with_effects([effect])
    theta = model.parameters.nominal
    channels = record_channels(concept, "full")
    rng = np.random.default_rng(seed)
    records = []
    for experiment in (deploy_retract(), validation(), validation_scaled()):
        clean = simulate_batch(model, theta, experiment.time, experiment.input_matrix(model))
        records.append(Measurement(concept, experiment, channels, add_noise(clean, PEER_NOISE, rng),
                                   {"noise_fraction": PEER_NOISE, "seed": seed, "source": "catalogue kernels"}))
    return records


def circular_peer(concept: str, seed: int) -> dict:
    rows = []
    for i, effect in enumerate((*get_model(concept).available_effects, None)):
        estimation, *held = circular_records(concept, effect, seed + 1000 + i)
        t0 = time.perf_counter()
        result = diagnose([estimation], held, seed=seed + 1000 + i)
        found = family_of(result, concept)
        truth = "none" if effect is None else getattr(get_model(concept).effect_catalogue[effect], "family", None)
        label = found if result.verdict == "effect" else result.verdict
        rows.append({"truth": truth or effect, "label": label, "seconds": time.perf_counter() - t0})
        print(f"    peer {concept}/{effect}: {label} ({time.perf_counter() - t0:.0f} s)", flush=True)
    effects = [r for r in rows if r["truth"] != "none"]
    return {"top1_accuracy": float(np.mean([r["label"] == r["truth"] for r in effects])),
            "false_alarm_rate": float(np.mean([r["label"] != "none" for r in rows if r["truth"] == "none"])),
            "rows": rows}


# ----------------------------------------------------------------------------------------
# the frozen protocol
# ----------------------------------------------------------------------------------------
def source_globs(root: Path = ROOT) -> list[str]:
    """The modules of :data:`SOURCE_PACKAGES` under ``root``, relative, sorted."""
    return sorted(p.relative_to(root).as_posix() for package in SOURCE_PACKAGES
                  for p in (Path(root) / package).glob("*.py"))


def hash_sources(root: Path = ROOT) -> tuple[str, dict[str, str]]:
    """(combined SHA-256, {file: SHA-256}) of the diagnosis sources under ``root``; the combined
    hash is that of the lines "<file sha256>  <path>" in path order."""
    files = sorted(set(source_globs(root)) | set(SOURCE_FILES))
    each = {}
    for rel in files:
        path = Path(root) / rel
        if not path.is_file():
            raise SystemExit(f"protocol source {rel} not found under {root}; the protocol lists it")
        each[rel] = hashlib.sha256(path.read_bytes()).hexdigest()
    combined = hashlib.sha256("".join(f"{h}  {rel}\n" for rel, h in each.items()).encode()).hexdigest()
    return combined, each


def _allowance_record(strategy, concept: str) -> dict | None:
    """The model-form allowance a strategy fits (constants, tolerance, lag bound), None without one."""
    allowance = strategy.model_form(get_model(concept)) if strategy.model_form is not None else None
    return None if allowance is None else allowance.to_json()


def _frozen_method(settings: DiagnosisSettings | None = None) -> dict:
    """Catalogue, thresholds and strategy knobs as the code sets them, under the diagnosis
    ``settings`` (default: the code's defaults)."""
    settings = DiagnosisSettings() if settings is None else settings
    def plain(obj):
        return {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(obj).items()}

    strategies = {}
    for concept in PROTOCOL_SELFCHECK["concepts"]:
        strategy = strategy_for(get_model(concept))
        strategies[concept] = {"name": strategy.name, "thresholds": plain(strategy.thresholds),
                               # the concept's knobs under the frozen method's switches (what a block runs)
                               "settings": plain(dataclasses.replace(
                                   strategy.settings, **{key: getattr(settings, key)
                                                         for key in method_switches(DEFAULT_METHOD_VERSION)
                                                         if key != "model_form_allowance"})),
                               "start_multiples": [float(m) for m in strategy.start_multiples],
                               "where_source": strategy.where_source,
                               "metric": type(strategy.metric).__name__,
                               "z_significant": getattr(strategy.metric, "z_significant", None),
                               "structure": plain(strategy.structure),
                               "model_form": _allowance_record(strategy, concept)}
    return {"catalogue": {c: catalogue_families(c, settings) for c in PROTOCOL_SELFCHECK["concepts"]},
            "thresholds": plain(Thresholds()), "settings": plain(settings),
            "constants": {"Z_HELD_OUT": attribute.Z_HELD_OUT, "PROFILE_POINTS": attribute.PROFILE_POINTS,
                          "SHRINK_BLOCKS": attribute.SHRINK_BLOCKS, "SHRINK_REPLICATES": attribute.SHRINK_REPLICATES,
                          "STROKE_BINS": structure.STROKE_BINS, "BANDS": [list(b) for b in structure.BANDS],
                          "RIDGE_PENALTIES": list(predictable.PENALTIES),
                          "MAX_AUTOCORRELATION_LAG": verdict.MAX_AUTOCORRELATION_LAG},
            "strategies": strategies}


def load_protocol(path) -> dict:
    with open(path, encoding="utf-8") as fh:
        return yaml.safe_load(fh)


def _fresh_block(size: int, taken: set[int]) -> list[int]:
    """The next ``size`` seeds above every seed taken (spent, development, in use before)."""
    start = max(max(taken, default=0), max(EVALUATION_SEEDS) - 1) + 1
    out = []
    while len(out) < size:
        if start not in taken and start not in USED_SEEDS:
            out.append(start)
        start += 1
    return out


PROTOCOL_HEADER = """\
# Frozen protocol of the gap diagnosis self-check (benchmarks/gap.py --protocol).
# Written by `python benchmarks/gap.py --protocol benchmarks/gap_protocol.yaml --freeze`; do not edit by
# hand. The evaluation block runs only while the sources hash to sources.sha256; a re-freeze after a
# change writes a new hash and a NEW evaluation block and records the old one under spent.
# Run a block:   python benchmarks/gap.py --protocol benchmarks/gap_protocol.yaml --block development [--jobs N]
# Scattered:     the same with --chunk I/N for I = 0..N-1 (one job each), then once without --chunk to gather.
"""


def freeze(path, *, root: Path = ROOT, development: list[int] | None = None, evaluation: list[int] | None = None,
           new_evaluation: bool = False, method_version: int | None = None) -> dict:
    """Write the protocol at ``path``: the sources' hash, catalogue, thresholds and knobs, the
    self-check settings and targets, the seed blocks (kept from an existing file unless the hash
    changed or ``new_evaluation``: then the evaluation block is spent and a fresh one drawn).
    ``method_version`` freezes that version's settings (:func:`method_settings`) instead of the
    code's defaults, e.g. a version under evaluation beside the default one in a file of its own."""
    path = Path(path)
    old = load_protocol(path) if path.is_file() else None
    combined, each = hash_sources(root)
    blocks = (old or {}).get("blocks") or {}
    dev = list(development if development is not None else (blocks.get("development") or {}).get("seeds")
               or DEVELOPMENT_SEEDS)
    old_eval = blocks.get("evaluation") or {}
    spent = [list(b) for b in old_eval.get("spent") or []]
    if evaluation is not None:
        seeds = list(evaluation)
    elif old_eval.get("seeds") and (new_evaluation or old["sources"]["sha256"] != combined):
        spent.append(list(old_eval["seeds"]))
        taken = {s for b in spent for s in b} | set(dev)
        seeds = _fresh_block(len(old_eval["seeds"]), taken)
    else:
        seeds = list(old_eval.get("seeds") or EVALUATION_SEEDS)
    clash = set(seeds) & ({s for b in spent for s in b} | set(dev) | USED_SEEDS)
    if clash:
        raise SystemExit(f"evaluation seeds {sorted(clash)} are spent, development or already used seeds; "
                         "choose unused ones")
    protocol = {
        "frozen": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
        "sources": {"sha256": combined, "files": each},
        "libraries": library_versions(),
        **({} if method_version is None else {"method_version": method_version}),
        **_frozen_method(None if method_version is None else method_settings(method_version)),
        "selfcheck": {**PROTOCOL_SELFCHECK,
                      "targets": {k: {"rate": prop, "target": t, "side": side} for k, (prop, t, side) in TARGETS.items()},
                      "status_rule": "met / not met only where the one-sided 95 % Clopper-Pearson bound shows it, "
                                     "else n too small"},
        "blocks": {"development": {"seeds": dev},
                   "evaluation": {"seeds": seeds, "spent": spent}},
    }
    path.write_text(PROTOCOL_HEADER + yaml.safe_dump(protocol, sort_keys=False, width=110), encoding="utf-8")
    return protocol


def check_sources(protocol: dict, *, root: Path = ROOT) -> str | None:
    """None when the sources still hash to the frozen value; else a one-line message naming the fix."""
    combined, each = hash_sources(root)
    if combined in accepted_hashes(protocol):
        return None
    frozen = protocol["sources"]["files"]
    changed = sorted(f for f in set(each) | set(frozen) if each.get(f) != frozen.get(f))
    return (f"gap sources changed since the protocol was frozen ({', '.join(changed)}); the evaluation block "
            f"is refused: re-freeze with `python benchmarks/gap.py --protocol <file> --freeze` (new hash and a "
            f"new evaluation block, the old one recorded as spent), or, for a change that moves code without "
            f"changing what it computes, attest it with `--attest-equivalent N`")


def accepted_hashes(protocol: dict) -> list[str]:
    """The frozen sources' hash and the hashes attested equivalent to it (a refactor whose
    outcomes were re-run and found identical, value for value)."""
    return [protocol["sources"]["sha256"]] + [e["sha256"] for e in protocol["sources"].get("equivalent") or []]


#: outcome keys that measure the run rather than the method: left out of the equivalence check
RUN_KEYS = frozenset({"wall_time_s", "index"})


def _differences(a, b, where: str = "") -> list[str]:
    """Paths at which two JSON values differ (floats compared exactly)."""
    if isinstance(a, dict) and isinstance(b, dict):
        out = []
        for key in sorted(set(a) | set(b)):
            if key in RUN_KEYS:
                continue
            out += _differences(a.get(key), b.get(key), f"{where}.{key}")
        return out
    if isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        return [d for i, (x, y) in enumerate(zip(a, b)) for d in _differences(x, y, f"{where}[{i}]")]
    same = a == b or (isinstance(a, float) and isinstance(b, float) and np.isnan(a) and np.isnan(b))
    return [] if same else [where or "."]


@contextlib.contextmanager
def _checkout(revision: str, root: Path = ROOT):
    """A temporary git worktree of ``revision`` of the repository at ``root`` (removed afterwards);
    yields (its folder, the revision's full commit id)."""
    def git(*args: str) -> str:
        done = subprocess.run(["git", "-C", str(root), *args], capture_output=True, text=True, check=False)
        if done.returncode != 0:
            raise SystemExit(f"git {' '.join(args)}: {done.stderr.strip() or done.stdout.strip()}")
        return done.stdout.strip()

    commit = git("rev-parse", "--verify", f"{revision}^{{commit}}")
    with tempfile.TemporaryDirectory(prefix="attest-") as folder:
        tree = Path(folder) / "sources"
        git("worktree", "add", "--detach", str(tree), commit)
        try:
            yield tree, commit
        finally:
            git("worktree", "remove", "--force", str(tree))


#: run in a checkout (its folder the working directory, so that it imports its own package): one
#: stored case diagnosed by that checkout's code under a protocol's settings, as JSON on stdout
_REFERENCE_RUN = ("import json, sys; sys.path.insert(0, 'benchmarks'); import gap; "
                  "from ema_uq.gap.selfcheck import CaseOutcome, run_case; "
                  "stored = json.load(open(sys.argv[1], encoding='utf-8')); protocol = gap.load_protocol(sys.argv[2]); "
                  "json.dump(run_case(CaseOutcome.from_json(stored).case, gap.protocol_settings(protocol)).to_json(), "
                  "sys.stdout)")


def _reference_outcome(tree: Path, stored_file: Path, protocol_path: Path) -> dict:
    """The outcome JSON of the stored case ``stored_file`` diagnosed by the sources checked out at
    ``tree``, in a process of its own on this machine."""
    done = subprocess.run([sys.executable, "-c", _REFERENCE_RUN, str(Path(stored_file).resolve()),
                           str(Path(protocol_path).resolve())], cwd=tree, capture_output=True, text=True,
                          env={**os.environ, "PYTHONPATH": str(tree)}, check=False)
    if done.returncode != 0:
        tail = (done.stderr.strip().splitlines() or ["no output"])[-1]
        raise SystemExit(f"the reference sources could not diagnose {Path(stored_file).name}: {tail}")
    return json.loads(done.stdout)


def attest_equivalent(path, n_cases: int, *, block: str = "evaluation", out_dir: Path, root: Path = ROOT,
                      reference: str | None = None) -> dict:
    """Re-run ``n_cases`` outcomes of ``block`` already computed on the frozen sources with the
    current sources and record the current hash as equivalent when every value agrees exactly.
    For changes that move code (a module split) and are meant to compute the same numbers: a
    behaviour change shows as a differing value and is refused, so it needs a re-freeze and a new
    evaluation block. The cases re-run are ones whose outcomes exist, so nothing new is learnt.

    ``reference``: a git revision whose sources hash to a value the protocol accepts. The same
    cases are then diagnosed by that revision too, in turn on this machine, and compared with the
    current sources' outcomes instead of the stored ones: the last digits of a fit move with the
    libraries and the processor, so stored outcomes reproduce exactly only on the setup that
    computed them, and a comparison on one setup tells a code change from a setup change."""
    path = Path(path)
    protocol = load_protocol(path)
    combined, each = hash_sources(root)
    if combined in accepted_hashes(protocol):
        raise SystemExit(f"the sources already hash to an accepted value ({combined[:12]}); nothing to attest")
    folder = Path(out_dir) / block / protocol["sources"]["sha256"][:12]
    files = sorted(folder.glob("seed*/*.json"))
    if len(files) < n_cases or n_cases < 1:
        raise SystemExit(f"{len(files)} outcome(s) of the {block} block under {folder}; give --attest-equivalent "
                         f"between 1 and that number (run some cases of the block on the frozen sources first)")
    # spread over the stored outcomes (they are sorted by concept, sensor set and case)
    picked = [files[round(i * (len(files) - 1) / max(n_cases - 1, 1))] for i in range(n_cases)]
    with contextlib.ExitStack() as stack:
        against = None
        if reference is not None:
            tree, commit = stack.enter_context(_checkout(reference, root))
            against = {"revision": commit, "sha256": hash_sources(tree)[0]}
            if against["sha256"] not in accepted_hashes(protocol):
                raise SystemExit(f"revision {reference} ({commit[:12]}) has sources hashing to "
                                 f"{against['sha256'][:12]}, which the protocol does not accept: give a revision "
                                 "it was frozen or attested on")
        compared, cases = 0, []
        for file in picked:
            stored = json.loads(file.read_text(encoding="utf-8"))
            outcome = CaseOutcome.from_json(stored)
            # the settings a cache file records are the folder's bookkeeping, not an outcome value
            stored.pop("diagnosis_settings", None)
            expected = stored if against is None else _reference_outcome(tree, file, path)
            fresh = json.loads(json.dumps(run_case(outcome.case, protocol_settings(protocol)).to_json()))
            differences = _differences(expected, fresh)
            source = "its stored outcome" if against is None else f"revision {commit[:12]} run here"
            print(f"{outcome.case.case_id}: "
                  f"{'identical' if not differences else 'DIFFERS at ' + ', '.join(differences[:5])} (against {source})",
                  flush=True)
            if differences:
                raise SystemExit(f"{outcome.case.case_id} differs from {source} ({', '.join(differences[:5])}): "
                                 "the change alters results; re-freeze (a new evaluation block) instead"
                                 + ("" if against is not None else _libraries_note(protocol)
                                    + "; if the stored outcomes come from another setup (libraries, processor), "
                                      "compare with a revision the protocol accepts, run here: --reference REVISION"))
            compared += _count_values(expected)
            cases.append(outcome.case.case_id)
    entry = {"sha256": combined, "files": each,
             "attested": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"),
             "cases_rerun": cases, "values_identical": compared, "libraries": library_versions()}
    if against is not None:
        entry["against_revision"] = against
    protocol["sources"].setdefault("equivalent", []).append(entry)
    path.write_text(PROTOCOL_HEADER + yaml.safe_dump(protocol, sort_keys=False, width=110), encoding="utf-8")
    return entry


def library_versions() -> dict[str, str]:
    """Versions of the libraries whose arithmetic the stored outcomes carry (a fit's last digits
    move with them: numpy 2.4.6 / scipy 1.17.1 / numba 0.68.1 reproduce a block-5203 outcome of
    other versions to about 1e-5 relative only)."""
    import numba
    import scipy
    return {"python": platform.python_version(), "numpy": np.__version__, "scipy": scipy.__version__,
            "numba": numba.__version__}


#: one line per run of a block's seed folder: when it started, its library versions, the cases
#: already stored (so the cases each environment diagnosed can be told apart afterwards)
ENVIRONMENTS = "environments.jsonl"


def _stored_cases(folder: Path) -> list[str]:
    return sorted(p.name for p in Path(folder).glob("*.json"))


def record_environment(folder: Path) -> str | None:
    """Append this run's line to ``folder/environments.jsonl`` (the folder of one seed's outcomes)
    and return a note when its library versions differ from an earlier run's. A block that spans
    sessions or machines then says which cases each environment diagnosed
    (:func:`cases_by_environment`): the last digits of a fit move with the libraries
    (:func:`library_versions`), and a verdict that rests on them could differ."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    current = library_versions()
    earlier = [r["libraries"] for r in _environment_records(folder)]
    line = {"started": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
            "libraries": current, "stored": _stored_cases(folder)}
    with open(folder / ENVIRONMENTS, "a", encoding="utf-8") as fh:
        fh.write(json.dumps(line) + "\n")
    others = [r for r in earlier if r != current]
    if not others:
        return None
    return (f"note: {folder} holds cases diagnosed with {others[-1]}, this run uses {current}; "
            "the folder's environments.jsonl tells which cases each diagnosed (benchmarks/gap_paired.py prints it)")


def _environment_records(folder: Path) -> list[dict]:
    path = Path(folder) / ENVIRONMENTS
    if not path.is_file():
        return []
    records = []
    for number, text in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        try:
            record = json.loads(text)
            record["libraries"], record["stored"]
        except (ValueError, TypeError, KeyError) as exc:
            raise SystemExit(f"{path}, line {number}: not an environment record ({exc}); "
                             "mend or remove that line") from None
        records.append(record)
    return records


def cases_by_environment(folder: Path) -> list[tuple[dict | None, list[str]]]:
    """(library versions, case files) per run of one seed folder, in the order the runs started;
    ``None`` for the cases stored before the first record. A case belongs to the first run that
    did not find it stored. Two runs of one folder at the same time (scattered chunks) cannot be
    told apart this way: their cases go to the later one."""
    records = _environment_records(folder)
    final = set(_stored_cases(folder))
    seen = set(records[0]["stored"]) if records else final
    groups = [(None, sorted(seen & final))]
    for i, record in enumerate(records):
        after = set(records[i + 1]["stored"]) if i + 1 < len(records) else final
        new = sorted((after & final) - seen)
        groups.append((record["libraries"], new))
        seen |= set(new)
    return [(libs, files) for libs, files in groups if files]


def _libraries_note(protocol: dict) -> str:
    """What a refused attestation should say about the environment: the libraries recorded with
    the accepted sources (the freeze and each attestation) against this run's."""
    recorded = [protocol.get("libraries")] + [e.get("libraries") for e in protocol["sources"].get("equivalent") or []]
    recorded = [r for r in recorded if r]
    current = library_versions()
    if not recorded:
        return (f"; the protocol records no library versions for its stored outcomes (this run: "
                f"{', '.join(f'{k} {v}' for k, v in current.items())}), so a difference can also come from them")
    if current in recorded:
        return ""
    return (f"; the stored outcomes come from {recorded[-1]}, this run uses {current}: re-run both sources in one "
            "environment to tell a code change from a library change")


def _count_values(value) -> int:
    if isinstance(value, dict):
        return sum(_count_values(v) for k, v in value.items() if k not in RUN_KEYS)
    if isinstance(value, list):
        return sum(_count_values(v) for v in value)
    return 1


def outcome_hash(protocol: dict, root: Path = ROOT) -> str:
    """The hash that names the outcome folders of the current sources: the frozen one when the
    sources hash to a value the protocol accepts (an attested refactor continues the frozen
    outcomes), else their own."""
    current = hash_sources(root)[0]
    return protocol["sources"]["sha256"] if current in accepted_hashes(protocol) else current


def protocol_settings(protocol: dict) -> DiagnosisSettings:
    """The diagnosis settings a protocol froze (its ``settings``). A protocol frozen before the
    model-form allowance existed (method version 1: no ``model_form_allowance`` in its settings)
    runs without it, and one frozen before the converged step (method versions 1-2: no
    ``converged_step``) at the model's own step, so that its blocks go on with the method they
    were frozen for."""
    known = {f.name for f in dataclasses.fields(DiagnosisSettings)}
    frozen = {k: v for k, v in dict(protocol.get("settings") or {}).items() if k in known}
    frozen.setdefault("model_form_allowance", False)
    frozen.setdefault("converged_step", False)
    frozen.setdefault("spanning_forms", False)
    # switches added after a protocol was frozen keep the value that protocol ran with, whatever
    # the defaults become
    frozen.setdefault("operating_point_forms", False)
    frozen.setdefault("nested_forms", True)
    frozen.setdefault("decision_fits", False)
    frozen.setdefault("decision_stop", "extrapolated")
    frozen.setdefault("nested_starts", False)
    frozen.setdefault("nested_start_tolerance", 0.0)
    return DiagnosisSettings(**frozen)


def method_settings(version: int) -> DiagnosisSettings:
    """The diagnosis settings of method ``version`` (:data:`METHOD_VERSIONS`)."""
    try:
        return DiagnosisSettings(**method_switches(version))
    except ValueError as exc:
        raise SystemExit(str(exc)) from None


def run_block(protocol: dict, block: str, out_dir: Path, jobs: int = 1, chunk: str | None = None,
              root: Path = ROOT) -> SelfCheckResult | None:
    """Every seed of the block, one outcome file per case under
    ``out_dir/<block>/<hash>/seed<S>/`` (``hash``: the first 12 hex digits of the current
    sources' SHA-256, so outcomes of other code are never mixed in; a rerun reads them back).
    Without ``chunk``: the outcomes of all seeds in one result, written to ``<block>.json``.
    ``chunk`` "I/N": only the I-th part of every seed's cases (a scattered job), no result."""
    settings = protocol["selfcheck"]
    diagnosis_settings = protocol_settings(protocol)
    seeds = protocol["blocks"][block]["seeds"]
    current = outcome_hash(protocol, root)
    outcomes, wall, parts, used = [], 0.0, {}, {}
    for seed in seeds:
        note = record_environment(Path(out_dir) / block / current[:12] / f"seed{seed}")
        if note:
            print(note, flush=True)
        part = self_check(seed=int(seed), concepts=settings["concepts"], sensors=settings["sensors"],
                          kinds=settings["kinds"], none_per_set=int(settings["none_per_set"]), jobs=jobs,
                          settings=diagnosis_settings,
                          cache=Path(out_dir) / block / current[:12] / f"seed{seed}", chunk=chunk,
                          progress=lambda line, s=seed: print(f"seed {s} {line}", flush=True))
        outcomes += part.outcomes
        wall += part.wall_time_s
        parts[str(seed)] = {"n_cases": len(part.outcomes), "status": part.status}
        used = part.settings
    if chunk is not None:
        return None
    result = SelfCheckResult(outcomes, int(seeds[0]), False, wall,
                             {**used, "seeds": list(seeds), "block": block, "sources_sha256": current,
                              "model_form_allowance": diagnosis_settings.model_form_allowance,
                              "protocol_sha256": protocol["sources"]["sha256"]})
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    with open(Path(out_dir) / f"{block}.json", "w", encoding="utf-8") as fh:
        json.dump({**result.to_json(), "per_seed": parts}, fh, indent=1)
    return result


def side_by_side(results: dict[str, SelfCheckResult]) -> str:
    """The targets of the blocks in columns: rate (count/n) and status."""
    names = list(results)
    lines = [f"    {'target':<32}" + "".join(f"{n:>34}" for n in names)]
    for key, (prop, target, side) in TARGETS.items():
        cells = []
        for n in names:
            rate, status = getattr(results[n], prop), results[n].status[key]
            cells.append(f"{rate['value']:.3f} ({rate['count']}/{rate['n']}) {status}")
        lines.append(f"    {TARGET_NAMES[key] + f' {side} {target}':<32}" + "".join(f"{c:>34}" for c in cells))
    return "\n".join(lines)


def protocol_main(path, block: str, *, root: Path = ROOT, out_dir: Path | None = None, jobs: int = 1,
                  chunk: str | None = None) -> None:
    protocol = load_protocol(path)
    out_dir = Path(out_dir or PROTOCOL_OUTCOMES)
    problem = check_sources(protocol, root=root)
    if problem and block == "evaluation":
        raise SystemExit(problem)
    if problem:
        print(f"note: {problem.split(';')[0]}; the development block runs anyway", flush=True)
    result = run_block(protocol, block, out_dir, jobs, chunk=chunk, root=root)
    if result is None:
        print(f"part {chunk} of the {block} block done; run the block without --chunk to gather it")
        return
    print()
    print(result.summary())
    results = {}
    for name in ("development", "evaluation"):
        if name == block:
            results[name] = result
        elif (out_dir / f"{name}.json").is_file():
            with open(out_dir / f"{name}.json", encoding="utf-8") as fh:
                results[name] = SelfCheckResult.from_json(json.load(fh))
    print("\n[[Blocks]] (seeds " + "; ".join(f"{n}: {', '.join(map(str, protocol['blocks'][n]['seeds']))}"
                                              for n in results) + ")")
    print(side_by_side(results))


def main() -> None:
    if "--protocol" in sys.argv:
        parser = argparse.ArgumentParser(description="the frozen self-check protocol (see the module docstring)")
        parser.add_argument("--protocol", required=True, metavar="YAML")
        parser.add_argument("--block", choices=("development", "evaluation"))
        parser.add_argument("--freeze", action="store_true", help="write the hash, catalogue, thresholds and blocks")
        parser.add_argument("--new-evaluation", action="store_true",
                            help="with --freeze: spend the evaluation block and draw a fresh one")
        parser.add_argument("--method-version", type=int, choices=tuple(METHOD_VERSIONS),
                            help="with --freeze: freeze this method version's settings, not the code's defaults")
        parser.add_argument("--evaluation-seeds", type=int, nargs="+", metavar="SEED",
                            help="with --freeze: these evaluation seeds (a new protocol file beside another "
                                 "protocol's, whose seeds must not be reused)")
        parser.add_argument("--jobs", type=int, default=1)
        parser.add_argument("--chunk", metavar="I/N",
                            help="run only every N-th case from case I (counted from 0) of every seed (a scattered "
                                 "job); the block's result comes from a run without --chunk, which reads them back")
        parser.add_argument("--results", default=str(PROTOCOL_OUTCOMES), metavar="DIR",
                            help="per-case outcomes and block results (default benchmarks/protocol_outcomes, "
                                 "kept in the repository: the evidence, and a block resumes on any machine)")
        parser.add_argument("--attest-equivalent", type=int, metavar="N",
                            help="re-run N stored evaluation outcomes on the current sources; if every value is "
                                 "identical, record the current sources' hash as equivalent to the frozen one")
        parser.add_argument("--reference", metavar="REVISION",
                            help="with --attest-equivalent: compare with the same cases diagnosed by this git "
                                 "revision (sources the protocol accepts) on this machine, not with the stored "
                                 "outcomes (their last digits carry the setup that computed them)")
        args = parser.parse_args()
        if args.reference and args.attest_equivalent is None:
            parser.error("--reference goes with --attest-equivalent N")
        if args.attest_equivalent is not None:
            entry = attest_equivalent(args.protocol, args.attest_equivalent, out_dir=Path(args.results),
                                      reference=args.reference)
            against = entry.get("against_revision")
            print(f"attested {entry['sha256'][:12]} equivalent to the frozen sources: {len(entry['cases_rerun'])} "
                  f"case(s) re-run, {entry['values_identical']} values identical"
                  + (f" to revision {against['revision'][:12]} run on this machine" if against else ""))
            return
        if args.freeze == bool(args.block):
            parser.error("give either --freeze, --block or --attest-equivalent")
        if args.freeze:
            p = freeze(args.protocol, new_evaluation=args.new_evaluation, method_version=args.method_version,
                       evaluation=args.evaluation_seeds)
            print(f"froze {args.protocol}: sources {p['sources']['sha256'][:12]}..., development seeds "
                  f"{p['blocks']['development']['seeds']}, evaluation seeds {p['blocks']['evaluation']['seeds']}"
                  + (f", spent {p['blocks']['evaluation']['spent']}" if p['blocks']['evaluation']['spent'] else ""))
            return
        protocol_main(args.protocol, args.block, out_dir=Path(args.results), jobs=args.jobs, chunk=args.chunk)
        return
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--concept", choices=("htls", "lths", "both"), default="both")
    parser.add_argument("--sensors", nargs="+", choices=SENSOR_SETS, default=list(SENSOR_SETS))
    parser.add_argument("--jobs", type=int, default=1, help="worker processes (results do not depend on it)")
    parser.add_argument("--quick", action="store_true", help="the 3-case subset on the first concept")
    parser.add_argument("--none-per-set", type=int, default=NONE_PER_SET)
    parser.add_argument("--kinds", nargs="+", choices=KINDS, default=list(KINDS),
                        help="case kinds to run (e.g. --kinds none --none-per-set 15: the false-alarm rate alone)")
    parser.add_argument("--none-from", type=int, default=0, metavar="K",
                        help="number the no-effect cases from K (--kinds none --none-from 6 --none-per-set 9: "
                             "cases #6-#14, adding to a run of 6 without repeating it)")
    parser.add_argument("--seed", type=int, default=DEFAULT_SEED)
    parser.add_argument("--peer", action="store_true", help="also run the former circular self-check")
    parser.add_argument("--out", metavar="JSON", help="write scores and per-case table as JSON")
    parser.add_argument("--cache", metavar="DIR", help="keep each case's outcome there and read it back (resume)")
    parser.add_argument("--method-version", type=int, choices=tuple(METHOD_VERSIONS), default=DEFAULT_METHOD_VERSION,
                        help="; ".join(f"{v}: {what}" for v, what in METHOD_VERSIONS.items()).replace("%", "%%")
                        + f" (default {DEFAULT_METHOD_VERSION})")
    args = parser.parse_args()

    concepts = ["htls", "lths"] if args.concept == "both" else [args.concept]
    load = os.getloadavg()[0]
    result = self_check(seed=args.seed, quick=args.quick, concepts=concepts, sensors=args.sensors,
                        none_per_set=args.none_per_set, kinds=args.kinds, none_first=args.none_from, jobs=args.jobs,
                        settings=method_settings(args.method_version), cache=args.cache,
                        progress=lambda line: print(line, flush=True))
    print()
    print(result.summary())
    print(f"\nper concept/sensor set: " + "; ".join(
        f"{k}: top-1 {v['top1_accuracy']:.2f}, false alarms {v['false_alarm_rate']:.2f}, out of catalogue "
        f"{v['out_of_catalogue_flagged']:.2f}, left out {v['left_out_flagged']:.2f}" for k, v in result.by_set().items()))
    print(f"{len(result.outcomes)} cases in {result.wall_time_s:.0f} s with {args.jobs} job(s) "
          f"(load average {load:.1f} on {os.cpu_count()} cores at the start)")
    peers = {}
    if args.peer:
        print("\n[[Peer: the former circular self-check (catalogue kernels, nominal magnitudes and base)]]")
        peers = {c: circular_peer(c, args.seed) for c in concepts}
        print(f"    {'':<26} {'independent variants':>22} {'circular (peer)':>16}   target")
        for c, p in peers.items():
            print(f"    {c + ' top-1 accuracy':<26} {result.by_set().get(c + '/full', {}).get('top1_accuracy', np.nan):>22.3f} "
                  f"{p['top1_accuracy']:>16.3f}   >= {TARGET_TOP1}")
            print(f"    {c + ' false alarms':<26} {result.by_set().get(c + '/full', {}).get('false_alarm_rate', np.nan):>22.3f} "
                  f"{p['false_alarm_rate']:>16.3f}   <= {TARGET_FALSE_ALARM}")
    if args.out:
        with open(args.out, "w", encoding="utf-8") as fh:
            json.dump({**result.to_json(), "jobs": args.jobs, "load_average": load, "circular_peer": peers}, fh,
                      indent=1)


if __name__ == "__main__":
    main()
