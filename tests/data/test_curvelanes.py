"""CurveLanes labels: the official layout read, every label checked before any work, refusals naming file and field."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from lanevil_train.data.datasets import CurveLanesDataset, EmptySplitError
from lanevil_train.data.formats.curvelanes import read_curvelanes, read_curvelanes_label

A, B = "00007f3230d35a893230c1b3ef8c52fd", "00022953ff37d3174cff99833df8799e"


def _points(*xy) -> list[dict]:
    """A lane as the official labels write it: {"x": "...", "y": "..."} strings."""
    return [{"x": str(x), "y": str(y)} for x, y in xy]


def _tree(root: Path, split: str, labels: dict[str, object], images: bool = True, listed=None) -> Path:
    """<root>/<split>/{<split>.txt, images/<name>.jpg, labels/<name>.lines.json}; returns the split folder."""
    folder = root / split
    (folder / "images").mkdir(parents=True, exist_ok=True)
    (folder / "labels").mkdir(exist_ok=True)
    names = list(labels) if listed is None else listed
    (folder / f"{split}.txt").write_text("".join(f"images/{name}.jpg\n" for name in names))
    for name, label in labels.items():
        text = label if isinstance(label, str) else json.dumps(label)
        (folder / "labels" / f"{name}.lines.json").write_text(text)
        if images:
            assert cv2.imwrite(str(folder / "images" / f"{name}.jpg"), np.zeros((66, 157, 3), np.uint8))
    return folder


LANE = _points((2079.41, 1439.0), (2078.19, 1438.08), (1500.5, 800))
OTHER = [{"x": 100, "y": 700.5}, {"x": 300, "y": 1200}]  # numbers too, the y order reversed


def test_the_official_layout_reads_every_lane(tmp_path):
    _tree(tmp_path, "valid", {A: {"Lines": [LANE, OTHER]}, B: {"Lines": []}})
    records = read_curvelanes(tmp_path, "valid")
    assert [r["rel_path"] for r in records] == [f"valid/images/{A}.jpg", f"valid/images/{B}.jpg"]
    assert records[0]["source"] == f"{tmp_path / 'valid' / 'valid.txt'}:1" and records[1]["lanes"] == []
    first, second = records[0]["lanes"]
    np.testing.assert_allclose(first, [[2079.41, 1439.0], [2078.19, 1438.08], [1500.5, 800.0]])
    np.testing.assert_allclose(second, [[300, 1200], [100, 700.5]])  # the package's order: y descending
    # the label's own order, which the metric command draws
    np.testing.assert_allclose(read_curvelanes_label(tmp_path / "valid" / "labels" / f"{A}.lines.json")[1],
                               [[100, 700.5], [300, 1200]])


def test_more_than_six_lanes_and_the_dataset(tmp_path):
    lanes = [_points((16 * i + 5, 60), (16 * i + 9, 20)) for i in range(9)]  # on the 157x66 image
    _tree(tmp_path, "train", {A: {"Lines": lanes}})
    dataset = CurveLanesDataset(tmp_path, "train")
    sample = dataset[0]
    assert len(sample["lanes"]) == 9 and sample["meta"]["culane_metric"] == "curvelanes"
    assert dataset.item_key(0) == f"train/images/{A}.jpg"
    assert [size for _, size in dataset.labelled_lanes()] == [(66, 157)]


def test_the_test_split_has_images_only(tmp_path):
    folder = tmp_path / "test" / "images"
    folder.mkdir(parents=True)
    assert cv2.imwrite(str(folder / f"{A}.jpg"), np.zeros((8, 8, 3), np.uint8))
    (tmp_path / "test" / "test.txt").write_text(f"images/{A}.jpg\n")
    (record,) = read_curvelanes(tmp_path, "test")
    assert record["labeled"] is False and record["lanes"] == [] and record["label_path"] is None


@pytest.mark.parametrize("label, field", [
    ({"Lines": [_points((1, 2))]}, f"{A}.lines.json: Lines[0]: 1 point(s); a CurveLanes lane has at least 2"),
    ({"Lines": [[{"x": "12,5", "y": "3"}, {"x": 1, "y": 2}]]}, "Lines[0][0].x: expected a number or a string of one"),
    ({"Lines": [[{"x": 1, "y": 2}, {"x": 1, "y": "nan"}]]}, "Lines[0][1].y: expected a finite number"),
    ({"Lines": [[{"x": True, "y": 2}, {"x": 1, "y": 2}]]}, "Lines[0][0].x: expected a number"),
    ({"Lines": [[{"x": 1}, {"x": 1, "y": 2}]]}, "Lines[0][0]: expected an object {\"x\": ..., \"y\": ...}"),
    ({"Lines": [LANE, "x"]}, "Lines[1]: expected a list of points"),
    ({"Lines": {"a": 1}}, "Lines: expected a list of lanes, got dict"),
    ({"lanes": []}, "expected a JSON object with key 'Lines' (a CurveLanes label), got keys ['lanes']"),
    ('{"Lines": [', "malformed JSON"),
])
def test_a_bad_label_is_refused_naming_file_and_field(tmp_path, label, field):
    # the bad label is the second listed: the first is read, then the run stops before any work
    _tree(tmp_path, "valid", {B: {"Lines": [LANE]}, A: label})
    with pytest.raises(ValueError) as err:
        read_curvelanes(tmp_path, "valid")
    assert str(tmp_path / "valid" / "labels" / f"{A}.lines.json") in str(err.value) and field in str(err.value)


def test_missing_files_and_list_problems_are_named(tmp_path):
    folder = _tree(tmp_path, "valid", {A: {"Lines": [LANE]}}, images=False)
    with pytest.raises(FileNotFoundError, match=rf"valid\.txt:1: image .*{A}\.jpg not found"):
        read_curvelanes(tmp_path, "valid")
    (folder / "images" / f"{A}.jpg").write_bytes(b"not an image")
    with pytest.raises(ValueError, match=rf"{A}\.jpg is not an image"):
        read_curvelanes(tmp_path, "valid")
    assert cv2.imwrite(str(folder / "images" / f"{A}.jpg"), np.zeros((8, 8, 3), np.uint8))
    (folder / "valid.txt").write_text(f"images/{A}.jpg\nimages/{B}.jpg\n")
    with pytest.raises(FileNotFoundError, match=rf"valid\.txt:2: CurveLanes label .*{B}\.lines\.json not found"):
        read_curvelanes(tmp_path, "valid")
    (folder / "valid.txt").write_text(f"images/{A}.jpg\n\n/images/{A}.jpg\n")
    with pytest.raises(ValueError, match=rf"valid\.txt:3: images/{A}\.jpg is listed twice \(first at line 1\)"):
        read_curvelanes(tmp_path, "valid")
    (folder / "valid.txt").write_text("../train/images/x.jpg\n")
    with pytest.raises(ValueError, match="is not a path inside the split folder"):
        read_curvelanes(tmp_path, "valid")
    with pytest.raises(FileNotFoundError, match=r"list file .*train\.txt not found"):
        read_curvelanes(tmp_path, "train")
    with pytest.raises(ValueError, match="split 'val': expected one of train, valid, test"):
        read_curvelanes(tmp_path, "val")


def test_a_label_whose_image_is_not_listed(tmp_path):
    folder = _tree(tmp_path, "valid", {A: {"Lines": [LANE]}, B: {"Lines": []}}, listed=[A])
    with pytest.raises(ValueError, match=rf"{B}\.lines\.json: its image is not in the list .*valid\.txt"):
        read_curvelanes(tmp_path, "valid")
    (folder / "subset.txt").write_text(f"images/{A}.jpg\n")  # a list of one's own may name a subset
    assert len(read_curvelanes(tmp_path, "valid", list_file="valid/subset.txt")) == 1
    (folder / "subset.txt").write_text("")
    with pytest.raises(EmptySplitError, match="lists no images"):
        CurveLanesDataset(tmp_path, "valid", list_file="valid/subset.txt")


def test_an_illusion_set_built_from_curvelanes_photos_is_scored_as_curvelanes(tmp_path):
    from lanevil_train.data.illusion_set import Plan, build_illusion_set, dataset_cases
    from lanevil_train.data.suites import IllusionSetDataset
    from tests.tasks.cli_helpers import write_photo_dataset

    (record,) = write_photo_dataset(tmp_path / "valid", [f"images/{A}.jpg"])  # a simulated road photo, 320x180
    lines = [[{"x": str(x), "y": str(y)} for x, y in lane] for lane in record["lanes"]]
    _tree(tmp_path, "valid", {A: {"Lines": lines}}, images=False)
    dataset = CurveLanesDataset(tmp_path, "valid")
    plan = Plan(illusions=("rail_shadow",), severities=(1,), label_format="culane", culane_metric="curvelanes")
    # the illusion is placed through the ground plane recovered from the photo's lanes (context_from_lanes)
    build_illusion_set(dataset_cases(dataset.records), plan, tmp_path / "set", progress="none")
    suite = IllusionSetDataset(tmp_path / "set")
    assert len(suite) == 2 and [suite[i]["meta"]["culane_metric"] for i in range(2)] == ["curvelanes"] * 2
    assert len(suite[1]["lanes"]) == len(record["lanes"])


@pytest.mark.parametrize("model", ["laneatt", "clrnet"])
def test_data_curvelanes_sets_sixteen_lanes_for_training_and_decoding(model):
    from tests.tasks.cli_helpers import composed

    cfg = composed(["data=curvelanes", "data.root=/data/curvelanes", f"model={model}"])
    assert cfg.data.max_lanes == 16 and cfg.model.head.max_lanes == 16 and cfg.model.decode.nms_topk == 16
    assert composed([f"model={model}"]).model.decode.nms_topk == (5 if model == "laneatt" else 6)  # unchanged
