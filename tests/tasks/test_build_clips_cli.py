"""`task=build data=clips` from the command line: killed mid-build, the rerun finishes the suite a reader accepts."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import pytest

from lanevil_train.vlm.clips.clip_set import ClipSetDataset
from lanevil_train.vlm.clips.qa_records import QA_CATEGORIES
from tests.tasks.cli_helpers import REPO, run_cli

ARGS = ["task=build", "data=clips", "task.cases=2", "task.illusions=[rail_shadow,vehicle]", "task.severities=[3]",
        "task.workers=0", "data.size=[64,112]", "progress=none"]


def kill_when_clips_appear(args: list[str], run_dir, clips_file) -> bool:
    """Start the CLI, SIGKILL it once clips.jsonl has a line; False if it finished first."""
    env = {**os.environ, "PYTHONPATH": str(REPO), "OMP_NUM_THREADS": "1"}
    proc = subprocess.Popen([sys.executable, "-m", "lanevil_train", *args, f"hydra.run.dir={run_dir}"],
                            cwd=run_dir.parent, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while proc.poll() is None and time.monotonic() < deadline:
        if clips_file.exists() and clips_file.read_bytes().count(b"\n") >= 1:
            proc.send_signal(signal.SIGKILL)
            proc.wait()
            return True
        time.sleep(0.05)
    proc.kill()
    proc.wait()
    return False


def test_build_clips_is_killed_then_resumed_to_a_complete_suite(tmp_path):
    out = tmp_path / "suite"
    args = [*ARGS, f"task.out_dir={out}"]
    killed = kill_when_clips_appear(args, tmp_path / "run0", out / "clips.jsonl")
    if killed:
        with pytest.raises(ValueError, match="incomplete"):
            ClipSetDataset(out)
    done = out.joinpath("clips.jsonl").read_bytes().count(b"\n")
    rerun = run_cli(args, tmp_path / "run1")
    assert f"clip set: 12 clips (30 QA) in {out} ({12 - done} written now, {done} already there)" in rerun.stdout
    data = ClipSetDataset(out)
    assert len(data) == 12 and len({data.item_key(i) for i in range(12)}) == 12
    metas = [data.clip_meta(i) for i in range(12)]
    assert [m["severity"] for m in metas[:2]] == [0, 3] and metas[1]["illusion"] == "rail_shadow"
    assert {m["category"] for m in metas} == {None, "shadow", "traffic_obstruction"}
    item = data[1]
    assert len(item["frames"]) == 6 and item["frames"][0].shape == (64, 112, 3)
    qas = [json.loads(line) for line in (out / "qa.jsonl").read_text().splitlines()]
    assert len(qas) == 30 and {q["category"] for q in qas} == set(QA_CATEGORIES)
    assert json.loads((out / "build.json").read_text())["complete"] is True
    assert not list(out.rglob(".*.partial"))
