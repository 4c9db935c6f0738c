"""task=train: fit a detector (checkpoints, resume with ckpt_path), then score it on the clean test set."""

from __future__ import annotations

import pytorch_lightning as pl
from omegaconf import DictConfig

from lanevil_train.tasks.builders import build_datamodule, build_model, build_trainer, model_config, output_dir
from lanevil_train.tasks.scoring import score_test_set


def train(cfg: DictConfig) -> float | None:
    """Train cfg.model on cfg.data; returns the clean test Accuracy (%) when the test runs."""
    pl.seed_everything(cfg.seed, workers=True)
    out = output_dir(cfg)
    model = build_model(model_config(cfg))
    splits = ("train", "val", "test") if cfg.task.test_after_fit else ("train", "val")
    datamodule = build_datamodule(cfg, splits, model)
    checkpoints = pl.callbacks.ModelCheckpoint(dirpath=out / "checkpoints", filename="epoch{epoch:03d}",
                                               auto_insert_metric_name=False, save_last=True)
    trainer = build_trainer(cfg, callbacks=[checkpoints, pl.callbacks.LearningRateMonitor("step")])
    trainer.fit(model, datamodule=datamodule, ckpt_path=cfg.ckpt_path)
    if not cfg.task.test_after_fit:
        return None
    label = {"model": cfg.model.name, "backbone": cfg.backbone.name, "data": cfg.data.name,
             "defense": cfg.defense.name}
    row = score_test_set(trainer, model, datamodule, out, label)
    return row["Accuracy"]
