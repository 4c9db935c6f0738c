"""A defense callback that fails its run while a trigger file exists: a launched compare job that fails, then passes
when rerun (tests/tasks/test_compare_jobs.py)."""

from __future__ import annotations

from pathlib import Path

import pytorch_lightning as pl


class FailWhile(pl.Callback):
    """Raises at the start of training while `trigger` exists."""

    def __init__(self, trigger: str):
        self.trigger = Path(trigger)

    def on_train_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if self.trigger.exists():
            raise RuntimeError(f"failing on purpose: {self.trigger} exists")
