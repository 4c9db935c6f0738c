"""Judges: DriveLM's prompt, a parser that never crashes, the reply cache (through a real local server), and the
offline embedding judge."""

import json

import pytest

from lanevil_dev.fake_server import FakeServer
from lanevil_train.vlm.answer_scoring.judge import EmbeddingJudge, OpenAIJudge, judge_prompt, parse_score


@pytest.fixture
def judge_server():
    server = FakeServer("--mode", "judge", idle_exit_s=60)
    yield server
    server.kill()


@pytest.mark.parametrize("reply, score", [
    ("85", 85.0), ("  62\n", 62.0), ("78.5", 78.5), ("Score: 85/100", 85.0), ("8.5/10", 85.0), ("0", 0.0),
    ("100", 100.0), ("I would rate it 41.", 41.0), ("101", None), ("-3", None), ("junk", None), ("", None),
    (None, None), ("7/0", 7.0),
])
def test_parse_score(reply, score):
    assert parse_score(reply) == score


def test_prompt_is_drivelms_concatenation():
    assert judge_prompt("Two lanes.", "Three lanes.") == (
        "Rate my answer based on the correct answer out of 100, with higher scores indicating that the answer is "
        "closer to the correct answer, and you should be accurate to single digits like 62, 78, 41,etc. Output the "
        "number onlyThis is the correct answer: Two lanes.This is my answer: Three lanes.")
    body = OpenAIJudge("http://127.0.0.1:9/v1", "j").request_body("R", "A")
    assert body["messages"][0] == {"role": "system",
                                   "content": "an evaluator who rates my answer based on the correct answer"}
    assert body["temperature"] == 0.6


QUESTIONS = ["How many lanes?", "What is ahead?", "Is it a marking?", "What should the car do?", "How many lanes?"]
REFERENCES = ["There are two lanes.", "A truck.", "No, it is a shadow.", "Keep the lane.", "There are two lanes."]
ANSWERS = ["There are two lanes.", "A bus.", "JUNK reply", "SCOREFMT keep lane", "There are two lanes."]


def test_scores_junk_retried_then_unscored(judge_server, tmp_path):
    judge = OpenAIJudge(judge_server.url, "fake-judge", cache_path=tmp_path / "judge.jsonl", parse_attempts=3,
                        backoff_s=0.01)
    scores = judge.score(QUESTIONS, REFERENCES, ANSWERS)
    assert scores[0] == scores[4] == 100.0 and scores[2] is None and scores[3] == 85.0
    assert 0 <= scores[1] < 100 and scores[1] == int(scores[1])
    # 4 distinct items, the junk one asked 3 times: 6 requests
    assert judge.summary() == {"items": 5, "scored": 4, "unscored": 1, "cached": 1, "requests": 6}
    assert judge_server.stats()["chat_requests"] == 6
    lines = [json.loads(line) for line in (tmp_path / "judge.jsonl").read_text().splitlines()]
    assert len(lines) == 4 and {line["judge_model"] for line in lines} == {"fake-judge"}
    assert [line for line in lines if line["score"] is None][0]["reply"] == "I cannot rate that."


def test_cache_makes_a_rerun_free_and_is_per_judge_model(judge_server, tmp_path):
    cache = tmp_path / "judge.jsonl"
    first = OpenAIJudge(judge_server.url, "fake-judge", cache_path=cache, backoff_s=0.01)
    scores = first.score(QUESTIONS, REFERENCES, ANSWERS)
    before = judge_server.stats()["chat_requests"]
    again = OpenAIJudge(judge_server.url, "fake-judge", cache_path=cache, backoff_s=0.01)
    assert again.score(QUESTIONS, REFERENCES, ANSWERS) == scores
    assert judge_server.stats()["chat_requests"] == before and again.summary()["requests"] == 0
    other = OpenAIJudge(judge_server.url, "other-judge", cache_path=cache, parse_attempts=1, backoff_s=0.01)
    other.score(QUESTIONS[:2], REFERENCES[:2], ANSWERS[:2])
    assert judge_server.stats()["chat_requests"] == before + 2  # another model: new keys, new requests
    retry = OpenAIJudge(judge_server.url, "fake-judge", cache_path=cache, parse_attempts=2, rescore_unscored=True,
                        backoff_s=0.01)
    assert retry.score(QUESTIONS, REFERENCES, ANSWERS)[2] is None and retry.summary()["requests"] == 2


def test_judge_refuses_mismatched_inputs():
    judge = OpenAIJudge("http://127.0.0.1:9/v1", "j")
    with pytest.raises(ValueError, match="2 references for 1 questions"):
        judge.score(["q"], ["a", "b"], ["c"])
    with pytest.raises(ValueError, match="answer 0: expected a string, got NoneType"):
        judge.score(["q"], ["a"], [None])


@pytest.fixture(scope="module")
def embedding_judge():
    return EmbeddingJudge()


def test_embedding_judge_scores_similarity(embedding_judge):
    refs = ["The ego car should keep its lane.", "The ego car should keep its lane.", "There are three lanes."]
    answers = ["The ego car should keep its lane.", "A red traffic light is ahead.", "The road has three lanes."]
    scores = embedding_judge.score(["q"] * 3, refs, answers)
    assert scores[0] == pytest.approx(100.0, abs=0.01)
    assert scores[1] < 50 < scores[2] < 99
    assert embedding_judge.score(["q"] * 3, refs, answers) == scores  # deterministic
    assert embedding_judge.score_name == "MiniLM_score" != OpenAIJudge.score_name == "GPT_score"
    assert embedding_judge.summary() == {"items": 3, "scored": 3, "unscored": 0}


def test_embedding_judge_refuses_a_folder_without_a_model(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"model_dir: .* \(no modules.json\)"):
        EmbeddingJudge(model_dir=tmp_path).score(["q"], ["a"], ["b"])
