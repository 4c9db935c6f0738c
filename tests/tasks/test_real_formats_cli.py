"""`data=tusimple` and `data=culane` with a root path: a tiny dataset on disk, trained and scored by the CLI."""

from __future__ import annotations

import json

import pytest

from lanevil_train.data.formats import write_culane, write_tusimple
from lanevil_train.evaluation.lane_records import read_records
from tests.tasks.cli_helpers import run_cli, run_in_process, write_photo_dataset

COMMON = ["data.input_size=[64,160]", "data.batch_size=2", "data.num_workers=0", "trainer.accelerator=cpu",
          "progress=none", "trainer.fast_dev_run=true"]


def test_train_on_a_tusimple_folder(tmp_path):
    root = tmp_path / "tusimple"
    records = write_photo_dataset(root, [f"clips/0530/{i}/20.jpg" for i in range(4)])
    write_tusimple(records[:2], root / "train.json")
    write_tusimple(records[2:], root / "test.json")
    run_dir = tmp_path / "run"
    run_cli(["data=tusimple", f"data.root={root}", "data.train.label_files=[train.json]",
             "data.val.label_files=[train.json]", "data.test.label_files=[test.json]", *COMMON], run_dir)
    row = json.loads((run_dir / "test_scores.json").read_text())[0]
    assert row["dataset"] == "tusimple" and row["images"] == 2
    cases = [r["case_id"] for r in read_records(run_dir / "per_image.jsonl")]
    assert cases == ["clips/0530/2/20.jpg", "clips/0530/3/20.jpg"]


def test_train_on_a_culane_folder(tmp_path):
    root = tmp_path / "culane"
    records = write_photo_dataset(root, [f"driver_00_01frame/05151640_0419.MP4/{i:05d}.jpg" for i in range(4)])
    write_culane(records[:2], root, root / "list" / "train_gt.txt")
    write_culane(records[2:], root, root / "list" / "test.txt")
    run_dir = tmp_path / "run"
    run_in_process(["data=culane", f"data.root={root}", "data.val.list_file=list/train_gt.txt", "data.max_lanes=6",
                    *COMMON], run_dir)  # the TuSimple folder's test above goes through the command line
    row = json.loads((run_dir / "test_scores.json").read_text())[0]
    assert row["dataset"] == "culane" and row["images"] == 2
    assert not (run_dir / "culane_categories.json").exists()  # no list/test_split/: no category table


def test_training_on_culane_tables_the_test_by_category_and_checks_the_lists_first(tmp_path):
    from lanevil_train.metrics.culane_files import CATEGORIES

    root = tmp_path / "culane"
    names = [f"driver_00_01frame/05151640_0419.MP4/{i:05d}.jpg" for i in range(4)]
    records = write_photo_dataset(root, names)
    write_culane(records[:2], root, root / "list" / "train_gt.txt")
    write_culane(records[2:], root, root / "list" / "test.txt")
    split = root / "list" / "test_split"
    split.mkdir()
    members = {"night": names[3:], "cross": names[3:]}  # the other lists: the first test image
    for name, filename in CATEGORIES:
        (split / filename).write_text("".join(f"/{n}\n" for n in members.get(name, names[2:3])))
    args = ["data=culane", f"data.root={root}", "data.val.list_file=list/train_gt.txt", "data.max_lanes=6", *COMMON]
    run_dir = tmp_path / "run"
    run_in_process(args, run_dir)
    rows = {row["list"]: row for row in json.loads((run_dir / "culane_categories.json").read_text())}
    scored = {r["key"]: r for r in read_records(run_dir / "per_image.jsonl")}
    night = next(r for key, r in scored.items() if names[3][:-4] in key)
    assert (rows["normal"]["images"], rows["night"]["images"], rows["total"]["images"]) == (1, 1, 2)
    assert rows["cross"]["FP"] == night["culane_fp"] and rows["cross"]["F1@50"] is None
    (split / "test3_shadow.txt").write_text("/driver_00_01frame/gone.MP4/00000.jpg\n")  # not a test image
    with pytest.raises(ValueError, match=r"test3_shadow.txt:1: image '/driver_00_01frame/gone.MP4/00000.jpg' is not"):
        run_in_process(args, tmp_path / "run2")
    assert not (tmp_path / "run2" / "checkpoints").exists()  # refused before training


def test_missing_label_file_names_it(tmp_path):
    root = tmp_path / "tusimple"
    root.mkdir()
    with pytest.raises(Exception, match="label_data_0313.json"):
        run_in_process(["data=tusimple", f"data.root={root}", "task.test_after_fit=false", *COMMON], tmp_path / "run")
