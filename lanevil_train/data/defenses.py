"""Data-only defense transforms (cutout, strong HSV jitter) for a training pipeline's `extra` steps.

They are albumentations transforms that run inside `build_pipeline` before the resize, so
they are seeded by the pipeline (`Compose.set_random_seed`) and picklable for DataLoader
workers. Neither moves or removes lane keypoints: the lane is still there under a hole.
"""

from __future__ import annotations

from typing import Any, Sequence

import albumentations as A
import numpy as np

from lanevil_train.data.normalization import NORMALIZATIONS
from lanevil_train.rules import Rule, check_settings, integer, is_list, is_number, number, ok, one_or_pair, probability

# ImageNet mean in uint8 RGB: a hole of this colour is 0 (within half a grey level) after the `imagenet`
# normalisation, which is what DeVries & Taylor's cutout does on normalised inputs. Under another preset the
# defense's fill is that preset's mean colour (tasks/builders.build_defense), so the meaning stays.
IMAGENET_MEAN_UINT8 = NORMALIZATIONS["imagenet"].mean_colour()


def _pair(value: Any, kind: type) -> tuple:
    """(min, max) of a value one_or_pair accepts: a scalar v is (v, v)."""
    low, high = value if is_list(value) else (value, value)
    return kind(low), kind(high)


class LaneCutout(A.ImageOnlyTransform):
    """Cutout (DeVries & Taylor 2017): paint random rectangles with a constant; lanes untouched.

    albumentations' CoarseDropout removes keypoints under its holes in our pipeline (the
    default KeypointParams(remove_invisible=True)), which would delete lane points whose
    paint is merely hidden; this transform only touches the image, so the lane labels stay.
    `hole_height`/`hole_width` are fractions of the image side; holes lie fully inside the image
    and may overlap. `fill` is one grey level or an RGB triple (default: the ImageNet mean; task=train passes the
    mean colour of data.normalize's preset, Normalization.mean_colour, unless the config sets a fill).
    """

    SETTINGS = {
        "num_holes": one_or_pair(integer(1)),
        "hole_height": one_or_pair(Rule("a fraction of the image height in [0, 1]", number(0, 1).test)),
        "hole_width": one_or_pair(Rule("a fraction of the image width in [0, 1]", number(0, 1).test)),
        "fill": Rule("one grey level or an RGB triple of them",
                     lambda v: ok(is_number(v) or is_list(v) and len(v) in (1, 3) and all(is_number(x) for x in v))),
        "p": probability(),
    }

    def __init__(self, num_holes: Sequence[int] | int = (1, 3), hole_height: Sequence[float] | float = (0.1, 0.3),
                 hole_width: Sequence[float] | float = (0.1, 0.3), fill: Sequence[float] | float = IMAGENET_MEAN_UINT8,
                 p: float = 0.5):
        check_settings(self.SETTINGS, locals(), "LaneCutout")
        super().__init__(p=p)
        self.num_holes = _pair(num_holes, int)
        self.hole_height = _pair(hole_height, float)
        self.hole_width = _pair(hole_width, float)
        self.cutout_fill = tuple(float(v) for v in (fill if is_list(fill) else [fill]))

    def get_transform_init_args(self) -> dict[str, Any]:
        """Constructor arguments, for albumentations' repr and (de)serialisation."""
        return {"num_holes": self.num_holes, "hole_height": self.hole_height, "hole_width": self.hole_width,
                "fill": self.cutout_fill}

    def get_params_dependent_on_data(self, params: dict[str, Any], data: dict[str, Any]) -> dict[str, Any]:
        """Draw the holes for this image: int (K, 4) rows [x1, y1, x2, y2), x2/y2 exclusive."""
        height, width = params["shape"][:2]
        return {"holes": sample_holes(height, width, self.num_holes, self.hole_height, self.hole_width,
                                      self.random_generator)}

    def apply(self, img: np.ndarray, holes: np.ndarray, **params: Any) -> np.ndarray:
        """The image with every hole painted with the fill colour (a copy; the input is kept)."""
        return fill_holes(img, holes, self.cutout_fill)


def sample_holes(height: int, width: int, num_holes: tuple[int, int], hole_height: tuple[float, float],
                 hole_width: tuple[float, float], rng: np.random.Generator) -> np.ndarray:
    """Random holes inside an image as int (K, 4) rows [x1, y1, x2, y2), sizes as fractions of the sides."""
    count = int(rng.integers(num_holes[0], num_holes[1] + 1))
    holes = np.zeros((count, 4), dtype=np.int64)
    for k in range(count):
        h = min(height, max(1, int(round(rng.uniform(*hole_height) * height))))
        w = min(width, max(1, int(round(rng.uniform(*hole_width) * width))))
        y1 = int(rng.integers(0, height - h + 1))
        x1 = int(rng.integers(0, width - w + 1))
        holes[k] = (x1, y1, x1 + w, y1 + h)
    return holes


def fill_holes(image: np.ndarray, holes: np.ndarray, fill: Sequence[float]) -> np.ndarray:
    """A copy of the image with each [x1, y1, x2, y2) rectangle set to `fill` (one value or per channel)."""
    out = image.copy()
    value = np.asarray(fill, dtype=np.float64)
    if value.size == 3 and (out.ndim != 3 or out.shape[2] != 3):
        raise ValueError(f"fill_holes: an RGB fill needs an HxWx3 image, got shape {out.shape}")
    value = value.astype(out.dtype) if value.size == 3 else out.dtype.type(value.item())
    for x1, y1, x2, y2 in np.asarray(holes, dtype=np.int64).reshape(-1, 4):
        out[y1:y2, x1:x2] = value
    return out


HSV_SETTINGS = {**{name: Rule(f"a shift limit in [0, {high}]", number(0, high).test)
                   for name, high in (("hue", 180), ("saturation", 255), ("value", 255))},
                "p": probability()}


def hsv_jitter(hue: float = 20, saturation: float = 40, value: float = 40, p: float = 0.8) -> A.HueSaturationValue:
    """The `hsv` defense: HSV jitter about 2.5x the default augmentation's (8, 20, 15 at p=0.4).

    Limits are symmetric shifts in albumentations' uint8 units (hue on OpenCV's 0-180 scale, so
    20 is +-40 degrees: a yellow marking can turn orange or green; saturation and value on 0-255).
    p=0.8 jitters most images while leaving some clean ones, as illusions (tints, glare, dusk)
    change colour and brightness far more than the mild default jitter does.
    """
    check_settings(HSV_SETTINGS, locals(), "hsv_jitter")
    return A.HueSaturationValue(hue_shift_limit=hue, sat_shift_limit=saturation, val_shift_limit=value, p=p)
