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


def _die_on_third_case(monkeypatch):
    """Make the build raise KeyboardInterrupt when it reaches its third case (an interruption); returns the real
    render_case, to put back."""
    real = illusion_set.render_case
    calls = {"n": 0}

    def dies_on_third_case(args):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt
        return real(args)

    monkeypatch.setattr(illusion_set, "render_case", dies_on_third_case)
    return real


def test_resume_after_an_interruption_gives_the_uninterrupted_result(tmp_path, monkeypatch):
    cases = synthetic_cases(3, 2000, frames=1)
    build_illusion_set(cases, PLAN, tmp_path / "whole", progress="none")

    real = _die_on_third_case(monkeypatch)
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


def _photo_records(tmp_path, lanes_ok: bool) -> tuple[list[dict], str]:
    """TuSimple records of two 72x128 photos; the second's lanes lie inside the image only if `lanes_ok`."""
    from lanevil_train.sim import render_scene as render
    sample = render(7, sample_scene_params(7), width=128, height=72)
    lines = []
    for i in range(2):
        cv2.imwrite(str(tmp_path / f"{i}.png"), cv2.cvtColor(sample["image"], cv2.COLOR_RGB2BGR))
        ys = list(range(30, 72, 6))
        rows = [[int(round(float(np.interp(y, lane[::-1, 1], lane[::-1, 0])))) for y in ys]
                for lane in sample["lanes"] if len(lane) > 1]
        if i == 1 and not lanes_ok:
            rows = [[5000 + x for x in row] for row in rows]  # far right of the image
        lines.append(json.dumps({"lanes": rows, "h_samples": ys, "raw_file": f"{i}.png"}))
    labels = tmp_path / "labels_in.json"
    labels.write_text("".join(line + "\n" for line in lines))
    return read_tusimple(labels, tmp_path), str(labels)


def test_photo_cases_without_a_ground_plane_are_refused_before_anything_is_written(tmp_path):
    records, labels = _photo_records(tmp_path, lanes_ok=False)
    cases = illusion_set.dataset_cases(records)
    assert cases[1].source == f"{labels}:2" and cases[0].source == f"{labels}:1"
    with pytest.raises(illusion_set.GroundPlaneError) as error:
        build_illusion_set(cases, PLAN, tmp_path / "set", progress="none")
    message = str(error.value)
    assert message.startswith("1 of 2 photo cases have lanes that give no ground plane")
    assert "set task.fallback=true" in message and "Nothing was built" in message
    assert f"\n  {labels}:2 (image {tmp_path / '1.png'}): lanes[" in message and f"{labels}:1" not in message
    assert not (tmp_path / "set").exists()
    summary = build_illusion_set(cases, Plan(**{**PLAN.__dict__, "fallback": True}), tmp_path / "set",
                                 progress="none")
    assert summary["written"] == 10


def test_errors_while_rendering_a_photo_case_name_its_label_line_and_image(tmp_path, monkeypatch):
    records, labels = _photo_records(tmp_path, lanes_ok=False)
    monkeypatch.setattr(illusion_set, "_header_size", lambda path: None)  # no pre-check: fail while rendering
    with pytest.raises(illusion_set.GroundPlaneError,
                       match=rf"^{labels}:2 \(image {tmp_path / '1.png'}\): lanes\[0\]: .*lies in the image"):
        build_illusion_set(illusion_set.dataset_cases(records), PLAN, tmp_path / "set", progress="none")
    (tmp_path / "0.png").write_bytes(b"not a png")  # load_image's error gets the case's source too
    with pytest.raises(ValueError, match=rf"^{labels}:1 \(image {tmp_path / '0.png'}\): image .*0.png"):
        illusion_set.case_source(illusion_set.dataset_cases(records)[0], PLAN)


def test_a_partial_set_is_refused_until_a_rerun_finishes_it(tmp_path, monkeypatch):
    from lanevil_train.data.suites import IllusionSetDataset
    cases, root = synthetic_cases(3, 2000, frames=1), tmp_path / "set"
    real = _die_on_third_case(monkeypatch)
    with pytest.raises(KeyboardInterrupt):
        build_illusion_set(cases, PLAN, root, progress="none")
    monkeypatch.setattr(illusion_set, "render_case", real)
    assert json.loads((root / "build.json").read_text())["complete"] is False
    with pytest.raises(ValueError) as error:
        IllusionSetDataset(root)
    assert str(error.value) == (
        f"illusion set {root} is incomplete: 10 of 15 images were built (build.json is not marked complete: the "
        f"build was interrupted or is still running); rerun task=build with the same out_dir ({root}) to finish it")
    with pytest.raises(ValueError, match=r"build.json: out_dir .* holds a set built with other cases or another "
                                         r"plan \(15 images of 3 cases, .*now 10 images of 2 cases"):
        build_illusion_set(cases[:2], PLAN, root, progress="none")
    build_illusion_set(cases, PLAN, root, progress="none")
    record = json.loads((root / "build.json").read_text())
    assert record["complete"] is True and record["images"] == 15 and record["cases"] == 3
    assert record["plan"]["illusions"] == ["fence_shadow", "vehicle"]
    assert len(IllusionSetDataset(root)) == 15
    (root / "build.json").unlink()  # a set written before build.json existed is read as before
    assert len(IllusionSetDataset(root)) == 15
