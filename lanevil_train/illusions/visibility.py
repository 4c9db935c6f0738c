"""How visible an illusion is: the fraction of pixels it changes, and a photo-like test image.

`changed_fraction(clean, perturbed)` counts pixels whose RGB sum moves by more than 6 (a change an
eye can notice on a flat area; smaller ones are rounding and anti-aliasing). Every illusion at
every severity must change at least MIN_CHANGED_FRACTION of a 1280x720 image and grow with
severity (issue 10); tests/illusions/test_visibility.py and docs/make_illusion_docs.py measure it.

`synthetic_road_photo(seed)` draws a textured road photo directly in image space (not with the
simulator), with its lane annotations, so the illusions can be checked on a ground plane that
`context_from_lanes` recovers, as on a real photo. `simulated_cases`, `photo_case` and `measure`
build the measured cases and the per illusion x seed x severity fractions.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from lanevil_train.illusions.context import IllusionContext, context_from_scene
from lanevil_train.illusions.recover import GroundPlaneError, context_from_lanes
from lanevil_train.illusions.registry import SEVERITIES, get_illusion
from lanevil_train.sim import SceneParams, build_scene, render_scene
from lanevil_train.sim.textures import noise_texture, sample

CHANGE_THRESHOLD = 6            # |sum_c new - sum_c old| above this counts as a changed pixel
MIN_CHANGED_FRACTION = 0.002    # level 1 must change at least 0.2 % of the image


def changed_pixels(clean: np.ndarray, perturbed: np.ndarray, threshold: int = CHANGE_THRESHOLD) -> np.ndarray:
    """Boolean (H, W) mask of pixels whose RGB sum differs by more than `threshold` (int32 sums)."""
    if clean.shape != perturbed.shape or clean.ndim != 3:
        raise ValueError(f"changed_pixels: expected two HxWx3 images of one shape, got {clean.shape} "
                         f"and {perturbed.shape}")
    diff = perturbed.astype(np.int32).sum(axis=2) - clean.astype(np.int32).sum(axis=2)
    return np.abs(diff) > threshold


def changed_fraction(clean: np.ndarray, perturbed: np.ndarray, threshold: int = CHANGE_THRESHOLD) -> float:
    """Fraction (0..1) of pixels whose RGB sum differs by more than `threshold` between the images."""
    return float(changed_pixels(clean, perturbed, threshold).mean())


def synthetic_road_photo(seed: int, width: int = 1280, height: int = 720,
                         num_lines: int | None = None) -> tuple[np.ndarray, list[np.ndarray]]:
    """A photo-like road image (uint8 HxWx3 RGB) and its lanes (left to right, y descending).

    A flat road seen by a pinhole camera, drawn row by row in image space: sky gradient, grass verge,
    asphalt with 1/f noise and patches, worn solid edge lines and dashed inner lines converging to a
    vanishing point. Horizon, vanishing column, lane count, brightness and tint vary with `seed`.
    """
    rng = np.random.default_rng([int(seed), 0x9407])
    h, w = int(height), int(width)
    n = int(num_lines) if num_lines is not None else int(rng.integers(3, 6))
    vp_u = w * (0.5 + rng.uniform(-0.06, 0.06))
    vp_v = h * rng.uniform(0.40, 0.50)
    light = rng.uniform(0.6, 1.15)
    tint = 1.0 + rng.uniform(-0.06, 0.06, 3)
    v, u = np.mgrid[0:h, 0:w].astype(np.float32)
    below = np.maximum(v - vp_v, 1e-3)
    # a flat ground plane: lateral metres x = (u - vp_u) * depth / f, depth z = f * cam_h / (v - vp_v)
    f, cam_h = w / 2.0, 1.5
    depth = f * cam_h / below
    lateral = (u - vp_u) * cam_h / below
    lane_w = rng.uniform(3.2, 3.8)
    centre = rng.uniform(-0.4, 0.4) * lane_w
    lines = centre + (np.arange(n) - (n - 1) / 2.0) * lane_w
    edge = lane_w * (n - 1) / 2.0 + 0.8
    tex = noise_texture(256, 2.0, 7)
    fine = noise_texture(256, 1.0, 8)
    grain = sample(tex, lateral * 4.0, depth * 4.0) * 0.05 + sample(fine, lateral * 30.0, depth * 30.0) * 0.03
    asphalt = np.float32(rng.uniform(0.30, 0.42)) + grain
    asphalt += 0.06 * np.clip(sample(tex, lateral * 0.5 + 50.0, depth * 0.5), -1.0, 1.0)  # patches
    img = np.empty((h, w, 3), np.float32)
    img[:] = asphalt[..., None]
    grass = np.stack([0.30 + grain * 2, 0.40 + grain * 2, 0.18 + grain], -1)
    off_road = np.abs(lateral - centre) > edge
    img[off_road] = grass[off_road]
    dash = ((depth + rng.uniform(0.0, 12.0)) % 12.0) < 4.0
    half = 0.075  # metres: a 15 cm line
    for i, d in enumerate(lines):
        solid = i in (0, n - 1)
        on = (np.abs(lateral - d) < half) & (solid | dash)
        wear = 0.8 + 0.2 * np.clip(sample(fine, lateral * 20.0, depth * 2.0), -1, 1)
        img[on] = (np.array([0.92, 0.92, 0.88], np.float32) * wear[on, None])
    # distance haze, then the sky above the horizon
    haze = np.clip(depth / 400.0, 0.0, 1.0)[..., None]
    img = img * (1.0 - haze) + np.array([0.72, 0.78, 0.86], np.float32) * haze
    sky_t = np.clip(v / max(vp_v, 1.0), 0.0, 1.0)[..., None]
    sky = np.array([0.30, 0.50, 0.85], np.float32) * (1.0 - sky_t) + np.array([0.75, 0.82, 0.90], np.float32) * sky_t
    img = np.where((v <= vp_v + 1.0)[..., None], sky, img)
    img = np.clip(img * light * tint, 0.0, 1.0)
    image = cv2.GaussianBlur((img * 255.0 + 0.5).astype(np.uint8), (3, 3), 0.6)
    # annotations every 10 rows from the bottom up to 10 % of the way to the horizon, as a labeller would
    rows = np.arange(h - 1, vp_v + 0.1 * (h - vp_v), -10.0)
    lanes = []
    for d in lines:
        xs = vp_u + d * (rows - vp_v) / cam_h
        keep = (xs >= 0) & (xs < w)
        if keep.sum() >= 5:
            lanes.append(np.stack([xs[keep], rows[keep]], 1))
    return np.ascontiguousarray(image), lanes


@dataclass(frozen=True)
class VisibilityCase:
    """One clean image and the geometry its illusions are drawn with."""

    kind: str            # "sim" (the scene's exact context) or "photo" (ground plane recovered from lanes)
    label: str
    image: np.ndarray
    context: IllusionContext


def simulated_cases(seed: int, params: SceneParams, width: int = 1280, height: int = 720) -> list[VisibilityCase]:
    """A rendered scene twice: with its exact context, and as a photo (context from its lanes only)."""
    sample = render_scene(seed, params, width, height)
    label = f"seed {seed} {params.road} {params.weather} {params.scene_kind} {params.num_lanes} lanes"
    exact = context_from_scene(build_scene(seed, params, width, height))
    cases = [VisibilityCase("sim", label, sample["image"], exact)]
    try:
        recovered = context_from_lanes(sample["lanes"], (height, width))
        cases.append(VisibilityCase("photo", label, sample["image"], recovered))
    except GroundPlaneError:
        pass
    return cases


def photo_case(seed: int, width: int = 1280, height: int = 720) -> VisibilityCase:
    """A `synthetic_road_photo` with its ground plane recovered from its lanes."""
    image, lanes = synthetic_road_photo(seed, width, height)
    return VisibilityCase("photo", f"synthetic photo {seed}", image, context_from_lanes(lanes, (height, width)))


def measure(case: VisibilityCase, names: list[str], seeds: list[int]) -> np.ndarray:
    """Changed fraction of every illusion x seed x severity on one case: array (names, seeds, 5)."""
    out = np.zeros((len(names), len(seeds), len(SEVERITIES)))
    for i, name in enumerate(names):
        illusion = get_illusion(name)
        for j, seed in enumerate(seeds):
            for k, severity in enumerate(SEVERITIES):
                out[i, j, k] = changed_fraction(case.image, illusion(case.image, case.context, severity, seed))
    return out
