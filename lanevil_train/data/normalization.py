"""Input normalisation presets (`data.normalize`): how each detector family's official code turns an image into
its network input, and the one function every consumer calls (`normalize_image`).

A preset is a channel order, a divisor and a per-channel mean and std, applied as
    tensor[c] = (pixel[order[c]] / divisor - mean[c]) / std[c]
to uint8 pixels, with mean and std in the tensor's channel order and the units of `pixel / divisor`. Our images
are RGB (data/formats/images.py converts OpenCV's BGR); the official codes that read with cv2.imread and never
convert feed BGR, which a preset names with order "BGR".

The preset a model was trained with is stored in its build config (`normalize`, tasks/builders.model_config),
so evaluation, export and the closed loop feed a checkpoint what it learnt on; build configs written before the
key existed were all trained on `imagenet`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Normalization:
    order: str                        # "RGB" or "BGR": the tensor's channel order
    divisor: float                    # pixels (0..255) are divided by this before the mean is taken off
    mean: tuple[float, float, float]  # in the tensor's channel order, in units of pixel / divisor
    std: tuple[float, float, float]

    def pixel_mean_std(self) -> tuple[tuple[float, ...], tuple[float, ...]]:
        """(mean, std) per tensor channel in [0, 1] pixel units: tensor = (pixel / 255 - mean) / std. What a
        callback working in [0, 1] pixel units (PGD's eps-ball and valid range) needs."""
        unit = 255.0 / self.divisor
        return tuple(m / unit for m in self.mean), tuple(s / unit for s in self.std)

    def mean_colour(self) -> tuple[int, int, int]:
        """The uint8 RGB colour closest to the mean: it normalises to 0 within half a grey level (cutout's fill)."""
        rgb = self.mean if self.order == "RGB" else self.mean[::-1]
        return tuple(int(np.clip(round(m * self.divisor), 0, 255)) for m in rgb)


NORMALIZATIONS: dict[str, Normalization] = {
    # RGB / 255 with ImageNet's mean and std: what timm's (and torchvision's) ImageNet weights expect, and what
    # UFLD (cfzd/Ultra-Fast-Lane-Detection data/dataset.py:11 PIL Image.open, data/dataloader.py:20-21 and 62-63
    # ToTensor + Normalize) and pytorch-auto-drive (utils/datasets/lane_as_bezier.py:48 and
    # lane_as_segmentation.py:37 PIL .convert('RGB'); configs/lane_detection/common/datasets/test_288.py and
    # test_360.py:9-16 ToTensor + Normalize) feed.
    "imagenet": Normalization("RGB", 255.0, (0.485, 0.456, 0.406), (0.229, 0.224, 0.225)),
    # BGR / 255, no mean or std: LaneATT lib/datasets/lane_dataset.py:272 cv2.imread, :287 img / 255, :288-289 the
    # ImageNet step only when `normalize`, which every cfgs/laneatt_*.yml sets false (lines 44, 68, 81).
    "laneatt": Normalization("BGR", 255.0, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)),
    # BGR / 255, no mean or std, as LaneATT: CLRNet clrnet/datasets/base_dataset.py:39 cv2.imread,
    # clrnet/datasets/process/generate_lane_line.py:211 img / 255. Its configs define img_norm (Caffe's BGR means
    # [103.939, 116.779, 123.68], std 1; configs/clrnet/clr_resnet34_tusimple.py:46) but no train_process or
    # val_process step uses it (the Normalize process it would feed appears in no config).
    "clrnet": Normalization("BGR", 255.0, (0.0, 0.0, 0.0), (1.0, 1.0, 1.0)),
    # BGR on the 0..255 scale with GANet's own statistics: mmdet/datasets/tusimple_dataset.py:52 and
    # culane_dataset.py:63 cv2.imread; configs/{tusimple,culane}/final_exp_res18_s8.py:36-37
    # img_norm_cfg mean [75.3, 76.6, 77.6], std [50.5, 53.8, 54.3], to_rgb=False, applied by the pipeline's
    # Normalize (mmcv.imnormalize: (img - mean) / std, no channel swap).
    "ganet": Normalization("BGR", 1.0, (75.3, 76.6, 77.6), (50.5, 53.8, 54.3)),
}
DEFAULT_NORMALIZATION = "imagenet"  # what every build config without a `normalize` key was trained with


def normalization(name: str, key: str = "data.normalize") -> Normalization:
    """The preset called `name`; an unknown name is an error naming `key` and the presets."""
    try:
        return NORMALIZATIONS[name]
    except (KeyError, TypeError):
        raise ValueError(f"{key}: expected one of {', '.join(NORMALIZATIONS)}, got {name!r}") from None


def spec_normalization(spec: dict | None) -> str:
    """The preset name a model's build config records (`imagenet` for build configs older than the key)."""
    return (spec or {}).get("normalize") or DEFAULT_NORMALIZATION


def normalize_image(image: np.ndarray, name: str = DEFAULT_NORMALIZATION) -> np.ndarray:
    """uint8 HxWx3 RGB -> float32 3xHxW network input, under the preset `name`."""
    preset = normalization(name)
    x = image.astype(np.float32)
    if preset.order == "BGR":
        x = x[..., ::-1]
    x = (x / np.float32(preset.divisor) - np.asarray(preset.mean, np.float32)) / np.asarray(preset.std, np.float32)
    return np.ascontiguousarray(x.transpose(2, 0, 1))


def unnormalize_image(x: np.ndarray, name: str = DEFAULT_NORMALIZATION) -> np.ndarray:
    """normalize_image undone: float 3xHxW network input -> float32 HxWx3 RGB in [0, 1] pixel units (unclipped),
    for figures of what the network saw."""
    preset = normalization(name)
    x = np.asarray(x, np.float32).transpose(1, 2, 0)
    x = (x * np.asarray(preset.std, np.float32) + np.asarray(preset.mean, np.float32)) * np.float32(preset.divisor)
    if preset.order == "BGR":
        x = x[..., ::-1]
    return np.ascontiguousarray(x / np.float32(255.0))
