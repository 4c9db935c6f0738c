"""task=evaluate: score a trained checkpoint on the configured test set (table, JSON, CSV)."""

from __future__ import annotations

from pathlib import Path

import pytorch_lightning as pl
import torch
from omegaconf import DictConfig

from lanevil_train.tasks.builders import build_datamodule, build_model, build_trainer, model_config, output_dir
from lanevil_train.tasks.scoring import score_test_set


def evaluate(cfg: DictConfig) -> float:
    """Rebuild the checkpoint's network, load its weights, and score it on cfg.data.test."""
    if cfg.ckpt_path is None:
        raise ValueError("task=evaluate needs ckpt_path=/path/to/checkpoint.ckpt")
    path = Path(cfg.ckpt_path)
    if not path.is_file():
        raise FileNotFoundError(f"ckpt_path={path}: no such checkpoint file")
    pl.seed_everything(cfg.seed, workers=True)
    checkpoint = torch.load(path, map_location="cpu", weights_only=False)
    spec = checkpoint.get("lanevil_model") or model_config(cfg)
    model = build_model(spec)
    model.load_state_dict(checkpoint["state_dict"])
    datamodule = build_datamodule(cfg, ("test",), encode=model.head.encode, input_size=spec["input_size"])
    trainer = build_trainer(cfg, logger=False)
    label = {"model": spec["model"]["name"], "backbone": spec["backbone"]["name"], "data": cfg.data.name,
             "checkpoint": str(path)}
    return score_test_set(trainer, model, datamodule, output_dir(cfg), label)["Accuracy"]
