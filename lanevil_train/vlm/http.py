"""A small client for OpenAI-compatible chat-completions endpoints, shared by the VLM backend, the judge and the
paraphraser.

It sends requests from a pool of threads (``concurrency`` in flight), retries what can succeed on a second try
(connection errors, timeouts, 429 and 5xx; exponential backoff with full jitter, or the server's Retry-After) and
never what cannot (other 4xx: an `EndpointError` with the server's own message), and yields replies as they arrive
so callers can append each one at once and resume an interrupted run. Only httpx and the standard library.
"""

from __future__ import annotations

import hashlib
import json
import os
import random
import threading
import time
from concurrent.futures import FIRST_COMPLETED, Future, ThreadPoolExecutor, wait
from email.utils import parsedate_to_datetime
from typing import Callable, Iterable, Iterator

import httpx

from lanevil_train.results_log import ResultsLog

RETRY_STATUSES = frozenset({408, 409, 429}) | frozenset(range(500, 600))
# Said with a 401 or 403 when no key was sent (api_key_env null).
NO_KEY_HINT = (" (no API key was sent: api_key_env is null; name the environment variable that holds the key, e.g. "
               "api_key_env=OPENAI_API_KEY)")


class EndpointError(RuntimeError):
    """A request that failed for good: a 4xx the server will answer the same way again, retries used up, or a reply
    without the expected fields. The message names the request and quotes the server."""


def _server_message(response: httpx.Response) -> str:
    """The server's own error message (OpenAI's {"error": {"message"}} or the body's start)."""
    try:
        body = response.json()
    except ValueError:
        return response.text[:500].strip() or "(empty body)"
    if isinstance(body, dict):
        error = body.get("error", body)
        if isinstance(error, dict) and error.get("message"):
            return str(error["message"])
        if isinstance(error, str):
            return error
    return str(body)[:500]


def api_key_problem(api_key_env) -> str | None:
    """Why `api_key_env` cannot give an API key (None: it can, or it is None and no key is wanted): not the name of
    an environment variable, or a variable that is not set or empty."""
    if api_key_env is None:
        return None
    if not isinstance(api_key_env, str) or not api_key_env:
        return f"expected the name of an environment variable holding the API key (or null), got {api_key_env!r}"
    if os.environ.get(api_key_env):
        return None
    state = "is empty" if api_key_env in os.environ else "is not set"
    return (f"the environment variable {api_key_env} {state}; export {api_key_env}=<the key>, or set api_key_env "
            f"to null for a server that takes no key")


def api_key(api_key_env: str | None) -> str | None:
    """The API key held by the environment variable `api_key_env`, or None when `api_key_env` is None (no key sent);
    a variable that is not set is a ValueError naming it, so a run that needs a key stops before its first request
    instead of getting the server's 401."""
    problem = api_key_problem(api_key_env)
    if problem is not None:
        raise ValueError(f"api_key_env: {problem}")
    return os.environ[api_key_env] if api_key_env is not None else None


def retry_after_seconds(response: httpx.Response) -> float | None:
    """The Retry-After header in seconds (a number or an HTTP date), None when absent or unreadable."""
    value = response.headers.get("retry-after")
    if value is None:
        return None
    try:
        return max(0.0, float(value))
    except ValueError:
        pass
    try:
        return max(0.0, parsedate_to_datetime(value).timestamp() - time.time())
    except (TypeError, ValueError):
        return None


def reply_text(body, where: str) -> str:
    """The first choice's message content of a chat-completions reply, stripped; an EndpointError naming `where`
    when the reply has no choices or no text content."""
    try:
        content = body["choices"][0]["message"]["content"]
    except (KeyError, IndexError, TypeError):
        raise EndpointError(f"{where}: the reply has no choices[0].message.content (got {str(body)[:300]})") from None
    if isinstance(content, list):  # some servers answer with content parts
        content = "".join(part.get("text", "") for part in content if isinstance(part, dict))
    if not isinstance(content, str):
        raise EndpointError(f"{where}: the reply's message content is {type(content).__name__}, expected text")
    return content.strip()


_STREAM = threading.local()  # per worker thread: the stop event of the stream it works for


def _bind_stream(stop: threading.Event) -> None:
    _STREAM.stop = stop


class ChatClient:
    """POSTs chat-completions bodies to `base_url` + /chat/completions with retries; thread-safe.

    base_url: e.g. http://host:8000/v1; api_key_env: the environment variable holding the API key (sent as a Bearer
    token; it must be set), or None for a server without auth; backoff_s: the first retry's mean wait, doubled each
    retry up to backoff_max_s; seed: the jitter's random seed.
    """

    def __init__(self, base_url: str, api_key_env: str | None = None, concurrency: int = 8,
                 max_retries: int = 5, timeout_s: float = 120.0, backoff_s: float = 1.0,
                 backoff_max_s: float = 60.0, seed: int = 0):
        if not isinstance(base_url, str) or not base_url.startswith(("http://", "https://")):
            raise ValueError(f"base_url: expected an http(s) URL such as http://localhost:8000/v1, got {base_url!r}")
        for name, value, low in (("concurrency", concurrency, 1), ("max_retries", max_retries, 0)):
            if not isinstance(value, int) or isinstance(value, bool) or value < low:
                raise ValueError(f"{name}: expected an integer >= {low}, got {value!r}")
        for name, value in (("timeout_s", timeout_s), ("backoff_s", backoff_s), ("backoff_max_s", backoff_max_s)):
            if not isinstance(value, (int, float)) or isinstance(value, bool) or not value >= 0:
                raise ValueError(f"{name}: expected a number >= 0, got {value!r}")
        self.base_url = base_url.rstrip("/")
        self.url = self.base_url + "/chat/completions"
        self.concurrency, self.max_retries = concurrency, max_retries
        self.backoff_s, self.backoff_max_s = float(backoff_s), float(backoff_max_s)
        headers = {"Content-Type": "application/json"}
        key = api_key(api_key_env)
        if key is not None:
            headers["Authorization"] = f"Bearer {key}"
        self.sends_key = key is not None
        self._http = httpx.Client(headers=headers, timeout=httpx.Timeout(float(timeout_s)),
                                  limits=httpx.Limits(max_connections=concurrency,
                                                      max_keepalive_connections=concurrency))
        self._random = random.Random(seed)
        self._random_lock = threading.Lock()
        self.retries = 0  # how many retries all requests took (for logs and tests)

    def close(self) -> None:
        """Close the pooled connections."""
        self._http.close()

    def _backoff(self, attempt: int) -> float:
        """Full-jitter exponential backoff: uniform in [0, min(max, base * 2**attempt)]."""
        with self._random_lock:
            return self._random.uniform(0.0, min(self.backoff_max_s, self.backoff_s * 2 ** attempt))

    def post(self, body: dict | bytes, where: str) -> dict:
        """One chat-completions request (a body, or its JSON already encoded) with retries; the decoded JSON reply,
        else an EndpointError naming `where`."""
        payload = body if isinstance(body, bytes) else json.dumps(body).encode("utf-8")
        last = ""
        for attempt in range(self.max_retries + 1):
            wait_s = None
            try:
                response = self._http.post(self.url, content=payload)
            except httpx.TransportError as error:  # connection refused/reset, timeouts, protocol errors
                last = f"{type(error).__name__}: {error}"
            else:
                if response.status_code < 300:
                    try:
                        return response.json()
                    except ValueError:
                        raise EndpointError(f"{where}: {self.url} answered {response.status_code} with a body that "
                                            f"is not JSON: {response.text[:300]!r}") from None
                message = _server_message(response)
                if response.status_code not in RETRY_STATUSES:
                    hint = NO_KEY_HINT if response.status_code in (401, 403) and not self.sends_key else ""
                    raise EndpointError(f"{where}: {self.url} refused the request with HTTP {response.status_code} "
                                        f"(not retried): {message}{hint}")
                last = f"HTTP {response.status_code}: {message}"
                wait_s = retry_after_seconds(response)
            if attempt == self.max_retries:
                break
            self.retries += 1
            stop = getattr(_STREAM, "stop", None)  # set when the stream this request belongs to was abandoned
            pause = min(wait_s, self.backoff_max_s) if wait_s is not None else self._backoff(attempt)
            if stop.wait(pause) if stop is not None else time.sleep(pause):
                raise EndpointError(f"{where}: cancelled (the run stopped) after: {last}")
        raise EndpointError(f"{where}: {self.url} failed {self.max_retries + 1} times; last: {last}")

    def complete(self, body: dict | bytes, where: str) -> str:
        """The reply text of one request (see `post` and `reply_text`)."""
        return reply_text(self.post(body, where), where)

    def stream(self, count: int, work: Callable[[int], object]) -> Iterator[tuple[int, object]]:
        """(i, work(i)) for i in range(count) as each finishes, `concurrency` at a time. The first error is raised
        after cancelling the work not yet started; closing the iterator early cancels it too."""
        stop = threading.Event()  # an abandoned or failed stream stops its requests' retries at once
        pool = ThreadPoolExecutor(max_workers=self.concurrency, thread_name_prefix="chat",
                                  initializer=_bind_stream, initargs=(stop,))
        pending: dict[Future, int] = {}
        upcoming: Iterable[int] = iter(range(count))
        try:
            for i in upcoming:
                pending[pool.submit(work, i)] = i
                if len(pending) >= 2 * self.concurrency:  # a bounded queue: work is encoded just before it is sent
                    break
            while pending:
                done, _ = wait(pending, return_when=FIRST_COMPLETED)
                for future in done:
                    i = pending.pop(future)
                    result = future.result()
                    nxt = next(upcoming, None)
                    if nxt is not None:
                        pending[pool.submit(work, nxt)] = nxt
                    yield i, result
        finally:
            stop.set()
            pool.shutdown(wait=False, cancel_futures=True)


def cache_key(*parts) -> str:
    """A stable hash of JSON-able parts (model, settings, texts): the key of a cached reply."""
    return hashlib.sha256(json.dumps(parts, ensure_ascii=False).encode("utf-8")).hexdigest()[:32]


class ReplyCache:
    """Finished replies by key, kept on disk as JSON lines (ResultsLog) when `path` is given, else in memory, so a
    rerun sends no request it already made. Appends come from one thread (the consumer of `ChatClient.stream`)."""

    def __init__(self, path=None):
        self.log = ResultsLog(path) if path is not None else None
        self.records: dict[str, dict] = {}
        if self.log is not None:
            if self.log.resume():
                self.records = {record["key"]: record for record in self.log.records()}

    def get(self, key: str) -> dict | None:
        """The cached record for `key`, or None."""
        return self.records.get(key)

    def add(self, record: dict) -> None:
        """Remember (and append to disk) a record with a "key"."""
        self.records[record["key"]] = record
        if self.log is not None:
            self.log.append([record])
