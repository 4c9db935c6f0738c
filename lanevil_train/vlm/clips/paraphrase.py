"""The optional paraphrasing pass over generated QA texts (off by default): any OpenAI-compatible endpoint rewords
each question (and, as the clip-set builder asks, each open answer), so a VLM is not scored on a handful of
template sentences.

A rewrite is kept only when it passes checks that the meaning-bearing form survived: not empty, not much longer,
still a question when the original was, still yes/no when the original was (and not yes/no when it was not), an
answer's leading Yes/No kept, and the same option letters in the same order for a choice question. Anything else keeps
the original text (and is counted), so the pass can only vary the wording, never break a QA pair. Replies are cached
per (model, temperature, question), so rebuilding a suite asks nothing twice.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Sequence

from lanevil_train.vlm.http import ChatClient, ReplyCache, cache_key

SYSTEM_PROMPT = "You reword questions and answers about driving scenes without changing what they say."
INSTRUCTION = ("Paraphrase the text below (a question or an answer about a driving scene). Keep its exact meaning. "
               "If it is a question that can be answered with yes or no, the paraphrase must be a yes/no question "
               "too; otherwise it must not be one. An answer that starts with Yes or No keeps that start. Keep every "
               "answer option with its letter (A., B., ...) unchanged and in the same order. Reply with the "
               "paraphrase only.\nText: ")
YES_NO_STARTS = frozenset("is are am was were do does did can could should would will shall may might must has have "
                          "had".split())
OPTION = re.compile(r"(?:^|[\s(])([A-H])[.):]\s")
QUOTES = "\"'`\u201c\u201d\u2018\u2019"


def is_yes_no(question: str) -> bool:
    """Whether a question asks yes or no: it starts with an auxiliary verb (Is, Does, Can, ...)."""
    words = question.strip().lstrip(QUOTES).split(maxsplit=1)
    return bool(words) and words[0].lower().strip(",") in YES_NO_STARTS


def leading_yes_no(text: str) -> str | None:
    """"yes" or "no" when an answer starts with it ("No, it is a shadow." -> "no"), else None."""
    match = re.match(r"\W*(yes|no)\b", text, flags=re.I)
    return match.group(1).lower() if match else None


def option_letters(question: str) -> list[str]:
    """The option letters of a choice question in order ("A. left B. right" -> ["A", "B"])."""
    return OPTION.findall(question)


def clean_reply(reply: str) -> str:
    """The reply without a "Question:"/"Paraphrase:" lead or wrapping quotes, on one stripped line per line."""
    text = reply.strip()
    text = re.sub(r"^(?:paraphrased (?:question|text|answer)|paraphrase|question|text)\s*:\s*", "", text, flags=re.I)
    if len(text) >= 2 and text[0] in QUOTES and text[-1] in QUOTES:
        text = text[1:-1].strip()
    return text


def rejection(original: str, paraphrase: str, max_ratio: float) -> str | None:
    """Why `paraphrase` cannot replace `original` (None: it can)."""
    if not paraphrase:
        return "empty"
    if len(paraphrase) > max_ratio * len(original) + 20:
        return "too long"
    if original.rstrip().endswith("?") and not paraphrase.rstrip().endswith("?"):
        return "not a question"
    if is_yes_no(original) != is_yes_no(paraphrase):
        return "changed yes/no-ness"
    if leading_yes_no(original) != leading_yes_no(paraphrase):
        return "changed the yes/no answer"
    if option_letters(original) != option_letters(paraphrase):
        return "lost the option letters"
    return None


class OpenAIParaphraser:
    """Callable list[str] -> list[str]: each question (or open answer) reworded through an OpenAI-compatible endpoint,
    or kept.

    api_key_env: the environment variable holding the API key (it must be set; None: no key); max_ratio: a
    paraphrase longer than max_ratio x the original (+20 characters) is refused; cache_path: a
    JSON-lines cache of replies (None: in memory). `last_summary` counts kept rewrites and refusals by reason.
    """

    def __init__(self, base_url: str, model: str, api_key_env: str | None = None,
                 concurrency: int = 8, max_retries: int = 5, timeout_s: float = 60.0, temperature: float = 0.7,
                 max_tokens: int = 128, max_ratio: float = 2.0, cache_path: str | Path | None = None,
                 backoff_s: float = 1.0):
        if not isinstance(model, str) or not model:
            raise ValueError(f"model: expected the paraphrasing model's name, got {model!r}")
        if not isinstance(max_ratio, (int, float)) or max_ratio < 1:
            raise ValueError(f"max_ratio: expected a number >= 1, got {max_ratio!r}")
        self.client = ChatClient(base_url, api_key_env, concurrency, max_retries, timeout_s, backoff_s)
        self.model, self.temperature, self.max_tokens, self.max_ratio = model, float(temperature), max_tokens, max_ratio
        self.cache = ReplyCache(cache_path)
        self.last_summary: dict = {}

    def request_body(self, question: str) -> dict:
        """The chat-completions body asking for one paraphrase."""
        return {"model": self.model, "temperature": self.temperature, "max_tokens": self.max_tokens,
                "messages": [{"role": "system", "content": SYSTEM_PROMPT},
                             {"role": "user", "content": INSTRUCTION + question}]}

    def __call__(self, questions: Sequence[str]) -> list[str]:
        """The texts reworded where a valid paraphrase came back, else unchanged, in order."""
        for i, question in enumerate(questions):
            if not isinstance(question, str):
                raise ValueError(f"text {i}: expected a string, got {type(question).__name__}")
        keys = [cache_key(self.model, self.temperature, question) for question in questions]
        first = {key: i for i, key in reversed(list(enumerate(keys)))}
        todo = sorted(i for key, i in first.items() if self.cache.get(key) is None)

        def work(j: int) -> str:
            return self.client.complete(self.request_body(questions[todo[j]]), f"paraphrase text {todo[j]}")

        for j, reply in self.client.stream(len(todo), work):
            i = todo[j]
            self.cache.add({"key": keys[i], "model": self.model, "temperature": self.temperature,
                            "question": questions[i], "reply": reply})
        out, summary = [], {"paraphrased": 0, "kept": 0, "requests": len(todo)}
        for question, key in zip(questions, keys):
            candidate = clean_reply(self.cache.get(key)["reply"])
            reason = rejection(question, candidate, self.max_ratio)
            summary["paraphrased" if reason is None else "kept"] += 1
            if reason is not None:
                summary[reason] = summary.get(reason, 0) + 1
            out.append(candidate if reason is None else question)
        self.last_summary = summary
        return out
