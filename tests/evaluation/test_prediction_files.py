"""task.predictions: the official TuSimple and CULane prediction files, scored by the official-format evaluations
exactly as the evaluation scored the images itself."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from lanevil_train.data.datasets import TuSimpleDataset
from lanevil_train.data.formats import write_culane, write_tusimple
from lanevil_train.evaluation.lane_records import lane_record, read_records
from lanevil_train.evaluation.prediction_files import (
    CULANE_DIR,
    CULANE_LIST,
    PREDICTIONS_DIR,
    TUSIMPLE_FILE,
    prediction_fields,
    write_prediction_files,
)
from lanevil_train.evaluation.streaming import stream_evaluate
from lanevil_train.metrics import evaluate_culane_dirs, evaluate_tusimple_files
from lanevil_train.metrics.culane_files import read_lines_file
from lanevil_train.results_log import ResultsLog
from lanevil_train.tasks.builders import build_model
from tests.tasks.cli_helpers import write_photo_dataset

NAMES = [f"clips/0530/{i}/20.jpg" for i in range(3)]
SPEC = {
    "model": {"name": "laneatt", "head": {"_target_": "lanevil_train.models.laneatt.LaneATTHead", "max_lanes": 6},
              "decode": {"conf_threshold": 0.0}},  # an untrained network: every kept anchor a lane
    "backbone": {"_target_": "lanevil_train.models.backbones.build_backbone", "name": "resnet18", "out_indices": [3]},
    "input_size": [64, 160],
}


def _untrained_model(spec=SPEC):
    """A random LaneATT whose anchors all reach 40 rows up (an untrained one predicts length 0: no lane)."""
    torch.manual_seed(0)
    model = build_model(spec)
    with torch.no_grad():
        model.head.reg_layer.bias[0] = 40.0
    return model


def _write_folder(tmp_path):
    root = tmp_path / "data"
    records = write_photo_dataset(root, NAMES)
    write_tusimple(records, root / "test.json")
    write_culane(records, root, root / "list" / "test.txt")
    return root, records


SPURIOUS = np.array([[5.0, 179.0], [5.0, 100.0]])  # a lane at the image's left edge, far from every true lane


def _records_file(tmp_path, shifts, spurious=()):
    """per_image.jsonl as an evaluation with predictions kept writes it, each image's predictions its ground
    truth shifted right by the given pixels per lane (a lane without a shift is not predicted), plus SPURIOUS on
    the images listed in `spurious`."""
    dataset = TuSimpleDataset(tmp_path / "data", ["test.json"])
    log = ResultsLog(tmp_path / "per_image.jsonl")
    log.resume()
    for index in range(len(dataset)):
        sample = dataset[index]
        pred = [lane + np.array([shift, 0.0]) for lane, shift in zip(sample["lanes"], shifts[index])]
        pred += [SPURIOUS] if index in spurious else []
        log.append([{"model": "m", "dataset": "d", **lane_record(pred, sample["lanes"], sample["meta"]),
                     **prediction_fields(pred, sample["meta"], 12.5)}])
    return log.path


def test_tusimple_lines_hold_x_at_every_h_sample_and_minus_2_beyond_the_lane(tmp_path):
    root, _ = _write_folder(tmp_path)
    results = _records_file(tmp_path, [[0.0, 3.0], [0.0], [0.0, 0.0, 0.0]], spurious={2})
    files = write_prediction_files(results, tmp_path)
    lines = [json.loads(line) for line in files["tusimple"].read_text().splitlines()]
    gt = [json.loads(line) for line in (root / "test.json").read_text().splitlines()]
    assert [line["raw_file"] for line in lines] == NAMES
    assert files["tusimple"].name == TUSIMPLE_FILE and TUSIMPLE_FILE.startswith("pred")
    first, truth = lines[0], gt[0]
    assert first["h_samples"] == truth["h_samples"] and first["run_time"] == 12.5
    assert len(first["lanes"]) == 2 and all(len(lane) == len(truth["h_samples"]) for lane in first["lanes"])
    for predicted, true, shift in zip(first["lanes"], truth["lanes"], [0.0, 3.0]):
        for x, x_true in zip(predicted, true):
            assert (x == -2) == (x_true == -2)  # the same rows, the others -2
            if x_true != -2:
                assert x == pytest.approx(x_true + shift, abs=0.01)


def test_the_files_score_as_the_evaluation_scored_its_images(tmp_path):
    root, _ = _write_folder(tmp_path)
    # image 0: two lanes right (3 px is inside TuSimple's 20 px), two missed; image 1: one right, three missed;
    # image 2: three right, two missed and a lane where there is none
    results = _records_file(tmp_path, [[0.0, 3.0], [0.0], [0.0, 0.0, 0.0]], spurious={2})
    records = read_records(results)
    write_prediction_files(results, tmp_path)

    scores = evaluate_tusimple_files(tmp_path / PREDICTIONS_DIR / TUSIMPLE_FILE, root / "test.json")
    n = len(records)
    assert scores["Accuracy"] == pytest.approx(sum(r["accuracy"] for r in records) / n)
    assert scores["FP"] == pytest.approx(sum(r["fp"] for r in records) / n)
    assert scores["FN"] == pytest.approx(sum(r["fn"] for r in records) / n)
    assert scores["FN_count"] == sum(r["fn_count"] for r in records) >= 2
    assert scores["FP_count"] == sum(r["fp_count"] for r in records) == 1
    assert scores["TP_count"] == sum(r["tp_count"] for r in records) == 6

    folder = tmp_path / PREDICTIONS_DIR / CULANE_DIR
    culane = evaluate_culane_dirs(str(folder), str(root), str(folder / CULANE_LIST),
                                  width=320, height=180, lane_width=6, workers=1)
    assert (culane["TP"], culane["FP"], culane["FN"]) == tuple(
        sum(r[k] for r in records) for k in ("culane_tp", "culane_fp", "culane_fn"))
    assert culane["FP"] == 1 and culane["TP"] >= 4
    shifted = read_lines_file(str(tmp_path / PREDICTIONS_DIR / CULANE_DIR / "clips/0530/0/20.lines.txt"))
    assert len(shifted) == 2


def test_streaming_keeps_the_lanes_and_run_time_and_the_files_agree(tmp_path):
    root, _ = _write_folder(tmp_path)
    path = stream_evaluate(_untrained_model(), TuSimpleDataset(root, ["test.json"]), tmp_path / "per_image.jsonl",
                           {"model": "m", "dataset": "tusimple"}, batch_size=2, progress="none", predictions=True)
    records = read_records(path)
    assert all(r["run_time"] > 0 and len(r["pred_points"]) == r["num_pred"] for r in records)
    assert sum(r["num_pred"] for r in records) > 0
    write_prediction_files(path, tmp_path)
    scores = evaluate_tusimple_files(tmp_path / PREDICTIONS_DIR / TUSIMPLE_FILE, root / "test.json")
    assert scores["FP"] == pytest.approx(sum(r["fp"] for r in records) / len(records))
    assert scores["Accuracy"] == pytest.approx(sum(r["accuracy"] for r in records) / len(records))


def test_records_scored_without_predictions_are_refused_naming_the_fix(tmp_path):
    root, _ = _write_folder(tmp_path)
    path = stream_evaluate(_untrained_model(), TuSimpleDataset(root, ["test.json"]), tmp_path / "per_image.jsonl",
                           {"model": "m", "dataset": "tusimple"}, progress="none")
    with pytest.raises(ValueError, match="3 of 3 images were scored without task.predictions=true"):
        write_prediction_files(path, tmp_path)


def test_a_killed_write_leaves_the_previous_tree_and_a_rerun_replaces_it(tmp_path):
    _write_folder(tmp_path)
    results = _records_file(tmp_path, [[0.0, 0.0], [0.0, 0.0], [0.0, 0.0, 0.0]])
    write_prediction_files(results, tmp_path)
    leftover = tmp_path / PREDICTIONS_DIR / f"{CULANE_DIR}.partial" / "stale.lines.txt"
    leftover.parent.mkdir()
    leftover.write_text("1 2 3 4\n")
    write_prediction_files(results, tmp_path)
    assert not leftover.parent.exists()
    written = (tmp_path / PREDICTIONS_DIR / CULANE_DIR).rglob("*.lines.txt")
    assert sorted(p.name for p in written) == ["20.lines.txt"] * 3


def test_task_evaluate_writes_the_files_beside_its_scores(tmp_path):
    """`python -m lanevil_train task=evaluate ... data=tusimple task.predictions=true`, run in this process."""
    from lanevil_train.tasks.builders import model_config
    from tests.tasks.cli_helpers import composed, run_in_process

    root, _ = _write_folder(tmp_path)
    data = ["data=tusimple", f"data.root={root}", "data.test.label_files=[test.json]", "data.input_size=[64,160]",
            "data.batch_size=2", "data.num_workers=0", "trainer.accelerator=cpu", "progress=none"]
    model = _untrained_model(model_config(composed(data)))
    ckpt = tmp_path / "tiny.ckpt"
    torch.save({"state_dict": model.state_dict(), "lanevil_model": model.build_config}, ckpt)
    run_dir = tmp_path / "run"
    run_in_process(["task=evaluate", f"ckpt_path={ckpt}", "task.predictions=true", "task.decode.conf_threshold=0.0",
                    *data], run_dir)
    scores = json.loads((run_dir / "test_scores.json").read_text())[0]
    official = evaluate_tusimple_files(run_dir / PREDICTIONS_DIR / TUSIMPLE_FILE, root / "test.json")
    assert scores["images"] == 3
    assert scores["Accuracy"] == pytest.approx(100 * official["Accuracy"], abs=1e-6)
    assert scores["FP"] == pytest.approx(100 * official["FP"], abs=1e-6)
    listed = (run_dir / PREDICTIONS_DIR / CULANE_DIR / CULANE_LIST).read_text().split()
    assert listed == ["/" + name for name in NAMES]
