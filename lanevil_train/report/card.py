"""Robustness cards: one model's robustness to one suite as a small, versioned JSON file that others can rank.

A card (robustness_card.json; its JSON Schema is robustness_card.schema.json beside this module, SCHEMA_VERSION)
holds the model's identity (family, backbone, checkpoint sha256, training data), the suite's (kind, cases, scene
seeds, severities, the hash of what was scored), per illusion category and overall the Original, Perturbed, Gap and
relative robustness of every score with its interval and sample size, the mCE against a named reference model and,
when given, the closed loop's ASR and collisions. It is built from the same record files the tables are
(`build_card`: records in, nothing read from a model), so its numbers are main.md's and relative.md's.

Intervals: a percentile bootstrap over the suite's cases (dataset, case_id: every image of a scene or every answer
about a clip move together, as in report/intervals.py), `replicates` draws with a fixed seed; Gap and RelRobustness
are computed within each replicate, so their intervals pair a case's perturbed and clean records. The overall values
are the mean of the category values (main.md's average), replicate by replicate. A score without an additive form
(a VLM's corpus-level Language score) gets its point value and no interval (null). Closed-loop rates get Wilson
95 % intervals over the runs, as closed_loop.md.

write_card validates and writes atomically; read_card validates; an error names the file and the field:
"card.json: suite.plan_hash: required field missing".
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import math
import re
import warnings
from functools import lru_cache
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from lanevil_train.files.atomic import atomic_write_text
from lanevil_train.report.intervals import case_key
from lanevil_train.report.records import (
    NAN,
    ModelRecords,
    RecordSet,
    categories_of,
    illusions_of,
    item_of,
    mean,
    ordered,
)
from lanevil_train.report.specs import record_set
from lanevil_train.stats import wilson_interval
from lanevil_train.taxonomy import CATEGORIES, ILLUSION_NAMES, PAIR

CARD_FILE = "robustness_card.json"
CARDS_DIR = "robustness_cards"  # task=report of several models: one card per model, <CARDS_DIR>/<label>.json
SCHEMA_NAME = "lanevil_train/robustness_card"
SCHEMA_VERSION = 1
SCHEMA_FILE = Path(__file__).with_name("robustness_card.schema.json")
REPLICATES = 1000
CONFIDENCE = 0.95
KINDS = ("Perturbed", "Original", "Gap", "RelRobustness")
_DIGITS = 6  # numbers are stored rounded to this many decimals


class CardError(ValueError):
    """A card that does not fit its schema, or cards that cannot be compared; the message names file and field."""


# ------------------------------------------------------------------------------------------------ validation
@lru_cache(maxsize=1)
def schema() -> dict:
    """The card's JSON Schema (robustness_card.schema.json, shipped in the package)."""
    return json.loads(SCHEMA_FILE.read_text(encoding="utf-8"))


def _where(path: Sequence) -> str:
    out = ""
    for part in path:
        out += f"[{part}]" if isinstance(part, int) else (f".{part}" if out else str(part))
    return out


def card_problems(card: Any) -> list[str]:
    """'field: what is wrong' for every way `card` breaks the schema (empty when it fits), sorted by field."""
    from jsonschema import Draft202012Validator

    if isinstance(card, dict) and isinstance(card.get("schema_version"), int) \
            and card.get("schema_version") != SCHEMA_VERSION:
        return [f"schema_version: {card['schema_version']} is not the version this package reads "
                f"({SCHEMA_VERSION}); write the card again with this version of lanevil_train"]
    problems = []
    for error in Draft202012Validator(schema()).iter_errors(card):
        path = list(error.absolute_path)
        if error.validator == "required" and isinstance(error.instance, dict):
            for name in error.validator_value:
                if name not in error.instance:
                    problems.append(f"{_where([*path, name])}: required field missing")
        elif error.validator == "additionalProperties" and isinstance(error.instance, dict):
            allowed = set(error.schema.get("properties", {}))
            for name in sorted(set(error.instance) - allowed):
                problems.append(f"{_where([*path, name])}: unknown field (not in schema version {SCHEMA_VERSION})")
        else:
            problems.append(f"{_where(path) or '(the card)'}: {error.message}")
    return sorted(dict.fromkeys(problems))


def validate_card(card: Any, where: str = "card") -> dict:
    """`card` when it fits the schema; else a CardError naming `where` and each bad field."""
    problems = card_problems(card)
    if problems:
        shown = problems[:6] + ([f"... and {len(problems) - 6} more"] if len(problems) > 6 else [])
        raise CardError(f"{where}: " + f"\n{where}: ".join(shown))
    return card


def write_card(path: str | Path, card: dict) -> Path:
    """Validate `card` and write it to `path` atomically (files/atomic.py), as indented JSON; the path."""
    path = Path(path)
    validate_card(card, path.name)
    atomic_write_text(path, json.dumps(card, indent=1, allow_nan=False) + "\n")
    return path


def read_card(path: str | Path) -> dict:
    """The card in `path`, validated; errors name the file (and the field)."""
    path = Path(path)
    try:
        card = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise CardError(f"{path}: no such card file") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
        raise CardError(f"{path}: not a JSON robustness card ({error})") from None
    return validate_card(card, path.name)


# ---------------------------------------------------------------------------------------------- the numbers
def _number(value) -> float | None:
    if value is None:
        return None
    value = float(value)
    return round(value, _DIGITS) if math.isfinite(value) else None


def _estimate(value: float, replicates: np.ndarray | None, confidence: float) -> dict:
    low = high = None
    if replicates is not None and _number(value) is not None:
        finite = replicates[np.isfinite(replicates)]
        if len(finite):
            alpha = (1 - confidence) / 2
            low, high = (float(q) for q in np.quantile(finite, [alpha, 1 - alpha]))
    return {"value": _number(value), "low": _number(low), "high": _number(high)}


class _Bootstrap:
    """Case weights of `replicates` draws of the cases with replacement, and scores under them."""

    def __init__(self, cases: Sequence[tuple], replicates: int, seed: int):
        self.index = {case: i for i, case in enumerate(sorted(set(cases), key=str))}
        n = len(self.index)
        rng = np.random.default_rng(seed)
        self.weights = (rng.multinomial(n, np.full(n, 1.0 / n), size=replicates).astype(float) if n
                        else np.zeros((replicates, 0)))

    def values(self, records: Sequence[dict], score) -> np.ndarray | None:
        """The score of `records` in each replicate; None for a score without an additive form."""
        additive = getattr(score.aggregate, "additive", None)
        if additive is None:
            return None
        if not records:
            return np.full(len(self.weights), np.nan)
        table = np.zeros((len(self.index), len(additive.parts(records[0]))))
        for r in records:
            table[self.index[case_key(r)]] += additive.parts(r)
        return additive.combine(self.weights @ table)


def _relative(p, o, higher: bool):
    """100 x Perturbed / Original (Original / Perturbed for a lower-is-better score); NaN for a zero denominator."""
    num, den = (p, o) if higher else (o, p)
    if isinstance(num, np.ndarray):
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(den != 0, 100.0 * num / den, np.nan)
    return 100.0 * num / den if den != 0 and not math.isnan(den) else NAN


def _nanmean(arrays: list[np.ndarray | None]) -> np.ndarray | None:
    if not arrays or any(a is None for a in arrays):
        return None
    stacked = np.stack(arrays)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a replicate where every category is NaN: NaN
        return np.nanmean(stacked, axis=0)


def _group(index: ModelRecords, rs: RecordSet, groups: dict[str, list[dict]], boot: _Bootstrap,
           confidence: float) -> tuple[dict, dict]:
    """results.categories and results.overall of one model."""
    categories, parts = {}, {}
    for cat in rs.categories:
        pert = groups.get(cat, [])
        orig = index.originals(pert) if pert else []
        values = index.pog(pert, rs.scores)
        scores, reps = {}, {}
        for score in rs.scores:
            p, o = values[f"{score.name}/Perturbed"], values[f"{score.name}/Original"]
            bp, bo = boot.values(pert, score), boot.values(orig, score)
            point = {"Perturbed": p, "Original": o, "Gap": p - o,
                     "RelRobustness": _relative(p, o, score.higher_is_better)}
            rep = ({"Perturbed": bp, "Original": bo, "Gap": bp - bo,
                    "RelRobustness": _relative(bp, bo, score.higher_is_better)} if bp is not None
                   else dict.fromkeys(KINDS))
            scores[score.name] = {k: _estimate(point[k], rep[k], confidence) for k in KINDS}
            reps[score.name] = (point, rep)
        categories[cat] = {"n_perturbed": len(pert), "n_original": len(orig),
                           "n_cases": len({case_key(r) for r in pert}), "scores": scores}
        parts[cat] = reps
    all_pert = index.pert
    overall_scores = {}
    for score in rs.scores:
        overall_scores[score.name] = {}
        for kind in KINDS:
            point = mean(parts[cat][score.name][0][kind] for cat in rs.categories)
            rep = _nanmean([parts[cat][score.name][1][kind] for cat in rs.categories])
            overall_scores[score.name][kind] = _estimate(point, rep, confidence)
    overall = {"n_perturbed": len(all_pert), "n_original": len(index.originals(all_pert)),
               "n_cases": len({case_key(r) for r in all_pert}), "scores": overall_scores}
    return categories, overall


def _mce(rs: RecordSet, model: str, reference: str, replicates: int, confidence: float, seed: int) -> dict:
    """The card's mce: relative.md's mCE, relative mCE and per-category CE of `model` against `reference`, with
    intervals from a paired bootstrap over both models' cases."""
    from lanevil_train.report.robustness import relative_table

    row = next(r for r in relative_table(rs, reference) if r["model"] == model)
    score, higher = rs.headline, rs.headline.higher_is_better
    own, base = rs.by_model[model], rs.by_model[reference]
    boot = _Bootstrap([case_key(r) for r in own.pert + base.pert], replicates, seed)

    def error(values):
        return None if values is None else (100.0 - values if higher else values)

    def by_type(index: ModelRecords) -> dict[str, tuple[str, list[dict], dict[int, list[dict]]]]:
        out = {}
        for (cat, ill), pert in rs.groups(index.model, ("category", "illusion")):
            sev: dict[int, list[dict]] = {}
            for r in pert:
                sev.setdefault(r["severity"], []).append(r)
            out[ill] = (cat, index.originals(pert), sev)
        return out

    mine, theirs = by_type(own), by_type(base)
    ce, rce, category_of = {}, {}, {}
    additive = getattr(score.aggregate, "additive", None) is not None
    for ill, (cat, base_orig, base_sev) in theirs.items():
        if ill not in mine:
            continue
        category_of[ill] = cat
        if not additive:
            continue
        _, own_orig, own_sev = mine[ill]
        sevs = [s for s in base_sev if s in own_sev]
        e_own = [error(boot.values(own_sev[s], score)) for s in sevs]
        e_base = [error(boot.values(base_sev[s], score)) for s in sevs]
        o_own, o_base = error(boot.values(own_orig, score)), error(boot.values(base_orig, score))
        with np.errstate(invalid="ignore", divide="ignore"):
            num, den = sum(e_own), sum(e_base)
            ce[ill] = np.where(den != 0, num / den, np.nan)
            rnum, rden = sum(e - o_own for e in e_own), sum(e - o_base for e in e_base)
            rce[ill] = np.where(rden != 0, rnum / rden, np.nan)

    def scaled(values: list) -> np.ndarray | None:
        result = _nanmean(values) if additive else None
        return None if result is None else 100.0 * result

    return {"reference": reference, "reference_weights_id": None,
            "mCE": _estimate(row["mCE"], scaled(list(ce.values())), confidence),
            "relative_mCE": _estimate(row["relative_mCE"], scaled(list(rce.values())), confidence),
            "categories": {cat: _estimate(row.get(f"{cat}/CE", NAN),
                                          scaled([v for k, v in ce.items() if category_of[k] == cat]), confidence)
                           for cat in rs.categories if any(c == cat for c in category_of.values())},
            "types": len(category_of), "n_cases": len(boot.index)}


def _closed_loop(records: Sequence[dict]) -> dict | None:
    """The card's closed_loop: ASR (%) of the perturbed runs and of their clean twins, and the perturbed runs'
    collision rate (%), per category and overall, with Wilson 95 % intervals (closed_loop.md's numbers)."""
    if not records:
        return None

    def rate(runs: list[dict], key: str) -> dict:
        hits = sum(bool(r.get(key)) for r in runs)
        if not runs:
            return {"value": None, "low": None, "high": None}
        low, high = wilson_interval(hits, len(runs))
        return {"value": _number(100.0 * hits / len(runs)), "low": _number(100.0 * low),
                "high": _number(100.0 * high)}

    def group(perturbed: list[dict], clean: list[dict]) -> dict:
        return {"runs": len(perturbed), "clean_runs": len(clean), "asr": rate(perturbed, "success"),
                "clean_asr": rate(clean, "success"), "collisions": rate(perturbed, "collision")}

    perturbed = [r for r in records if r.get("perturbed")]
    clean = [r for r in records if not r.get("perturbed")]
    categories = ordered((r["category"] for r in perturbed), tuple(CATEGORIES))
    return {"interval": "Wilson 95 % interval over the runs (cases x repeats)",
            "overall": group(perturbed, clean),
            "categories": {cat: group([r for r in perturbed if r["category"] == cat],
                                      [r for r in clean if r.get("category") == cat]) for cat in categories}}


# ------------------------------------------------------------------------------------------------ the suite
_SCENE_SEED = re.compile(r"^(?:sim|clip)-0*(\d+)")


def suite_kind(illusions: Sequence[str]) -> str:
    """illusions, combined (pairs "<a>+<b>" among them) or corruptions, from the perturbation names scored."""
    if any(PAIR in name for name in illusions):
        return "combined"
    return "illusions" if all(name in ILLUSION_NAMES for name in illusions) else "corruptions"


def plan_hash(index: ModelRecords) -> str:
    """sha256 of the canonical JSON of what was scored: the clean items and every (item, perturbation, severity)."""
    def item(record: dict) -> list:  # (case_id[, item key]): not the dataset's name, a built set's folder name
        return list(item_of(record, index.spec)[2:])

    items = sorted({json.dumps(item(r)) for r in index.clean.values()})
    variants = sorted({json.dumps([*item(r), r["illusion"], r["severity"]]) for r in index.pert})
    text = json.dumps({"items": items, "variants": variants}, sort_keys=True, separators=(",", ":"))
    return "sha256:" + hashlib.sha256(text.encode("utf-8")).hexdigest()


def suite_identity(index: ModelRecords, plan: dict | None = None) -> dict:
    """The card's suite, from one model's records (and the Plan the evaluation used, when it knew it)."""
    records = [*index.clean.values(), *index.pert]
    illusions = illusions_of(index.pert)
    cases = {r["case_id"] for r in records}
    seeds = sorted({int(m.group(1)) for m in map(_SCENE_SEED.match, cases) if m})
    return {"kind": suite_kind(illusions), "dataset": " + ".join(sorted({r["dataset"] for r in records})),
            "cases": len(cases), "seeds": seeds if len(seeds) == len(cases) else [],
            "severities": sorted({r["severity"] for r in index.pert}), "illusions": illusions,
            "categories": categories_of(index.pert), "plan": _plain(plan), "plan_hash": plan_hash(index)}


def _plain(value):
    """JSON values only (tuples as lists), so a card compares equal to itself read back."""
    return None if value is None else json.loads(json.dumps(value))


# ------------------------------------------------------------------------------------------------ the card
MODEL_FIELDS = ("family", "backbone", "checkpoint", "checkpoint_sha256", "weights_id", "training_data", "defense")


def build_card(records, model: str | None = None, identity: dict | None = None, plan: dict | None = None,
               reference: str | None = None, closed_loop: Sequence[dict] | None = None, run: dict | None = None,
               replicates: int = REPLICATES, confidence: float = CONFIDENCE, seed: int = 0,
               created: str | None = None) -> dict:
    """The card of `model` (default: the records' first model) from per-item records (a list or a RecordSet; the
    reference model's records among them when `reference` names one), validated.

    identity: the model's family, backbone, checkpoint, checkpoint_sha256, weights_id, training_data, defense,
    kind (MODEL_FIELDS; missing ones null); plan: the suite's Plan as a dict when known; reference: the label of
    the mCE reference model; closed_loop: the model's closed-loop run records (runs.jsonl); run: dir, command,
    files.
    """
    from lanevil_train import __version__

    rs = record_set(records)
    model = model if model is not None else rs.models[0]
    if model not in rs.by_model:
        raise ValueError(f"robustness card: model {model!r} not among the records' models {rs.models}")
    if reference is not None and reference not in rs.by_model:
        raise ValueError(f"robustness card: reference model {reference!r} not among the records' models "
                         f"{rs.models}")
    if isinstance(replicates, bool) or not isinstance(replicates, int) or replicates < 1:
        raise ValueError(f"robustness card: replicates must be an integer >= 1, got {replicates!r}")
    index = rs.by_model[model]
    if not index.pert:
        raise ValueError(f"robustness card: model {model!r} has no perturbed records (a clean test set): a card "
                         f"describes robustness to an illusion suite")
    identity = dict(identity or {})
    groups = {cat: pert for (cat,), pert in rs.groups(model, ("category",))}
    boot = _Bootstrap([case_key(r) for r in index.pert], replicates, seed)
    categories, overall = _group(index, rs, groups, boot, confidence)
    mce = None
    if reference is not None:
        mce = _mce(rs, model, reference, replicates, confidence, seed)
        mce["reference_weights_id"] = identity.pop("reference_weights_id", None)
    identity.pop("reference_weights_id", None)
    run = dict(run or {})
    card = {
        "schema": SCHEMA_NAME, "schema_version": SCHEMA_VERSION,
        "created": created or _dt.datetime.now(_dt.timezone.utc).replace(microsecond=0).isoformat(),
        "package_version": __version__,
        "model": {"label": model, "kind": identity.get("kind") or ("vlm" if rs.spec.name == "vqa" else "detector"),
                  **{k: (None if identity.get(k) is None else str(identity[k])) for k in MODEL_FIELDS}},
        "suite": suite_identity(index, plan),
        "metrics": {"record_kind": rs.spec.name, "unit": rs.spec.unit, "primary": rs.headline.name,
                    "scores": [{"name": s.name, "higher_is_better": s.higher_is_better} for s in rs.scores],
                    "confidence": confidence, "replicates": replicates,
                    "interval": f"percentile bootstrap over the suite's cases ({replicates} replicates, seed {seed}); "
                                f"none for a score without an additive form"},
        "results": {"overall": overall, "categories": categories},
        "mce": mce,
        "closed_loop": _closed_loop([r for r in closed_loop or () if r.get("model") == model]),
        "run": {"dir": None if run.get("dir") is None else str(run["dir"]), "command": run.get("command"),
                "files": [str(f) for f in run.get("files", ())]},
    }
    return validate_card(card, f"robustness card of {model!r}")


def estimate(card: dict, key: str, category: str | None = None) -> dict | None:
    """The estimate a ranking key names in a card ("<score>/<kind>", "mCE", "relative_mCE", "ASR", "collisions"),
    overall or for one category; None when the card has none."""
    if key in ("mCE", "relative_mCE"):
        mce = card.get("mce")
        if mce is None:
            return None
        return mce[key] if category is None else mce["categories"].get(category)
    if key in ("ASR", "collisions"):
        loop = card.get("closed_loop")
        if loop is None:
            return None
        group = loop["overall"] if category is None else loop["categories"].get(category)
        return None if group is None else group["asr" if key == "ASR" else "collisions"]
    score, _, kind = key.rpartition("/")
    group = card["results"]["overall"] if category is None else card["results"]["categories"].get(category)
    if group is None or score not in group["scores"]:
        return None
    return group["scores"][score].get(kind)


def card_name(label: str) -> str:
    """A file name for a model label's card in CARDS_DIR: the label with anything but [A-Za-z0-9._+-] as _."""
    return re.sub(r"[^A-Za-z0-9._+-]+", "_", label).strip("_") + ".json"
