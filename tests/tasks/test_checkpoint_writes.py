"""Checkpoints are written atomically: a run killed while saving leaves the previous last.ckpt whole."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest
import torch
from hydra import compose, initialize_config_module

from lanevil_train.checkpoints import AtomicCheckpointIO, read_lightning_checkpoint
from lanevil_train.tasks.builders import build_trainer
from lanevil_train.tasks.detector.train import train
from tests.tasks.cli_helpers import REPO, TINY


def _state(value: float, size: int = 1000) -> dict:
    return {"state_dict": {"w": torch.full((size,), value)}, "global_step": int(value)}


def test_save_replaces_the_file_whole_with_the_usual_mode(tmp_path):
    path = tmp_path / "checkpoints" / "last.ckpt"
    old_umask = os.umask(0o022)
    try:
        AtomicCheckpointIO().save_checkpoint(_state(1.0), path)
        AtomicCheckpointIO().save_checkpoint(_state(2.0), path)
    finally:
        os.umask(old_umask)
    assert read_lightning_checkpoint(path, "ckpt_path")["global_step"] == 2
    assert os.stat(path).st_mode & 0o777 == 0o644
    assert sorted(p.name for p in path.parent.iterdir()) == ["last.ckpt"]


def test_a_save_that_fails_before_the_rename_keeps_the_old_checkpoint(tmp_path, monkeypatch):
    path = tmp_path / "last.ckpt"
    AtomicCheckpointIO().save_checkpoint(_state(1.0), path)

    def interrupted(*args):
        raise KeyboardInterrupt

    monkeypatch.setattr(os, "replace", interrupted)
    with pytest.raises(KeyboardInterrupt):
        AtomicCheckpointIO().save_checkpoint(_state(2.0), path)
    assert read_lightning_checkpoint(path, "ckpt_path")["global_step"] == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["last.ckpt"]


SAVER = """
import sys, torch
from lanevil_train.checkpoints import AtomicCheckpointIO
io = AtomicCheckpointIO()
for step in range(1, 10**6):
    io.save_checkpoint({"state_dict": {"w": torch.full((4_000_000,), float(step))}, "global_step": step}, sys.argv[1])
    print(step, flush=True)
"""


def test_kill_9_while_saving_leaves_a_whole_checkpoint(tmp_path):
    """A process rewriting a 16 MB checkpoint in a loop is killed at a few moments; the file always loads whole."""
    path = tmp_path / "last.ckpt"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    for delay in (0.05, 0.2):
        proc = subprocess.Popen([sys.executable, "-c", SAVER, str(path)], env=env, stdout=subprocess.PIPE, text=True)
        assert proc.stdout.readline().strip() == "1"  # one full save exists; the next is under way
        time.sleep(delay)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait()
        checkpoint = read_lightning_checkpoint(path, "ckpt_path")
        step = checkpoint["global_step"]
        assert step >= 1 and torch.equal(checkpoint["state_dict"]["w"], torch.full((4_000_000,), float(step))), delay


def test_training_saves_through_it_and_removes_what_a_killed_save_left(tmp_path):
    run = tmp_path / "run"
    stale = run / "checkpoints" / ".last.ckpt.12345.0badc0de.partial"
    stale.parent.mkdir(parents=True)
    stale.write_bytes(b"half a checkpoint")
    with initialize_config_module(config_module="lanevil_train.conf", version_base="1.3"):
        cfg = compose(config_name="config", overrides=[*TINY, "logger=none", f"output_dir={run}",
                                                       "trainer.max_steps=1", "task.test_after_fit=false"])
    assert isinstance(build_trainer(cfg).strategy.checkpoint_io, AtomicCheckpointIO)
    train(cfg)
    assert not stale.exists()
    assert read_lightning_checkpoint(run / "checkpoints" / "last.ckpt", "ckpt_path")["global_step"] == 1
    assert not list((run / "checkpoints").glob(".*"))
