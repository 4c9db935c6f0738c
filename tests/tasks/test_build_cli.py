"""`task=build` from the command line writes a set a rerun recognises as finished."""

from __future__ import annotations

from lanevil_train.data.formats.manifest import read_manifest
from tests.tasks.cli_helpers import run_cli


def test_build_task_writes_and_then_skips(tmp_path):
    out = tmp_path / "set"
    args = ["task=build", "task.cases=2", "task.illusions=[rail_shadow,pedestrian]", "task.severities=[3]",
            "task.workers=0", f"task.out_dir={out}", "data.test.size=[90,160]", "progress=none"]
    first = run_cli(args, tmp_path / "run1")
    assert "6 images" in first.stdout and "6 written now" in first.stdout
    manifest = read_manifest(out / "manifest.jsonl")
    assert sorted({r["illusion"] for r in manifest if r["illusion"]}) == ["pedestrian", "rail_shadow"]
    second = run_cli(args, tmp_path / "run2")
    assert "0 written now, 6 already there" in second.stdout
