"""Where a VLM's vision tokens lie on the frames of a clip: the attention layer of each family, and its tokens laid
out as frame-aligned feature maps, so that AAM / AAM++ (paper §4.1) can take a Grad-CAM map of every frame of a
VLM being fine-tuned (paper §5.4, Fig. enhance c-d).

VISION_LAYERS names, per model_type, the module of the Hugging Face model whose output holds the frames' tokens as
the language model receives them:
  * qwen2_vl, qwen2_5_vl: `model.visual`; its last output (pooler_output) is the merged tokens, every unit (a
    two-frame temporal patch of a video, or an image) in raster order (Qwen2.5's window order is undone there);
  * llava, llava_onevision: `model.multi_modal_projector`, [frames, tokens, D];
  * idefics3, smolvlm: `model.connector`, [frames, tokens, D] (after its pixel shuffle).

A unit of tokens covers one frame, or (a Qwen video) `temporal_patch_size` consecutive frames. The Qwen processors
resize the whole frame, so a unit's token grid covers the frame edge to edge. The others may crop (LLaVA's CLIP
processor cuts the centre square), squash or pad (Idefics3): `probe_cells` sends a frame whose pixels encode their
own coordinates through the model's own processor and reads back which part of the frame each token sees.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

VISION_LAYERS = {"qwen2_vl": "model.visual", "qwen2_5_vl": "model.visual",
                 "llava": "model.multi_modal_projector", "llava_onevision": "model.multi_modal_projector",
                 "idefics3": "model.connector", "smolvlm": "model.connector"}
QWEN_FAMILIES = ("qwen2_vl", "qwen2_5_vl")


def vision_layer(model_type: str, layer: str = "auto") -> str:
    """The attention layer's name in the Hugging Face model: `layer` as given, or the family's (VISION_LAYERS)."""
    if layer != "auto":
        return layer
    if model_type not in VISION_LAYERS:
        raise ValueError(f"model.attention_layer: auto knows the vision output of {', '.join(VISION_LAYERS)}, not "
                         f"{model_type!r}; name the module whose output holds the frames' tokens")
    return VISION_LAYERS[model_type]


@dataclass(frozen=True)
class TokenLayout:
    """How the attention layer's tokens lie on a batch's frames: `units` token groups in clip order, each covering
    `frames_per_unit` consecutive frames with `tokens` tokens, and `index`, a frame-aligned grid (h, w) giving the
    token (within a unit) that sees each cell of the frame, -1 where none does (cropped away)."""

    units: int
    frames_per_unit: int
    tokens: int
    index: np.ndarray

    def feature_maps(self, values):
        """The layer's tokens ([units, tokens(+1 class token), D] or, packed, [units * tokens, D]) as frame-aligned
        maps [frames, D, h, w]; a cell no token sees is 0."""
        import torch

        dim = values.shape[-1]
        if values.numel() % (self.units * dim):
            raise ValueError(f"attention layer: {tuple(values.shape)} tokens do not split into {self.units} units "
                             f"of the batch's frames")
        per_unit = values.reshape(self.units, -1, dim)
        if per_unit.shape[1] == self.tokens + 1:  # a class token first (CLIP's, kept by some projectors)
            per_unit = per_unit[:, 1:]
        if per_unit.shape[1] != self.tokens:
            raise ValueError(f"attention layer: {per_unit.shape[1]} tokens per unit, but the processor lays "
                             f"{self.tokens} on each; name a layer whose output holds the frames' tokens "
                             f"(model.attention_layer=auto picks one)")
        padded = torch.cat([per_unit, per_unit.new_zeros(self.units, 1, dim)], dim=1)
        index = torch.as_tensor(self.index, device=values.device).flatten()  # -1: the zero row
        maps = padded[:, index].transpose(1, 2).reshape(self.units, dim, *self.index.shape)
        return maps.repeat_interleave(self.frames_per_unit, dim=0)


def qwen_layout(inputs: dict, merge: int, frames: int) -> TokenLayout:
    """The layout of a Qwen-VL batch from its grids (t, h, w in patches per video or image): merged tokens in
    raster order, the whole frame resized, so token (i, j) sees cell (i, j) of a grid over the frame."""
    grid = inputs.get("video_grid_thw", inputs.get("image_grid_thw"))
    rows = {tuple(int(v) for v in row) for row in grid.tolist()}
    if len(rows) != 1:
        raise ValueError(f"attention layer: the batch's frames have different grids {sorted(rows)}; a batch holds "
                         f"clips of one frame size")
    t, h, w = rows.pop()
    units = int(grid[:, 0].sum())
    per_unit = frames * len(grid) // units  # a video unit: temporal_patch_size frames; an image: one
    index = np.arange((h // merge) * (w // merge)).reshape(h // merge, w // merge)
    return TokenLayout(units=units, frames_per_unit=per_unit, tokens=index.size, index=index)


def probe_cells(processor, frames_as: str, frame_size: tuple[int, int], tokens: int) -> np.ndarray:
    """The frame-aligned token index of a processor that gives one square-ish image per frame: a frame whose red and
    green channels are its x and y (blue 1) goes through the processor, and each of the `tokens` token cells of the
    processed image (a grid of its aspect ratio) takes the box of frame coordinates its real pixels came from."""
    import torch

    height, width = frame_size
    ys, xs = torch.meshgrid(torch.linspace(0, 1, height), torch.linspace(0, 1, width), indexing="ij")
    probe = torch.stack([xs, ys, torch.ones_like(xs)]) * 255.0
    part = processor.video_processor if frames_as == "video" else processor.image_processor
    media = {"videos": [probe.expand(6, -1, -1, -1)]} if frames_as == "video" else {"images": [[probe]]}
    out = part(**media, return_tensors="pt")
    pixels = next(value for key, value in out.items() if key.startswith("pixel_values") and torch.is_tensor(value))
    mean = torch.tensor(part.image_mean).view(3, 1, 1)
    std = torch.tensor(part.image_std).view(3, 1, 1)
    image = (pixels.reshape(-1, 3, *pixels.shape[-2:])[0].float() * std + mean).numpy()
    rows, cols = _grid_shape(tokens, image.shape[1] / image.shape[2])
    real = image[2] > 0.75  # padding carries the processor's fill, not the probe's blue
    fx, fy = image[0] * (width - 1), image[1] * (height - 1)
    cell_h, cell_w = image.shape[1] / rows, image.shape[2] / cols
    boxes = []
    for r in range(rows):
        for c in range(cols):
            sl = (slice(round(r * cell_h), round((r + 1) * cell_h)), slice(round(c * cell_w), round((c + 1) * cell_w)))
            seen = real[sl]
            boxes.append(None if not seen.any() else (fx[sl][seen].min(), fx[sl][seen].max(),
                                                      fy[sl][seen].min(), fy[sl][seen].max()))
    centres = [((b[0] + b[1]) / 2, (b[2] + b[3]) / 2) if b is not None else None for b in boxes]
    step_x = _spacing([centres[r * cols:(r + 1) * cols] for r in range(rows)], 0, width)
    step_y = _spacing([centres[c::cols] for c in range(cols)], 1, height)
    out_h, out_w = max(1, round(height / step_y)), max(1, round(width / step_x))
    index = np.full((out_h, out_w), -1, dtype=np.int64)
    for i in range(out_h):
        for j in range(out_w):  # the cell takes the nearest token whose box (widened by half a step) holds its centre
            y, x = (i + 0.5) * height / out_h - 0.5, (j + 0.5) * width / out_w - 0.5
            inside = [k for k, b in enumerate(boxes) if b is not None and b[0] - step_x / 2 <= x <= b[1] + step_x / 2
                      and b[2] - step_y / 2 <= y <= b[3] + step_y / 2]
            if inside:
                index[i, j] = min(inside, key=lambda k: abs(centres[k][0] - x) + abs(centres[k][1] - y))
    return index


def _spacing(lines: list[list], axis: int, extent: int) -> float:
    """The median distance between neighbouring token centres along `axis` (0: x, 1: y) of each line of tokens;
    the whole extent when every line holds one token."""
    gaps = [abs(b[axis] - a[axis]) for line in lines for a, b in zip(line, line[1:]) if a is not None and b is not None]
    return max(1.0, float(np.median(gaps))) if gaps else float(extent)


def _grid_shape(tokens: int, aspect: float) -> tuple[int, int]:
    """(rows, cols) with rows * cols == tokens closest to the aspect ratio rows / cols."""
    pairs = [(r, tokens // r) for r in range(1, tokens + 1) if tokens % r == 0]
    return min(pairs, key=lambda p: abs(math.log(p[0] / p[1]) - math.log(aspect)))


class VisionMaps:
    """The attention layer's tokens of the last encoded batch as frame-aligned feature maps (AttentionAreaMixing's
    `feature_map`): `observe` takes each batch's processor inputs and frame size, `__call__` lays tokens out."""

    def __init__(self, processor, model_type: str, frames_as: str):
        self.processor, self.model_type, self.frames_as = processor, model_type, frames_as
        self._inputs: dict | None = None
        self._clips, self._per_clip, self._size = 0, 0, (0, 0)
        self._probed: dict[tuple, np.ndarray] = {}

    def observe(self, inputs: dict, clips: int, frames: int, frame_size: tuple[int, int]) -> None:
        """The processor inputs of the batch just encoded: `clips` clips of `frames` frames of `frame_size`."""
        self._inputs, self._clips, self._per_clip, self._size = inputs, clips, frames, tuple(frame_size)

    def layout(self, values) -> TokenLayout:
        """The layout of the last batch for the layer output `values` (its token count per frame, for the probe)."""
        if self._inputs is None:
            raise ValueError("attention layer: no batch encoded yet; the maps follow the training step's batch")
        if self.model_type in QWEN_FAMILIES:
            part = self.processor.video_processor if self.frames_as == "video" else self.processor.image_processor
            return qwen_layout(self._inputs, int(part.merge_size), self._per_clip)
        frames = self._clips * self._per_clip
        if values.ndim != 3 or values.shape[0] != frames:
            raise ValueError(f"attention layer: expected [frames, tokens, D] tokens for the batch's {frames} frames, "
                             f"got {tuple(values.shape)}")
        tokens = values.shape[1]
        if math.isqrt(tokens) ** 2 != tokens and math.isqrt(tokens - 1) ** 2 == tokens - 1:
            tokens -= 1  # a class token first
        key = (self._size, tokens)
        if key not in self._probed:
            self._probed[key] = probe_cells(self.processor, self.frames_as, self._size, tokens)
        return TokenLayout(units=frames, frames_per_unit=1, tokens=tokens, index=self._probed[key])

    def __call__(self, values):
        """The layer's output tokens of the last batch as frame-aligned maps [frames, D, h, w]."""
        return self.layout(values).feature_maps(values)
