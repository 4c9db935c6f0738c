"""The VLM evaluation loop: every QA on every clip variant answered once, scored, resumable after an interruption,
and reported in the paper's layout from per_answer.jsonl."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lanevil_train.evaluation.results import write_results
from lanevil_train.metrics.vqa import language_scores
from lanevil_train.report.robustness import main_table
from lanevil_train.report.specs import VQA_SPEC, record_set
from lanevil_train.results_log import ResultsLog
from lanevil_train.vlm.answer_scoring.evaluation import ANSWERS, PER_ANSWER, evaluate_clips, pair_key
from lanevil_train.vlm.base import VLM, BlindVLM
from lanevil_train.vlm.clips.clip_set import SyntheticClipSuite
from lanevil_train.vlm.clips.qa_records import answer_is_correct, prompt_text

LABEL = {"model": "brightness", "dataset": "tiny-clips"}


class BrightnessVLM(VLM):
    """Answers from what it sees: "Yes." when the clip's last frame is brighter than a threshold, else "No." plus
    the brightness, so an illusion that darkens or lightens the road changes some answers."""

    name = "brightness"
    batch_size = 3

    def __init__(self, stop_after: int | None = None):
        self.calls = 0
        self.stop_after = stop_after

    def answer(self, clips, questions):
        out = []
        for frames, question in zip(clips, questions):
            if self.stop_after is not None and self.calls >= self.stop_after:
                raise KeyboardInterrupt("interrupted on purpose")
            self.calls += 1
            level = float(np.mean(frames[-1]))
            out.append(f"Yes. The road is bright ({level:.2f})." if level > 110 else f"No. It is dark ({level:.2f}).")
        return out


@pytest.fixture(scope="module")
def suite():
    return SyntheticClipSuite(2, 1000000, ["rail_shadow", "vehicle"], (2, 4), (64, 112))


def _answers_expected(suite) -> int:
    return sum(len(suite.qa_for(suite.clip_meta(i)["base_clip_id"])) for i in range(len(suite)))


def test_every_qa_of_every_clip_variant_is_answered_once_and_scored(suite, tmp_path):
    vlm = BrightnessVLM()
    path = evaluate_clips(vlm, suite, tmp_path, LABEL, progress="none")
    records = ResultsLog(path).records()
    assert len(records) == _answers_expected(suite) == vlm.calls == 2 * 3 * 3 * 5  # cases x segments x variants x QA
    assert len({r["key"] for r in records}) == len(records)
    for record in records:
        qa = next(q for q in suite.qa_for(record["case_id"]) if q["qa_id"] == record["qa_id"])
        assert record["reference"] == qa["answer"] and record["question"] == qa["question"]
        correct = answer_is_correct(qa, record["answer"])
        assert record["correct"] == (None if correct is None else int(correct))
        assert record["answer_tokens"] == record["answer_tokens"].lower()
        assert record["case_illusion"] in ("rail_shadow", "vehicle")
    clean = [r for r in records if r["severity"] == 0]
    assert {r["illusion"] for r in clean} == {None} and len(clean) == 2 * 3 * 5
    # the same question on a base clip's clean and perturbed variants is one item: Original pairs them
    rs = record_set(records)
    assert rs.spec is VQA_SPEC
    assert [s.name for s in rs.scores] == ["Language", "Accuracy"]  # no judge: no judge score


def test_scores_are_the_language_metrics_and_accuracy_of_the_answers(suite, tmp_path):
    records = ResultsLog(evaluate_clips(BrightnessVLM(), suite, tmp_path, LABEL, progress="none")).records()
    row = main_table(records)[0]
    vehicle = [r for r in records if r["illusion"] == "vehicle"]
    by_severity = {sev: [r for r in vehicle if r["severity"] == sev] for sev in (2, 4)}
    expected = np.mean([100 * language_scores({r["key"]: r["answer_tokens"] for r in part},
                                              {r["key"]: r["reference_tokens"] for r in part},
                                              meteor=False, tokenized=True)["Language"]
                        for part in by_severity.values()])  # equal-sized corpora, each question once
    assert row["traffic_obstruction/Language/Perturbed"] == pytest.approx(expected, rel=1e-9)
    scored = [r for r in vehicle if r["correct"] is not None]
    assert scored and row["traffic_obstruction/Accuracy/Perturbed"] == pytest.approx(
        100 * np.mean([r["correct"] for r in scored]))


def test_two_models_answering_the_same_questions_get_their_own_language_scores(suite, tmp_path):
    """A model and another answering the very same questions (as a model and its blind baseline do) in one table:
    each row's Language is that of its own answers (the corpus memo once returned the first model's for both)."""
    class Constant(BrightnessVLM):
        name = "constant"

        def answer(self, clips, questions):
            return ["The road has three lanes and the markings are white." for _ in questions]

    bright = ResultsLog(evaluate_clips(BrightnessVLM(), suite, tmp_path / "a", LABEL, progress="none")).records()
    constant = ResultsLog(evaluate_clips(Constant(), suite, tmp_path / "b", {**LABEL, "model": "constant"},
                                         progress="none")).records()
    rows = {row["model"]: row for row in main_table(bright + constant)}
    alone = {"brightness": main_table(bright)[0], "constant": main_table(constant)[0]}
    for model in ("brightness", "constant"):
        assert rows[model]["average/Language/Original"] == pytest.approx(alone[model]["average/Language/Original"])
    assert rows["brightness"]["average/Language/Original"] != pytest.approx(
        rows["constant"]["average/Language/Original"])


def test_an_unchanged_answer_has_no_language_gap(suite, tmp_path):
    class Constant(BrightnessVLM):
        def answer(self, clips, questions):
            return ["The road has three lanes and the markings are white." for _ in questions]

    records = ResultsLog(evaluate_clips(Constant(), suite, tmp_path, LABEL, progress="none")).records()
    row = main_table(records)[0]
    for category in ("shadow", "traffic_obstruction", "average"):
        assert row[f"{category}/Language/Original"] > 0
        assert row[f"{category}/Language/Gap"] == pytest.approx(0.0, abs=1e-9)


def test_an_interrupted_evaluation_resumes_to_the_same_tables_without_asking_again(suite, tmp_path):
    whole = tmp_path / "whole"
    write_results([evaluate_clips(BrightnessVLM(), suite, whole, LABEL, progress="none")], whole)
    cut = tmp_path / "cut"
    with pytest.raises(KeyboardInterrupt):
        evaluate_clips(BrightnessVLM(stop_after=50), suite, cut, LABEL, progress="none", pairs_per_chunk=20)
    answered = ResultsLog(cut / ANSWERS).records()
    scored = ResultsLog(cut / PER_ANSWER).records()
    # a batch answered in full is logged at once; the batch the interruption hit is lost; the last chunk unscored
    assert 50 - BrightnessVLM.batch_size < len(answered) <= 50 and len(scored) < len(answered)
    with open(cut / ANSWERS, "a") as handle:
        handle.write('{"key": "torn')  # a kill in the middle of a write
    again = BrightnessVLM()
    write_results([evaluate_clips(again, suite, cut, LABEL, progress="none", pairs_per_chunk=20)], cut)
    assert again.calls == _answers_expected(suite) - len(answered)  # no question asked twice
    for table in ("main.json", "per_qa_category.json", "per_severity.json", "test_scores.json"):
        assert json.loads((cut / table).read_text()) == json.loads((whole / table).read_text())
    keys = [r["key"] for r in ResultsLog(cut / PER_ANSWER).records()]
    assert len(keys) == len(set(keys)) == _answers_expected(suite)


def test_answers_stream_into_the_log_as_they_arrive(suite, tmp_path):
    seen = []

    class Streaming(BrightnessVLM):
        def answer_stream(self, clips, questions):
            for i in reversed(range(len(questions))):  # out of order, like concurrent requests
                seen.append(len(ResultsLog(tmp_path / ANSWERS).records()) if (tmp_path / ANSWERS).exists() else 0)
                yield i, f"answer {questions[i][:10]}"

    evaluate_clips(Streaming(), suite, tmp_path, LABEL, progress="none")
    assert seen[:4] == [0, 1, 2, 0 + 3]  # each answer is on disk before the next is asked for
    records = {r["key"]: r for r in ResultsLog(tmp_path / PER_ANSWER).records()}
    meta = suite.clip_meta(0)
    qa = suite.qa_for(meta["base_clip_id"])[2]
    assert records[pair_key(meta["clip_id"], qa["qa_id"])]["answer"] == f"answer {qa['question'][:10]}"


def test_the_blind_baseline_asks_the_same_model_on_grey_frames(suite):
    seen = []

    class Recording(BrightnessVLM):
        def answer(self, clips, questions):
            seen.extend(clips)
            return super().answer(clips, questions)

    blind = BlindVLM(Recording())
    clip = suite[1]["frames"]
    [answer] = blind.answer([clip], ["Is the road bright?"])
    assert answer == "Yes. The road is bright (128.00)."  # the wrapped model saw a uniform grey clip
    assert len(seen[0]) == 6 and all(f.shape == clip[0].shape and (f == 128).all() for f in seen[0])
    assert blind.name == "brightness-blind" and blind.identity()["blind"] is True


def test_a_choice_question_is_asked_with_its_options(suite, tmp_path):
    asked = []

    class Recording(BrightnessVLM):
        def answer(self, clips, questions):
            asked.extend(questions)
            return super().answer(clips, questions)

    evaluate_clips(Recording(), suite, tmp_path, LABEL, progress="none")
    qas = [qa for i in range(len(suite)) for qa in suite.qa_for(suite.clip_meta(i)["base_clip_id"])]
    choice = next(qa for qa in qas if qa["type"] == "choice")
    text = prompt_text(choice)
    assert text in asked and text.startswith(choice["question"])
    assert all(option in text for option in choice["choices"])
    yes_no = next(qa for qa in qas if qa["type"] == "yes_no")
    assert yes_no["question"] in asked  # other questions are asked as they are
