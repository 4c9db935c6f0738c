"""The OpenAI-compatible backend (model=vlm/openai): any chat-completions server that takes images, such as a vLLM
server running a big VLM across GPUs.

One request per (clip, question): one user message whose content is the clip's frames as base64 data-URL
``image_url`` parts followed by the question as a ``text`` part (vLLM's multi-image format; the server must allow
6 images, ``--limit-mm-per-prompt '{"image": 6}'``). Requests run `concurrency` at a time with retries
(vlm/http.py); `answer_stream` yields each answer as it arrives so an evaluation appends it and a rerun resumes.
"""

from __future__ import annotations

import base64
import json
import threading
from typing import Iterator, Sequence

import cv2
import numpy as np

from lanevil_train.vlm.base import VLM, Frames, check_batch
from lanevil_train.vlm.http import ChatClient

IMAGE_FORMATS = ("png", "jpeg")


def encode_frame(frame: np.ndarray, image_format: str = "png", jpeg_quality: int = 90) -> str:
    """One RGB uint8 frame as a data URL (data:image/png;base64,... or image/jpeg), the form image_url parts take."""
    if image_format not in IMAGE_FORMATS:
        raise ValueError(f"image_format: expected one of {IMAGE_FORMATS}, got {image_format!r}")
    bgr = cv2.cvtColor(np.ascontiguousarray(frame), cv2.COLOR_RGB2BGR)
    params = [cv2.IMWRITE_JPEG_QUALITY, int(jpeg_quality)] if image_format == "jpeg" else []
    ok, data = cv2.imencode("." + ("jpg" if image_format == "jpeg" else "png"), bgr, params)
    if not ok:
        raise ValueError(f"could not encode a {frame.shape} frame as {image_format}")
    return f"data:image/{image_format};base64," + base64.b64encode(data.tobytes()).decode("ascii")


class _ClipEncoder:
    """Encodes each clip of one call once (the QA of a clip share its frames), from many threads: the JSON of its
    image_url parts, ready to splice into each request's body (serialising megabytes of base64 per request would
    hold the GIL for milliseconds)."""

    def __init__(self, clips: Sequence[Frames], image_format: str, jpeg_quality: int):
        self.clips, self.image_format, self.jpeg_quality = clips, image_format, jpeg_quality
        self._done: dict[int, str] = {}
        self._locks: dict[int, threading.Lock] = {}
        self._guard = threading.Lock()

    def parts_json(self, i: int) -> str:
        """The JSON list of clip i's image_url parts (encoded at the first request that needs them)."""
        key = id(self.clips[i])  # stable: `clips` holds every clip for the whole call
        with self._guard:
            lock = self._locks.setdefault(key, threading.Lock())
        with lock:
            if key not in self._done:
                urls = [encode_frame(f, self.image_format, self.jpeg_quality) for f in self.clips[i]]
                self._done[key] = json.dumps(image_parts(urls))
            return self._done[key]


def image_parts(frame_urls: Sequence[str]) -> list[dict]:
    """The image_url content parts of a clip's frames, in order."""
    return [{"type": "image_url", "image_url": {"url": url}} for url in frame_urls]


class OpenAIVLM(VLM):
    """A VLM behind an OpenAI-compatible chat-completions endpoint.

    base_url: the API root (http://host:8000/v1); name: the served model name; api_key_env: the environment
    variable with the key (it must be set; None: no key, a server without auth); concurrency: requests in flight;
    max_retries, timeout_s, backoff_s: see ChatClient; max_new_tokens, temperature: generation (greedy by default);
    image_format: "png" (lossless) or "jpeg" (smaller, jpeg_quality); system_prompt: a system message before the
    user's; label: the model's name in tables (default: name); batch_size: pairs handed over at once by the
    evaluation (default 4 x concurrency, so the pool stays busy).
    """

    def __init__(self, base_url: str, name: str, api_key_env: str | None = None, concurrency: int = 8,
                 max_retries: int = 5, timeout_s: float = 120.0, max_new_tokens: int = 128,
                 temperature: float = 0.0, image_format: str = "png", jpeg_quality: int = 90,
                 system_prompt: str | None = None, label: str | None = None, backoff_s: float = 1.0,
                 batch_size: int | None = None):
        if not isinstance(name, str) or not name:
            raise ValueError(f"name: expected the served model's name, got {name!r}")
        if image_format not in IMAGE_FORMATS:
            raise ValueError(f"image_format: expected one of {IMAGE_FORMATS}, got {image_format!r}")
        if not isinstance(jpeg_quality, int) or not 1 <= jpeg_quality <= 100:
            raise ValueError(f"jpeg_quality: expected an integer in 1..100, got {jpeg_quality!r}")
        if not isinstance(max_new_tokens, int) or isinstance(max_new_tokens, bool) or max_new_tokens < 1:
            raise ValueError(f"max_new_tokens: expected an integer >= 1, got {max_new_tokens!r}")
        if not isinstance(temperature, (int, float)) or isinstance(temperature, bool) or not 0 <= temperature <= 2:
            raise ValueError(f"temperature: expected a number in 0..2, got {temperature!r}")
        if system_prompt is not None and not isinstance(system_prompt, str):
            raise ValueError(f"system_prompt: expected text or None, got {type(system_prompt).__name__}")
        self.client = ChatClient(base_url, api_key_env, concurrency, max_retries, timeout_s, backoff_s)
        self.model, self.name = name, label or name
        self.max_new_tokens, self.temperature = max_new_tokens, float(temperature)
        self.image_format, self.jpeg_quality, self.system_prompt = image_format, jpeg_quality, system_prompt
        self.batch_size = batch_size or 4 * concurrency

    def request_body(self, frame_urls: Sequence[str], question: str) -> dict:
        """The chat-completions body for one clip (as data URLs) and question."""
        content = image_parts(frame_urls) + [{"type": "text", "text": question}]
        messages = [{"role": "system", "content": self.system_prompt}] if self.system_prompt else []
        messages.append({"role": "user", "content": content})
        return {"model": self.model, "messages": messages, "max_tokens": self.max_new_tokens,
                "temperature": self.temperature}

    def request_bytes(self, parts_json: str, question: str) -> bytes:
        """`request_body` as JSON bytes, with the clip's image parts spliced in already serialised: the same JSON
        value, built without re-serialising the frames for every question."""
        marker = "\u0000IMAGES\u0000"  # a text no question contains: it holds the parts' place
        text = json.dumps(self.request_body([marker], question))
        placeholder = json.dumps(image_parts([marker]))[1:-1]
        head, found, tail = text.partition(placeholder)
        if not found:
            raise AssertionError("request_bytes: the image placeholder vanished from the body")
        return (head + parts_json[1:-1] + tail).encode("utf-8")

    def answer_stream(self, clips: Sequence[Frames], questions: Sequence[str]) -> Iterator[tuple[int, str]]:
        """(index, answer) as each reply arrives; the first failed request raises an EndpointError naming it."""
        check_batch(clips, questions)
        encoder = _ClipEncoder(clips, self.image_format, self.jpeg_quality)

        def ask(i: int) -> str:
            where = f"{self.model} request {i} (question {questions[i][:60]!r})"
            return self.client.complete(self.request_bytes(encoder.parts_json(i), questions[i]), where)

        yield from self.client.stream(len(questions), ask)

    def answer(self, clips: Sequence[Frames], questions: Sequence[str]) -> list[str]:
        """One answer per (clip, question), in order."""
        answers: list[str | None] = [None] * len(questions)
        for i, text in self.answer_stream(clips, questions):
            answers[i] = text
        return answers  # type: ignore[return-value]

    def identity(self) -> dict:
        """The endpoint, model and generation settings a resumed evaluation must share."""
        identity = {"backend": type(self).__name__, "name": self.model, "base_url": self.client.base_url,
                    "max_new_tokens": self.max_new_tokens, "temperature": self.temperature,
                    "image_format": self.image_format, "system_prompt": self.system_prompt}
        if self.image_format == "jpeg":
            identity["jpeg_quality"] = self.jpeg_quality
        return identity
