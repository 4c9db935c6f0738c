"""The OpenAI-compatible backend against a real local HTTP server process (lanevil_dev/fake_server.py), not a mock."""

import hashlib
import json

import numpy as np
import pytest

from lanevil_dev.fake_server import FakeServer
from lanevil_train.results_log import ResultsLog
from lanevil_train.vlm.answer_scoring.judge import OpenAIJudge
from lanevil_train.vlm.backends.openai import OpenAIVLM
from lanevil_train.vlm.http import EndpointError, reply_text


@pytest.fixture
def start_server():
    """Starts fake servers with the given options; every one is killed at the end of the test."""
    servers = []

    def start(*options):
        servers.append(FakeServer(*options, idle_exit_s=60))
        return servers[-1]

    yield start
    for server in servers:
        server.kill()


def make_clip(seed: int, height: int = 24, width: int = 40) -> list[np.ndarray]:
    """6 distinct random frames."""
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, (height, width, 3), dtype=np.uint8) for _ in range(6)]


def expected_answer(question: str, clip: list[np.ndarray]) -> str:
    """What the fake server answers when it received `clip` whole (lossless) with `question`."""
    digest = hashlib.md5("".join(hashlib.md5(f.tobytes()).hexdigest()[:8] for f in clip).encode()).hexdigest()[:8]
    height, width = clip[0].shape[:2]
    return f"answer: {question} [images=6 size={width}x{height} digest={digest}]"


def test_six_png_frames_arrive_whole_and_in_order(start_server):
    server = start_server()
    clips = [make_clip(1), make_clip(2)]
    questions = ["How many lanes are there?", "Is the dark line a lane marking?"]
    vlm = OpenAIVLM(server.url, "fake-vlm", concurrency=2)
    assert vlm.answer(clips, questions) == [expected_answer(q, c) for q, c in zip(questions, clips)]
    # frames in another order are another digest: the order of the image_url parts is checked too
    assert vlm.answer([clips[0][::-1]], questions[:1]) != [expected_answer(questions[0], clips[0])]
    assert server.stats()["chat_requests"] == 3


def test_jpeg_frames_arrive_at_their_size(start_server):
    server = start_server()
    vlm = OpenAIVLM(server.url, "fake-vlm", image_format="jpeg", jpeg_quality=80)
    [reply] = vlm.answer([make_clip(3, 36, 64)], ["What is ahead?"])
    assert reply.startswith("answer: What is ahead? [images=6 size=64x36 digest=")


def test_request_layout_is_vllms():
    vlm = OpenAIVLM("http://127.0.0.1:9/v1", "m", system_prompt="You drive.", max_new_tokens=7)
    body = vlm.request_body(["data:image/png;base64,AA=="] * 6, "Why?")
    assert [m["role"] for m in body["messages"]] == ["system", "user"]
    parts = body["messages"][1]["content"]
    assert [p["type"] for p in parts] == ["image_url"] * 6 + ["text"]
    assert parts[-1]["text"] == "Why?" and body["max_tokens"] == 7 and body["temperature"] == 0.0
    # the bytes actually sent splice pre-serialised image parts into the same JSON value
    urls = ["data:image/png;base64,AA==", "data:image/png;base64,BB=="]
    parts_json = json.dumps([{"type": "image_url", "image_url": {"url": url}} for url in urls])
    question = 'Is the "line" a marking? \\ \u00e9 \u0000IMAGES'
    assert json.loads(vlm.request_bytes(parts_json, question)) == vlm.request_body(urls, question)


def test_500s_and_429s_are_retried(start_server):
    # requests 1-2 get 429 (Retry-After 0.05 s), then every 4th gets a 500: 6 answers take requests 1..10
    server = start_server("--rate-limit-first", "2", "--fail-every", "4", "--retry-after", "0.05")
    clips = [make_clip(i) for i in range(6)]
    questions = [f"Question {i}?" for i in range(6)]
    vlm = OpenAIVLM(server.url, "fake-vlm", concurrency=2, backoff_s=0.01)
    assert vlm.answer(clips, questions) == [expected_answer(q, c) for q, c in zip(questions, clips)]
    assert server.stats() == {"chat_requests": 10, "statuses": {"429": 2, "500": 2, "200": 6}}
    assert vlm.client.retries == 4


def test_a_400_is_not_retried_and_names_the_request(start_server):
    server = start_server()
    vlm = OpenAIVLM(server.url, "fake-vlm", concurrency=1, backoff_s=0.01)
    with pytest.raises(EndpointError, match=r"request 0 .*BAD_REQUEST.*HTTP 400 \(not retried\): the question asked"):
        vlm.answer([make_clip(0)], ["BAD_REQUEST please"])
    assert server.stats()["chat_requests"] == 1


def test_too_many_images_is_the_servers_message(start_server):
    server = start_server("--max-images", "4")
    with pytest.raises(EndpointError, match="At most 4 image"):
        OpenAIVLM(server.url, "fake-vlm").answer([make_clip(0)], ["Why?"])


def test_retries_run_out_with_the_last_error(start_server):
    server = start_server("--fail-first", "100")
    vlm = OpenAIVLM(server.url, "fake-vlm", max_retries=2, backoff_s=0.01)
    with pytest.raises(EndpointError, match="failed 3 times; last: HTTP 500: injected failure of request 3"):
        vlm.answer([make_clip(0)], ["Why?"])
    assert server.stats()["chat_requests"] == 3


def test_api_key_from_the_named_variable(start_server, monkeypatch):
    server = start_server("--require-key", "sekrit")
    monkeypatch.setenv("LANEVIL_TEST_KEY", "sekrit")
    clip = make_clip(0)
    assert OpenAIVLM(server.url, "fake-vlm", api_key_env="LANEVIL_TEST_KEY").answer([clip], ["Q?"]) == \
        [expected_answer("Q?", clip)]
    with pytest.raises(EndpointError, match=r"HTTP 401 .*missing or wrong API key \(no API key was sent: "
                                            r"api_key_env is null; name the environment variable"):
        OpenAIVLM(server.url, "fake-vlm").answer([clip], ["Q?"])  # no key named: the server refuses, and why is said
    asked = server.stats()["chat_requests"]
    monkeypatch.delenv("LANEVIL_TEST_KEY")  # a key named but not set: said before any request, not as the 401
    with pytest.raises(ValueError, match=r"^api_key_env: the environment variable LANEVIL_TEST_KEY is not set; "
                                         r"export LANEVIL_TEST_KEY=<the key>, or set api_key_env to null"):
        OpenAIVLM(server.url, "fake-vlm", api_key_env="LANEVIL_TEST_KEY")
    monkeypatch.setenv("LANEVIL_TEST_KEY", "")
    with pytest.raises(ValueError, match=r"^api_key_env: the environment variable LANEVIL_TEST_KEY is empty"):
        OpenAIJudge(server.url, "fake-judge", api_key_env="LANEVIL_TEST_KEY")
    assert server.stats()["chat_requests"] == asked


def run_logged(vlm, clips, questions, log: ResultsLog, stop_after: int | None = None) -> int:
    """Answer the questions the log lacks, appending each answer as it arrives; stop after `stop_after`."""
    done = log.resume()
    todo = [i for i in range(len(questions)) if str(i) not in done]
    stream = vlm.answer_stream([clips[i] for i in todo], [questions[i] for i in todo])
    for count, (j, text) in enumerate(stream, 1):
        log.append([{"key": str(todo[j]), "answer": text}])
        if count == stop_after:
            stream.close()
            break
    return len(todo)


def test_stream_resumes_after_the_consumer_stops(start_server, tmp_path):
    server = start_server("--delay-ms", "10")
    clips = [make_clip(i % 3) for i in range(10)]
    questions = [f"Question {i}?" for i in range(10)]
    log = ResultsLog(tmp_path / "answers.jsonl")
    vlm = OpenAIVLM(server.url, "fake-vlm", concurrency=2)
    assert run_logged(vlm, clips, questions, log, stop_after=3) == 10
    assert len(log.records()) == 3
    assert run_logged(vlm, clips, questions, log) == 7  # the rerun asks only for the missing ones
    answers = {int(r["key"]): r["answer"] for r in log.records()}
    assert answers == {i: expected_answer(questions[i], clips[i]) for i in range(10)}
    assert server.stats()["chat_requests"] <= 10 + 2 * 2  # at most the stopped run's queue was wasted


def test_stream_resumes_after_the_server_dies(start_server, tmp_path):
    clips = [make_clip(i) for i in range(8)]
    questions = [f"Question {i}?" for i in range(8)]
    log = ResultsLog(tmp_path / "answers.jsonl")
    first = start_server("--delay-ms", "30")
    vlm = OpenAIVLM(first.url, "fake-vlm", concurrency=2, max_retries=1, backoff_s=0.01)
    log.resume()
    with pytest.raises(EndpointError, match="ConnectError"):
        for count, (i, text) in enumerate(vlm.answer_stream(clips, questions), 1):
            log.append([{"key": str(i), "answer": text}])
            if count == 3:
                first.kill()
    finished = len(log.records())
    assert 3 <= finished < 8
    second = start_server()
    assert run_logged(OpenAIVLM(second.url, "fake-vlm"), clips, questions, log) == 8 - finished
    answers = {int(r["key"]): r["answer"] for r in log.records()}
    assert answers == {i: expected_answer(questions[i], clips[i]) for i in range(8)}


def test_reply_without_content_names_the_request():
    with pytest.raises(EndpointError, match="request 7: the reply has no choices"):
        reply_text({"choices": []}, "request 7")
    with pytest.raises(EndpointError, match="request 8: the reply's message content is NoneType"):
        reply_text({"choices": [{"message": {"content": None}}]}, "request 8")
    assert reply_text({"choices": [{"message": {"content": [{"type": "text", "text": " a "}]}}]}, "r") == "a"


def test_identity_loss_and_bad_arguments():
    vlm = OpenAIVLM("http://127.0.0.1:9/v1/", "served", label="Shown", image_format="jpeg", temperature=0.2)
    assert vlm.name == "Shown"
    assert vlm.identity() == {"backend": "OpenAIVLM", "name": "served", "base_url": "http://127.0.0.1:9/v1",
                              "max_new_tokens": 128, "temperature": 0.2, "image_format": "jpeg",
                              "system_prompt": None, "jpeg_quality": 90}
    with pytest.raises(NotImplementedError, match="no token probabilities"):
        vlm.answer_loss([make_clip(0)], ["q"], ["a"])
    with pytest.raises(ValueError, match="image_format"):
        OpenAIVLM("http://x/v1", "m", image_format="gif")
    with pytest.raises(ValueError, match="base_url"):
        OpenAIVLM("localhost:8000", "m")
    with pytest.raises(ValueError, match="concurrency"):
        OpenAIVLM("http://x/v1", "m", concurrency=0)
    with pytest.raises(ValueError, match="clip 0: frame 0 must be a uint8"):
        vlm.answer([[np.zeros((4, 4, 3), np.float32)] * 6], ["q"])


def test_a_failed_stream_stops_the_retries_of_its_other_requests(start_server):
    import threading
    import time

    # every 2nd request gets a 500 (retried after a long backoff), the others a 400 (an error at once)
    server = start_server("--fail-every", "2")
    vlm = OpenAIVLM(server.url, "fake-vlm", concurrency=4, max_retries=5, backoff_s=20.0)
    with pytest.raises(EndpointError, match="HTTP 400"):
        list(vlm.answer_stream([make_clip(i) for i in range(4)], [f"BAD_REQUEST {i}" for i in range(4)]))
    start = time.monotonic()
    while any(t.name.startswith("chat") for t in threading.enumerate()) and time.monotonic() - start < 10:
        time.sleep(0.05)
    assert time.monotonic() - start < 3.0  # not the 20 s backoff: the waiting retries were cancelled
