"""DriveLM-nuScenes QA JSON: our suite round-trips exactly; a DriveLM-style file reads as clips + QA."""

from __future__ import annotations

import json

import numpy as np
import pytest

from lanevil_train.vlm.clips import clip_set
from lanevil_train.vlm.clips.clip_set import ClipSetDataset, build_clip_set
from lanevil_train.vlm.clips.drivelm import read_drivelm, to_drivelm, write_drivelm
from tests.vlm import fake_clips


def built_suite(tmp_path, monkeypatch):
    monkeypatch.setattr(clip_set, "_geometry", lambda: fake_clips)
    build_clip_set(fake_clips.clip_cases(2, 700, ["wire_shadow", "bicycle"]), [1, 5], tmp_path, size=(16, 24),
                   progress="none")
    load = lambda name: [json.loads(line) for line in (tmp_path / name).read_text().splitlines()]  # noqa: E731
    return load("clips.jsonl"), load("qa.jsonl")


def test_round_trip_is_exact_and_the_layout_is_drivelms(tmp_path, monkeypatch):
    clips, qas = built_suite(tmp_path, monkeypatch)
    write_drivelm(tmp_path / "drivelm.json", clips, qas)
    assert read_drivelm(tmp_path / "drivelm.json") == (clips, qas)
    data = json.loads((tmp_path / "drivelm.json").read_text())
    assert list(data) == ["case-0000700", "case-0000701"]
    frame = data["case-0000700"]["key_frames"]["case-0000700-over"]
    assert set(frame["QA"]) == {"perception", "prediction", "planning", "behavior"}
    assert frame["image_paths"]["FRAME_5"] == "clips/case-0000700/over/clean/5.png"
    items = [item for section in frame["QA"].values() for item in section]
    assert len(items) == 5 and all({"Q", "A", "C", "con_up", "con_down", "cluster", "layer"} <= set(i) for i in items)
    for item in frame["QA"]["planning"]:
        assert item["lanevil"]["category"] == "action"
    for item in items:
        if item["lanevil"]["type"] == "choice":
            assert "Please select the correct answer" in item["Q"] and item["lanevil"]["choices"][-1] in item["Q"]
    # the dataset built from the JSON is the dataset on disk
    on_disk, from_json = ClipSetDataset(tmp_path), ClipSetDataset.from_drivelm(tmp_path / "drivelm.json")
    assert len(from_json) == len(on_disk) == 18
    for i in (0, 7):
        assert from_json.clip_meta(i) == on_disk.clip_meta(i)
        a, b = from_json[i], on_disk[i]
        assert a["qa"] == b["qa"] and all(np.array_equal(x, y) for x, y in zip(a["frames"], b["frames"]))


def drivelm_style(image_paths) -> dict:
    return {"scene-a": {"scene_description": "A city street.", "key_frames": {"tok1": {
        "key_object_infos": {},
        "QA": {"perception": [{"Q": "What are the important objects in the current scene? ", "A": "A car ahead.",
                               "C": None, "con_up": None, "con_down": None, "cluster": None, "layer": None},
                              {"Q": "Is there a pedestrian? Please select the correct answer from the following "
                                    "options: A. Yes. B. No.", "A": "B"}],
               "prediction": [{"Q": "Is the car ahead moving?", "A": "No, it is parked."}],
               "planning": [], "behavior": []},
        "image_paths": image_paths}}}}


def test_a_drivelm_file_reads_as_one_clean_clip_per_key_frame(tmp_path):
    cameras = {"CAM_BACK": "b.jpg", "CAM_FRONT": "f.jpg", "CAM_FRONT_LEFT": "fl.jpg", "CAM_FRONT_RIGHT": "fr.jpg",
               "CAM_BACK_LEFT": "bl.jpg", "CAM_BACK_RIGHT": "br.jpg"}
    (tmp_path / "d.json").write_text(json.dumps(drivelm_style(cameras)))
    clips, qas = read_drivelm(tmp_path / "d.json")
    assert clips == [{"clip_id": "tok1", "base_clip_id": "tok1", "case_id": "scene-a", "segment": "key_frame",
                      "illusion": None, "category": None, "severity": 0, "seed": 0,
                      "frames": ["fl.jpg", "f.jpg", "fr.jpg", "br.jpg", "b.jpg", "bl.jpg"]}]
    assert [(q["qa_id"], q["category"], q["type"]) for q in qas] == [
        ("tok1-perception-0", "object_recognition", "open"), ("tok1-perception-1", "object_recognition", "choice"),
        ("tok1-prediction-0", "object_behavior", "yes_no")]
    assert qas[1]["question"] == "Is there a pedestrian?" and qas[1]["choices"] == ["A. Yes.", "B. No."]
    assert qas[1]["answer"] == "B. No."
    (tmp_path / "one.json").write_text(json.dumps(drivelm_style({"CAM_FRONT": "f.jpg"})))
    assert read_drivelm(tmp_path / "one.json")[0][0]["frames"] == ["f.jpg"] * 6  # one view, repeated


@pytest.mark.parametrize("breakage, message", [
    (lambda d: d["scene-a"].pop("key_frames"), "scene scene-a: missing 'key_frames'"),
    (lambda d: d["scene-a"]["key_frames"]["tok1"].pop("image_paths"),
     "scene scene-a frame tok1: missing 'image_paths'"),
    (lambda d: d["scene-a"]["key_frames"]["tok1"]["QA"]["perception"][0].pop("A"),
     r"scene scene-a frame tok1: QA.perception\[0\]: A: expected a non-empty string"),
    (lambda d: d["scene-a"]["key_frames"]["tok1"]["QA"].update(weather=[]), "QA.weather: unknown section"),
])
def test_missing_fields_are_named_with_scene_and_frame(tmp_path, breakage, message):
    data = drivelm_style({"CAM_FRONT": "f.jpg"})
    breakage(data)
    (tmp_path / "d.json").write_text(json.dumps(data))
    with pytest.raises(ValueError, match=message):
        read_drivelm(tmp_path / "d.json")


def test_qa_of_an_unknown_clip_is_refused():
    clip = {"clip_id": "c-clean", "base_clip_id": "c", "case_id": "k", "segment": "over", "illusion": None,
            "category": None, "severity": 0, "seed": 1, "frames": ["x.png"] * 6}
    qa = {"qa_id": "d-q0", "base_clip_id": "d", "category": "action", "type": "open", "question": "Q?", "answer": "A."}
    with pytest.raises(ValueError, match="QA d-q0: base_clip_id 'd' is not a clip of this suite"):
        to_drivelm([clip], [qa])
