"""Build library objects from a composed config: the bridge between Hydra and plain Python."""

from __future__ import annotations

from pathlib import Path

import pytorch_lightning as pl
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from lanevil_train.data.datamodule import LaneDataModule
from lanevil_train.models.detector import LaneDetector

# The parts of a config that define the network; stored in every checkpoint so that
# `task=evaluate ckpt_path=...` rebuilds the same model whatever the command line says.
MODEL_KEYS = ("model", "backbone")


def model_config(cfg: DictConfig) -> dict:
    """The network-defining part of cfg, as a plain dict (model, backbone, input size)."""
    out = {key: OmegaConf.to_container(cfg[key], resolve=True) for key in MODEL_KEYS}
    out["input_size"] = list(cfg.data.input_size)
    out["crop_top"] = float(cfg.data.get("crop_top", 0.0))
    return out


def read_checkpoint(path: str | Path, option: str) -> dict:
    """A Lightning checkpoint from disk (on CPU); errors name the option that gave the path."""
    import torch

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{option}={path}: no such checkpoint file")
    checkpoint = torch.load(path, map_location="cpu", weights_only=False)
    if not isinstance(checkpoint, dict) or "state_dict" not in checkpoint:
        raise ValueError(f"{option}={path}: not a Lightning checkpoint (no 'state_dict')")
    return checkpoint


def build_model(spec: dict) -> LaneDetector:
    """A LaneDetector from a model_config() dict."""
    backbone = instantiate(spec["backbone"])
    model = spec["model"]
    head = instantiate(model["head"], in_channels=backbone.channels[-1], feature_stride=backbone.strides[-1],
                       image_size=tuple(spec["input_size"]))
    opt = model.get("optimizer", {})
    detector = LaneDetector(backbone, head, lr=opt.get("lr", 3e-4), weight_decay=opt.get("weight_decay", 0.0),
                            scheduler=model.get("scheduler", "cosine"), decode=model.get("decode"),
                            crop_top=spec.get("crop_top", 0.0))
    detector.build_config = spec
    return detector


def build_defense(cfg: DictConfig) -> dict:
    """The configured defense as library objects: {"transforms": [...], "mixer": ..., "callback": ...}.

    Data-only defenses are albumentations transforms (added to the training pipeline) or a collate-level
    mixer; model-aware ones are a Lightning callback. Any part may be empty.
    """
    defense = cfg.defense
    unknown = set(defense) - {"name", "transforms", "mixer", "callback"}
    if unknown:
        raise ValueError(f"defense={defense.name}: unknown keys {sorted(unknown)}; a defense config has "
                         f"name, transforms, mixer and callback")
    transforms = [instantiate(node) for node in (defense.get("transforms") or [])]
    mixer = instantiate(defense.mixer) if defense.get("mixer") is not None else None
    callback = instantiate(defense.callback) if defense.get("callback") is not None else None
    return {"transforms": transforms, "mixer": mixer, "callback": callback}


def build_datamodule(cfg: DictConfig, splits: tuple[str, ...], model: LaneDetector,
                     defense: dict | None = None) -> LaneDataModule:
    """The datamodule with only the named splits instantiated (reading a split can be slow).

    The input geometry (size, top crop) and target encoder come from the model, so a checkpoint
    is always fed what it was trained on; a defense's transforms and mixer act on the train split.
    """
    defense = defense or {}
    # data.train_transforms: the user's own training-set transforms (e.g. illusions in the training scenes,
    # as the paper's LanEvil training set has), applied before the defense's
    transforms = [instantiate(node) for node in (cfg.data.get("train_transforms") or [])]
    transforms += list(defense.get("transforms") or [])
    spec = model.build_config
    sets = {}
    for split in ("train", "val", "test"):
        node = cfg.data.get(split)
        sets[split] = instantiate(node) if split in splits and node is not None else None
    return LaneDataModule(sets["train"], sets["val"], sets["test"], input_size=tuple(spec["input_size"]),
                          batch_size=cfg.data.batch_size, num_workers=cfg.data.num_workers,
                          augment=cfg.data.augment, encode=model.head.encode, crop_top=spec.get("crop_top", 0.0),
                          train_transforms=transforms, train_mixer=defense.get("mixer"))


def build_callbacks(cfg: DictConfig) -> list[pl.Callback]:
    """The Lightning callbacks of the `callbacks` config group, one per entry with a _target_ (null entries are
    skipped). A LearningRateMonitor is left out when there is no logger, since it has nowhere to write."""
    out = []
    for name, node in (cfg.get("callbacks") or {}).items():
        if node is None:
            continue
        if not OmegaConf.is_dict(node) or not node.get("_target_"):
            raise ValueError(f"callbacks.{name}: expected a mapping with a _target_ naming a Lightning callback "
                             f"class, got {OmegaConf.to_container(node) if OmegaConf.is_config(node) else node!r}")
        callback = instantiate(node)
        if not isinstance(callback, pl.Callback):
            raise ValueError(f"callbacks.{name}: {node._target_} built a {type(callback).__name__}, not a "
                             f"pytorch_lightning Callback")
        if isinstance(callback, pl.callbacks.LearningRateMonitor) and not cfg.logger.get("_target_"):
            continue
        out.append(callback)
    return out


def build_trainer(cfg: DictConfig, callbacks: list | None = None, logger=True) -> pl.Trainer:
    """A Lightning Trainer from cfg.trainer, with the configured progress display and logger."""
    from lanevil_train.tasks.trainer_progress import progress_callback

    args = OmegaConf.to_container(cfg.trainer, resolve=True)
    callbacks = list(callbacks or [])
    bar = progress_callback(cfg.progress)
    if bar is not None:
        callbacks.append(bar)
    return pl.Trainer(**args, callbacks=callbacks, logger=build_logger(cfg) if logger else False,
                      enable_progress_bar=bar is not None, default_root_dir=cfg.output_dir)


def build_logger(cfg: DictConfig):
    """The configured Lightning logger, or False for logger=none."""
    if cfg.logger.get("_target_") is None:
        return False
    if "Wandb" in cfg.logger._target_:
        import os

        os.environ.setdefault("WANDB_MODE", "offline")
    return instantiate(cfg.logger)


def output_dir(cfg: DictConfig) -> Path:
    path = Path(cfg.output_dir)
    path.mkdir(parents=True, exist_ok=True)
    return path
