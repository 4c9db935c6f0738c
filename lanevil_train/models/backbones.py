"""Backbone factory: timm ``features_only`` networks that return a list of feature maps.

Any timm model with a features-only form works by name (the ResNets and VGG-16 are tested). The returned
module is timm's own, with ``.channels`` and ``.strides`` (from feature_info) added. ``output_stride``
(8 or 16) dilates the last stages instead of striding them, as SCNN does with VGG-16 and DeepLab with
ResNets: timm's own dilation for the models that have it, our own for VGG (pool4 / pool5 removed,
the later 3x3 convolutions dilated, as DeepLab-LargeFOV and SCNN's VGG-16).

Only ``pretrained=True`` may touch the network (timm's hub download); the default is random
init, and ``checkpoint=path`` loads a local state dict (timm / torchvision / our own layout).

ViT-style networks are built with timm's ``dynamic_img_size=True`` where they take it, so they run at the data's
input size rather than only at their pretraining size; ``input_size_problem`` says, before any work, when a
backbone cannot take an input size (a forward pass on the meta device), with a size it takes.
"""

from __future__ import annotations

import re
from functools import lru_cache
from pathlib import Path
from typing import Sequence

import timm
import torch
from torch import nn
from torch.nn import functional as F

from lanevil_train.checkpoints import WEIGHT_KEYS, load_checkpoint_file, weights_in, what_it_holds

# The backbones the tests build (any timm name with a features-only form works too).
TESTED_BACKBONES: tuple[str, ...] = ("resnet18", "resnet34", "resnet50", "resnet101", "vgg16")
OUTPUT_STRIDES = (8, 16, 32)

# Prefixes that wrappers put in front of backbone keys (DataParallel, Lightning, our detector).
_WRAPPER_PREFIXES = ("module.", "model.", "backbone.", "encoder.", "body.", "net.")
# Classifier keys of ImageNet checkpoints that a features-only network does not have.
_HEAD_KEY = re.compile(r"^(fc|head|classifier|pre_logits|last_linear)\.")


def check_backbone_name(name: str) -> None:
    """A ValueError naming `name` unless timm has a model of that name."""
    if not isinstance(name, str) or not timm.is_model(name):
        close = timm.list_models(f"*{name}*")[:8] if isinstance(name, str) else []
        hint = f"; close names: {', '.join(close)}" if close else ""
        raise ValueError(f"unknown backbone {name!r}: not a timm model name (tested: {', '.join(TESTED_BACKBONES)})"
                         f"{hint}")


@lru_cache(maxsize=None)
def stage_strides(name: str, output_stride: int | None = None) -> tuple[int, ...]:
    """The stride of each stage timm's features-only `name` returns (index = an out_indices entry), with
    `output_stride` applied; built on the meta device (shapes only, no memory, no weights)."""
    check_backbone_name(name)
    _check_output_stride(output_stride)
    with torch.device("meta"):
        if name.startswith("vgg"):
            strides = timm.create_model(name, features_only=True).feature_info.reduction()
            return tuple(min(s, output_stride or s) for s in strides)
        # every stage, indexed as timm's out_indices are (its default out_indices skip DLA's stride-1 level0)
        return tuple(stage["reduction"] for stage in timm.create_model(
            name, features_only=True, **_timm_kwargs(name, None, output_stride)).feature_info.info)


def indices_for_strides(name: str, strides: Sequence[int], output_stride: int | None = None) -> tuple[int, ...]:
    """The out_indices giving feature maps at `strides` (the deepest stage of each stride: with dilation several
    stages share one), e.g. (2, 3, 4) for a ResNet and strides (8, 16, 32); a ValueError when one has none."""
    have = stage_strides(name, output_stride)
    out = []
    for stride in strides:
        found = [i for i, s in enumerate(have) if s == stride]
        if not found:
            raise ValueError(f"model.feature_strides: backbone {name} (output_stride={output_stride}) has no stage of "
                             f"stride {stride}; its stages have strides {list(have)}")
        out.append(found[-1])
    return tuple(out)


@lru_cache(maxsize=None)
def size_kwargs(name: str) -> dict:
    """timm's ``dynamic_img_size=True`` for the models that take it (ViT-style: the patch grid follows the input and
    the position embedding is resampled to it, so any size the patches divide works, not only the pretraining
    size); {} for the others (convolutional networks take any size as they are)."""
    try:
        with torch.device("meta"):
            timm.create_model(name, features_only=True, dynamic_img_size=True)
    except Exception:  # noqa: BLE001 - a TypeError for the models without it; any other failure: the real build says
        return {}
    return {"dynamic_img_size": True}


def _timm_kwargs(name: str, out_indices: Sequence[int] | None, output_stride: int | None) -> dict:
    """The keyword arguments of timm.create_model for a features-only `name` (our own dilation for VGG)."""
    kwargs = {} if out_indices is None else {"out_indices": tuple(out_indices)}
    if output_stride and not name.startswith("vgg"):
        kwargs["output_stride"] = output_stride
    return {**kwargs, **size_kwargs(name)}


def _meta_forward(name: str, size: tuple[int, int], kwargs: dict) -> tuple[list, list[int]]:
    """The feature maps (shapes only, on the meta device) and feature_info channels of `name` for a size input."""
    with torch.device("meta"):
        net = timm.create_model(name, features_only=True, **kwargs)
        return list(net(torch.empty(1, 3, *size))), list(net.feature_info.channels())


@lru_cache(maxsize=256)
def input_size_problem(name: str, size: tuple[int, int], out_indices: tuple[int, ...] | None = None,
                       output_stride: int | None = None) -> str | None:
    """Why the features-only backbone `name` cannot take a (height, width) input: a forward pass on the meta device
    (shapes only, no weights, milliseconds) fails, or gives maps that are not (N, C, H, W); with a size it takes
    when one is near. None when it takes the input (or the check cannot run: an operation without a meta kernel)."""
    kwargs = _timm_kwargs(name, out_indices, output_stride)
    try:
        maps, channels = _meta_forward(name, size, kwargs)
    except NotImplementedError:
        return None
    except Exception as error:  # noqa: BLE001 - timm's own words say what the network needs
        reason = str(error).strip().splitlines()[0] if str(error).strip() else type(error).__name__
        return f"timm's {name} fails on a {size[0]}x{size[1]} input ({reason}){_size_that_works(name, size, kwargs)}"
    if any(m.ndim != 4 or m.shape[1] != c for m, c in zip(maps, channels)):
        return (f"timm's {name} gives its feature maps as {tuple(maps[0].shape)}, not (N, C, H, W) with C = "
                f"{channels[0]} (channels last, as Swin's), which the heads cannot read; choose a backbone whose "
                f"features come channels first")
    return None


def _size_that_works(name: str, size: tuple[int, int], kwargs: dict) -> str:
    """"; ... takes [h, w]": the size rounded up to its largest stride, when the network takes that; else the size
    timm's pretrained_cfg names."""
    stride = max(stage_strides(name))
    rounded = tuple(-(-side // stride) * stride for side in size)
    try:
        _meta_forward(name, rounded, kwargs)
        return f"; it takes data.input_size=[{rounded[0]},{rounded[1]}] (multiples of its stride {stride})"
    except Exception:  # noqa: BLE001 - no near size: name the one it was made for
        made_for = tuple(getattr(timm.get_pretrained_cfg(name), "input_size", ())[1:])
        return f"; it was made for {made_for[0]}x{made_for[1]} inputs" if len(made_for) == 2 else ""


def _check_output_stride(output_stride) -> None:
    if output_stride is not None and output_stride not in OUTPUT_STRIDES:
        raise ValueError(f"output_stride={output_stride!r}: expected null or one of "
                         f"{', '.join(map(str, OUTPUT_STRIDES))}")


def build_backbone(
    name: str,
    pretrained: bool = False,
    checkpoint: str | None = None,
    out_indices: Sequence[int] | None = (4,),
    output_stride: int | None = None,
) -> nn.Module:
    """Build a timm features-only backbone; weights random, hub (``pretrained``) or a local file.

    ``out_indices`` are timm's: (4,) is layer4 (stride 32) for ResNets and conv5_3 (stride 16)
    for vgg16 (whose index 5 is the stride-32 max-pool); None means every stage.
    """
    check_backbone_name(name)
    _check_output_stride(output_stride)
    if pretrained and checkpoint is not None:
        raise ValueError("build_backbone: give either pretrained=True or checkpoint=..., not both")
    net = timm.create_model(name, pretrained=pretrained, features_only=True,
                            **_timm_kwargs(name, out_indices, output_stride))
    # the timm module itself (so hooks address e.g. "backbone.layer4"), plus our attributes
    backbone = net
    backbone.backbone_name = name
    backbone.channels = list(net.feature_info.channels())
    backbone.strides = list(net.feature_info.reduction())
    if output_stride and name.startswith("vgg"):
        _dilate_vgg(backbone, output_stride)
    _pool_channels_last(backbone)
    if checkpoint is not None:
        load_backbone_checkpoint(backbone, checkpoint)
    return backbone


def _dilate_vgg(net: nn.Module, output_stride: int) -> None:
    """Remove the max-pools that would take the stride past `output_stride` and dilate every 3x3 convolution
    after them by the stride they skip (DeepLab-LargeFOV, SCNN's VGG-16): the weights keep their shapes, so
    ImageNet checkpoints still load."""
    stride, dilation = 1, 1
    for name, module in net.named_children():
        if isinstance(module, nn.MaxPool2d):
            if stride * 2 > output_stride:
                setattr(net, name, nn.Identity())
                dilation *= 2
            else:
                stride *= 2
        elif isinstance(module, nn.Conv2d) and module.kernel_size == (3, 3) and dilation > 1:
            module.dilation, module.padding = (dilation, dilation), (dilation, dilation)
    net.strides = [min(s, output_stride) for s in net.strides]


class ChannelsLastMaxPool2d(nn.MaxPool2d):
    """nn.MaxPool2d that, without autograd (inference), pools a channels-last copy of its input: the same values
    (a maximum does not depend on the memory layout; returned contiguous, so the layers after it run as before) about
    4x faster on a CPU, whose NCHW max-pool kernel is slow (1x64x56x160: 4.2 ms against 0.8 ms on one thread,
    benchmarks/RESULTS.md). With autograd on (training) it is nn.MaxPool2d itself, so gradients are untouched."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if torch.is_grad_enabled() or self.return_indices or x.ndim != 4 or x.device.type != "cpu":
            return super().forward(x)
        pooled = F.max_pool2d(x.contiguous(memory_format=torch.channels_last), self.kernel_size, self.stride,
                              self.padding, self.dilation, ceil_mode=self.ceil_mode)
        return pooled.contiguous()


def _pool_channels_last(net: nn.Module) -> None:
    """Every nn.MaxPool2d of `net` becomes a ChannelsLastMaxPool2d of the same settings (no weights: the state
    dict's keys do not change)."""
    for parent in net.modules():
        for child_name, child in parent.named_children():
            if type(child) is nn.MaxPool2d:
                setattr(parent, child_name, ChannelsLastMaxPool2d(
                    child.kernel_size, child.stride, child.padding, child.dilation, child.return_indices,
                    child.ceil_mode))


def _read_state_dict(path: Path) -> dict[str, torch.Tensor]:
    """Read a state dict file: a plain dict of tensors or one wrapped under a key of WEIGHT_KEYS."""
    obj = load_checkpoint_file(path, "backbone.checkpoint")
    state = weights_in(obj)
    if state is None:
        raise ValueError(f"backbone.checkpoint={path}: {what_it_holds(obj)}; expected a dict of tensors (a state "
                         f"dict), or one under {' / '.join(repr(k) for k in WEIGHT_KEYS)}")
    return state


def _normalise_keys(state: dict[str, torch.Tensor], wanted: set[str]) -> dict[str, torch.Tensor]:
    """Strip wrapper prefixes and map torchvision/timm names onto the features-only layout."""
    changed = True
    while changed and state:
        changed = False
        for prefix in _WRAPPER_PREFIXES:
            if all(k.startswith(prefix) for k in state) and not any(k.startswith(prefix) for k in wanted):
                state = {k[len(prefix):]: v for k, v in state.items()}
                changed = True
    # a whole-detector checkpoint: keep the backbone part only
    if not any(k in wanted for k in state):
        for prefix in _WRAPPER_PREFIXES:
            sub = {k[len(prefix):]: v for k, v in state.items() if k.startswith(prefix)}
            if any(k in wanted for k in sub):
                state = sub
                break
    out = {}
    for k, v in state.items():
        if k not in wanted:
            alt = re.sub(r"^features\.(\d+)\.", r"features_\1.", k)  # timm flattens vgg's Sequential
            if alt in wanted:
                k = alt
        out[k] = v
    return out


def load_backbone_checkpoint(backbone: nn.Module, path: str | Path) -> None:
    """Load a local state dict into ``backbone``; classifier keys and pruned stages are ignored."""
    path = Path(path)
    name = getattr(backbone, "backbone_name", type(backbone).__name__)
    model_state = backbone.state_dict()
    wanted = set(model_state)
    state = _normalise_keys(_read_state_dict(path), wanted)
    present_modules = {k.split(".")[0] for k in wanted}
    unexpected = [
        k for k in state
        if k not in wanted and not _HEAD_KEY.match(k) and k.split(".")[0] in present_modules
    ]
    missing = [k for k in model_state if k not in state and not k.endswith("num_batches_tracked")]
    if missing or unexpected:
        raise ValueError(
            f"backbone checkpoint {str(path)!r} does not fit {name}: "
            f"{len(missing)} missing keys (first: {missing[:5]}), "
            f"{len(unexpected)} unexpected keys (first: {unexpected[:5]})"
        )
    bad_shapes = [
        f"{k}: file {tuple(state[k].shape)} vs model {tuple(model_state[k].shape)}"
        for k in model_state if k in state and state[k].shape != model_state[k].shape
    ]
    if bad_shapes:
        raise ValueError(f"backbone checkpoint {str(path)!r}: shape mismatch, first: {bad_shapes[:3]}")
    backbone.load_state_dict({k: v for k, v in state.items() if k in wanted}, strict=False)
