"""The paraphrasing pass: valid rewrites replace the question, invalid ones keep it; replies are cached."""

import pytest

from lanevil_dev.fake_server import FakeServer
from lanevil_train.vlm.clips.paraphrase import OpenAIParaphraser, clean_reply, is_yes_no, option_letters, rejection


@pytest.fixture
def paraphrase_server():
    server = FakeServer("--mode", "paraphrase", idle_exit_s=60)
    yield server
    server.kill()


def test_validation_rules():
    assert is_yes_no("Is the dark line a lane marking?") and not is_yes_no("What is ahead?")
    assert option_letters("Which lane? A. left B) middle (C) right") == ["A", "B", "C"]
    assert clean_reply('Paraphrase: "Which lane is ours?"') == "Which lane is ours?"
    original = "Is the dark straight line in the left lane a lane marking?"
    assert rejection(original, "Is that dark line on the left a lane marking?", 2.0) is None
    assert rejection(original, "", 2.0) == "empty"
    assert rejection(original, "What is the dark line on the left?", 2.0) == "changed yes/no-ness"
    assert rejection(original, "Is the dark line a marking", 2.0) == "not a question"
    assert rejection(original, "Is it " + "very " * 40 + "dark?", 2.0) == "too long"
    assert rejection("Which way? A. left B. right", "Which direction? A. left", 2.0) == "lost the option letters"
    assert rejection("No, it is a shadow.", "It is a shadow, not a marking.", 2.0) == "changed the yes/no answer"
    assert rejection("No, it is a shadow.", "No: that line is a shadow.", 2.0) is None


def test_paraphrases_through_the_endpoint_and_keeps_what_fails(paraphrase_server, tmp_path):
    questions = ["Is the dark line a lane marking?", "What is the weather like?",
                 "Which lane is the ego car in? A. left B. middle C. right",
                 "Which way is the road curving? A. left B. right DROPOPTIONS", "EMPTY what is this?",
                 "What is the weather like?", "No, it is a shadow.", "No, FLIPYESNO it is a crack.",
                 "The ego car keeps its lane."]
    cache = tmp_path / "paraphrases.jsonl"
    paraphrase = OpenAIParaphraser(paraphrase_server.url, "fake-writer", cache_path=cache, backoff_s=0.01)
    out = paraphrase(questions)
    assert out == ["Is it true that the dark line a lane marking?", "Please tell me: What is the weather like?",
                   "Please tell me: Which lane is the ego car in? A. left B. middle C. right",
                   questions[3], questions[4], "Please tell me: What is the weather like?",
                   "No, indeed it is a shadow.", questions[7], "In other words: The ego car keeps its lane."]
    assert paraphrase.last_summary == {"paraphrased": 6, "kept": 3, "requests": 8, "lost the option letters": 1,
                                       "empty": 1, "changed the yes/no answer": 1}
    assert paraphrase_server.stats()["chat_requests"] == 8
    again = OpenAIParaphraser(paraphrase_server.url, "fake-writer", cache_path=cache)
    assert again(questions) == out and paraphrase_server.stats()["chat_requests"] == 8


def test_refuses_bad_arguments():
    with pytest.raises(ValueError, match="text 1: expected a string"):
        OpenAIParaphraser("http://127.0.0.1:9/v1", "m")(["ok?", 3])
    with pytest.raises(ValueError, match="max_ratio"):
        OpenAIParaphraser("http://127.0.0.1:9/v1", "m", max_ratio=0.5)
