"""LaneDetector: the one LightningModule for every detector family (backbone + optional neck + family head).

forward(images) -> raw head outputs (no NMS, exportable); head.loss(raw, targets) -> losses, every part
logged; head.decode(raw) -> lanes in input pixels, scaled here to each image's original size and scored
by the same TuSimple metric for every family. The head contract is models/head.py's LaneHead.
"""

from __future__ import annotations

from dataclasses import dataclass
from fnmatch import fnmatchcase

import numpy as np
import pytorch_lightning as pl
import torch
from torch import nn

from lanevil_train.data.normalization import DEFAULT_NORMALIZATION
from lanevil_train.data.preprocessor import Preprocessor, lanes_to_original
from lanevil_train.data.resize import DEFAULT_RESIZE
from lanevil_train.lanes import check_culane_rows, check_row_sampling, default_h_samples
from lanevil_train.metrics import TuSimpleMetric, tusimple_lane_scores
from lanevil_train.models.head import check_decode_options, targets_to
from lanevil_train.models.schedules import cosine, scaled_lr

TUSIMPLE_WIDTH = 1280  # the TuSimple 20 px threshold is for images this wide
# What the head's loss returns besides its named parts (which are logged one by one).
_LOSS_KEYS = ("loss", "per_sample")


@dataclass(frozen=True)
class PredictedLane:
    """One predicted lane: its points (N, 2) in the image's own pixels, y descending, and the family's confidence
    in [0, 1] (its head's decode with_scores: a class score, an existence probability)."""

    points: np.ndarray
    score: float


def adam(params, lr: float = 3e-4, weight_decay: float = 0.0) -> torch.optim.Optimizer:
    return torch.optim.Adam(params, lr=lr, weight_decay=weight_decay)


class LaneDetector(pl.LightningModule):
    """A lane detector = backbone (list of feature maps) + optional neck + head (forward/loss/decode/encode).

    `optimizer` is a callable params -> optimizer (a `_partial_` config, e.g. torch.optim.AdamW with its lr),
    `scheduler` one (optimizer, total_steps) -> LR scheduler stepped every optimizer step, or None for a
    constant rate. The optimizer's rate is the one at `reference_batch_size`, scaled to the run's global batch by
    `lr_scaling` (models/schedules.py). `lr_multipliers` ({pattern: factor}, fnmatch patterns over the parameter
    names, the first match wins, others 1) give parts of the network their own rate, as DETR's backbone at 0.1x;
    `gradient_clip_norm` clips the total gradient norm (DETR's 0.1) unless the trainer's gradient_clip_val is set.
    """

    def __init__(self, backbone: nn.Module, head: nn.Module, neck: nn.Module | None = None, optimizer=None,
                 scheduler=cosine, reference_batch_size: int | None = None, lr_scaling: str = "none",
                 decode: dict | None = None, crop_top: float = 0.0, lr_multipliers: dict | None = None,
                 gradient_clip_norm: float | None = None, row_sampling: str = "linear", culane_rows=None):
        super().__init__()
        self.backbone = backbone
        self.neck = neck
        self.head = head
        self.optimizer_factory = optimizer or adam
        self.scheduler_factory = scheduler
        self.reference_batch_size = reference_batch_size
        self.lr_scaling = lr_scaling
        self.lr_multipliers = check_lr_multipliers(self, dict(lr_multipliers or {}))
        if gradient_clip_norm is not None and not gradient_clip_norm > 0:
            raise ValueError(f"gradient_clip_norm: expected null or a positive maximum norm, "
                             f"got {gradient_clip_norm!r}")
        self.gradient_clip_norm = gradient_clip_norm
        self.decode_kwargs = dict(decode or {})
        check_decode_options(head, self.decode_kwargs, "model.decode")
        self.crop_top = crop_top  # fraction of the original height cut before resizing (data.crop_top)
        # how the decoded lanes are read at a dataset's rows, in scores and prediction files (lanes.ROW_SAMPLINGS)
        self.row_sampling = check_row_sampling(row_sampling)
        # the rows a CULane .lines.txt reads each lane at (lanes.culane_lanes), None: its own points
        self.culane_rows = check_culane_rows(culane_rows)
        self.val_metric = TuSimpleMetric(row_sampling=row_sampling)
        self.test_metric = TuSimpleMetric(row_sampling=row_sampling)
        # The config that built this model (set by the tasks); saved in checkpoints so that
        # evaluation rebuilds the same network.
        self.build_config: dict | None = None
        # Score each training image (TuSimple accuracy in input pixels) in training_step: hard-example
        # defenses (AAM, AAM++) switch this on; it costs one decode per step.
        self.score_train_batches = False

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        if self.build_config is not None:
            checkpoint["lanevil_model"] = self.build_config

    def features(self, images: torch.Tensor) -> list[torch.Tensor]:
        """The feature maps the head reads: the backbone's, through the neck if there is one."""
        features = self.backbone(images)
        return features if self.neck is None else self.neck(features)

    def forward(self, images: torch.Tensor) -> dict[str, torch.Tensor]:
        return self.head(self.features(images))

    def predict_lanes(self, images: torch.Tensor, original_sizes: list[tuple[int, int]]) -> list[list[np.ndarray]]:
        """Decoded lanes per image, in each image's original pixels (original_sizes: (H, W) each)."""
        return self.decode_lanes(self(images), tuple(images.shape[-2:]), original_sizes)

    def decode_lanes(self, raw: dict[str, torch.Tensor], input_size: tuple[int, int],
                     original_sizes: list[tuple[int, int]], with_scores: bool = False) -> list[list]:
        """The lanes of the network's outputs `raw` for inputs of `input_size` (H, W), in original pixels; with
        `with_scores`, each a PredictedLane (its points and the family's confidence)."""
        if not with_scores:
            lanes = self.head.decode(raw, **self.decode_kwargs)
            return [lanes_to_original(per_image, input_size, size, self.crop_top)
                    for per_image, size in zip(lanes, original_sizes)]
        decoded = self.head.decode(raw, **self.decode_kwargs, with_scores=True)
        out = []
        for per_image, size in zip(decoded, original_sizes):
            points = lanes_to_original([lane for lane, _ in per_image], input_size, size, self.crop_top)
            out.append([PredictedLane(lane, float(score)) for lane, (_, score) in zip(points, per_image)])
        return out

    @property
    def preprocessor(self) -> Preprocessor:
        """The input geometry and pixel conventions this network was built for (its build config)."""
        spec = self.build_config or {}
        if "input_size" not in spec:
            raise ValueError("this detector has no build config (input size, crop, normalisation, resize): build it "
                             "with models.factory.create_detector or load it with load_detector")
        return Preprocessor(tuple(spec["input_size"]), float(spec.get("crop_top") or 0.0),
                            spec.get("normalize") or DEFAULT_NORMALIZATION, spec.get("resize") or DEFAULT_RESIZE)

    @torch.inference_mode()
    def predict(self, images, color: str = "bgr", batch_size: int = 8) -> list:
        """Lanes of one image (a uint8 HxWx3 array, `color` "bgr" as cv2.imread gives it or "rgb") or of a list of
        images of any sizes: per image a list of PredictedLane (points (N, 2) in that image's own pixels, y
        descending, left to right, and the family's confidence), in batches of `batch_size`, on the network's
        device."""
        single = isinstance(images, np.ndarray) and images.ndim == 3
        images = [images] if single else list(images)
        preprocessor = self.preprocessor
        device = next(self.parameters()).device
        was_training = self.training
        self.eval()
        out = []
        for start in range(0, len(images), max(1, int(batch_size))):
            chunk = images[start:start + batch_size]
            inputs = preprocessor.batch(chunk, color).to(device)
            sizes = [tuple(int(v) for v in image.shape[:2]) for image in chunk]
            out.extend(self.decode_lanes(self(inputs), preprocessor.input_size, sizes, with_scores=True))
        self.train(was_training)
        return out[0] if single else out

    def batch_loss(self, batch: dict) -> dict[str, torch.Tensor]:
        """The head's losses on a batch (total, parts and the per-sample vector), and the raw outputs."""
        raw = self(batch["images"])
        return {**self.head.loss(raw, targets_to(batch["targets"], batch["images"].device)), "raw": raw}

    def training_step(self, batch: dict, batch_idx: int) -> dict[str, torch.Tensor]:
        losses = self.batch_loss(batch)
        batch_size = len(batch["images"])
        self.log("train/loss", losses["loss"], prog_bar=True, batch_size=batch_size)
        for key, value in losses.items():
            if key not in _LOSS_KEYS and isinstance(value, torch.Tensor) and value.ndim == 0:
                self.log(f"train/{key}", value, batch_size=batch_size)
        out = {"loss": losses["loss"], "per_sample_loss": losses["per_sample"].detach()}
        if self.score_train_batches:
            out["per_sample_accuracy"] = self.train_accuracy(losses["raw"], batch)
        return out

    def train_accuracy(self, raw: dict, batch: dict) -> torch.Tensor:
        """Per-image TuSimple accuracy of a training batch, in input pixels (threshold scaled to the width)."""
        height, width = batch["images"].shape[-2:]
        preds = self.head.decode(raw, **self.decode_kwargs)
        rows = default_h_samples(height)
        thresh = 20.0 * width / TUSIMPLE_WIDTH
        scores = [tusimple_lane_scores(pred, [np.asarray(lane, dtype=np.float64) for lane in gt], rows,
                                       pixel_thresh=thresh, row_sampling=self.row_sampling, height=height)[0]
                  for pred, gt in zip(preds, batch["input_lanes"])]
        return torch.tensor(scores, dtype=torch.float32)

    def _score_batch(self, batch: dict, metric: TuSimpleMetric) -> list[list[np.ndarray]]:
        sizes = [_original_size(meta) for meta in batch["meta"]]
        preds = self.predict_lanes(batch["images"], sizes)
        h_samples = [meta["h_samples"] for meta in batch["meta"]]
        metric.update(preds, batch["lanes"], h_samples, heights=[h for h, _ in sizes])
        return preds

    def validation_step(self, batch: dict, batch_idx: int) -> None:
        self._score_batch(batch, self.val_metric)

    def on_validation_epoch_end(self) -> None:
        self._log_metric("val", self.val_metric)

    def test_step(self, batch: dict, batch_idx: int) -> list[list[np.ndarray]]:
        """Scores the batch into the test metric; returns the decoded lanes (original pixels) per image, which
        a callback may turn into per-image records (evaluation/lane_records.PerImageWriter)."""
        return self._score_batch(batch, self.test_metric)

    def on_test_epoch_end(self) -> None:
        self._log_metric("test", self.test_metric)

    def _log_metric(self, stage: str, metric: TuSimpleMetric) -> None:
        scores = metric.compute()  # reduced across DDP ranks
        for key, value in scores.items():
            self.log(f"{stage}/{key}", value, sync_dist=False, rank_zero_only=False)
        metric.reset()

    def global_batch_size(self) -> int:
        """Images per optimizer step over all devices: the loader's batch x devices x gradient accumulation."""
        trainer = self.trainer
        loader_batch = getattr(trainer.datamodule, "batch_size", None) if trainer.datamodule is not None else None
        if loader_batch is None:
            raise ValueError("LaneDetector: the global batch size needs the datamodule's batch_size (data.batch_size)")
        return int(loader_batch) * trainer.world_size * trainer.accumulate_grad_batches

    def parameter_groups(self) -> list[dict]:
        """The trainable parameters in one group per rate multiplier (`lr_multipliers`), each with its `lr_factor`."""
        groups: dict[float, list] = {}
        for name, parameter in self.named_parameters():
            if parameter.requires_grad:
                groups.setdefault(lr_factor(name, self.lr_multipliers), []).append(parameter)
        return [{"params": params, "lr_factor": factor} for factor, params in groups.items()]

    def configure_optimizers(self):
        optimizer = self.optimizer_factory(self.parameter_groups())
        for group in optimizer.param_groups:
            group["lr"] *= group["lr_factor"]
        if self.lr_scaling != "none" and self.reference_batch_size:
            batch = self.global_batch_size()
            for group in optimizer.param_groups:
                group["lr"] = scaled_lr(group["lr"], batch, self.reference_batch_size, self.lr_scaling)
        if self.scheduler_factory is None:
            return optimizer
        total = max(int(self.trainer.estimated_stepping_batches), 1)
        schedule = self.scheduler_factory(optimizer, total)
        return {"optimizer": optimizer, "lr_scheduler": {"scheduler": schedule, "interval": "step"}}


    def configure_gradient_clipping(self, optimizer, gradient_clip_val=None, gradient_clip_algorithm=None) -> None:
        if gradient_clip_val is None and self.gradient_clip_norm is not None:
            gradient_clip_val, gradient_clip_algorithm = self.gradient_clip_norm, "norm"
        self.clip_gradients(optimizer, gradient_clip_val=gradient_clip_val,
                            gradient_clip_algorithm=gradient_clip_algorithm)


def lr_factor(name: str, multipliers: dict[str, float]) -> float:
    """The rate multiplier of a parameter: the first pattern its name matches, else 1."""
    return next((float(factor) for pattern, factor in multipliers.items() if fnmatchcase(name, pattern)), 1.0)


def check_lr_multipliers(model: nn.Module, multipliers: dict) -> dict[str, float]:
    """Each pattern must name some parameter (a typo would silently train at the full rate) and its factor be >= 0."""
    names = [name for name, _ in model.named_parameters()]
    for pattern, factor in multipliers.items():
        if not isinstance(factor, (int, float)) or isinstance(factor, bool) or factor < 0:
            raise ValueError(f"lr_multipliers.{pattern}: expected a rate factor >= 0, got {factor!r}")
        if not any(fnmatchcase(name, pattern) for name in names):
            roots = sorted({name.split(".")[0] + ".*" for name in names})
            raise ValueError(f"lr_multipliers: the pattern {pattern!r} names no parameter; parameter names start with "
                             f"{', '.join(roots)} (e.g. {names[0]})")
    return {str(k): float(v) for k, v in multipliers.items()}


def _original_size(meta: dict) -> tuple[int, int]:
    """(H, W) of the image the ground truth refers to."""
    if "height" in meta and "width" in meta:
        return int(meta["height"]), int(meta["width"])
    raise KeyError(f"sample meta has no original image size (height/width): keys {sorted(meta)}")
