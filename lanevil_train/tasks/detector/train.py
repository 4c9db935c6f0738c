"""task=train: fit a detector with the configured defense (checkpoints, resume with ckpt_path), score it on
the clean test set, and, with task.suite set, on an illusion suite (the value a sweep optimises)."""

from __future__ import annotations

import logging
from pathlib import Path

import pytorch_lightning as pl
from omegaconf import DictConfig

from lanevil_train.checkpoints import (
    ARCHIVE_MEMBER,
    CheckpointError,
    is_release_archive,
    load_checkpoint_file,
    load_weights,
    remove_stale_checkpoint_temporaries,
)
from lanevil_train.data.normalization import spec_normalization
from lanevil_train.data.resize import spec_resize
from lanevil_train.evaluation.culane_categories import category_lists, write_category_table
from lanevil_train.evaluation.lane_records import RESULTS, PerImageWriter
from lanevil_train.evaluation.results import score_test_set, write_results
from lanevil_train.models.official import load_detector_weights, official_state_dict
from lanevil_train.tasks.builders import (
    build_callbacks,
    build_datamodule,
    build_defense,
    build_model,
    build_trainer,
    model_config,
    model_label,
    output_dir,
)
from lanevil_train.tasks.detector.anchor_use import choose_anchors
from lanevil_train.tasks.detector.evaluate import Scoring, stream_dataset, test_dataset

log = logging.getLogger(__name__)


def train(cfg: DictConfig) -> float | None:
    """Train cfg.model on cfg.data with cfg.defense.

    Returns the average Accuracy (%) over the perturbed images of task.suite when one is set, else the
    clean test Accuracy (%) when the test runs, else None. The clean test's per-image records go to
    per_image.jsonl in the run directory (the suite's to robustness/per_image.jsonl), which task=report reads.
    """
    pl.seed_everything(cfg.seed, workers=True)
    out = output_dir(cfg)
    model = build_model(model_config(cfg))
    # a checkpoint to resume (ckpt_path) or to start from (task.init_from) is read and fitted to the network now,
    # so a corrupt file or another network is reported before any data is read or any step runs
    # (task.init_from: its weights only, to fine-tune; ckpt_path: Lightning then restores the whole training state)
    if cfg.ckpt_path is not None:
        if ARCHIVE_MEMBER in str(cfg.ckpt_path) or is_release_archive(Path(cfg.ckpt_path)):
            raise CheckpointError(f"ckpt_path={cfg.ckpt_path}: a checkpoint inside an archive cannot be resumed "
                                  f"(Lightning reads the training state from the file itself): extract it, or start "
                                  f"a run from its weights with task.init_from={cfg.ckpt_path}")
        saved = load_checkpoint_file(cfg.ckpt_path, "ckpt_path")
        if official_state_dict(saved) is not None:
            raise CheckpointError(f"ckpt_path={cfg.ckpt_path}: a file of weights alone (an official repository's "
                                  f"checkpoint or a plain state dict) holds no training state to resume; start a run "
                                  f"from its weights with task.init_from={cfg.ckpt_path}")
        check_same_network(load_weights(model, cfg.ckpt_path, "ckpt_path", checkpoint=saved), model.build_config,
                           cfg.ckpt_path)
    elif cfg.task.get("init_from"):
        official = load_detector_weights(model, cfg.task.init_from, "task.init_from")  # ours or an official file
        if official:
            log.info(official)
    defense = build_defense(cfg)
    callbacks = build_callbacks(cfg)
    remove_stale_checkpoint_temporaries(callbacks)
    label = model_label(model, cfg.task.get("label"), cfg.defense.name)
    writer = PerImageWriter(out / RESULTS, {"model": label, "dataset": cfg.data.name})
    callbacks.append(writer)
    if defense["callback"] is not None:
        callbacks.append(defense["callback"])
    trainer = build_trainer(cfg, callbacks=callbacks)  # before the data: Lightning checks its arguments here
    splits = ("train", "val", "test") if cfg.task.test_after_fit else ("train", "val")
    datamodule = build_datamodule(cfg, splits, model, defense)
    # LaneATT: its anchors from the train split's lanes (kept in the checkpoint)
    crop_top = model.build_config.get("crop_top", 0.0)
    choose_anchors(model.head, datamodule.sets["train"], crop_top=crop_top, cache_dir=out)
    suite = test_dataset(cfg) if cfg.task.get("suite") is not None else None  # read and checked before training
    # CULane's nine category lists (task.culane_categories), checked against the test split before training
    categories = category_lists(cfg, datamodule.sets["test"], suite_replaces_test=False) \
        if cfg.task.test_after_fit else None
    trainer.fit(model, datamodule=datamodule, ckpt_path=cfg.ckpt_path)
    result = None
    if cfg.task.test_after_fit:
        result = score_test_set(trainer, model, datamodule, writer)
        if categories is not None and trainer.is_global_zero:
            write_category_table(writer.path, out, categories)
    if suite is not None and trainer.is_global_zero:
        result = score_robustness(cfg, model, suite, out / "robustness")
    return result


# The parts of a checkpoint's network spec that a resumed run must share: the weights fit either way, but
# the same weights fed another input geometry (size, top crop), normalisation or resize filter would silently learn
# something else.
RESUME_KEYS = (("input_size",), ("crop_top",), ("normalize",), ("resize",), ("backbone", "name"),
               ("backbone", "out_indices"), ("model", "head"))
DATA_KEYS = ("input_size", "crop_top", "normalize", "resize")  # named data.<key> in the messages


def check_same_network(checkpoint: dict, spec: dict, path) -> None:
    """A checkpoint resumed with ckpt_path must have been trained with this run's network and input geometry."""
    saved = checkpoint.get("lanevil_model")
    if saved is None:
        return  # a checkpoint without its spec: the weights were checked, nothing more to compare

    def at(tree: dict, keys: tuple):
        for key in keys:
            tree = tree.get(key) if isinstance(tree, dict) else None
        return list(tree) if isinstance(tree, tuple) else tree

    # checkpoints (and specs) older than the keys: imagenet, area
    saved = {**saved, "normalize": spec_normalization(saved), "resize": spec_resize(saved)}
    spec = {**spec, "normalize": spec_normalization(spec), "resize": spec_resize(spec)}
    changed = [(".".join(k), at(saved, k), at(spec, k)) for k in RESUME_KEYS if at(saved, k) != at(spec, k)]
    if changed:
        differences = "; ".join(f"{'data.' if key in DATA_KEYS else ''}{key} was {old!r}, now "
                                f"{new!r}" for key, old, new in changed)
        raise ValueError(f"ckpt_path={path}: resuming needs the network the checkpoint was trained with, and this "
                         f"config differs ({differences}); set those back, or start a new run from its weights with "
                         f"task.init_from={path}")


def score_robustness(cfg: DictConfig, model, suite, out: Path) -> float:
    """Stream the trained model over the task.suite dataset into `out` (resumable); the perturbed Accuracy (%)."""
    dataset, dataset_name = suite
    scoring = Scoring.from_config(cfg)
    results = stream_dataset(model, dataset, dataset_name, out,
                             model_label(model, cfg.task.get("label"), cfg.defense.name), scoring)
    return write_results([results], out, baseline=scoring.baseline, html=scoring.html)
