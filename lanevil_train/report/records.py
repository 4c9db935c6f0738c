"""Result records, whatever the model kind: validation, grouping, ordering and the Perturbed / Original / Gap
arithmetic, with the metric set given as a small `RecordSpec`.

A record is one scored item (an image for a lane detector, an answer for a VLM) as a plain dict::

    {"model", "dataset", "case_id", "severity" (0 = the clean original, 1..5 perturbed), "illusion", "category",
     <the spec's item key, if it has one>, <the spec's per-item fields>, ...anything else (kept, ignored)}

Conventions (the paper's tables; every score in the spec's unit, e.g. %):
- Perturbed = a score over all perturbed records of a group, pooled (each record weighs the same, over types
  and severities).
- Original = the same score over the clean (severity 0) records of THE SAME ITEMS: the (dataset, case_id, item)
  of the group's perturbed records, each once.
- Gap = Perturbed - Original (for a higher-is-better score, a model hurt by the illusion has a negative Gap).
- "average" = the unweighted mean of the per-category values over the categories present (Gap included).
"""

from __future__ import annotations

import math
from collections import defaultdict
from dataclasses import dataclass
from typing import Callable, Iterable, Sequence

import numpy as np

from lanevil_train.taxonomy import CATEGORIES, ILLUSION_CATEGORY, ILLUSION_NAMES, PAIR_CATEGORIES

NAN = float("nan")
KINDS = ("Perturbed", "Original", "Gap")
AVERAGE = "average"
IDENTITY = ("model", "dataset", "case_id", "severity")


@dataclass(frozen=True)
class Field:
    """A number every record of a spec carries (or may carry, when not required), with its valid range."""

    name: str
    low: float = -math.inf
    high: float = math.inf
    required: bool = True


@dataclass(frozen=True)
class Score:
    """A reported score: its name, its value over a group of records, and its direction.

    `needs` names the record fields it reads beyond the spec's required ones: the score is left out of
    a table when some record lacks them (e.g. CULane counts in a TuSimple-only run). `needs_any`: fields the score
    reads from the records that have them (e.g. accuracy over yes/no and choice answers only): it is left out when
    no record has one of them.
    """

    name: str
    aggregate: Callable[[Sequence[dict]], float]
    higher_is_better: bool = True
    needs: tuple[str, ...] = ()
    needs_any: tuple[str, ...] = ()


@dataclass(frozen=True)
class RecordSpec:
    """What a kind of record holds and which scores its tables report.

    scores: the robustness tables' scores (the first is the headline: plots, relative robustness, worst cases,
    the best defense); summary: the headline table's scores (defaults to `scores`); item_key: the field naming
    an item within a case when a case has several (e.g. a question of a clip); groups: record fields that get a
    table of their own (e.g. the QA category); count_name: what a record is, for the tables' count column.
    """

    name: str
    fields: tuple[Field, ...]
    scores: tuple[Score, ...]
    summary: tuple[Score, ...] = ()
    item_key: str | None = None
    groups: tuple[str, ...] = ()
    unit: str = "%"
    count_name: str = "images"

    @property
    def headline(self) -> Score:
        return self.scores[0]

    def summary_scores(self) -> tuple[Score, ...]:
        return self.summary or self.scores


@dataclass(frozen=True)
class Additive:
    """A score written as a function of per-record sums: `parts(record)` is a record's k addends and `combine`
    maps totals (..., k) to score values (...). The bootstrap (report/intervals.py) resamples such a score as a
    matrix product instead of re-aggregating record lists. An aggregate carries it as its `additive` attribute."""

    parts: Callable[[dict], tuple[float, ...]]
    combine: Callable[[np.ndarray], np.ndarray]


def ratio(scale: float = 1.0) -> Callable[[np.ndarray], np.ndarray]:
    """combine for (sum, count) totals: scale * sum / count, NaN where the count is 0."""

    def combine(totals: np.ndarray) -> np.ndarray:
        with np.errstate(invalid="ignore", divide="ignore"):
            return np.where(totals[..., 1] > 0, scale * totals[..., 0] / totals[..., 1], np.nan)

    return combine


def mean_of(field: str, scale: float = 100.0) -> Callable[[Sequence[dict]], float]:
    """An aggregate: scale * the mean of one field (NaN for no records)."""

    def aggregate(records: Sequence[dict]) -> float:
        return scale * (sum(r[field] for r in records) / len(records)) if records else NAN

    aggregate.__name__ = f"mean_{field}"
    aggregate.additive = Additive(lambda r: (r[field], 1.0), ratio(scale))
    return aggregate


# ------------------------------------------------------------------------------------------------- validation
def validate_records(records: Sequence[dict], spec: RecordSpec) -> list[dict]:
    """Check and normalise records against `spec` (a missing category is filled from a known illusion); the
    same clean item written more than once counts once. Raises naming the bad record and what was expected."""
    if not isinstance(records, (list, tuple)):
        raise TypeError(f"records must be a list of dicts, got {type(records).__name__}")
    required = IDENTITY + ((spec.item_key,) if spec.item_key else ()) + tuple(f.name for f in spec.fields
                                                                             if f.required)
    out, clean_seen, pert_seen = [], {}, set()
    for i, rec in enumerate(records):
        if not isinstance(rec, dict):
            raise TypeError(f"record {i}: expected a dict, got {type(rec).__name__}")
        if rec.get("spec", spec.name) != spec.name:
            raise ValueError(f"record {i}: a {rec['spec']!r} record among {spec.name!r} records")
        missing = [k for k in required if k not in rec or rec[k] is None]
        if missing:
            raise ValueError(f"record {i}: missing required key(s) {missing}; expected keys {list(required)}")
        sev = rec["severity"]
        if isinstance(sev, bool) or not isinstance(sev, int) or not 0 <= sev <= 5:
            raise ValueError(f"record {i}: severity must be an int in 0..5 (0 = clean), got {sev!r}")
        norm = dict(rec)
        for key in ("model", "dataset", "case_id") + ((spec.item_key,) if spec.item_key else ()):
            norm[key] = str(rec[key])
        for field in spec.fields:
            if rec.get(field.name) is None:
                continue
            val = rec[field.name]
            if isinstance(val, bool) or not isinstance(val, (int, float)) or not field.low <= float(val) <= field.high:
                raise ValueError(f"record {i}: {field.name} must be a number in [{field.low}, {field.high}], "
                                 f"got {val!r}")
            norm[field.name] = float(val)
        item = item_of(norm, spec)
        if sev == 0:
            values = tuple(norm.get(f.name) for f in spec.fields)
            if item in clean_seen:
                if clean_seen[item] != values:
                    raise ValueError(f"record {i}: a second clean (severity 0) record for model/dataset/case "
                                     f"{item} with different scores {values} vs {clean_seen[item]} (two runs of "
                                     f"different models under one label? give each run its own task.label)")
                continue  # the same clean item written once per illusion: count it once
            clean_seen[item] = values
        else:
            illusion = rec.get("illusion")
            if not illusion:
                raise ValueError(f"record {i}: a perturbed record (severity {sev}) needs an 'illusion' name")
            category = rec.get("category") or ILLUSION_CATEGORY.get(illusion)
            if not category:
                raise ValueError(f"record {i}: perturbed record of unknown illusion {illusion!r} has no 'category'")
            norm["illusion"], norm["category"] = str(illusion), str(category)
            key = item + (norm["illusion"], sev)
            if key in pert_seen:
                raise ValueError(f"record {i}: duplicate perturbed record for (model, dataset, case_id, illusion, "
                                 f"severity) {key}")
            pert_seen.add(key)
        out.append(norm)
    return out


def item_of(record: dict, spec: RecordSpec) -> tuple:
    """A record's item: (model, dataset, case_id), plus the spec's item key when it has one."""
    item = (record["model"], record["dataset"], record["case_id"])
    return item + (record[spec.item_key],) if spec.item_key else item


def available_scores(records: Iterable[dict], scores: Sequence[Score]) -> list[Score]:
    """The scores the records have the fields for (every record its `needs`, some record each of its `needs_any`)."""
    records = list(records)
    return [s for s in scores if all(all(r.get(k) is not None for k in s.needs) for r in records)
            and all(any(r.get(k) is not None for r in records) for k in s.needs_any)]


# --------------------------------------------------------------------------------------------------- ordering
def ordered(values: Iterable, order: Sequence = ()) -> list:
    """The distinct values, those in `order` first in its order, then the rest sorted."""
    present = set(values)
    return [v for v in order if v in present] + sorted(present - set(order), key=str)


def categories_of(records: Iterable[dict]) -> list[str]:
    """The perturbed records' categories in the paper's order (others after, sorted)."""
    return ordered((r["category"] for r in records if r["severity"] > 0), tuple(CATEGORIES) + PAIR_CATEGORIES)


def illusions_of(records: Iterable[dict]) -> list[str]:
    """The perturbed records' illusion names in the paper's order (others after, sorted)."""
    return ordered((r["illusion"] for r in records if r["severity"] > 0), ILLUSION_NAMES)


def models_of(records: Iterable[dict]) -> list[str]:
    """Model names in first-seen order."""
    return list(dict.fromkeys(r["model"] for r in records))


def mean(values: Iterable[float]) -> float:
    """Mean of the non-NaN values; NaN when there are none."""
    vals = [v for v in values if not math.isnan(v)]
    return sum(vals) / len(vals) if vals else NAN


# ----------------------------------------------------------------------------------- Perturbed / Original / Gap
class ModelRecords:
    """One model's validated records: clean ones by item, perturbed ones in a list; P/O/G of any group."""

    def __init__(self, model: str, records: list[dict], spec: RecordSpec):
        self.model = model
        self.spec = spec
        self.clean = {item_of(r, spec): r for r in records if r["severity"] == 0}
        self.pert = [r for r in records if r["severity"] > 0]

    def originals(self, pert: Sequence[dict]) -> list[dict]:
        """The clean records of the items in `pert` (each once); raises when one is missing."""
        items = dict.fromkeys(item_of(r, self.spec) for r in pert)
        missing = [i for i in items if i not in self.clean]
        if missing:
            raise ValueError(f"model {self.model!r}: no clean (severity 0) record for {len(missing)} item(s) with "
                             f"perturbed records, e.g. (model, dataset, case_id[, item]) {missing[0]}; Original "
                             f"needs the same items")
        return [self.clean[i] for i in items]

    def pog(self, pert: Sequence[dict], scores: Sequence[Score]) -> dict[str, float]:
        """"<score>/Perturbed", "<score>/Original" and "<score>/Gap" of a group of perturbed records."""
        orig = self.originals(pert) if pert else []
        out = {}
        for score in scores:
            p, o = score.aggregate(pert), score.aggregate(orig)
            out.update({f"{score.name}/Perturbed": p, f"{score.name}/Original": o, f"{score.name}/Gap": p - o})
        return out


class RecordSet:
    """Validated records of one spec, split by model: what every table and plot is computed from."""

    def __init__(self, records: Sequence[dict], spec: RecordSpec):
        self.spec = spec
        self.records = validate_records(records, spec)
        self.models = models_of(self.records)
        by_model = defaultdict(list)
        for r in self.records:
            by_model[r["model"]].append(r)
        self.by_model = {m: ModelRecords(m, by_model[m], spec) for m in self.models}
        # the scores every model's records support: a judge that scored one run only does not head a comparison
        self.scores = [s for s in available_scores(self.records, spec.scores)
                       if all(available_scores(by_model[m], (s,)) for m in self.models)]
        if not self.scores:
            raise ValueError(f"the {spec.name!r} records carry none of the fields of its scores "
                             f"{[sc.name for sc in spec.scores]}")
        self.categories = categories_of(self.records)
        self.illusions = illusions_of(self.records)

    @property
    def headline(self) -> Score:
        """The first of the spec's scores these records support: plots, relative robustness, worst cases."""
        return self.scores[0]

    def groups(self, model: str, by: Sequence[str], orders: dict[str, Sequence] | None = None):
        """(key values, perturbed records) of `model` grouped by the fields `by`, in table order: categories and
        illusions in the paper's order, severities ascending, other fields sorted."""
        orders = {"category": self.categories, "illusion": self.illusions, **(orders or {})}
        grouped: dict[tuple, list[dict]] = defaultdict(list)
        for r in self.by_model[model].pert:
            grouped[tuple(r.get(f) for f in by)].append(r)
        rank = [{v: i for i, v in enumerate(ordered((k[j] for k in grouped), orders.get(f, ())))}
                for j, f in enumerate(by)]
        return sorted(grouped.items(), key=lambda kv: tuple(rank[j][v] for j, v in enumerate(kv[0])))
