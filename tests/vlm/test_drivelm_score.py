"""DriveLM's challenge score (vlm/answer_scoring/drivelm_score.py) on constructed parts: the match F1 of points, the
final score's weights, a missing match counted 0, and the tags a DriveLM file carries read and written."""

from __future__ import annotations

import json

import pytest

from lanevil_train.report.specs import language_part
from lanevil_train.vlm.answer_scoring.drivelm_score import drivelm_parts, final_score, match_f1
from lanevil_train.vlm.answer_scoring.evaluation import answer_records
from lanevil_train.vlm.clips.drivelm import read_drivelm, to_drivelm


def test_match_f1_pairs_points_greedily_within_an_l1_distance_of_16():
    # (1, 2) is 1.0 from (1.5, 2.5): a hit; (30.5, 40.5) is far from what is left: a false positive; one miss
    assert match_f1("<c1,CAM_FRONT,1.0,2.0> and <c2,CAM_FRONT,30.5,40.5>", "1.5, 2.5 then 100.0, 100.0") == \
        pytest.approx(0.5, abs=1e-6)
    # a second answer point near the same reference point finds it taken: a false positive (P 1/2, R 1)
    assert match_f1("(10.0, 10.0) (11.0, 11.0)", "(10.5, 10.5)") == pytest.approx(2 * 0.5 * 1 / 1.5, abs=1e-6)
    assert match_f1("(10.0, 10.0) (50.0, 50.0)", "(50.0, 50.0) (10.0, 10.0)") == pytest.approx(1.0, abs=1e-6)
    # L1, not Euclidean: 8 + 8.5 = 16.5 misses although the Euclidean distance is 11.7
    assert match_f1("(8.0, 8.5)", "(0.0, 0.0)") == pytest.approx(0.0, abs=1e-6)
    assert match_f1("(1.0, 1.0) 7.5", "(1.0, 1.0)") == pytest.approx(1.0, abs=1e-6)  # an odd last number is dropped
    assert match_f1("no numbers", "(1.0, 1.0)") == pytest.approx(0.0, abs=1e-6)
    assert match_f1("3 4", "") == pytest.approx(0.0, abs=1e-6)  # integers are not DriveLM's \d+\.\d+ numbers
    with pytest.raises(ValueError, match="odd count"):
        match_f1("(1.0, 1.0)", "(1.0, 1.0) 2.0")


def test_final_score_weighs_gpt_language_match_and_accuracy_as_drivelm():
    assert final_score(50.0, 40.0, None, 80.0) == pytest.approx(0.4 * 50 + 0.2 * 40 + 0.2 * 80)  # match counted 0
    assert final_score(50.0, 40.0, 30.0, 80.0) == pytest.approx(0.4 * 50 + 0.2 * 40 + 0.2 * 30 + 0.2 * 80)
    assert final_score(100.0, 100.0, 100.0, 100.0) == pytest.approx(100.0)


def _record(i, kind, answer, reference, gpt=None, correct=None, tags=()):
    tokens = lambda text: " ".join(text.lower().replace(".", " ").split())  # noqa: E731  (PTB-like tokens)
    record = {"key": f"k{i}", "severity": 0, "case_illusion": "rail_shadow", "answer_tokens": tokens(answer),
              "reference_tokens": [tokens(reference)], "qa_type": kind, "answer": answer, "reference": reference,
              "gpt_score": gpt, "correct": correct}
    if 3 in tags:
        record["match_f1"] = 100.0 * match_f1(answer, reference)
    return record


def test_drivelm_parts_of_constructed_answers():
    records = [_record(0, "choice", "A", "A. Two lanes.", correct=1),
               _record(1, "yes_no", "No.", "Yes. It is wet.", correct=0),
               _record(2, "open", "the road has two lanes", "the road has three lanes", gpt=60.0),
               _record(3, "open", "the car at 10.0, 20.0", "the car at 12.0, 21.0", gpt=90.0, tags=(3,))]
    parts = drivelm_parts(records)
    language = language_part("Language")(records)
    assert parts["GPT"] == pytest.approx(75.0) and parts["Accuracy"] == pytest.approx(50.0)
    assert parts["Language"] == pytest.approx(language)
    assert parts["Match"] == pytest.approx((100.0 + 90.0) / 2)  # F1 100 of the one coordinate question, its GPT 90
    assert parts["final"] == pytest.approx(0.4 * 75 + 0.2 * language + 0.2 * 95 + 0.2 * 50)
    no_match = drivelm_parts(records[:3])
    assert no_match["Match"] is None
    assert no_match["final"] == pytest.approx(0.4 * 60 + 0.2 * language_part("Language")(records[:3]) + 0.2 * 50)
    assert drivelm_parts([{**r, "gpt_score": None} for r in records]) is None  # no LLM judge: no DriveLM score


def test_a_drivelm_files_tags_are_read_and_its_coordinate_answers_get_their_match(tmp_path):
    data = {"scene": {"key_frames": {"frame": {
        "image_paths": {"CAM_FRONT": "a.jpg"},
        "QA": {"perception": [{"Q": "Where is the car <c1,CAM_FRONT,10.5,20.5>?", "A": "At 11.0, 21.0.", "tag": [3]},
                              {"Q": "Is it raining?", "A": "No.", "tag": [0]}],
               "prediction": [], "planning": [{"Q": "What should the ego vehicle do?", "A": "Keep its lane."}],
               "behavior": []}}}}}
    path = tmp_path / "drivelm.json"
    path.write_text(json.dumps(data))
    clips, qas = read_drivelm(path)
    assert [qa.get("drivelm_tag") for qa in qas] == [[3], [0], None]
    meta = {"clip_id": clips[0]["clip_id"], "base_clip_id": clips[0]["base_clip_id"], "severity": 0}
    records = answer_records([(meta, qa) for qa in qas], ["It is at 10.0, 20.0.", "No.", "Keep its lane."],
                             {"model": "m", "dataset": "d"}, tokenize=lambda texts: [t.lower() for t in texts])
    assert records[0]["match_f1"] == pytest.approx(100.0, abs=1e-4) and "match_f1" not in records[1]
    exported = to_drivelm(clips, qas)["scene"]["key_frames"]["frame"]["QA"]
    assert [item["tag"] for section in ("perception", "planning") for item in exported[section]] == [[3], [0], [1, 2]]
    (tmp_path / "bad.json").write_text(json.dumps({"scene": {"key_frames": {"frame": {
        "image_paths": {"CAM_FRONT": "a.jpg"}, "QA": {"perception": [{"Q": "Q?", "A": "A.", "tag": ["x"]}]}}}}}))
    with pytest.raises(ValueError, match=r"tag: expected a list of DriveLM score tags"):
        read_drivelm(tmp_path / "bad.json")
