"""AttentionAreaMixing: AAM++ (and the original AAM) as a drop-in Lightning callback (paper §4.1).

Each training step, with no extra forward pass:
1. a forward hook on the named layer keeps its activation, a tensor hook its gradient from the step's own
   backward; Grad-CAM turns them into the attention map M of every image;
2. hard examples (per-image accuracy below the mean, or per-sample loss above it) give up their
   mismatched high- (and, for AAM++, low-) attention regions: blurred map thresholded at T_HAA / T_LAA,
   connected components larger than S whose overlap with the lane ground truth is below theta, cut out
   at their bounding rectangles into a bounded bank (shared by all DDP ranks);
3. before the next steps' forward, a share of the batch images receive one banked region each, blended
   with ratio beta at a place S_k picks from the image's own ground truth: an HAA region where the lanes
   call for low attention, an LAA region where they call for high attention.

The module only has to return per-sample scores from training_step: a dict with "loss" and
"per_sample_accuracy" or "per_sample_loss" (B,). A module with a boolean `score_train_batches`
attribute has it switched on, so it can add per-image accuracy when it is able to; one with a boolean
`attention_gradients` attribute has it switched on too, so it lets its input images take gradients and a layer
behind frozen weights (a VLM's frozen vision tower) still receives them.

A layer whose output is not a (B, C, H, W) map of the batch images (a vision transformer's tokens) takes a
`feature_map` callable that lays its output out as one: a VLM's tokens on its frames (vlm/training/vision_maps.py).
"""

from __future__ import annotations

from collections import deque
from collections.abc import Mapping
from typing import Callable

import numpy as np
import pytorch_lightning as pl
import torch
import torch.distributed as dist
import torch.nn.functional as F

from lanevil_train.callbacks.adapter import BatchAdapter
from lanevil_train.callbacks.regions import (
    HAA,
    LAA,
    blend_region,
    choose_place,
    extract_regions,
    grad_cam,
    hard_examples,
    target_area,
)
from lanevil_train.rules import Rule, check_settings, integer, is_int, number, ok, one_of

MODES = {"aam": (HAA,), "aam++": (HAA, LAA)}
HARDNESS = ("auto", "accuracy", "loss")


class RegionBank:
    """The last `capacity` banked regions of each kind, as (C, h, w) float16 CPU tensors."""

    def __init__(self, kinds: tuple[str, ...], capacity: int):
        self.regions = {kind: deque(maxlen=capacity) for kind in kinds}

    def add(self, kind: str, patch: torch.Tensor) -> None:
        self.regions[kind].append(patch)

    def __len__(self) -> int:
        return sum(len(q) for q in self.regions.values())

    def available(self) -> list[str]:
        return [kind for kind, q in self.regions.items() if q]

    def sample(self, kind: str, rng: np.random.Generator) -> torch.Tensor:
        queue = self.regions[kind]
        return queue[int(rng.integers(len(queue)))]


class AttentionAreaMixing(pl.Callback):
    """AAM++ (mode="aam++", high and low attention areas) or AAM (mode="aam", high only).

    Args (paper defaults where the paper gives one):
        layer: dotted name of the module whose output is the attention source (e.g. "backbone.layer4"): a
            4-D (B, C, H, W) feature map with H, W > 1 that receives gradients. Anything else (a 2-D fc output,
            a 1x1 globally pooled map, a frozen layer, a layer the training step does not run) is a ValueError
            at the first training step, since it would bank no region.
        output_index: which tensor, if that module returns a list or tuple (a position), or a mapping such as a
            Hugging Face model output (a position among its values, or a key).
        feature_map: a callable laying the layer's output tensor out as a (B, C, h, w) map aligned with the batch
            images (B of them), for a layer that gives no such map itself (default: the output as it is).
        sigma: std of the Gaussian blur of M, in input pixels.
        t_haa, t_laa: thresholds on the [0, 1]-normalised blurred map (0.6, 0.4).
        min_area: S, as a fraction of the image area.
        overlap_threshold: theta, the largest fraction of a region on the lanes that is still a mismatch.
        lane_width: the width of the drawn ground-truth lanes, as a fraction of the image width.
        beta: mixing ratio (0.5).
        mix_prob: the share of each batch that receives a region.
        bank_size: regions kept per kind.
        max_region_fraction: larger regions (a fraction of the image) are not banked.
        hardness: "accuracy", "loss", or "auto" (accuracy when training_step returns it). The paper's
            dataset mean is estimated on each batch: a running mean lags behind a model that is learning
            (with a falling loss no image would ever be above it).
        start_step: no mixing before this global step.
        adapter: where images and lane ground truth sit in a batch (default: lanevil_train batches).
        seed: seeds the choices of regions and places (offset by the DDP rank).
    """

    MODEL_ARGUMENTS = ("layer",)  # the arguments check_model checks against the model (task=compare names them)
    # t_haa < t_laa is allowed (the paper's sensitivity grid has T_HAA 0.2 with T_LAA 0.4): the masks overlap
    SETTINGS = {
        "layer": Rule("the dotted name of a module of the model (e.g. 'backbone.layer4')",
                      lambda v: ok(isinstance(v, str) and v != "")),
        "mode": one_of(*MODES),
        "output_index": Rule("an integer (which of the layer's outputs, when it returns a list) or a key (of a "
                             "mapping output)", lambda v: ok(is_int(v) or isinstance(v, str))),
        "feature_map": Rule("null or a callable (layer output -> (B, C, h, w) map)",
                            lambda v: ok(v is None or callable(v))),
        "sigma": Rule("a number >= 0 (the blur's std in input pixels; 0: no blur)", number(0).test),
        **{name: number(0, 1) for name in ("t_haa", "t_laa", "beta", "mix_prob", "overlap_threshold", "min_area",
                                           "max_region_fraction")},
        "lane_width": Rule("a fraction of the image width in (0, 1]", number(0, 1, low_open=True).test),
        "bank_size": integer(1),
        "hardness": one_of(*HARDNESS),
        "start_step": integer(0),
    }

    def __init__(self, layer: str, mode: str = "aam++", output_index: int | str = -1, sigma: float = 3.0,
                 t_haa: float = 0.6, t_laa: float = 0.4, min_area: float = 0.002, overlap_threshold: float = 0.2,
                 lane_width: float = 0.02, beta: float = 0.5, mix_prob: float = 0.5, bank_size: int = 256,
                 max_region_fraction: float = 0.25, hardness: str = "auto",
                 start_step: int = 0, adapter: BatchAdapter | None = None, seed: int = 0,
                 feature_map: Callable[[torch.Tensor], torch.Tensor] | None = None):
        check_settings(self.SETTINGS, locals(), "AttentionAreaMixing")
        self.layer = layer
        self.mode = mode
        self.kinds = MODES[mode]
        self.output_index = output_index
        self.sigma = sigma
        self.t_haa, self.t_laa = t_haa, t_laa
        self.min_area = min_area
        self.overlap_threshold = overlap_threshold
        self.lane_width = lane_width
        self.beta = beta
        self.mix_prob = mix_prob
        self.max_region_fraction = max_region_fraction
        self.hardness = hardness
        self.start_step = start_step
        self.adapter = adapter or BatchAdapter()
        self.seed = seed
        self.feature_map = feature_map
        self.bank = RegionBank(self.kinds, bank_size)
        self.stats = {"hard": 0, "banked": 0, "mixed": 0}
        self._rng = np.random.default_rng(seed)
        self._handle = None
        self._capture = False
        self._indexed = False
        self._activation: torch.Tensor | None = None
        self._gradient: torch.Tensor | None = None
        self._mixed: set[int] = set()
        self._masks: np.ndarray | None = None  # this step's lane masks, drawn once for mixing and mining

    # ------------------------------------------------------------------ hooks on the named layer
    def setup(self, trainer: pl.Trainer, pl_module: pl.LightningModule, stage: str) -> None:
        self._rng = np.random.default_rng([self.seed, trainer.global_rank])

    def check_model(self, model: torch.nn.Module) -> torch.nn.Module:
        """The module `layer` names in `model`; a ValueError naming `layer` when the model has none.

        Run at fit start, and by task=compare on each run's model before any run trains. What the layer gives
        (a 4-D feature map that receives gradients, H, W > 1) can only be checked in the first training step.
        """
        try:
            return model.get_submodule(self.layer)
        except AttributeError as error:
            names = [name for name, _ in model.named_modules() if name and name.count(".") < 2]
            raise ValueError(f"AttentionAreaMixing: layer={self.layer!r} is not a module of "
                             f"{type(model).__name__}; some names: {names[:20]}") from error

    def on_fit_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        module = self.check_model(pl_module)
        self._handle = module.register_forward_hook(self._keep_activation)
        if self.hardness != "loss" and isinstance(getattr(pl_module, "score_train_batches", None), bool):
            pl_module.score_train_batches = True
        if isinstance(getattr(pl_module, "attention_gradients", None), bool):
            pl_module.attention_gradients = True

    def on_fit_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if self._handle is not None:
            self._handle.remove()
            self._handle = None

    def on_exception(self, trainer: pl.Trainer, pl_module: pl.LightningModule, exception: BaseException) -> None:
        self.on_fit_end(trainer, pl_module)  # a failed fit leaves no hook on the user's model

    def _keep_activation(self, module, inputs, output) -> None:
        if not (self._capture and module.training and torch.is_grad_enabled()):
            return
        self._indexed = isinstance(output, (list, tuple, Mapping))
        if isinstance(output, Mapping):
            output = output[self.output_index] if isinstance(self.output_index, str) else \
                list(output.values())[self.output_index]
        elif self._indexed:
            output = output[self.output_index]
        activation = self._as_map(output.detach()) if isinstance(output, torch.Tensor) else output
        self._check_output(output, activation)
        self._activation = activation
        output.register_hook(self._keep_gradient)

    def _as_map(self, tensor: torch.Tensor) -> torch.Tensor:
        """The layer's output (or its gradient) as a (B, C, h, w) map of the batch images (feature_map's)."""
        return tensor if self.feature_map is None else self.feature_map(tensor)

    def _check_output(self, output, activation) -> None:
        """Refuse, at the first training step, a layer output AAM cannot use (it would bank nothing, silently).

        AAM needs a 4-D (B, C, H, W) feature map with H, W > 1 (a map of 1x1, e.g. after global pooling, has
        no area to cut out; with a feature_map, the map it makes) that receives gradients (Grad-CAM needs them:
        a frozen layer gets none).
        """
        if isinstance(output, torch.Tensor):
            gave = f"a {tuple(output.shape)} tensor (requires_grad={output.requires_grad})"
            if self.feature_map is not None:
                gave += f", mapped to {tuple(activation.shape)} by feature_map"
        else:
            gave = f"a {type(output).__name__}"
        problem = None
        if not isinstance(activation, torch.Tensor) or activation.ndim != 4:
            problem = "not a 4-D feature map"
        elif activation.shape[-2] < 2 or activation.shape[-1] < 2:
            problem = "no spatial extent to cut regions from (H, W must both be > 1)"
        elif not output.requires_grad:
            problem = "no gradient reaches it (is the layer frozen, or run under torch.no_grad?)"
        if problem is not None:
            which = f" (output_index={self.output_index} of its outputs)" if self._indexed else ""
            raise ValueError(f"AttentionAreaMixing: layer={self.layer!r}{which} gave {gave} in the training step: "
                             f"{problem}. AAM needs a 4-D (B, C, H, W) feature map with H, W > 1 that receives "
                             f"gradients; set layer to such a module (e.g. a backbone stage like "
                             f"'backbone.layer4', not a pooled or fully connected layer)")

    def _keep_gradient(self, grad: torch.Tensor) -> None:
        self._gradient = self._as_map(grad.detach())

    # ------------------------------------------------------------------ the training step
    def on_train_batch_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule, batch, batch_idx: int) -> None:
        self._activation = self._gradient = None
        self._capture = True
        self._mixed = set()
        self._masks = None
        if trainer.global_step >= self.start_step and len(self.bank):
            self._mixed = self.mix(self.adapter.images(batch), self.step_masks(batch))

    def step_masks(self, batch) -> np.ndarray:
        """The lane masks of this step's batch (mixing leaves the labels as they are, so one drawing serves)."""
        if self._masks is None:
            self._masks = self.adapter_masks(batch)
        return self._masks

    def adapter_masks(self, batch) -> np.ndarray:
        """Boolean (B, H, W) lane masks of a batch, lanes drawn `lane_width` of the image width wide."""
        images = self.adapter.images(batch)
        height, width = images.shape[-2:]
        masks = self.adapter.lane_masks(batch, (height, width), max(1, round(self.lane_width * width)))
        if masks.shape[0] != images.shape[0]:
            raise ValueError(f"AttentionAreaMixing: the batch has {images.shape[0]} images but lane ground truth "
                             f"for {masks.shape[0]}; check the adapter's lanes/lane_mask location")
        return masks

    def mix(self, images: torch.Tensor, masks: np.ndarray) -> set[int]:
        """Blend one banked region into a `mix_prob` share of the images, in place; returns their indices."""
        mixed = set()
        available = self.bank.available()
        with torch.no_grad():
            for i in range(images.shape[0]):
                if not available or self._rng.random() >= self.mix_prob:
                    continue
                kind = available[int(self._rng.integers(len(available)))]
                patch = self.bank.sample(kind, self._rng)
                area = target_area(masks[i], kind, self.sigma, self.t_haa, self.t_laa)
                box = choose_place(area, patch.shape[1], patch.shape[2], self._rng)
                blend_region(images[i], patch, box, self.beta)
                mixed.add(i)
        self.stats["mixed"] += len(mixed)
        return mixed

    def on_train_batch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule, outputs, batch,
                           batch_idx: int) -> None:
        self._capture = False
        activation, gradient = self._activation, self._gradient
        self._activation = self._gradient = None
        found = []
        if outputs is not None:  # None: training_step skipped the batch (no backward)
            self._check_captured(activation, gradient)
        if activation is not None and gradient is not None:
            scores, higher_is_harder = self.per_sample_scores(outputs)
            found = self.harvest(activation, gradient, scores, higher_is_harder, batch)
        self._masks = None
        for kind, patch in self._gather(found):
            self.bank.add(kind, patch)
        self.stats["banked"] += len(found)
        pl_module.log("aam/bank", float(len(self.bank)), on_step=True, on_epoch=False, batch_size=1)

    def _check_captured(self, activation, gradient) -> None:
        """The step ran the layer in training mode and its backward reached it; else AAM would bank nothing."""
        if activation is None:
            raise ValueError(f"AttentionAreaMixing: layer={self.layer!r} gave no output in the training step (it "
                             f"was not called, or only in eval mode or under torch.no_grad); AAM needs a 4-D "
                             f"(B, C, H, W) feature map of the training forward that receives gradients")
        if gradient is None:
            raise ValueError(f"AttentionAreaMixing: layer={self.layer!r} gave a {tuple(activation.shape)} feature "
                             f"map but the step's backward sent it no gradient (does the loss depend on it?); AAM "
                             f"needs a 4-D (B, C, H, W) feature map that receives gradients")

    def per_sample_scores(self, outputs) -> tuple[np.ndarray, bool]:
        """(scores, higher_is_harder) from what training_step returned."""
        if not isinstance(outputs, dict):
            raise TypeError("AttentionAreaMixing needs per-sample scores: training_step must return a dict with "
                            "'loss' and 'per_sample_accuracy' or 'per_sample_loss' (one value per image)")
        if self.hardness in ("auto", "accuracy") and "per_sample_accuracy" in outputs:
            return _as_numpy(outputs["per_sample_accuracy"]), False
        if self.hardness == "accuracy":
            raise KeyError("AttentionAreaMixing(hardness='accuracy'): training_step returned no 'per_sample_accuracy'")
        if "per_sample_loss" in outputs:
            return _as_numpy(outputs["per_sample_loss"]), True
        raise KeyError(f"AttentionAreaMixing needs 'per_sample_accuracy' or 'per_sample_loss' in the dict "
                       f"training_step returns; it has {sorted(outputs)}")

    def harvest(self, activation: torch.Tensor, gradient: torch.Tensor, scores: np.ndarray,
                higher_is_harder: bool, batch) -> list[tuple[str, torch.Tensor]]:
        """Regions of this step's hard examples (images mixed in this step are not mined)."""
        images = self.adapter.images(batch)
        if len(scores) != images.shape[0]:
            raise ValueError(f"AttentionAreaMixing: {len(scores)} per-sample scores for a batch of {images.shape[0]}")
        hard = [i for i in hard_examples(scores, float(scores.mean()), higher_is_harder) if i not in self._mixed]
        self.stats["hard"] += len(hard)
        if not hard:
            return []
        height, width = images.shape[-2:]
        cams = grad_cam(activation[hard], gradient[hard])
        cams = F.interpolate(cams[:, None], size=(height, width), mode="bilinear", align_corners=False)[:, 0]
        cams = cams.cpu().numpy()
        masks = self.step_masks(batch)
        max_pixels = self.max_region_fraction * height * width
        found = []
        for cam, i in zip(cams, hard):
            regions = extract_regions(cam, masks[i], self.kinds, self.sigma, self.t_haa, self.t_laa,
                                      self.min_area, self.overlap_threshold)
            for kind, boxes in regions.items():
                for box in boxes:
                    if box.height * box.width <= max_pixels:
                        patch = images[i, :, box.y0:box.y1, box.x0:box.x1]
                        found.append((kind, patch.detach().to("cpu", torch.float16).clone()))
        return found

    def _gather(self, found: list) -> list:
        """The regions every rank found this step, in rank order (the bank is the same on every rank)."""
        if not (dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1):
            return found
        everyone: list = [None] * dist.get_world_size()
        dist.all_gather_object(everyone, found)
        return [item for rank_found in everyone for item in rank_found]

    def state_dict(self) -> dict:
        return {"stats": dict(self.stats)}

    def load_state_dict(self, state_dict: dict) -> None:
        self.stats.update(state_dict.get("stats", {}))


def _as_numpy(values) -> np.ndarray:
    if isinstance(values, torch.Tensor):
        values = values.detach().float().cpu().numpy()
    return np.asarray(values, dtype=np.float64).reshape(-1)
