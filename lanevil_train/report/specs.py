"""The record specs the reports know, by name: what each kind of per-item record holds and how its scores
aggregate. A new kind of model (a VLM's answers, say) is one more spec here, and gets every table and plot.
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np

from lanevil_train.metrics import tusimple_summary
from lanevil_train.metrics.culane import MF1_THRESHOLDS
from lanevil_train.report.records import NAN, Additive, Field, RecordSet, RecordSpec, Score, mean_of, ratio


def _tusimple_f1(records: Sequence[dict]) -> float:
    """TuSimple F1 (%) as LaneATT/CLRNet report it, from the mean per-image FP and FN rates."""
    if not records:
        return NAN
    summary = tusimple_summary(sum(r["accuracy"] for r in records), sum(r["fp"] for r in records),
                               sum(r["fn"] for r in records), len(records))
    return 100.0 * summary["F1"]


def count_f1(tp_field: str, fp_field: str, fn_field: str):
    """An aggregate: F1 (%) = 2 TP / (2 TP + FP + FN) of per-record counts summed over the records (0 when TP is 0,
    NaN for no records); bootstrapped through its totals."""
    fields = (tp_field, fp_field, fn_field)

    def aggregate(records: Sequence[dict]) -> float:
        if not records:
            return NAN
        return float(_count_f1_totals(np.array([sum(r[k] for r in records) for k in fields], dtype=np.float64)))

    aggregate.__name__ = f"count_f1_{tp_field}"
    aggregate.additive = Additive(lambda r: tuple(r[k] for k in fields), _count_f1_totals)
    return aggregate


def _tusimple_f1_totals(totals: np.ndarray) -> np.ndarray:
    """_tusimple_f1 of (accuracy, fp, fn, images) totals, vectorised: F1 (%) from the mean FP and FN rates."""
    n = totals[..., 3]
    with np.errstate(invalid="ignore", divide="ignore"):
        fp, fn = totals[..., 1] / n, totals[..., 2] / n
        tp = 1 - fp
        precision = tp / (tp + fp)
        recall = np.where(tp + fn != 0, tp / (tp + fn), 0.0)
        f1 = np.where(precision + recall != 0, 2 * precision * recall / (precision + recall), 0.0)
    return np.where(n > 0, 100.0 * f1, np.nan)


def _count_f1_totals(totals: np.ndarray) -> np.ndarray:
    """F1 (%) of (tp, fp, fn) totals, vectorised: 2 TP / (2 TP + FP + FN), 0 where TP is 0."""
    tp, fp, fn = totals[..., 0], totals[..., 1], totals[..., 2]
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(tp > 0, 100.0 * 2 * tp / (2 * tp + fp + fn), 0.0)


_tusimple_f1.additive = Additive(lambda r: (r["accuracy"], r["fp"], r["fn"], 1.0), _tusimple_f1_totals)

ACCURACY = Score("Accuracy", mean_of("accuracy"))
TUSIMPLE_F1 = Score("F1", _tusimple_f1)
# TuSimple lanes counted (metrics/tusimple.py F1_count): a silent model reads 0 where the papers' F1 reads 66.7.
# Records written before the counts existed lack the fields: the score is then left out of their tables.
COUNT_FIELDS = ("tp_count", "fp_count", "fn_count")
F1_COUNT = Score("F1_count", count_f1(*COUNT_FIELDS), needs=COUNT_FIELDS)
_CULANE_FIELDS = ("culane_tp", "culane_fp", "culane_fn")
CULANE_F1 = Score("CULane_F1", count_f1(*_CULANE_FIELDS), needs=_CULANE_FIELDS)
# A CULane-scored record's TP at each mF1 IoU threshold 0.50, 0.55, ..., 0.95 (metrics/culane.py MF1_THRESHOLDS;
# one matching per image); FP and FN there follow from its lane counts. LLAMAS records and older ones lack it.
CULANE_SWEEP = "culane_tp_sweep"


def _sweep_parts(record: dict) -> tuple[int, ...]:
    """(TP, FP, FN) at each mF1 threshold, flattened: FP = predicted - TP, FN = GT - TP."""
    n_pred, n_gt = record["culane_tp"] + record["culane_fp"], record["culane_tp"] + record["culane_fn"]
    return tuple(v for tp in record[CULANE_SWEEP] for v in (tp, n_pred - tp, n_gt - tp))


def culane_sweep_f1(at: float | None):
    """An aggregate: CULane F1 (%) at IoU threshold `at` (one of the mF1 thresholds), or mF1 (the mean of the ten
    F1 values) for None, from the records' summed counts; NaN for no records; bootstrapped through its totals."""

    def combine(totals: np.ndarray) -> np.ndarray:
        f1 = _count_f1_totals(totals.reshape(*totals.shape[:-1], len(MF1_THRESHOLDS), 3))
        return f1.mean(axis=-1) if at is None else f1[..., MF1_THRESHOLDS.index(at)]

    def aggregate(records: Sequence[dict]) -> float:
        if not records:
            return NAN
        return float(combine(np.sum([_sweep_parts(r) for r in records], axis=0, dtype=np.float64)))

    aggregate.__name__ = "culane_mf1" if at is None else f"culane_f1_at_{at}"
    aggregate.additive = Additive(_sweep_parts, combine)
    return aggregate


CULANE_F1_75 = Score("CULane_F1@75", culane_sweep_f1(0.75), needs=_CULANE_FIELDS + (CULANE_SWEEP,))
CULANE_MF1 = Score("CULane_mF1", culane_sweep_f1(None), needs=_CULANE_FIELDS + (CULANE_SWEEP,))

# One record per scored image. Ranges of the official TuSimple per-image scores: accuracy and FN can exceed 1
# with more than 4 GT lanes (with n > 4 lanes the worst lane / one miss is dropped but the sum is divided by 4:
# up to (n - 1) / 4, 5/4 with the 6 lanes of a simulated 5-lane road, more on a user's wider roads), and FP can
# be negative (one prediction may match several GT lanes, e.g. short ones mostly outside the image).
LANE_SPEC = RecordSpec(
    name="lane",
    fields=(Field("accuracy", 0.0), Field("fp", -math.inf, 1.0), Field("fn", 0.0),
            *(Field(name, 0.0, required=False) for name in COUNT_FIELDS + _CULANE_FIELDS)),
    scores=(ACCURACY, TUSIMPLE_F1, F1_COUNT),
    summary=(ACCURACY, Score("FP", mean_of("fp"), higher_is_better=False),
             Score("FN", mean_of("fn"), higher_is_better=False), TUSIMPLE_F1, F1_COUNT,
             CULANE_F1, CULANE_F1_75, CULANE_MF1),
)


def mean_present(field: str, scale: float = 1.0):
    """An aggregate: scale * the mean of one field over the records that carry it (NaN when none does)."""

    def aggregate(records: Sequence[dict]) -> float:
        values = [r[field] for r in records if r.get(field) is not None]
        return scale * sum(values) / len(values) if values else NAN

    aggregate.__name__ = f"mean_present_{field}"
    aggregate.additive = Additive(lambda r: (r[field], 1.0) if r.get(field) is not None else (0.0, 0.0),
                                  ratio(scale))
    return aggregate


_LANGUAGE_CACHE: dict[tuple, dict] = {}


def _corpus_scores(records: Sequence[dict]) -> dict:
    """The COCO caption scores of one corpus of answers from their stored PTB tokens (metrics/vqa.py), memoised:
    a table asks for each part of the same group in turn. The memo is keyed by the answers and references, not
    just the questions: two models (or a model and its blind baseline) answer the same questions."""
    key = tuple((r["key"], str(r["answer_tokens"]), str(r["reference_tokens"])) for r in records)
    if key not in _LANGUAGE_CACHE:
        from lanevil_train.metrics.vqa import language_scores

        if len(_LANGUAGE_CACHE) > 1024:
            _LANGUAGE_CACHE.clear()
        _LANGUAGE_CACHE[key] = language_scores({r["key"]: r["answer_tokens"] for r in records},
                                               {r["key"]: r["reference_tokens"] for r in records},
                                               meteor=False, tokenized=True)
    return _LANGUAGE_CACHE[key]


def language_part(name: str):
    """An aggregate: one COCO caption score (x 100) of a group of answers; NaN for no records.

    BLEU and CIDEr are corpus scores (CIDEr's document frequencies come from the corpus scored), so pooling the
    answers of several severities would count each question several times and change the score even for identical
    answers. A group is therefore split into corpora that hold each question once, one per (case illusion,
    severity), and the corpus scores are averaged weighted by their sizes: an answer unchanged by the illusion has
    a Gap of exactly 0.
    """

    def aggregate(records: Sequence[dict]) -> float:
        if not records:
            return NAN
        parts: dict[tuple, list[dict]] = {}
        for r in records:
            parts.setdefault((r.get("case_illusion") or r.get("illusion"), r["severity"]), []).append(r)
        total = sum(float(_corpus_scores(part)[name]) * len(part) for part in parts.values())
        return 100.0 * total / len(records)

    aggregate.__name__ = f"language_{name}"
    return aggregate


_TOKENS = ("answer_tokens", "reference_tokens")
LANGUAGE_PARTS = ("BLEU_1", "BLEU_2", "BLEU_3", "BLEU_4", "ROUGE_L", "CIDEr")
_VQA_SCORES = (Score("GPT_score", mean_present("gpt_score"), needs_any=("gpt_score",)),
               Score("MiniLM_score", mean_present("minilm_score"), needs_any=("minilm_score",)),
               Score("Language", language_part("Language"), needs=_TOKENS),
               Score("Accuracy", mean_present("correct", 100.0), needs_any=("correct",)))

# One record per answer of a VLM to one QA of one clip variant (tasks/vlm/evaluate.py). The item is the QA of a base
# clip (case_id = base_clip_id, item_key = qa_id), so Original is the same question on the clean clip. GPT_score:
# an LLM judge on an OpenAI-compatible endpoint (DriveLM's 0-100 rubric); MiniLM_score: the offline embedding judge
# (cosine of all-MiniLM-L6-v2 embeddings x 100), never called a GPT score; Language: DriveLM's weighted sum of
# BLEU-1..4, ROUGE-L and CIDEr (metrics/vqa.py), x 100; Accuracy: yes/no and choice questions only.
VQA_SPEC = RecordSpec(
    name="vqa",
    fields=(Field("correct", 0.0, 1.0, required=False), Field("gpt_score", 0.0, 100.0, required=False),
            Field("minilm_score", 0.0, 100.0, required=False)),
    scores=_VQA_SCORES,
    summary=_VQA_SCORES + tuple(Score(name, language_part(name), needs=_TOKENS) for name in LANGUAGE_PARTS),
    item_key="qa_id",
    groups=("qa_category", "segment"),
    count_name="answers",
)

SPECS: dict[str, RecordSpec] = {LANE_SPEC.name: LANE_SPEC, VQA_SPEC.name: VQA_SPEC}


def spec_for(records: Sequence[dict]) -> RecordSpec:
    """The spec of a set of records: the one their "spec" field names, else the only known spec whose required
    fields they all carry. Raises when they name several specs, an unknown one, or none fits."""
    named = {r["spec"] for r in records if isinstance(r, dict) and r.get("spec") is not None}
    if len(named) > 1:
        raise ValueError(f"records of different kinds cannot share a report: specs {sorted(named)}")
    if named:
        name = named.pop()
        if name not in SPECS:
            raise ValueError(f"records name an unknown spec {name!r}; known: {sorted(SPECS)}")
        return SPECS[name]
    fits = [spec for spec in SPECS.values()
            if all(isinstance(r, dict) and all(f.name in r for f in spec.fields if f.required)
                   and (spec.item_key is None or spec.item_key in r) for r in records)]
    if len(fits) != 1:
        raise ValueError(f"cannot tell which kind of records these are ({len(fits)} specs fit); give each record "
                         f"a 'spec' field, one of {sorted(SPECS)}")
    return fits[0]


def record_set(records, spec: RecordSpec | None = None) -> RecordSet:
    """Records as a validated RecordSet (returned as is when already one); the spec is inferred when not given."""
    if isinstance(records, RecordSet):
        return records
    return RecordSet(records, spec or spec_for(records))
