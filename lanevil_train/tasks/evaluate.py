"""task=evaluate: score a trained checkpoint on the configured test set (table, JSON, CSV)."""

from __future__ import annotations

from pathlib import Path

import pytorch_lightning as pl
import torch
from omegaconf import DictConfig, OmegaConf

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
    # decoding is post-processing, not the network: task.decode.* overrides what the checkpoint used
    overrides = OmegaConf.to_container(cfg.task.decode, resolve=True)
    model.decode_kwargs.update({key: value for key, value in overrides.items() if value is not None})
    datamodule = build_datamodule(cfg, ("test",), model)
    trainer = build_trainer(cfg, logger=False)
    label = {"model": spec["model"]["name"], "backbone": spec["backbone"]["name"], "data": cfg.data.name,
             "checkpoint": str(path)}
    return score_test_set(trainer, model, datamodule, output_dir(cfg), label)["Accuracy"]
