"""Answer every QA on every clip variant of a suite and score each answer, streaming and resumable.

Two JSON-lines logs in the output folder, both appended as work finishes:
- `answers.jsonl`: the raw answer to each (clip variant, QA) pair, written the moment the backend returns it (an
  interrupted run against a paid endpoint never asks the same question twice);
- `per_answer.jsonl`: the scored records (report/specs.py VQA_SPEC), written per chunk once the chunk's answers are
  tokenised (PTB, one Java call per chunk) and judged.
A rerun with the same folder skips what either log holds; the tables are built from per_answer.jsonl alone.
"""

from __future__ import annotations

from pathlib import Path
from typing import Iterator, Sequence

from lanevil_train.progress import progress_counter
from lanevil_train.report.specs import VQA_SPEC
from lanevil_train.results_log import ResultsLog
from lanevil_train.vlm.base import VLM
from lanevil_train.vlm.clips.qa_records import prompt_text

ANSWERS = "answers.jsonl"
PER_ANSWER = "per_answer.jsonl"
# The judges' score names and the record field each fills (report/specs.py VQA_SPEC).
JUDGE_FIELDS = {"GPT_score": "gpt_score", "MiniLM_score": "minilm_score"}


def pair_key(clip_id: str, qa_id: str) -> str:
    """The key of one answer: a QA asked on one clip variant."""
    return f"{clip_id}/{qa_id}"


def judge_field(judge) -> str | None:
    """The record field a judge's scores go to (None without a judge); an unknown score name is an error."""
    if judge is None:
        return None
    name = getattr(judge, "score_name", None)
    if name not in JUDGE_FIELDS:
        raise ValueError(f"judge {type(judge).__name__}: score_name {name!r} is not one of {sorted(JUDGE_FIELDS)}")
    return JUDGE_FIELDS[name]


def _pairs(dataset, index: int, done: set[str]) -> list[tuple[dict, dict]]:
    """(clip meta, QA) pairs of clip variant `index` not yet in `done`, without loading its frames."""
    meta = dataset.clip_meta(index)
    return [(meta, qa) for qa in dataset.qa_for(meta["base_clip_id"])
            if pair_key(meta["clip_id"], qa["qa_id"]) not in done]


def _chunks(dataset, done: set[str], pairs_per_chunk: int) -> Iterator[list[tuple[int, dict, dict]]]:
    """The unfinished pairs as (clip index, meta, QA), grouped into chunks of whole clips of about
    `pairs_per_chunk` pairs."""
    chunk: list[tuple[int, dict, dict]] = []
    for index in range(len(dataset)):
        chunk += [(index, meta, qa) for meta, qa in _pairs(dataset, index, done)]
        if len(chunk) >= pairs_per_chunk:
            yield chunk
            chunk = []
    if chunk:
        yield chunk


def _ask(vlm: VLM, dataset, pairs: list[tuple[int, dict, dict]], answers: dict[str, str], log: ResultsLog) -> None:
    """Answer the pairs that have no answer yet, `vlm.batch_size` at a time, logging each answer as it arrives."""
    todo = [p for p in pairs if pair_key(p[1]["clip_id"], p[2]["qa_id"]) not in answers]
    frames: dict[int, list] = {}
    step = max(1, int(getattr(vlm, "batch_size", 1) or 1))
    reads = getattr(vlm, "reads_frames", True)
    for start in range(0, len(todo), step):
        batch = todo[start:start + step]
        for index, _, _ in batch:
            if index not in frames:
                frames[index] = dataset[index]["frames"] if reads else []  # a text-only model: nothing rendered
        clips = [frames[index] for index, _, _ in batch]
        for i, text in vlm.answer_stream(clips, [prompt_text(qa) for _, _, qa in batch]):
            _, meta, qa = batch[i]
            key = pair_key(meta["clip_id"], qa["qa_id"])
            answers[key] = text
            log.append([{"key": key, "answer": text}])


def answer_records(pairs: Sequence[tuple[dict, dict]], answers: Sequence[str], label: dict, judge=None,
                   tokenize=None) -> list[dict]:
    """The scored VQA records of (clip meta, QA) pairs and their answers: accuracy for yes/no and choice
    questions, the judge's score, and the PTB tokens of answer and reference (from which the Language score of any
    group is computed later)."""
    from lanevil_train.vlm.answer_scoring.drivelm_score import MATCH_TAG, match_f1
    from lanevil_train.vlm.clips.qa_records import answer_is_correct

    if tokenize is None:
        from lanevil_train.metrics.vqa import ptb_tokenize as tokenize
    references = [qa["answer"] for _, qa in pairs]
    tokens = tokenize(list(answers) + references) if pairs else []
    field = judge_field(judge)
    judged = judge.score([qa["question"] for _, qa in pairs], references, list(answers)) if judge and pairs else []
    records = []
    for i, ((meta, qa), text) in enumerate(zip(pairs, answers)):
        correct = answer_is_correct(qa, text)
        record = {"spec": VQA_SPEC.name, "key": pair_key(meta["clip_id"], qa["qa_id"]), **label,
                  "case_id": meta["base_clip_id"], "qa_id": qa["qa_id"], "clip_id": meta["clip_id"],
                  "scene": meta.get("case_id"), "case_illusion": meta.get("case_illusion"),
                  "segment": meta.get("segment"), "illusion": meta.get("illusion"),
                  "category": meta.get("category"), "severity": int(meta.get("severity") or 0),
                  "qa_category": qa["category"], "qa_type": qa["type"], "question": qa["question"],
                  "reference": qa["answer"], "answer": text, "answer_tokens": tokens[i],
                  "reference_tokens": [tokens[len(pairs) + i]],
                  "correct": None if correct is None else int(bool(correct))}
        if field:
            record[field] = judged[i]
            record["judge"] = judge.name
        if MATCH_TAG in qa.get("drivelm_tag", ()):  # a DriveLM coordinate question: its match F1 (x 100)
            record["match_f1"] = 100.0 * match_f1(text, qa["answer"])
        records.append(record)
    return records


def evaluate_clips(vlm: VLM, dataset, out_dir: str | Path, label: dict, judge=None, progress: str = "auto",
                   pairs_per_chunk: int | None = None) -> Path:
    """Answer and score every (clip variant, QA) pair of `dataset` not yet in out_dir/per_answer.jsonl, in chunks
    of about `pairs_per_chunk` pairs (default: 64, or 4 backend batches when larger); returns that file.
    `label` ({"model", "dataset"}) is copied into every record; `dataset` is a clip suite (vlm/clips/clip_set.py:
    clip_meta, qa_for, item frames)."""
    out_dir = Path(out_dir)
    answer_log, score_log = ResultsLog(out_dir / ANSWERS), ResultsLog(out_dir / PER_ANSWER)
    scored = score_log.resume()
    answers = {r["key"]: r["answer"] for r in answer_log.records()} if answer_log.resume() else {}
    metas = [dataset.clip_meta(i) for i in range(len(dataset))]
    total = sum(len(dataset.qa_for(meta["base_clip_id"])) for meta in metas)
    # the illusion each base clip's variants show: the clean records carry it too (report/specs.py language_part)
    case_illusion = {meta["base_clip_id"]: meta["illusion"] for meta in metas if meta.get("illusion")}
    bar = progress_counter(total, len(scored), "evaluate", "answer", progress)
    # a chunk is answered, then scored (one Java call to tokenise, one judge pass): big enough that scoring is a
    # small part of it and several backend batches fill it (a server keeps its requests in flight)
    pairs_per_chunk = pairs_per_chunk or max(64, 4 * int(getattr(vlm, "batch_size", 1) or 1))
    for chunk in _chunks(dataset, scored, pairs_per_chunk):
        _ask(vlm, dataset, chunk, answers, answer_log)
        pairs = [({**meta, "case_illusion": case_illusion.get(meta["base_clip_id"])}, qa) for _, meta, qa in chunk]
        texts = [answers[pair_key(meta["clip_id"], qa["qa_id"])] for meta, qa in pairs]
        score_log.append(answer_records(pairs, texts, label, judge))
        bar.update(len(chunk))
    bar.close()
    return score_log.path
