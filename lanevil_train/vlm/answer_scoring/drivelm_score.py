"""DriveLM's challenge score of a set of answers, as its evaluation computes it (OpenDriveLab/DriveLM 1de72a7,
challenge/evaluation.py), beside the project's own tables.

Facts (file and line of challenge/evaluation.py):
- each QA has a `tag` list (l.177): 0 accuracy (exact match, the MCQ letter), 1 GPT score, 2 language, 3 match
  (l.126-138 `forward`); an item is scored by every part its tags name;
- match (l.56-67 `eval_match`): the mean over tag-3 QA of 100 x F1 of the matched points, averaged with the GPT
  score of the same QA: (mean F1 x 100 + their GPT) / 2;
- the F1 of one answer (l.79-120 `match_result`): the numbers `\\d+\\.\\d+` of answer and reference in order, paired
  as (x, y) points (an answer's odd last number dropped); each answer point, in order, takes the nearest reference
  point left by L1 distance, a true positive when that distance is < 16 (the point is then removed), else a false
  positive; false negatives = reference points - true positives; precision, recall and F1 with 1e-8 added to each
  denominator;
- final (l.194-222): 0.4 GPT / 100 + 0.2 language + 0.2 match / 100 + 0.2 accuracy, language = BLEU-1..4 / 12 +
  ROUGE-L / 3 + CIDEr / 30 (metrics/vqa.py `language_score`, the same weights), accuracy on 0..1.
- DriveLM's script also scores a frame's later questions only where their coordinates are among the points its
  first answer matched (l.69-77 `eval_graph`, l.180-186); every question is scored here.

This project's clips hold no coordinate question, so their match is absent: DriveLM's final score is then reported
with match counted as 0, as DriveLM scores a submission without it, and said so. A user's DriveLM file whose QA carry
tag 3 (read as "drivelm_tag", vlm/clips/drivelm.py) gets its match. Here the parts are the project's own aggregates
of a model's answers (report/specs.py): GPT the mean judge score (`gpt_score`), Language over every answer, accuracy
over the yes/no and choice answers.
"""

from __future__ import annotations

import re
from collections.abc import Sequence

import numpy as np

MATCH_TAG = 3
MATCH_DISTANCE = 16.0
WEIGHTS = {"GPT": 0.4, "Language": 0.2, "Match": 0.2, "Accuracy": 0.2}
_NUMBER = re.compile(r"\d+\.\d+")


def _points(text: str, drop_odd: bool) -> np.ndarray:
    numbers = [float(v) for v in _NUMBER.findall(text)]
    if len(numbers) % 2:
        if not drop_odd:
            raise ValueError(f"reference {text!r}: expected (x, y) pairs of decimal numbers, got an odd count "
                             f"({len(numbers)})")
        numbers = numbers[:-1]
    return np.asarray(numbers, dtype=np.float64).reshape(-1, 2)


def match_f1(answer: str, reference: str) -> float:
    """DriveLM's F1 (0..1) of the answer's points matched to the reference's (module docstring)."""
    predicted, truth = _points(answer, drop_odd=True), _points(reference, drop_odd=False)
    total, hits, misses = len(truth), 0, 0
    for point in predicted:
        if len(truth):
            distances = np.abs(truth - point).sum(axis=1)
            nearest = int(np.argmin(distances))
            if distances[nearest] < MATCH_DISTANCE:
                hits += 1
                truth = np.delete(truth, nearest, axis=0)
                continue
        misses += 1
    precision = hits / (hits + misses + 1e-8)
    recall = hits / (hits + (total - hits) + 1e-8)
    return 2 * precision * recall / (precision + recall + 1e-8)


def final_score(gpt: float, language: float, match: float | None, accuracy: float) -> float:
    """DriveLM's final score x 100 from its parts, each x 100 (GPT 0..100, Language x 100, match 0..100, accuracy
    in %); a missing match counts 0."""
    parts = {"GPT": gpt, "Language": language, "Match": 0.0 if match is None else match, "Accuracy": accuracy}
    return sum(WEIGHTS[name] * float(value) for name, value in parts.items())


def drivelm_parts(records: Sequence[dict]) -> dict | None:
    """{"GPT", "Language", "Match" (None without tag-3 QA), "Accuracy", "final", "answers"} of one set of scored
    answers (tasks/vlm evaluation records), all x 100; None where no answer has a GPT score (no LLM judge)."""
    from lanevil_train.report.specs import language_part

    judged = [r["gpt_score"] for r in records if r.get("gpt_score") is not None]
    closed = [r["correct"] for r in records if r.get("correct") is not None]
    if not judged or not closed:
        return None
    matched = [r for r in records if r.get("match_f1") is not None]
    match = None
    if matched:
        gpt_of_matched = [r["gpt_score"] for r in matched if r.get("gpt_score") is not None]
        f1 = float(np.mean([r["match_f1"] for r in matched]))
        match = (f1 + float(np.mean(gpt_of_matched))) / 2 if gpt_of_matched else f1
    parts = {"GPT": float(np.mean(judged)), "Language": float(language_part("Language")(records)), "Match": match,
             "Accuracy": 100.0 * float(np.mean(closed))}
    return {**parts, "final": final_score(parts["GPT"], parts["Language"], match, parts["Accuracy"]),
            "answers": len(records)}
