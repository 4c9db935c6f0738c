"""Build library objects from a composed config: the bridge between Hydra and plain Python."""

from __future__ import annotations

import logging
from collections.abc import Mapping
from pathlib import Path

import pytorch_lightning as pl
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from lightning_fabric.utilities.exceptions import MisconfigurationException
from omegaconf import DictConfig, OmegaConf

from lanevil_train.checkpoints import (
    AtomicCheckpointIO,
)
from lanevil_train.data.datamodule import LaneDataModule
from lanevil_train.data.datasets import EmptySplitError
from lanevil_train.data.normalization import DEFAULT_NORMALIZATION, Normalization, normalization, spec_normalization
from lanevil_train.data.resize import DEFAULT_RESIZE, resize_filter, spec_resize
from lanevil_train.errors import prefixed
from lanevil_train.models.detector import LaneDetector
from lanevil_train.models.factory import DetectorSpec, create_detector, read_detector

log = logging.getLogger(__name__)

# The parts of a config that define the network; stored in every checkpoint so that
# `task=evaluate ckpt_path=...` rebuilds the same model whatever the command line says.
MODEL_KEYS = ("model", "backbone")


def model_config(cfg: DictConfig) -> dict:
    """The network-defining part of cfg, as a plain dict (model, backbone, input size, crop, normalisation, resize
    filter)."""
    out = {key: OmegaConf.to_container(cfg[key], resolve=True) for key in MODEL_KEYS}
    out["input_size"] = list(cfg.data.input_size)
    out["crop_top"] = float(cfg.data.get("crop_top", 0.0))
    # the input normalisation preset (data/normalization.py): the weights only mean something under it
    out["normalize"] = str(cfg.data.get("normalize") or DEFAULT_NORMALIZATION)
    normalization(out["normalize"])
    # the resize filter (data/resize.py): the official weights were measured on images resized with theirs
    out["resize"] = resize_filter(str(cfg.data.get("resize") or DEFAULT_RESIZE))
    return out


def instantiate_at(node, key: str, **kwargs):
    """instantiate(node, **kwargs), where any error names the config key `key` the node came from.

    Hydra wraps a constructor's error in its own exception; the user gets the constructor's message prefixed
    with the key instead (e.g. "defense.callback: beta must be in [0, 1], got 2.0", or "model.api_key_env: ..."
    when the message starts with one of the node's own keys), of the original's type
    where it can be (errors.prefixed). An empty dataset names the argument to change too:
    "data.test.label_files: the test split is empty: ...".
    """
    try:
        return instantiate(node, **kwargs)
    except InstantiationException as error:
        cause = error.__cause__ or error
        if isinstance(cause, EmptySplitError):
            split = key.rsplit(".", 1)[-1]
            raise EmptySplitError(f"{key}.{cause.argument}: the {split} split is empty: {cause}",
                                  cause.argument) from None
        if str(cause).startswith(key):  # the message names the key already (e.g. backbone.checkpoint=...)
            raise cause from None
        argument = str(cause).split(":", 1)[0]
        if isinstance(node, Mapping) and argument in node:  # "api_key_env: ..." -> "model.api_key_env: ..."
            raise prefixed(cause, key, sep=".") from cause
        raise prefixed(cause, key) from cause


def build_split(cfg: DictConfig, split: str):
    """The dataset data.<split> configures, read and checked now (an empty split is an error naming its key)."""
    node = cfg.data.get(split)
    if node is None:
        raise ValueError(f"data.{split}: this run needs a {split} split, and data={cfg.data.name} configures none")
    return instantiate_at(node, f"data.{split}")


def build_model(spec: dict) -> LaneDetector:
    """A LaneDetector from a model_config() dict (models/factory.py create_detector, which builds it without
    Hydra)."""
    return create_detector(DetectorSpec.from_build_config(spec))


def model_label(model, label: str | None = None, defense: str | None = None) -> str:
    """A detector's name in results, tables and reports: `label` (task.label) when one is set, else
    <family>-<backbone> of the network's build config (laneatt-resnet18), with +<defense> when it was trained
    with one (laneatt-resnet18+aam++; None or "none": no defense)."""
    if label:
        return str(label)
    spec = model.build_config or {}
    try:
        name = f"{spec['model']['name']}-{spec['backbone']['name']}"
    except (KeyError, TypeError):
        raise ValueError(f"a {type(model).__name__} without a build config naming its model and backbone has no "
                         f"label: set task.label") from None
    return name if defense in (None, "none") else f"{name}+{defense}"


def build_defense(cfg: DictConfig) -> dict:
    """The configured defense as library objects: {"transforms": [...], "mixer": ..., "callback": ...}.

    Data-only defenses are albumentations transforms (added to the training pipeline) or a collate-level
    mixer; model-aware ones are a Lightning callback. Any part may be empty.
    """
    defense = cfg.defense
    if defense.get("prompt") is not None:
        raise ValueError(f"defense={defense.name}: a textual defense of VLMs (a prompt prefix); a lane detector has "
                         f"no prompt: use it with model=vlm/<backend>")
    unknown = set(defense) - {"name", "transforms", "mixer", "callback"}
    if unknown:
        raise ValueError(f"defense={defense.name}: unknown keys {sorted(unknown)}; a defense config has "
                         f"name, transforms, mixer and callback")
    preset = normalization(str(cfg.data.get("normalize") or DEFAULT_NORMALIZATION))
    transforms = [instantiate_at(node, f"defense.transforms[{i}]", **_normalization_arguments(node, preset))
                  for i, node in enumerate(defense.get("transforms") or [])]
    mixer = instantiate_at(defense.mixer, "defense.mixer") if defense.get("mixer") is not None else None
    # a callback working on pixels (PGD) reads the normalisation of the model it trains: its build config's
    callback = instantiate_at(defense.callback, "defense.callback") if defense.get("callback") is not None else None
    return {"transforms": transforms, "mixer": mixer, "callback": callback}


def _normalization_arguments(node, preset: Normalization) -> dict:
    """What a defense working on pixels must know of the input normalisation, unless its config says it: cutout's
    fill is the preset's mean colour (0 after normalising, as DeVries & Taylor's holes)."""
    from hydra.utils import get_class

    from lanevil_train.data.defenses import LaneCutout

    try:
        target = get_class(node._target_)
    except Exception:  # noqa: BLE001 - instantiate_at reports a bad target, naming its key
        return {}
    if not isinstance(target, type):
        return {}
    if issubclass(target, LaneCutout) and "fill" not in node:
        return {"fill": preset.mean_colour()}
    return {}


def build_datamodule(cfg: DictConfig, splits: tuple[str, ...], model: LaneDetector,
                     defense: dict | None = None) -> LaneDataModule:
    """The datamodule with only the named splits instantiated (reading a split can be slow).

    The input geometry (size, top crop), normalisation and target encoder come from the model, so a checkpoint
    is always fed what it was trained on; a defense's transforms and mixer act on the train split.
    """
    defense = defense or {}
    # data.train_transforms: the user's own training-set transforms (e.g. illusions in the training scenes,
    # as the paper's LanEvil training set has), applied before the defense's
    spec = model.build_config
    preset = normalization(spec_normalization(spec))
    transforms = [instantiate_at(node, f"data.train_transforms[{i}]", **_normalization_arguments(node, preset))
                  for i, node in enumerate(cfg.data.get("train_transforms") or [])]
    transforms += list(defense.get("transforms") or [])
    # every split the run uses is read (labels parsed, image files checked) here, before any training step
    sets = {split: build_split(cfg, split) if split in splits and cfg.data.get(split) is not None else None
            for split in ("train", "val", "test")}
    return LaneDataModule(sets["train"], sets["val"], sets["test"], input_size=tuple(spec["input_size"]),
                          batch_size=cfg.data.batch_size, num_workers=cfg.data.num_workers,
                          augment=cfg.data.augment, encode=model.head.encode, crop_top=spec.get("crop_top", 0.0),
                          train_transforms=transforms, train_mixer=defense.get("mixer"),
                          normalize=spec_normalization(spec), resize=spec_resize(spec))


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
        callback = instantiate_at(node, f"callbacks.{name}")
        if not isinstance(callback, pl.Callback):
            raise ValueError(f"callbacks.{name}: {node._target_} built a {type(callback).__name__}, not a "
                             f"pytorch_lightning Callback")
        if isinstance(callback, pl.callbacks.LearningRateMonitor) and not cfg.logger.get("_target_"):
            continue
        out.append(callback)
    return out


def build_trainer(cfg: DictConfig, callbacks: list | None = None, logger=True) -> pl.Trainer:
    """A Lightning Trainer from cfg.trainer, with the configured progress display and logger."""
    from lanevil_train.trainer_progress import progress_callback

    args = OmegaConf.to_container(cfg.trainer, resolve=True)
    if isinstance(args.get("strategy"), dict):  # a strategy object from its config node (trainer=fsdp, deepspeed)
        args["strategy"] = instantiate_at(cfg.trainer.strategy, "trainer.strategy")
    callbacks = list(callbacks or [])
    bar = progress_callback(cfg.progress)
    if bar is not None:
        callbacks.append(bar)
    if "plugins" not in args:  # checkpoints written atomically (a user's own plugins take over)
        args["plugins"] = [AtomicCheckpointIO()]
    try:
        return pl.Trainer(**args, callbacks=callbacks, logger=build_logger(cfg) if logger else False,
                          enable_progress_bar=bar is not None, default_root_dir=cfg.output_dir)
    except (MisconfigurationException, ValueError, TypeError) as error:  # Lightning's check of its arguments
        raise ValueError(f"trainer: Lightning refused the trainer.* arguments: {error}") from None


def build_logger(cfg: DictConfig):
    """The configured Lightning logger, or False for logger=none."""
    if cfg.logger.get("_target_") is None:
        return False
    if "Wandb" in cfg.logger._target_:
        import os

        os.environ.setdefault("WANDB_MODE", "offline")
    return instantiate_at(cfg.logger, "logger")


def inference_device(cfg: DictConfig):
    """Where an evaluation runs the network: a CUDA device when trainer.accelerator allows one (gpu, cuda, auto) and
    one is present (the first of trainer.devices when it lists them), else the CPU."""
    import torch

    trainer = cfg.get("trainer") or {}
    if str(trainer.get("accelerator", "auto")) not in ("gpu", "cuda", "auto") or not torch.cuda.is_available():
        return torch.device("cpu")
    devices = trainer.get("devices")
    index = int(devices[0]) if OmegaConf.is_list(devices) and len(devices) else 0
    return torch.device("cuda", index)


def output_dir(cfg: DictConfig) -> Path:
    path = Path(cfg.output_dir)
    path.mkdir(parents=True, exist_ok=True)
    return path


def checkpoint_model(cfg: DictConfig) -> LaneDetector:
    """The network of the checkpoint at ckpt_path (its stored build config; the command line's for checkpoints
    without one, and for an official repository's checkpoint, converted: models/official.py) with its weights
    (models/factory.py read_detector)."""
    return read_detector(cfg.ckpt_path, default=lambda: DetectorSpec.from_build_config(model_config(cfg)),
                         where=f"ckpt_path={cfg.ckpt_path}")
