"""The 11 non-illusion corruptions x 5 severities of the robustness suite (paper §5.4), rendered with albumentations.

Each corruption is one albumentations 2.0.x transform (snow: a Compose of two) whose random ranges are collapsed to
one fixed value per severity (modelled on ImageNet-C's five levels where one exists), applied with probability 1.
Each (name, severity) transform is built once per thread and reused. The only randomness left (where rain streaks,
snow flakes and fog patches fall, the noise pattern, the motion-blur angle) comes from `seed`, through the
transform's own generators (`set_random_seed`, done only for the RANDOM_CORRUPTIONS): the same (image, name,
severity, seed) gives the same bytes, and neither numpy's nor Python's global random state is touched. Parameters
are in pixels or fractions valid from 64x160 to 1280x720 images (blur sizes stay in pixels, as imagecorruptions
does for COCO-C / Cityscapes-C). fog is slow at full size (~1 s at 1280x720, one CPU core): RandomFog blends one
full-image copy per fog particle.

| name           | transform                                            | severity 1 .. 5                        |
|----------------|------------------------------------------------------|----------------------------------------|
| snow           | Compose(RandomSnow(method="bleach"), flakes =        | snow_point 0.10 0.20 0.30 0.40 0.50;   |
|                |   RandomRain(white 3 px drops, slant -2..2, blur 3)) |   brightness_coeff 1.2 1.4 1.6 1.8 2.0;|
|                |                                                      |   flakes drizzle default heavy heavy   |
|                |                                                      |   torrential; flake width 2 2 3 3 4 px |
| rain           | RandomRain(slant -10..10 px, length H/8, blur 3)     | rain_type drizzle default heavy heavy  |
|                |                                                      |   torrential; drop_width 1 1 1 2 2;    |
|                |                                                      |   brightness 0.90 0.85 0.80 0.75 0.70  |
| fog            | RandomFog(alpha_coef 0.06 0.08 0.10 0.12 0.15)       | fog_coef 0.20 0.35 0.50 0.65 0.80      |
| gaussian_blur  | GaussianBlur(kernel from sigma: int(3.5 s) * 2 + 1)  | sigma 1 2 3 4 6 (ImageNet-C)           |
| motion_blur    | MotionBlur(angle 0..360 from seed, centred)          | kernel 5 9 13 19 25 px                 |
| gaussian_noise | GaussNoise(per channel, std as a fraction of 255)    | std 0.08 0.12 0.18 0.26 0.38 (IN-C)    |
| iso_noise      | ISONoise (sensor colour shift + luminance noise)     | color_shift 0.01 0.02 0.03 0.04 0.05;  |
|                |                                                      |   intensity 0.2 0.4 0.6 0.8 1.0        |
| brightness     | RandomBrightnessContrast(contrast 0, by max)         | +0.1 0.2 0.3 0.4 0.5 x 255 (IN-C)      |
| contrast       | RandomBrightnessContrast(by mean): m + k (x - m)     | k 0.40 0.30 0.20 0.10 0.05 (IN-C)      |
| jpeg           | ImageCompression(jpeg)                               | quality 25 18 15 10 7 (IN-C)           |
| pixelate       | Downscale(area down, nearest up)                     | scale 0.50 0.40 0.30 0.20 0.15         |

snow: RandomSnow's "texture" method adds its snow layer to all three HSV channels (hue and saturation too) and
casts overflowing floats to uint8, so scenes turn green and wrap to black at snow_point >= 0.4; its "bleach" method
whitens but has no random part. So snow = bleach (the whitened scene) + white flakes drawn by RandomRain, seeded.
rain: the streaks are added, then the image is darkened; a darkening beyond 0.7 cancels the bright streaks it
covers (distortion fell from severity 4 to 5), so darkening stops at 0.7. (RandomRain's slant is a horizontal
offset in pixels, not degrees.)
pixelate: ImageNet-C's scale 0.6 with nearest-neighbour upscaling (a non-integer block size) distorts less than 0.5
(mean absolute difference), so the ladder starts at 0.5 and extends to 0.15.
contrast: albumentations multiplies by 1 + contrast and then adds brightness * mean(image), so contrast -c with
brightness +c gives mean + (1 - c)(x - mean), ImageNet-C's contrast with k = 1 - c.
GaussNoise reseeds OpenCV's RNG (cv2.setRNGSeed) from its own generator before cv2.randn: deterministic per seed,
but it changes OpenCV's (thread-local) RNG state.
"""

from __future__ import annotations

import threading
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

import albumentations as A
import cv2
import numpy as np

from lanevil_train.taxonomy import SEVERITIES

CORRUPTION_CATEGORIES: Mapping[str, tuple[str, ...]] = MappingProxyType({
    "weather": ("snow", "rain", "fog"),
    "blur": ("gaussian_blur", "motion_blur"),
    "noise": ("gaussian_noise", "iso_noise"),
    "digital": ("brightness", "contrast", "jpeg", "pixelate"),
})
CORRUPTION_NAMES: tuple[str, ...] = tuple(name for names in CORRUPTION_CATEGORIES.values() for name in names)

# name -> five parameter dicts (severity 1..5); the builders below turn one into a transform
LEVELS: Mapping[str, tuple[dict, ...]] = MappingProxyType({
    "snow": tuple({"snow_point": s, "brightness_coeff": b, "flakes": t, "flake_width": w} for s, b, t, w in zip(
        (0.10, 0.20, 0.30, 0.40, 0.50), (1.2, 1.4, 1.6, 1.8, 2.0),
        ("drizzle", "default", "heavy", "heavy", "torrential"), (2, 2, 3, 3, 4))),
    "rain": tuple({"rain_type": t, "drop_width": w, "brightness": b} for t, w, b in zip(
        ("drizzle", "default", "heavy", "heavy", "torrential"), (1, 1, 1, 2, 2), (0.90, 0.85, 0.80, 0.75, 0.70))),
    "fog": tuple({"fog_coef": f, "alpha_coef": a} for f, a in zip(
        (0.20, 0.35, 0.50, 0.65, 0.80), (0.06, 0.08, 0.10, 0.12, 0.15))),
    "gaussian_blur": tuple({"sigma": s} for s in (1.0, 2.0, 3.0, 4.0, 6.0)),
    "motion_blur": tuple({"kernel": k} for k in (5, 9, 13, 19, 25)),
    "gaussian_noise": tuple({"std": s} for s in (0.08, 0.12, 0.18, 0.26, 0.38)),
    "iso_noise": tuple({"color_shift": c, "intensity": i} for c, i in zip(
        (0.01, 0.02, 0.03, 0.04, 0.05), (0.2, 0.4, 0.6, 0.8, 1.0))),
    "brightness": tuple({"shift": b} for b in (0.1, 0.2, 0.3, 0.4, 0.5)),
    "contrast": tuple({"keep": k} for k in (0.40, 0.30, 0.20, 0.10, 0.05)),
    "jpeg": tuple({"quality": q} for q in (25, 18, 15, 10, 7)),
    "pixelate": tuple({"scale": s} for s in (0.50, 0.40, 0.30, 0.20, 0.15)),
})



def _snow(snow_point: float, brightness_coeff: float, flakes: str, flake_width: int) -> A.Compose:
    """Snow: the scene whitened (RandomSnow bleach), then white flakes where the seed puts them (RandomRain)."""
    return A.Compose([
        A.RandomSnow(method="bleach", snow_point_range=(snow_point, snow_point), brightness_coeff=brightness_coeff,
                     p=1.0),
        A.RandomRain(slant_range=(-2, 2), drop_length=3, drop_width=flake_width, drop_color=(255, 255, 255),
                     blur_value=3, brightness_coefficient=1.0, rain_type=flakes, p=1.0),
    ], p=1.0)


_BUILDERS: dict[str, Callable[..., A.BasicTransform | A.Compose]] = {
    "snow": _snow,
    "rain": lambda rain_type, drop_width, brightness: A.RandomRain(
        slant_range=(-10, 10), drop_length=None, drop_width=drop_width, blur_value=3,
        brightness_coefficient=brightness, rain_type=rain_type, p=1.0),
    "fog": lambda fog_coef, alpha_coef: A.RandomFog(
        fog_coef_range=(fog_coef, fog_coef), alpha_coef=alpha_coef, p=1.0),
    "gaussian_blur": lambda sigma: A.GaussianBlur(blur_limit=0, sigma_limit=(sigma, sigma), p=1.0),
    "motion_blur": lambda kernel: A.MotionBlur(
        blur_limit=(kernel, kernel), angle_range=(0, 360), direction_range=(0.0, 0.0), allow_shifted=False, p=1.0),
    "gaussian_noise": lambda std: A.GaussNoise(std_range=(std, std), mean_range=(0.0, 0.0), per_channel=True, p=1.0),
    "iso_noise": lambda color_shift, intensity: A.ISONoise(
        color_shift=(color_shift, color_shift), intensity=(intensity, intensity), p=1.0),
    "brightness": lambda shift: A.RandomBrightnessContrast(
        brightness_limit=(shift, shift), contrast_limit=(0.0, 0.0), brightness_by_max=True, p=1.0),
    "contrast": lambda keep: A.RandomBrightnessContrast(
        brightness_limit=(1.0 - keep, 1.0 - keep), contrast_limit=(keep - 1.0, keep - 1.0), brightness_by_max=False,
        p=1.0),
    "jpeg": lambda quality: A.ImageCompression(compression_type="jpeg", quality_range=(quality, quality), p=1.0),
    "pixelate": lambda scale: A.Downscale(
        scale_range=(scale, scale), interpolation_pair={"downscale": cv2.INTER_AREA, "upscale": cv2.INTER_NEAREST},
        p=1.0),
}

# the corruptions whose output depends on the seed; the others draw only from collapsed ranges, so reseeding them
# (tens of microseconds, a SeedSequence per call) would change nothing
RANDOM_CORRUPTIONS: frozenset[str] = frozenset({"snow", "rain", "fog", "motion_blur", "gaussian_noise", "iso_noise"})

# one transform per (name, severity) and thread: seeding mutates the transform, so threads must not share one
_local = threading.local()


def _cached_transform(name: str, severity: int) -> A.BasicTransform | A.Compose:
    cache = getattr(_local, "cache", None)
    if cache is None:
        cache = _local.cache = {}
    transform = cache.get((name, severity))
    if transform is None:
        transform = cache[(name, severity)] = _BUILDERS[name](**LEVELS[name][severity - 1])
    return transform


def _check_severity(severity: Any) -> int:
    if isinstance(severity, bool) or not isinstance(severity, (int, np.integer)) or severity not in SEVERITIES:
        raise ValueError(f"severity must be an integer from 1 (subtle) to 5 (severe), got {severity!r}")
    return int(severity)


def _check_seed(seed: Any) -> int:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ValueError(f"seed must be an integer >= 0, got {seed!r}")
    return int(seed)


def _check_image(image: Any) -> np.ndarray:
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8 or image.ndim != 3 or image.shape[2] != 3:
        got = f"{image.dtype} array of shape {image.shape}" if isinstance(image, np.ndarray) else type(image).__name__
        raise ValueError(f"image must be a uint8 HxWx3 RGB array, got {got}")
    if min(image.shape[:2]) < 8:
        raise ValueError(f"image must be at least 8x8 pixels, got shape {image.shape}")
    return image


@dataclass(frozen=True)
class Corruption:
    """One non-illusion corruption: its name, category and per-severity albumentations transform."""

    name: str
    category: str

    def __call__(self, image: np.ndarray, ctx: Any = None, severity: int = 1, seed: int = 0) -> np.ndarray:
        """Corrupt a uint8 HxWx3 RGB image at `severity` (1..5) with `seed`; `ctx` is ignored (no scene geometry)."""
        image = _check_image(image)
        transform = self.transform(severity)
        seed = _check_seed(seed)
        if self.random:
            transform.set_random_seed(seed)
        out = transform(image=image)["image"]
        return out if out.dtype == np.uint8 else np.clip(np.rint(out), 0, 255).astype(np.uint8)

    def transform(self, severity: int) -> A.BasicTransform | A.Compose:
        """The (cached) albumentations transform used at `severity`; seed it before use to reproduce a call."""
        return _cached_transform(self.name, _check_severity(severity))

    @property
    def random(self) -> bool:
        """Whether the seed changes the output (where flakes, streaks, fog and noise fall, the blur angle)."""
        return self.name in RANDOM_CORRUPTIONS

    @property
    def levels(self) -> tuple[dict, ...]:
        """The five parameter dicts, severity 1..5."""
        return LEVELS[self.name]


CORRUPTIONS: Mapping[str, Corruption] = MappingProxyType({
    name: Corruption(name, category) for category, names in CORRUPTION_CATEGORIES.items() for name in names
})


def get_corruption(name: str) -> Corruption:
    """The corruption called `name`, or a ValueError listing the known names."""
    if not isinstance(name, str) or name not in CORRUPTIONS:
        raise ValueError(f"unknown corruption name {name!r}; expected one of: {', '.join(CORRUPTION_NAMES)}")
    return CORRUPTIONS[name]
