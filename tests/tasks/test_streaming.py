"""Streaming evaluation: one line per image, and a resumed run equals an uninterrupted one."""

from __future__ import annotations

import json

import pytest
import torch

from lanevil_train.data.suites import SyntheticIllusionSuite
from lanevil_train.evaluation.lane_records import read_records
from lanevil_train.evaluation.streaming import stream_evaluate
from lanevil_train.tasks.builders import build_model

SPEC = {
    "model": {"name": "laneatt", "head": {"_target_": "lanevil_train.models.laneatt.LaneATTHead", "max_lanes": 6},
              "decode": {"conf_threshold": 0.45}},
    "backbone": {"_target_": "lanevil_train.models.backbones.build_backbone", "name": "resnet18", "out_indices": [3]},
    "input_size": [64, 160],
    "crop_top": 0.3,
}


def _model():
    torch.manual_seed(0)
    return build_model(SPEC)


def _suite():
    return SyntheticIllusionSuite(2, 1000000, size=(90, 160), illusions=["vehicle", "rail_shadow"], severities=(1, 5))


def test_every_image_gets_one_line_with_its_case_and_severity(tmp_path):
    path = stream_evaluate(_model(), _suite(), tmp_path / "per_image.jsonl", {"model": "m", "dataset": "d"},
                           batch_size=3, progress="none")
    records = read_records(path)
    assert len(records) == 10
    assert sorted({r["severity"] for r in records}) == [0, 1, 5]
    assert {r["category"] for r in records if r["illusion"]} == {"traffic_obstruction", "shadow"}
    for r in records:
        assert r["model"] == "m" and r["dataset"] == "d" and 0.0 <= r["accuracy"] <= 1.0
        assert len(r["gt_lanes"]) == r["num_gt"] >= 2


def test_resume_after_an_interruption_gives_the_uninterrupted_results(tmp_path):
    model, suite = _model(), _suite()
    whole = read_records(stream_evaluate(model, suite, tmp_path / "a.jsonl", {"model": "m"}, batch_size=4,
                                         progress="none"))
    # an interrupted run: four finished lines and a torn fifth
    lines = (tmp_path / "a.jsonl").read_text().splitlines()
    (tmp_path / "b.jsonl").write_text("\n".join(lines[:4]) + "\n" + lines[4][:25])
    resumed = read_records(stream_evaluate(model, suite, tmp_path / "b.jsonl", {"model": "m"}, batch_size=4,
                                           progress="none"))
    assert len(resumed) == 10
    key = lambda r: r["key"]  # noqa: E731
    assert sorted(resumed, key=key) == sorted(whole, key=key)
    assert all(json.loads(line) for line in (tmp_path / "b.jsonl").read_text().splitlines())
    # nothing left to do: a third run adds nothing
    stream_evaluate(model, suite, tmp_path / "b.jsonl", {"model": "m"}, progress="none")
    assert len(read_records(tmp_path / "b.jsonl")) == 10


def test_resuming_another_models_results_is_refused(tmp_path):
    model, suite = _model(), _suite()
    path = tmp_path / "per_image.jsonl"
    stream_evaluate(model, suite, path, {"model": "m", "dataset": "d"}, progress="none")
    finished = path.read_bytes()
    torch.manual_seed(1)
    other = build_model(SPEC)  # the same network with other weights
    with pytest.raises(ValueError, match=rf"^{path} holds results of another evaluation \(other weights\); resuming "
                                         r"would report them as this one's: write to another folder \(task\.out_dir\)"):
        stream_evaluate(other, suite, path, {"model": "m", "dataset": "d"}, progress="none")
    model.decode_kwargs["conf_threshold"] = 0.9
    with pytest.raises(ValueError, match=r"decode was \{'conf_threshold': 0\.45.*now \{'conf_threshold': 0\.9"):
        stream_evaluate(model, suite, path, {"model": "m", "dataset": "d"}, progress="none")
    model.decode_kwargs["conf_threshold"] = 0.45
    with pytest.raises(ValueError, match=r"model was 'm', now 'untrained'"):
        stream_evaluate(model, suite, path, {"model": "untrained", "dataset": "d"}, progress="none")
    assert path.read_bytes() == finished  # nothing was appended
    stream_evaluate(model, suite, path, {"model": "m", "dataset": "d"}, progress="none")  # the same run resumes
    assert path.read_bytes() == finished
