"""A text-only reader: a baseline that answers a benchmark's questions from their words alone, never the frames.

A VLM benchmark measures seeing only where no wording gives the answer away; DriveBench (ICCV 2025) found driving
VLMs' text-only scores close to their clean ones. This reader is fitted on a training split's QA (question and
options, never a frame) and answers like any model (`TextOnlyVLM`, `task.blind=text`: `<label>-text` in every
table), and `task=audit_qa` cross-fits it on any QA file to find the templates that leak their answer. The model is
fixed, fast and plain (scikit-learn):

- yes/no: tf-idf of the question's word 1- and 2-grams (sublinear term frequency), an L2 logistic regression
  (C = 10) -> "Yes" or "No"; a training set of one answer only answers that one;
- choice: every option scored by one logistic regression over [tf-idf 1- and 2-grams of the option's text, the
  option's letter, hashed (question word, option word) pairs (2^18 buckets)], the highest-scoring option's letter
  wins: what the option says, where it stands and how its words go with the question's;
- open: the reference answer of the most similar training question (tf-idf cosine), as a retrieval baseline for the
  language and judge scores;
- a question's type when only its text is given: choice when its options follow it (qa_records.OPTIONS_LEAD), yes/no
  when it opens with an auxiliary verb ("Is ...", "Should ..."), open when with a question word ("What ...",
  "Describe ..."), else the type of the most similar training question.
"""

from __future__ import annotations

import hashlib
import re
from typing import Sequence

import numpy as np

from lanevil_train.vlm.base import VLM, Frames
from lanevil_train.vlm.clips.qa_records import OPTIONS_LEAD, QA_TYPES

C = 10.0  # inverse L2 strength of both logistic regressions
CROSS_BUCKETS = 2 ** 18
NGRAMS = (1, 2)
_WORD = re.compile(r"[a-z0-9]+")
_OPTION = re.compile(r"(?:^|\s)([A-Z])\.\s")
_YES_NO_OPENERS = ("is", "are", "does", "do", "did", "can", "could", "may", "might", "should", "would", "will",
                   "was", "were", "has", "have", "had", "must", "shall")
_OPEN_OPENERS = ("what", "which", "how", "where", "why", "when", "who", "describe", "identify", "count", "explain")


def words(text: str) -> list[str]:
    return _WORD.findall(text.lower())


def option_text(choice: str) -> tuple[str, str]:
    """("B", "Two lanes.") of "B. Two lanes."."""
    letter, _, text = choice.partition(".")
    return letter.strip(), text.strip()


def split_prompt(prompt: str) -> tuple[str, list[str] | None]:
    """(question, options as "A. ...") of a prompt as prompt_text writes it; options None without OPTIONS_LEAD."""
    if OPTIONS_LEAD not in prompt:
        return prompt.strip(), None
    question, _, listed = prompt.partition(OPTIONS_LEAD)
    starts = [m.start(1) for m in _OPTION.finditer(listed)]
    options = [listed[a:b].strip() for a, b in zip(starts, [*starts[1:], len(listed)])]
    return question.strip(), options or None


def _yes(answer: str) -> bool:
    return words(answer)[:1] == ["yes"]


def _vectorizer():
    from sklearn.feature_extraction.text import TfidfVectorizer

    return TfidfVectorizer(ngram_range=NGRAMS, sublinear_tf=True, token_pattern=r"[A-Za-z0-9]+", lowercase=True)


def _logistic():
    from sklearn.linear_model import LogisticRegression

    return LogisticRegression(C=C, max_iter=2000)


class TextOnlyReader:
    """Fit on QA records (qa_records' form), then answer a record or a prompt text; see the module docstring."""

    def __init__(self):
        self.fitted = False

    # ------------------------------------------------------------------------------------------------ fitting
    def fit(self, qas: Sequence[dict]) -> "TextOnlyReader":
        qas = [qa for qa in qas if qa.get("type") in QA_TYPES]
        if not qas:
            raise ValueError("text-only reader: no QA to fit on (expected records with a type: open, yes_no, choice)")
        self.questions = _vectorizer().fit([qa["question"] for qa in qas])
        self.train_matrix = self.questions.transform([qa["question"] for qa in qas])
        self.train_types = [qa["type"] for qa in qas]
        self.train_answers = [qa["answer"] for qa in qas]
        self._fit_yes_no([qa for qa in qas if qa["type"] == "yes_no"])
        self._fit_choice([qa for qa in qas if qa["type"] == "choice"])
        self.fitted = True
        self.digest = hashlib.sha256("\n".join(f"{qa['type']}|{qa['question']}|{qa.get('choices')}|{qa['answer']}"
                                               for qa in qas).encode("utf-8")).hexdigest()[:16]
        self.size = len(qas)
        return self

    def _fit_yes_no(self, qas: list[dict]) -> None:
        self.yes_no_model, self.yes_no_constant = None, True
        if not qas:
            return
        labels = np.array([_yes(qa["answer"]) for qa in qas])
        self.yes_no_constant = bool(labels.mean() >= 0.5)
        if labels.all() or not labels.any():
            return
        self.yes_no_words = _vectorizer().fit([qa["question"] for qa in qas])
        self.yes_no_model = _logistic().fit(self.yes_no_words.transform([qa["question"] for qa in qas]), labels)

    def _pair_features(self, question: str, options: list[str]):
        """One row per option: its text's n-grams, its letter, hashed (question word, option word) pairs."""
        from scipy import sparse
        from sklearn.feature_extraction import FeatureHasher

        texts = [option_text(o) for o in options]
        hasher = FeatureHasher(n_features=CROSS_BUCKETS, input_type="string", alternate_sign=False)
        q_words = sorted(set(words(question)))
        pairs = [[f"{q}|{o}" for q in q_words for o in sorted(set(words(text)))] or ["-"] for _, text in texts]
        cross = hasher.transform(pairs)
        counts = np.asarray(cross.sum(axis=1)).ravel()
        cross = sparse.diags(1.0 / np.sqrt(np.maximum(counts, 1.0))) @ cross
        letters = sparse.csr_matrix(np.array([[float(letter == chr(65 + k)) for k in range(26)]
                                              for letter, _ in texts]))
        return sparse.hstack([self.option_words.transform([text for _, text in texts]), letters, cross]).tocsr()

    def _fit_choice(self, qas: list[dict]) -> None:
        from scipy import sparse

        self.choice_model = None
        if not qas:
            return
        self.option_words = _vectorizer().fit([option_text(c)[1] for qa in qas for c in qa["choices"]])
        rows, labels = [], []
        for qa in qas:
            rows.append(self._pair_features(qa["question"], qa["choices"]))
            right = qa["answer"].split(".", 1)[0].strip()
            labels += [option_text(c)[0] == right for c in qa["choices"]]
        labels = np.array(labels)
        if labels.all() or not labels.any():
            return
        self.choice_model = _logistic().fit(sparse.vstack(rows).tocsr(), labels)

    # ------------------------------------------------------------------------------------------------ answering
    def _check(self) -> None:
        if not self.fitted:
            raise RuntimeError("text-only reader: fit it on a training split's QA before asking it")

    def _nearest(self, question: str, rows: list[int]) -> int | None:
        """The row of `rows` whose training question is most similar to `question` (tf-idf cosine), None when
        none shares a word with it."""
        if not rows:
            return None
        similarity = (self.train_matrix[rows] @ self.questions.transform([question]).T).toarray().ravel()
        best = int(np.argmax(similarity))
        return rows[best] if similarity[best] > 0 else None

    def guess_type(self, question: str, options: list[str] | None) -> str:
        if options:
            return "choice"
        first = (words(question) or [""])[0]
        if first in _YES_NO_OPENERS or first in _OPEN_OPENERS:
            return "yes_no" if first in _YES_NO_OPENERS else "open"
        near = self._nearest(question, [i for i, t in enumerate(self.train_types) if t != "choice"])
        return self.train_types[near] if near is not None else "open"

    def answer_yes_no(self, question: str) -> str:
        if self.yes_no_model is None:
            return "Yes" if self.yes_no_constant else "No"
        return "Yes" if bool(self.yes_no_model.predict(self.yes_no_words.transform([question]))[0]) else "No"

    def answer_choice(self, question: str, options: list[str]) -> str:
        if self.choice_model is None or not options:
            return option_text(options[0])[0] if options else "A"
        scores = self.choice_model.decision_function(self._pair_features(question, options))
        return option_text(options[int(np.argmax(scores))])[0]

    def answer_open(self, question: str) -> str:
        near = self._nearest(question, [i for i, t in enumerate(self.train_types) if t == "open"])
        return self.train_answers[near] if near is not None else "I cannot tell."

    def predict(self, qa: dict) -> str:
        """The reader's answer to a QA record (its type known)."""
        self._check()
        if qa["type"] == "yes_no":
            return self.answer_yes_no(qa["question"])
        if qa["type"] == "choice":
            return self.answer_choice(qa["question"], qa["choices"])
        return self.answer_open(qa["question"])

    def answer_prompt(self, prompt: str) -> str:
        """The reader's answer to a prompt as a model gets it (the question, and a choice question's options)."""
        self._check()
        question, options = split_prompt(prompt)
        kind = self.guess_type(question, options)
        return self.predict({"type": kind, "question": question, "choices": options})


class TextOnlyVLM(VLM):
    """A fitted TextOnlyReader behind the VLM interface: it is given the clips and never looks at them (an
    evaluation does not even load them: `reads_frames`)."""

    reads_frames = False

    def __init__(self, reader: TextOnlyReader, name: str = "text-only", batch_size: int = 64):
        self.reader, self.name, self.batch_size = reader, name, batch_size

    def answer(self, clips: Sequence[Frames], questions: Sequence[str]) -> list[str]:
        if len(clips) != len(questions):
            raise ValueError(f"{len(clips)} clips for {len(questions)} questions: expected one clip per question")
        return [self.reader.answer_prompt(question) for question in questions]

    def identity(self) -> dict:
        return {"backend": type(self).__name__, "name": self.name, "fitted_on": self.reader.digest,
                "train_qa": self.reader.size}
