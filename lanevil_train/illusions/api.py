"""`apply_illusion`: perturb any image with known lanes — simulated or a real photo."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from lanevil_train.illusions.context import IllusionContext
from lanevil_train.illusions.recover import context_from_lanes
from lanevil_train.illusions.registry import Illusion, check_seed, check_severity, get_illusion


def check_image(image) -> np.ndarray:
    """The image if it is uint8 HxWx3, else a ValueError saying what was expected."""
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        got = f"{type(image).__name__}" if not isinstance(image, np.ndarray) else f"{image.dtype} array {image.shape}"
        raise ValueError(f"image must be a uint8 HxWx3 RGB array, got {got}")
    return image


def apply_illusion(image: np.ndarray, lanes: list[np.ndarray], name: str, severity: int, seed: int = 0,
                   context: IllusionContext | None = None, **recover_kwargs) -> np.ndarray:
    """The image with illusion `name` at `severity` (1..5) composited in world space.

    The ground plane comes from `context` when given (a simulated scene: `context_from_scene`),
    otherwise it is recovered from the lanes (`context_from_lanes(lanes, image_size, **recover_kwargs)`:
    lane_width, camera_height, hfov_deg ...). The lanes themselves never change. Lanes that give no ground
    plane raise GroundPlaneError, also a lane outside the image (named as `lanes[i]`, see
    recover.LANE_X_MARGIN_FRAC); with a `context` the lanes are not used.
    """
    check_image(image)
    illusion = get_illusion(name)
    check_severity(severity)
    check_seed(seed)
    ctx = context if context is not None else context_from_lanes(lanes, image.shape[:2], **recover_kwargs)
    if ctx.image_size != image.shape[:2]:
        raise ValueError(f"context is for a {ctx.image_size} image, the image is {image.shape[:2]}")
    return illusion(image, ctx, severity, seed)


def apply_illusions(image: np.ndarray, lanes: list[np.ndarray], combo: list[tuple[str, int]], seed: int = 0,
                    context: IllusionContext | None = None, **recover_kwargs) -> np.ndarray:
    """Several illusions at once (paper §5.6), applied in order, e.g. [("rail_shadow", 3), ("vehicle", 2)]."""
    check_image(image)
    steps = check_combo(combo)
    seed = check_seed(seed)
    ctx = context if context is not None else context_from_lanes(lanes, image.shape[:2], **recover_kwargs)
    out = image
    for k, (illusion, severity) in enumerate(steps):
        out = illusion(out, ctx, severity, seed * 1000 + k)
    return out


def check_combo(combo) -> list[tuple[Illusion, int]]:
    """The (illusion, severity) steps of a non-empty list of (name, severity) pairs, or a ValueError naming combo[i]."""
    example = "e.g. [('rail_shadow', 3), ('vehicle', 2)]"
    if not _is_list(combo) or not combo:
        got = repr(combo) if isinstance(combo, (Sequence, str)) else type(combo).__name__
        raise ValueError(f"combo must be a non-empty list of (name, severity) pairs, {example}; got {got}")
    steps = []
    for k, item in enumerate(combo):
        if not _is_list(item) or len(item) != 2 or not isinstance(item[0], str):
            raise ValueError(f"combo[{k}] must be a (name, severity) pair like ('rail_shadow', 3), got {item!r} "
                             f"(combo is a list of such pairs, {example})")
        try:
            steps.append((get_illusion(item[0]), check_severity(item[1])))
        except ValueError as e:
            raise ValueError(f"combo[{k}]: {e}") from None
    return steps


def _is_list(value) -> bool:
    """A list, tuple or other sequence (Hydra's ListConfig), but not a string."""
    return isinstance(value, Sequence) and not isinstance(value, (str, bytes))
