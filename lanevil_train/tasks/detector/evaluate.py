"""task=evaluate: score a checkpoint on a test set or an illusion suite, streaming and resumable.

Per-image scores go to `<out_dir>/per_image.jsonl` as they are produced (a rerun with the same
out_dir continues where it stopped); the tables and plots are then built from that file alone.
"""

from __future__ import annotations

import json
import logging
from dataclasses import dataclass
from pathlib import Path

import pytorch_lightning as pl
import torch
from omegaconf import DictConfig, OmegaConf

from lanevil_train.data.suites import IllusionSetDataset, SyntheticIllusionSuite
from lanevil_train.errors import prefixed
from lanevil_train.evaluation.culane_categories import category_lists, write_category_table
from lanevil_train.evaluation.lane_records import RESULTS, read_records
from lanevil_train.evaluation.prediction_files import write_prediction_files
from lanevil_train.evaluation.results import log_results, write_results
from lanevil_train.evaluation.streaming import stream_evaluate
from lanevil_train.files.atomic import atomic_write_text
from lanevil_train.models.detector import LaneDetector
from lanevil_train.models.head import check_decode_options
from lanevil_train.report.page import suite_file
from lanevil_train.report.specs import LANE_SPEC
from lanevil_train.tasks.builders import (
    build_logger,
    build_split,
    checkpoint_model,
    inference_device,
    model_label,
    output_dir,
)
from lanevil_train.tasks.detector.export import OnnxLaneDetector

log = logging.getLogger(__name__)


def load_checkpoint(cfg: DictConfig) -> LaneDetector:
    """The checkpoint's network with its weights, or the ONNX model of task.onnx (run by onnxruntime, decoded by
    the family's head as the checkpoint would be); decoding overridable with task.decode.*."""
    if cfg.task.get("onnx"):
        model = OnnxLaneDetector(cfg.task.onnx)
    else:
        if cfg.ckpt_path is None:
            raise ValueError("task=evaluate needs ckpt_path=/path/to/checkpoint.ckpt (or task.onnx=model.onnx)")
        model = checkpoint_model(cfg)
    # decoding is post-processing, not the network: task.decode.* overrides what the checkpoint used
    overrides = {key: value for key, value in OmegaConf.to_container(cfg.task.decode, resolve=True).items()
                 if value is not None}
    check_decode_options(model.head, overrides, "task.decode")
    model.decode_kwargs.update(overrides)
    return model


ON_THE_FLY = {"synthetic": "illusions", "corruptions": "corruptions", "combined": "combined"}  # task.suite -> kind


@dataclass(frozen=True)
class Scoring:
    """How a detector is streamed over a test set, read once from the config: the loader's batch and workers, the
    device, the progress display, whether the official prediction files are written (task.predictions), the
    baseline model of the tables (task.baseline) and whether report.html is written (task.html)."""

    batch_size: int
    num_workers: int
    device: torch.device
    progress: str = "auto"
    predictions: bool = False
    baseline: str | None = None
    html: bool = True

    @classmethod
    def from_config(cls, cfg: DictConfig) -> Scoring:
        return cls(batch_size=cfg.data.batch_size, num_workers=cfg.data.num_workers, device=inference_device(cfg),
                   progress=cfg.progress, predictions=bool(cfg.task.get("predictions", False)),
                   baseline=cfg.task.get("baseline"), html=bool(cfg.task.get("html", True)))


def test_dataset(cfg: DictConfig):
    """data.test as is (task.suite=null), the suite generated from it (task.suite=synthetic: the illusions;
    corruptions: the non-illusion corruptions; combined: illusion pairs), or a set written by task=build
    (task.suite=/path/to/set)."""
    suite = cfg.task.suite
    if suite is None:
        return build_split(cfg, "test"), cfg.data.name
    if suite in ON_THE_FLY:
        return synthetic_suite(cfg, ON_THE_FLY[suite]), f"synthetic-{ON_THE_FLY[suite]}"
    try:
        return IllusionSetDataset(suite), Path(suite).name
    except (FileNotFoundError, ValueError) as error:
        raise prefixed(error, f"task.suite={suite}") from None


def synthetic_suite(cfg: DictConfig, kind: str = "illusions") -> SyntheticIllusionSuite:
    """The on-the-fly suite of `kind`, from data.test's seeds when data=synthetic (else the defaults)."""
    test = cfg.data.test if cfg.data.name == "synthetic" else {"first_seed": 1000000, "size": [720, 1280]}
    illusions = cfg.task.illusions if isinstance(cfg.task.illusions, str) else list(cfg.task.illusions)
    try:
        return SyntheticIllusionSuite(cfg.task.cases, test["first_seed"], tuple(test["size"]), illusions,
                                      tuple(cfg.task.severities), cfg.task.repeats, kind=kind)
    except ValueError as error:
        raise ValueError(f"task.suite={cfg.task.suite}: {error}") from None


def evaluate(cfg: DictConfig) -> float:
    """Score the checkpoint; returns the Accuracy (%) over the perturbed images (all images if none). (A VLM's
    task=evaluate is tasks/vlm/evaluate.evaluate_vlm: conf/task/evaluate.yaml names one function per kind.)"""
    pl.seed_everything(cfg.seed, workers=True)
    model = load_checkpoint(cfg)
    dataset, dataset_name = test_dataset(cfg)
    categories = category_lists(cfg, dataset)  # CULane's nine lists, checked before any image is scored
    scoring = Scoring.from_config(cfg)
    out = Path(cfg.task.out_dir) if cfg.task.out_dir else output_dir(cfg)
    results = stream_dataset(model, dataset, dataset_name, out, model_label(model, cfg.task.label), scoring)
    value = write_results([results], out, baseline=scoring.baseline, html=scoring.html)
    if categories is not None:
        write_category_table(results, out, categories)
    from lanevil_train.tasks.cards import detector_identity, suite_plan, write_evaluation_card

    write_evaluation_card(results, out, detector_identity(cfg, model), suite_plan(dataset), scoring.baseline)
    log_results(build_logger(cfg), out)
    return value


def cross_domain(cfg: DictConfig) -> float:
    """task=cross_domain (paper §5.5): data.test (e.g. a TuSimple or CULane folder) and the simulated
    illusion suite, scored side by side in one table; returns the real data's Accuracy (%)."""
    pl.seed_everything(cfg.seed, workers=True)
    model = load_checkpoint(cfg)
    real_set, suite = build_split(cfg, "test"), synthetic_suite(cfg)
    scoring, label = Scoring.from_config(cfg), model_label(model, cfg.task.label)
    out = Path(cfg.task.out_dir) if cfg.task.out_dir else output_dir(cfg)
    real = stream_dataset(model, real_set, cfg.data.name, out / cfg.data.name, label, scoring)
    perturbed = stream_dataset(model, suite, "synthetic-illusions", out / "synthetic-illusions", label, scoring)
    write_results([real, perturbed], out, baseline=scoring.baseline, html=scoring.html)
    log_results(build_logger(cfg), out)
    return LANE_SPEC.headline.aggregate(read_records(real, keep_lanes=False))


def stream_dataset(model: LaneDetector, dataset, dataset_name: str, out: Path, label: str,
                   scoring: Scoring) -> Path:
    """Score `model` on `dataset` into out/per_image.jsonl (resumes a partial file), and with scoring.predictions
    write the official prediction files beside it; returns the per_image.jsonl path. A suite made on the fly also
    gets per_image.suite.json, its description (what renders its images again for the report page's gallery)."""
    model.to(scoring.device)
    results = stream_evaluate(model, dataset, out / RESULTS, {"model": label, "dataset": dataset_name},
                              batch_size=scoring.batch_size, num_workers=scoring.num_workers,
                              progress=scoring.progress, predictions=scoring.predictions)
    if isinstance(dataset, SyntheticIllusionSuite):
        atomic_write_text(suite_file(results), json.dumps(dataset.description(), indent=1) + "\n")
    if scoring.predictions:
        files = write_prediction_files(results, out)
        log.info("prediction files: %s (TuSimple JSON lines), %s/ (CULane .lines.txt)", files["tusimple"],
                 files["culane"])
    return results
