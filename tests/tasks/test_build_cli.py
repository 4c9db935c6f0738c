"""`task=build` from the command line writes a set a rerun recognises as finished."""

from __future__ import annotations

from lanevil_train.data.formats.manifest import read_manifest
from tests.tasks.cli_helpers import run_cli, run_in_process


def test_build_task_writes_and_then_skips(tmp_path, capsys):
    out = tmp_path / "set"
    args = ["task=build", "task.cases=2", "task.illusions=[rail_shadow,pedestrian]", "task.severities=[3]",
            "task.workers=0", f"task.out_dir={out}", "data.test.size=[90,160]", "progress=none"]
    first = run_cli(args, tmp_path / "run1")
    assert "6 images" in first.stdout and "6 written now" in first.stdout
    manifest = read_manifest(out / "manifest.jsonl")
    assert sorted({r["illusion"] for r in manifest if r["illusion"]}) == ["pedestrian", "rail_shadow"]
    run_in_process(args, tmp_path / "run2")  # the rerun in this process
    assert "0 written now, 6 already there" in capsys.readouterr().out


def test_build_from_tusimple_and_culane_folders(tmp_path):
    from lanevil_train.data.formats import read_culane, read_tusimple, write_culane, write_tusimple
    from tests.tasks.cli_helpers import write_photo_dataset

    common = ["task=build", "task.illusions=[vehicle]", "task.severities=[2,4]", "task.workers=0", "progress=none"]
    tusimple = tmp_path / "tusimple"
    write_tusimple(write_photo_dataset(tusimple, [f"clips/a/{i}/20.jpg" for i in range(2)]), tusimple / "test.json")
    out = tmp_path / "tusimple_set"
    run_in_process([*common, "data=tusimple", f"data.root={tusimple}", "data.test.label_files=[test.json]",
                    f"task.out_dir={out}"], tmp_path / "run1")
    labels = read_tusimple(out / "labels.json", out)
    assert len(labels) == 2 * 3 and all(len(r["lanes"]) >= 2 for r in labels)
    manifest = read_manifest(out / "manifest.jsonl")
    assert {r["case_id"] for r in manifest} == {"clips/a/0/20.jpg", "clips/a/1/20.jpg"}

    culane = tmp_path / "culane"
    write_culane(write_photo_dataset(culane, [f"driver_1/v.MP4/{i:05d}.jpg" for i in range(2)]), culane,
                 culane / "list" / "test.txt")
    out = tmp_path / "culane_set"
    run_in_process([*common, "data=culane", f"data.root={culane}", f"task.out_dir={out}"], tmp_path / "run2")
    records = read_culane(out / "list" / "test.txt", out)
    assert len(records) == 6 and all(len(r["lanes"]) >= 2 for r in records)
