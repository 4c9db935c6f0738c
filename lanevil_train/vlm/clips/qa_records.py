"""A QA record (what qa.jsonl holds and suite_qa.suite_qa writes) and the accuracy rule for yes/no and choice answers.

A record: {"qa_id", "base_clip_id", "category" (QA_CATEGORIES, the paper's six), "type" (QA_TYPES), "question",
"answer", and "choices" (["A. ...", ...]) for a choice question, whose answer is its letter and text ("B. Two lanes.")}.
"""

from __future__ import annotations

import re

QA_CATEGORIES = ("scene_description", "object_recognition", "lane_recognition", "object_behavior",
                 "motion_reasoning", "action")
QA_TYPES = ("open", "yes_no", "choice")
# How a choice question's options follow it in the text a model is asked (DriveLM's multiple-choice layout).
OPTIONS_LEAD = " Please select the correct answer from the following options: "


def prompt_text(qa: dict) -> str:
    """The text a model is asked for a QA: the question, and for a choice question its options after it (a model
    cannot pick letter B without seeing the options)."""
    return qa["question"] + (OPTIONS_LEAD + " ".join(qa["choices"]) if qa["type"] == "choice" else "")


def _normalise(text: str) -> str:
    return " ".join(re.sub(r"[^a-z0-9 ]+", " ", text.lower()).split())


_LETTER = re.compile(r"^\s*(?:the\s+)?(?:answer|option|choice)?\s*(?:is)?\s*[:\-]?\s*\(?([a-z])\s*(?:[.):]|$)",
                     re.IGNORECASE)


def chosen_letter(qa: dict, prediction: str) -> str | None:
    """The option letter a prediction picks ("B", "b)", "(B) Two lanes", "Answer: B", or an option's text)."""
    letters = [c.split(".", 1)[0] for c in qa["choices"]]
    match = _LETTER.match(prediction)
    if match and match.group(1).upper() in letters:
        return match.group(1).upper()
    said = _normalise(prediction)
    for choice in qa["choices"]:
        letter, _, text = choice.partition(".")
        if said and said in (_normalise(text), _normalise(choice)):
            return letter
    return None


def answer_is_correct(qa: dict, prediction: str) -> bool | None:
    """Accuracy of a prediction: yes/no by its first word, choice by its letter (or an option's exact text);
    None for open questions (scored by the language and judge scores instead)."""
    if qa["type"] == "open":
        return None
    if qa["type"] == "yes_no":
        words = _normalise(prediction).split()
        return bool(words) and words[0] == _normalise(qa["answer"]).split()[0]
    if qa["type"] == "choice":
        return chosen_letter(qa, prediction) == qa["answer"].split(".", 1)[0]
    raise ValueError(f"QA {qa.get('qa_id')}: type: expected one of {', '.join(QA_TYPES)}, got {qa['type']!r}")


_QA_FIELDS = {"qa_id": str, "base_clip_id": str, "category": str, "type": str, "question": str, "answer": str}


def check_qa_record(record, where: str) -> dict:
    """A QA record as qa.jsonl holds it (the fields suite_qa.suite_qa gives), else a ValueError naming `where` and the
    field."""
    if not isinstance(record, dict):
        raise ValueError(f"{where}: expected a QA object, got {type(record).__name__}")
    for field, kind in _QA_FIELDS.items():
        if not isinstance(record.get(field), kind) or not record[field]:
            raise ValueError(f"{where}: {field}: expected a non-empty string, got {record.get(field)!r}")
    if record["category"] not in QA_CATEGORIES:
        raise ValueError(f"{where}: category: expected one of {', '.join(QA_CATEGORIES)}, got {record['category']!r}")
    if record["type"] not in QA_TYPES:
        raise ValueError(f"{where}: type: expected one of {', '.join(QA_TYPES)}, got {record['type']!r}")
    choices = record.get("choices")
    if record["type"] == "choice":
        if not isinstance(choices, list) or len(choices) < 2 or not all(isinstance(c, str) for c in choices):
            raise ValueError(f"{where}: choices: a choice question needs a list of at least 2 option strings "
                             f"(\"A. ...\"), got {choices!r}")
        if record["answer"].split(".", 1)[0] not in [c.split(".", 1)[0] for c in choices]:
            raise ValueError(f"{where}: answer: expected one of the choices' letters first, got {record['answer']!r}")
    elif choices is not None:
        raise ValueError(f"{where}: choices: only choice questions have choices, this one is {record['type']!r}")
    return record
