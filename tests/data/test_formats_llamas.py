"""LLAMAS labels: the official per-row lanes from markers, the four lanes' order, the split layout and its errors."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from lanevil_train.data.datasets import EmptySplitError, LLAMASDataset
from lanevil_train.data.formats.llamas import image_path_for, llamas_rows, read_llamas, read_llamas_label
from lanevil_train.metrics.llamas import llamas_image_counts

REC = "images-2014-12-22-12-35-10_mapping_280N_ramps"
NAME = "1419280632_0483124000"


def _marker(sx, sy, ex, ey, z=10.0):
    """A marker as the label files write it (numbers; world coordinates in metres, z forward)."""
    return {"lane_marker_id": "m", "pixel_start": {"x": sx, "y": sy}, "pixel_end": {"x": ex, "y": ey},
            "world_start": {"x": 1.0, "y": 0.0, "z": z}, "world_end": {"x": 1.0, "y": 0.0, "z": z + 2.0}}


def _label(lanes):
    return {"image_name": NAME, "projection_matrix": [[1, 0, 0], [0, 1, 0], [0, 0, 1]],
            "lanes": [{"lane_id": lane_id, "markers": markers} for lane_id, markers in lanes]}


def _tree(root: Path, split: str, labels: dict[str, dict], image: bool = True) -> list[Path]:
    paths = []
    for name, label in labels.items():
        path = root / "labels" / split / REC / f"{name}.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(label))
        if image:
            img = image_path_for(path, root)
            img.parent.mkdir(parents=True, exist_ok=True)
            assert cv2.imwrite(str(img), np.zeros((717, 1276, 3), np.uint8))
        paths.append(path)
    return paths


# A lane of two markers: a near one from (600, 700) up to (620, 600) at z = 5, a far dash from (640, 500) to
# (650, 450) at z = 20. The near one is extended to the bottom row: x0 = 600 + (716 - 700) * (20 / -100) = 596.8,
# the new marker (597, 716) -> (600, 700).
R0 = [_marker(600, 700, 620, 600, z=5.0), _marker(640, 500, 650, 450, z=20.0)]


def test_rows_follow_the_official_procedure_by_hand():
    rows = llamas_rows(_label([("r0", R0)]))
    xs = rows["r0"]
    assert set(rows) == {"r0"} and xs.shape == (717,)
    # row 716: the extension's start 597 (twice: its start and i = 0 of its 16 rows)
    assert xs[716] == 597.0
    # row 708: the extension only, i = 8 of 16: round(597 + 8 * 3 / 16) = round(598.5) = 598 (half to even)
    assert xs[708] == 598.0
    # row 700: the extension's end round(597 + 3) = 600 and the near marker's start 600 twice
    assert xs[700] == 600.0
    # row 650: the near marker, i = 50 of 100: round(600 + 50 * 20 / 100) = 610
    assert xs[650] == 610.0
    # rows 599..501 lie between the markers: filled linearly from x[600] = 620 to x[500] = 640
    assert xs[550] == pytest.approx(630.0, abs=1e-9)
    # the far marker: row 475, i = 25 of 50: round(640 + 25 * 10 / 50) = 645; nothing above its end row 450
    assert xs[475] == 645.0 and xs[450] == 650.0 and xs[449] == -1.0 and xs[0] == -1.0


def test_four_lanes_in_the_official_order_and_renaming():
    left = [_marker(300, 700, 350, 600, z=5.0), _marker(400, 500, 420, 460, z=20.0)]
    far_left = [_marker(100, 700, 200, 600, z=5.0), _marker(300, 500, 330, 460, z=20.0)]
    # ids l3 and l1 become l1 and l0 (each side renumbered in sorted order); r2 alone becomes r0; a lane
    # spanning under 20 rows (r5) and a lane of one marker (r7) are dropped before the renaming
    label = _label([("r2", R0), ("l3", far_left), ("l1", left),
                    ("r5", [_marker(900, 700, 910, 690), _marker(905, 695, 915, 685)]),
                    ("r7", [_marker(1000, 700, 1100, 500)])])
    lanes_rows = llamas_rows(label)
    assert sorted(lanes_rows) == ["l0", "l1", "r0"]
    np.testing.assert_array_equal(lanes_rows["r0"], llamas_rows(_label([("r0", R0)]))["r0"])


def test_read_a_split_tree(tmp_path):
    left = [_marker(300, 700, 350, 600, z=5.0), _marker(400, 500, 420, 460, z=20.0)]
    _tree(tmp_path, "valid", {NAME: _label([("r0", R0), ("l0", left)]), "0002": _label([])})
    records = read_llamas(tmp_path, "valid")
    assert [r["rel_path"] for r in records] == [f"color_images/valid/{REC}/0002_color_rect.png",
                                                f"color_images/valid/{REC}/{NAME}_color_rect.png"]
    empty, rec = records
    assert empty["lanes"] == [] and empty["labeled"]
    assert rec["lane_ids"] == ["l0", "r0"]  # the order l1, l0, r0, r1
    lane = rec["lanes"][1]
    assert lane[0].tolist() == [597.0, 716.0] and lane[-1].tolist() == [650.0, 450.0]  # y descending
    assert len(lane) == 716 - 450 + 1
    dataset = LLAMASDataset(tmp_path, "valid")
    sample = dataset[1]
    assert sample["image"].shape == (717, 1276, 3) and sample["meta"]["culane_metric"] == "llamas"
    assert dataset.item_key(1) == rec["rel_path"]


def test_test_split_lists_images_without_labels(tmp_path):
    img = tmp_path / "color_images/test" / REC / f"{NAME}_color_rect.png"
    img.parent.mkdir(parents=True)
    assert cv2.imwrite(str(img), np.zeros((8, 8, 3), np.uint8))
    (rec,) = read_llamas(tmp_path, "test")
    assert rec["image_path"] == img and rec["lanes"] == [] and rec["labeled"] is False


@pytest.mark.parametrize(
    "label, message",
    [
        ([1, 2], r"expected a JSON object with key 'lanes'"),
        ({"lanes": {}}, r"lanes: expected a list of lanes, got dict"),
        ({"lanes": [{"lane_id": "x0", "markers": []}]},
         r"lanes\[0\].lane_id: expected a name starting with 'l' or 'r'"),
        ({"lanes": [{"lane_id": "l0", "markers": [{"pixel_start": {"x": 1}}]}]},
         r"lanes\[0\].markers\[0\].pixel_start: expected an object"),
        ({"lanes": [{"lane_id": "l0", "markers": [_marker("a", 2, 3, 4)]}]},
         r"lanes\[0\].markers\[0\].pixel_start.x: expected a number, got \"a\""),
        ({"lanes": [{"lane_id": "l0", "markers": [{**_marker(1, 2, 3, 4), "world_start": {}}]}]},
         r"lanes\[0\].markers\[0\].world_start: expected an object with 'z'"),
        ({"lanes": [{"lane_id": "l0", "markers": [_marker(5, 700, 5, 600), _marker(5, 500, 5, 400)]}]},
         r"lanes\[0\] \(lane_id 'l0'\): no marker whose pixel start and end differ in both x and y"),
    ],
)
def test_label_errors_name_the_file_and_key(tmp_path, label, message):
    (path,) = _tree(tmp_path, "valid", {NAME: label})
    with pytest.raises(ValueError, match=f"{NAME}.json: {message}"):
        read_llamas(tmp_path, "valid")


def test_malformed_json_missing_image_and_bad_split(tmp_path):
    (path,) = _tree(tmp_path, "valid", {NAME: _label([("r0", R0)])}, image=False)
    with pytest.raises(FileNotFoundError, match=rf"{NAME}.json: image .*{NAME}_color_rect.png not found"):
        read_llamas(tmp_path, "valid")
    path.write_text('{"lanes": [\n  {"lane_id": }\n]}')
    with pytest.raises(ValueError, match=rf"{NAME}.json:2: malformed JSON"):
        read_llamas_label(path)
    with pytest.raises(ValueError, match=r"LLAMAS split 'val': expected one of train, valid, test"):
        read_llamas(tmp_path, "val")
    with pytest.raises(FileNotFoundError, match=r"labels/train not found"):
        read_llamas(tmp_path, "train")
    (tmp_path / "labels/train").mkdir()
    with pytest.raises(EmptySplitError, match="holds no labels"):
        LLAMASDataset(tmp_path, "train")


def test_metric_official_setting():
    gt = [np.stack([np.full(417, 600.0), np.arange(716, 299, -1.0)], 1)]
    # a prediction 10 px off over the same rows overlaps well (30 px lanes), one 40 px off does not
    near = [np.stack([np.full(40, 610.0), np.linspace(716, 300, 40)], 1)]
    far = [np.stack([np.full(40, 640.0), np.linspace(716, 300, 40)], 1)]
    assert llamas_image_counts(near, gt) == (1, 0, 0)
    assert llamas_image_counts(far, gt) == (0, 1, 1)
    # the ground truth is scored from row 300 down: a lane above it is no lane; 1-point predictions are not counted
    high = [np.stack([np.full(200, 600.0), np.arange(299, 99, -1.0)], 1)]
    assert llamas_image_counts(near + [np.array([[5.0, 5.0]])], high) == (0, 1, 0)
    assert llamas_image_counts([], gt) == (0, 0, 1)


def test_official_experiments_compose():
    from tests.tasks.cli_helpers import composed

    cfg = composed(["experiment=official_laneatt_llamas", "data.root=/unused"])
    assert cfg.data.name == "llamas" and list(cfg.data.input_size) == [360, 640] and cfg.data.crop_top == 0.0
    assert cfg.data.test.split == "valid" and cfg.model.decode.conf_threshold == 0.5
    cfg = composed(["experiment=official_clrnet_llamas", "data.root=/unused", "backbone=dla34"])
    assert cfg.data.name == "llamas" and list(cfg.data.input_size) == [320, 800]
    assert int(round(cfg.data.crop_top * 717)) == 300
    assert (cfg.model.decode.conf_threshold, cfg.model.decode.nms_threshold, cfg.model.decode.nms_topk) == (0.45, 60, 4)
