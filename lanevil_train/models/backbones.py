"""Backbone factory: timm ``features_only`` networks that return a list of feature maps.

The returned module is timm's own, with ``.channels`` and ``.strides`` (from feature_info) added.

Only ``pretrained=True`` may touch the network (timm's hub download); the default is random
init, and ``checkpoint=path`` loads a local state dict (timm / torchvision / our own layout).
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Sequence

import timm
import torch
from torch import nn

from lanevil_train.checkpoints import load_checkpoint_file

# The stride of each feature stage timm's features_only backbones return (index = an out_indices entry);
# tests check it against timm. Config checks read it to validate out_indices and the input size.
_RESNET_STRIDES = (2, 4, 8, 16, 32)
STAGE_STRIDES: dict[str, tuple[int, ...]] = {"resnet18": _RESNET_STRIDES, "resnet34": _RESNET_STRIDES,
                                             "resnet50": _RESNET_STRIDES, "resnet101": _RESNET_STRIDES,
                                             "vgg16": (1, 2, 4, 8, 16, 32)}
SUPPORTED_BACKBONES: tuple[str, ...] = tuple(STAGE_STRIDES)

# Prefixes that wrappers put in front of backbone keys (DataParallel, Lightning, our detector).
_WRAPPER_PREFIXES = ("module.", "model.", "backbone.", "encoder.", "body.", "net.")
# Classifier keys of ImageNet checkpoints that a features-only network does not have.
_HEAD_KEY = re.compile(r"^(fc|head|classifier|pre_logits|last_linear)\.")


def build_backbone(
    name: str,
    pretrained: bool = False,
    checkpoint: str | None = None,
    out_indices: Sequence[int] = (4,),
) -> nn.Module:
    """Build a timm features-only backbone; weights random, hub (``pretrained``) or a local file.

    ``out_indices`` are timm's: (4,) is layer4 (stride 32) for ResNets and conv5_3 (stride 16)
    for vgg16 (whose index 5 is the stride-32 max-pool).
    """
    if name not in SUPPORTED_BACKBONES:
        raise ValueError(f"unknown backbone {name!r}; supported: {', '.join(SUPPORTED_BACKBONES)}")
    if pretrained and checkpoint is not None:
        raise ValueError("build_backbone: give either pretrained=True or checkpoint=..., not both")
    net = timm.create_model(name, pretrained=pretrained, features_only=True, out_indices=tuple(out_indices))
    # the timm module itself (so hooks address e.g. "backbone.layer4"), plus our two attributes
    backbone = net
    backbone.backbone_name = name
    backbone.channels = list(net.feature_info.channels())
    backbone.strides = list(net.feature_info.reduction())
    if checkpoint is not None:
        load_backbone_checkpoint(backbone, checkpoint)
    return backbone


def _read_state_dict(path: Path) -> dict[str, torch.Tensor]:
    """Read a state dict file: a plain dict of tensors or one wrapped as {"state_dict": ...}."""
    obj = load_checkpoint_file(path, "backbone.checkpoint")
    for key in ("state_dict", "model", "model_state_dict"):
        if isinstance(obj, dict) and key in obj and isinstance(obj[key], dict):
            obj = obj[key]
            break
    if not isinstance(obj, dict) or not all(isinstance(v, torch.Tensor) for v in obj.values()):
        raise ValueError(f"backbone.checkpoint={path}: expected a dict of tensors (a state dict), or one under "
                         f"'state_dict' / 'model' / 'model_state_dict'")
    return dict(obj)


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
