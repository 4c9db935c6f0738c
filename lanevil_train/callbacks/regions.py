"""The image-space steps of attention area mixing (paper §4.1), as plain functions on numpy arrays.

attention map M -> blurred, normalised M' -> high/low attention masks (T_HAA, T_LAA) -> connected
components larger than S -> those whose overlap with the lane ground truth is below theta -> their
bounding rectangles. And the other half: where a banked region goes in a target image (S_k) and the
beta blend that puts it there.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np
import torch

HAA = "haa"
LAA = "laa"


@dataclass(frozen=True)
class Box:
    """An axis-aligned rectangle in pixels: rows y0:y1, columns x0:x1 (ends exclusive)."""

    x0: int
    y0: int
    x1: int
    y1: int

    @property
    def height(self) -> int:
        return self.y1 - self.y0

    @property
    def width(self) -> int:
        return self.x1 - self.x0


def grad_cam(activation: torch.Tensor, gradient: torch.Tensor) -> torch.Tensor:
    """Grad-CAM maps (B, h, w) from a layer's activation and the loss gradient at it (both (B, C, h, w)).

    The score whose evidence is mapped is the negative training loss, so the channel weights are the
    spatial means of -dL/dA; the map is the ReLU of the weighted channel sum.
    """
    if activation.ndim != 4 or activation.shape != gradient.shape:
        raise ValueError(f"grad_cam: activation and gradient must both be (B, C, h, w), got "
                         f"{tuple(activation.shape)} and {tuple(gradient.shape)}")
    act, grad = activation.float(), gradient.float()
    weights = -grad.mean(dim=(2, 3), keepdim=True)
    return torch.relu((weights * act).sum(dim=1))


def blur_and_normalise(attention: np.ndarray, sigma: float) -> np.ndarray:
    """M' = G(M, sigma), min-max normalised to [0, 1] (an all-flat map becomes all zeros)."""
    m = np.asarray(attention, dtype=np.float32)
    if sigma > 0:
        m = cv2.GaussianBlur(m, (0, 0), sigmaX=float(sigma), borderType=cv2.BORDER_REPLICATE)
    lo, hi = float(m.min()), float(m.max())
    if hi - lo < 1e-12:
        return np.zeros_like(m)
    return (m - lo) / (hi - lo)


def lane_mask(lanes: list[np.ndarray], shape: tuple[int, int], width: int) -> np.ndarray:
    """The ground truth G as a boolean (H, W) mask: each lane polyline, widened to `width` pixels."""
    mask = np.zeros(shape, dtype=np.uint8)
    for lane in lanes:
        points = np.round(np.asarray(lane, dtype=np.float64)).astype(np.int32).reshape(-1, 1, 2)
        if len(points) >= 2:
            cv2.polylines(mask, [points], isClosed=False, color=1, thickness=1)
    width = max(int(width), 1)
    if width > 1:  # cv2's thick lines are wider than asked; a square dilation is exact
        mask = cv2.dilate(mask, np.ones((width, width), np.uint8))
    return mask.astype(bool)


def attention_masks(normalised: np.ndarray, t_haa: float, t_laa: float) -> dict[str, np.ndarray]:
    """B_HAA = M' > T_HAA and B_LAA = M' <= T_LAA."""
    return {HAA: normalised > t_haa, LAA: normalised <= t_laa}


def mismatched_regions(mask: np.ndarray, gt: np.ndarray, min_area: float, overlap_threshold: float) -> list[Box]:
    """Bounding rectangles of the connected components of `mask` that cover more than `min_area` (a
    fraction of the image) and of which less than `overlap_threshold` lies on the ground truth `gt`."""
    count, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    min_pixels = min_area * mask.size
    boxes = []
    for label in range(1, count):
        x, y, w, h, area = (int(v) for v in stats[label])
        if area <= min_pixels:
            continue
        on_lanes = np.count_nonzero(gt[y:y + h, x:x + w] & (labels[y:y + h, x:x + w] == label))
        if on_lanes / area < overlap_threshold:
            boxes.append(Box(x, y, x + w, y + h))
    return boxes


def extract_regions(attention: np.ndarray, gt: np.ndarray, kinds: tuple[str, ...], sigma: float, t_haa: float,
                    t_laa: float, min_area: float, overlap_threshold: float) -> dict[str, list[Box]]:
    """R_k for each kind k: the mismatched high/low attention regions of one image (paper eqs. 1-4)."""
    if attention.shape != gt.shape:
        raise ValueError(f"attention map {attention.shape} and lane mask {gt.shape} must have the same size")
    masks = attention_masks(blur_and_normalise(attention, sigma), t_haa, t_laa)
    return {kind: mismatched_regions(masks[kind], gt, min_area, overlap_threshold) for kind in kinds}


def target_area(gt: np.ndarray, kind: str, sigma: float, t_haa: float, t_laa: float) -> np.ndarray:
    """Where S_k looks in a target image: the attention its ground truth calls for is the lane mask,
    blurred and normalised; an HAA region goes where that is low (<= T_LAA), an LAA region where it is
    high (> T_HAA). A target with no lanes is all low attention."""
    wanted = blur_and_normalise(gt.astype(np.float32), sigma)
    if kind == HAA:
        return wanted <= t_laa
    if kind == LAA:
        return wanted > t_haa
    raise ValueError(f"region kind must be {HAA!r} or {LAA!r}, got {kind!r}")


def choose_place(area: np.ndarray, height: int, width: int, rng: np.random.Generator) -> Box:
    """S_k: a (height, width) box in the image of `area`, drawn among the positions that cover the most
    of `area` (ties of the best coverage any position reaches)."""
    rows, cols = area.shape
    height, width = min(height, rows), min(width, cols)
    integral = np.pad(area.astype(np.float64), ((1, 0), (1, 0))).cumsum(0).cumsum(1)
    cover = (integral[height:, width:] - integral[:-height, width:] - integral[height:, :-width]
             + integral[:-height, :-width])  # (rows - height + 1, cols - width + 1): box sums by top-left
    best = cover.max()
    ys, xs = np.nonzero(cover >= best - 0.5)  # box sums are pixel counts: ties are exact
    pick = int(rng.integers(len(ys)))
    y0, x0 = int(ys[pick]), int(xs[pick])
    return Box(x0, y0, x0 + width, y0 + height)


def blend_region(image: torch.Tensor, patch: torch.Tensor, box: Box, beta: float) -> None:
    """In place: image[:, box] = (1 - beta) * image[:, box] + beta * patch (cropped to the box)."""
    region = image[:, box.y0:box.y1, box.x0:box.x1]
    source = patch[:, :box.height, :box.width].to(device=image.device, dtype=torch.float32)
    mixed = (1.0 - beta) * region.float() + beta * source
    if not image.is_floating_point():
        mixed = mixed.round().clamp(torch.iinfo(image.dtype).min, torch.iinfo(image.dtype).max)
    region.copy_(mixed.to(image.dtype))


def hard_examples(scores: np.ndarray, mean: float, higher_is_harder: bool) -> np.ndarray:
    """Indices of the hard examples: accuracy below the mean, or loss above it."""
    scores = np.asarray(scores, dtype=np.float64)
    return np.flatnonzero(scores > mean if higher_is_harder else scores < mean)
