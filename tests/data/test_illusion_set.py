"""Illusion test sets on disk: manifest round trip, contents, and resume after an interruption."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

import lanevil_train.data.illusion_set as illusion_set
from lanevil_train.data.formats import read_tusimple
from lanevil_train.data.formats.manifest import MANIFEST_KEYS, manifest_record, read_manifest
from lanevil_train.data.illusion_set import Plan, build_illusion_set, synthetic_cases
from lanevil_train.results_log import ResultsLog
from lanevil_train.sim import render_scene, sample_scene_params

PLAN = Plan(illusions=("fence_shadow", "vehicle"), severities=(1, 5), size=(90, 160))


def test_manifest_round_trip_and_errors(tmp_path):
    records = [{"image": f"images/a/{i}.png", "source_image": "images/a/0.png", "case_id": "a", "illusion": name,
                "category": cat, "severity": sev, "seed": i} for i, (name, cat, sev) in
               enumerate([(None, None, 0), ("vehicle", "traffic_obstruction", 3)])]
    ResultsLog(tmp_path / "m.jsonl", key_field="image").append(
        manifest_record({**record, "extra": "not written"}) for record in records)
    assert read_manifest(tmp_path / "m.jsonl") == records
    assert list(read_manifest(tmp_path / "m.jsonl")[1]) == list(MANIFEST_KEYS)
    with pytest.raises(ValueError, match=r"missing \['seed'\]"):
        manifest_record({k: v for k, v in records[0].items() if k != "seed"})
    (tmp_path / "bad.jsonl").write_text(json.dumps(records[0]) + "\n{oops\n")
    with pytest.raises(ValueError, match=r"bad.jsonl:2: malformed JSON"):
        read_manifest(tmp_path / "bad.jsonl")
    (tmp_path / "short.jsonl").write_text(json.dumps({"image": "x"}) + "\n")
    with pytest.raises(ValueError, match=r"short.jsonl:1: missing key"):
        read_manifest(tmp_path / "short.jsonl")


def test_build_writes_originals_variants_labels_and_manifest(tmp_path):
    summary = build_illusion_set(synthetic_cases(2, 1000, frames=1), PLAN, tmp_path, progress="none")
    assert summary == {"root": str(tmp_path), "images": 10, "written": 10, "skipped": 0}
    manifest = read_manifest(tmp_path / "manifest.jsonl")
    assert len(manifest) == 10 and all(set(r) == set(MANIFEST_KEYS) for r in manifest)
    originals = [r for r in manifest if r["severity"] == 0]
    assert [r["case_id"] for r in originals] == ["sim-0001000-f0", "sim-0001001-f0"]
    clean = render_scene(1000, sample_scene_params(1000), width=160, height=90)["image"]
    on_disk = cv2.cvtColor(cv2.imread(str(tmp_path / originals[0]["image"])), cv2.COLOR_BGR2RGB)
    assert np.array_equal(on_disk, clean)  # lossless: the pair differs only where the illusion acts
    labels = read_tusimple(tmp_path / "labels.json", tmp_path)
    assert sorted(str(r["raw_file"]) for r in labels) == sorted(r["image"] for r in manifest)
    variant = next(r for r in manifest if r["illusion"] == "vehicle" and r["severity"] == 5)
    assert variant["category"] == "traffic_obstruction" and variant["source_image"] == originals[0]["image"]


def test_resume_after_an_interruption_gives_the_uninterrupted_result(tmp_path, monkeypatch):
    cases = synthetic_cases(3, 2000, frames=1)
    build_illusion_set(cases, PLAN, tmp_path / "whole", progress="none")

    real = illusion_set.render_case
    calls = {"n": 0}

    def dies_on_third_case(args):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return real(args)

    monkeypatch.setattr(illusion_set, "render_case", dies_on_third_case)
    with pytest.raises(KeyboardInterrupt):
        build_illusion_set(cases, PLAN, tmp_path / "resumed", progress="none")
    assert len(read_manifest(tmp_path / "resumed" / "manifest.jsonl")) == 10
    monkeypatch.setattr(illusion_set, "render_case", real)
    summary = build_illusion_set(cases, PLAN, tmp_path / "resumed", progress="none")
    assert summary["skipped"] == 10 and summary["written"] == 5
    whole = read_manifest(tmp_path / "whole" / "manifest.jsonl")
    resumed = read_manifest(tmp_path / "resumed" / "manifest.jsonl")
    assert resumed == whole
    for record in whole:
        a = (tmp_path / "whole" / record["image"]).read_bytes()
        b = (tmp_path / "resumed" / record["image"]).read_bytes()
        assert a == b, record["image"]
    lines = lambda p: sorted((p / "labels.json").read_text().splitlines())  # noqa: E731
    assert lines(tmp_path / "resumed") == lines(tmp_path / "whole")
    assert not list((tmp_path / "resumed").rglob(".*"))  # no temporary left behind


def test_unknown_illusion_is_rejected_before_any_work(tmp_path):
    with pytest.raises(ValueError, match="unknown illusion 'smoke'"):
        build_illusion_set(synthetic_cases(1, 0), Plan(illusions=("smoke",)), tmp_path, progress="none")


def test_no_cases_is_refused_before_anything_is_written(tmp_path):
    with pytest.raises(ValueError, match=r"^build_illusion_set: no cases to build"):
        build_illusion_set([], PLAN, tmp_path / "set", progress="none")
    assert not (tmp_path / "set").exists()
