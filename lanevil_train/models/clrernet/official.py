"""The published CLRerNet checkpoints (hirotomusiker/CLRerNet): recognised, checked and converted.

The files (README at 21761ed: ``clrernet_culane_dla34.pth`` and ``clrernet_culane_dla34_ema.pth``, release v0.1.0)
are mmdetection's: ``{'meta': ..., 'state_dict': ...}`` (an ``'optimizer'`` too when the training saved one), keys
without a ``module.`` prefix, the network's three parts ``backbone.``, ``neck.``, ``bbox_head.`` (mmdet's
SingleStageDetector, libs/models/detectors/clrernet.py:5-20). Key names and shapes (the facts:
models/clrernet/__init__.py):

- ``backbone.model.*``: the DLA-34 of CLRNet's code (DLANet.model, libs/models/backbones/dla.py:404-424), timm's
  names; it builds a ``project`` only in one-level trees (l. 247-253), as timm does, so every key loads
  (``backbone=dla34``); a ResNet under ``backbone.model.`` (CLRNet's wrapper names) would load as CLRNet's does;
- ``neck.lateral_convs.<i>.conv``, ``neck.fpn_convs.<i>.conv``: CLRerNetFPN's ConvModules without norm
  (libs/models/necks/clrernet_fpn.py:36-58), CLRNet's layout: renamed by ``clrnet.official.backbone_neck_name``;
- ``bbox_head.sample_x_indices`` (36,), ``bbox_head.prior_feat_ys`` (36,), ``bbox_head.prior_ys`` (72,): buffers
  (clrernet_head.py:66-82), checked here, not loaded;
- ``bbox_head.anchor_generator.prior_embeddings.weight`` (192, 3) [y0, x0, theta], y0 the start's height from the
  TOP as a fraction of H (anchor_generator.py:28, 81-92): ours is start_y = 1 - y0; its forward adds reg[0] to y0
  (clrernet_head.py:225), so ours adds -reg[0]: row 0 of ``bbox_head.reg_layers`` (weight (76, 64), bias (76,)) is
  negated;
- ``bbox_head.attention.{convs,catconv}.<i>.{conv,bn}``, ``.fc``, ``.fc_norm`` and
  ``bbox_head.attention.attention.{f_key.{conv,bn},f_query.0,f_value,W}`` (libs/models/layers/attentions.py:42-72,
  166-198): CLRNet's ROIGather one level deeper, renamed through ``clrnet.official.head_name``;
- ``bbox_head.{cls,reg}_modules.{0,2}``, ``cls_layers`` (2, 64), ``reg_layers`` (76, 64): CLRNet's names;
- training only: ``bbox_head.seg_decoder.conv`` (5 classes, clrernet_head.py:101-109) and the loss's buffer
  ``bbox_head.loss_seg.criterion.weight`` (libs/models/losses/seg_loss.py:8-14). The published file has neither:
  loading it into the official training code reports exactly those three keys missing (hirotomusiker/CLRerNet issue
  #35); the decoder loads where the file has it (optional), the criterion weight is dropped;
- ``ema_*``: buffers mmdet 2.x's EMA hook registers on the model (BaseEMAHook: "the original model parameters are
  actually saved in ema field after train", mmdet/core/hook/ema.py), so a file saved by it has the EMA weights as its
  parameters: dropped if present (the EMA release may or may not carry them).

Unlike CLRNet's files, no priors are stored: the head derives them from the embeddings at every forward, so the file
cannot tell the input size; the rows must span the height (``model.head.row_span=height``, as the official's
anchors, anchor_generator.py:91) and the ROI layout is CLRerNetHead's own (``official_sampling``).
"""

from __future__ import annotations

import torch

from lanevil_train.models.clrernet.head import official_sampling
from lanevil_train.models.clrnet.official import backbone_name, backbone_neck_name, head_name, unused_projections
from lanevil_train.models.release import Recognised, Release

HEAD = "bbox_head."
EMBEDDINGS = "anchor_generator.prior_embeddings.weight"
# the published release's settings (configs/clrernet/base_clrernet.py:22-33)
PUBLISHED = {"num_priors": 192, "num_points": 72, "refine_layers": 3, "sample_points": 36}
_WORDS = {"num_priors": "priors", "num_points": "points", "refine_layers": "refinement stages",
          "sample_points": "sampled rows"}
# segmentation classes -> dataset: CULane's 4 lanes + background (base_clrernet.py:45); the CurveLanes draft branch's
# 1 + 1 (feature/curvelanes configs/clrernet/curvelanes/clrernet_curvelanes_dla34.py:30-33)
DATASETS = {5: "culane", 2: "curvelanes"}
DERIVED = ("sample_x_indices", "prior_feat_ys", "prior_ys", "loss_seg.criterion.weight")  # checked or dropped
# the head's parts under bbox_head. (clrernet_head.py:44-109)
_HEAD_PARTS = ("attention.", "cls_modules.", "reg_modules.", "cls_layers.", "reg_layers.", "seg_decoder.")
_REQUIRED = {HEAD + EMBEDDINGS, HEAD + "reg_layers.weight", HEAD + "attention.fc.weight"}


def _fits_layout(key: str) -> bool:
    """Whether a key is a name of CLRerNet's checkpoint layout (the module docstring)."""
    if key.startswith("ema_") or backbone_neck_name(key) is not None:
        return True
    rest = key[len(HEAD):] if key.startswith(HEAD) else None
    return rest is not None and (rest in DERIVED or rest == EMBEDDINGS or rest.startswith(_HEAD_PARTS))


def layout_difference(state: dict) -> str | None:
    """None for a state dict in CLRerNet's layout, else its first key (in the file's order) that is not."""
    key = next((k for k in state if not _fits_layout(k)), None)
    if key is None:
        return None
    return (f"its first key that differs from CLRerNet's layout is {key} (CLRerNet's head is {HEAD}*: "
            f"{HEAD}sample_x_indices, {HEAD}{EMBEDDINGS}, {HEAD}attention.*, {HEAD}reg_layers.*, ...)")


def _settings(state: dict) -> dict[str, int]:
    fc = state[HEAD + "attention.fc.weight"]  # (C, sample_points x C)
    stages = {k[len(HEAD + "attention.catconv."):].split(".")[0] for k in state
              if k.startswith(HEAD + "attention.catconv.")}
    return {"num_priors": state[HEAD + EMBEDDINGS].shape[0],
            "num_points": state[HEAD + "reg_layers.weight"].shape[0] - 4,
            "refine_layers": len(stages), "sample_points": fc.shape[1] // fc.shape[0]}


def describe(state: dict) -> Recognised | None:
    """What a CLRerNet state dict is (dataset where its segmentation decoder tells it, backbone, head settings), or
    None if it is not one."""
    if not _REQUIRED <= state.keys():
        return None
    settings = _settings(state)
    shapes = ", ".join(f"{v} {_WORDS[k]}" for k, v in settings.items())
    decoder = state.get(HEAD + "seg_decoder.conv.weight")
    classes = None if decoder is None else int(decoder.shape[0])
    dataset = "culane" if classes is None else DATASETS.get(classes, "an unpublished dataset")
    release = (f"the {dataset} release" if dataset in DATASETS.values() else dataset) + \
        (" (no segmentation decoder: the published CULane files)" if classes is None else "")
    backbone = backbone_name(state)
    if backbone is None:
        first = next((k for k in state if k.startswith("backbone.")), "no backbone key")
        return Recognised(f"{release}, an unknown backbone: {shapes}", "",
                          unsupported=f"its backbone (first key {first}) is none this project builds: the published "
                                      f"CLRerNet files are DLA-34 (backbone.model.base_layer..level5, backbone=dla34, "
                                      f"timm's dla34)")
    experiment = dataset if dataset in DATASETS.values() else "<culane|curvelanes>"
    config = [f"experiment=official_clrernet_{experiment}", f"backbone={backbone}"]
    config += [f"model.head.{k}={v}" for k, v in settings.items() if v != PUBLISHED[k]]
    return Recognised(f"{release}, {backbone}: {shapes}", " ".join(config))


def _official_head_name(rest: str) -> str:
    """A name under bbox_head. (not the embeddings or reg_layers) -> ours, through CLRNet's official names."""
    for old in ("attention.attention.", "attention."):
        if rest.startswith(old):
            return head_name("roi_gather." + rest[len(old):])
    return head_name(rest)


def convert(state: dict) -> dict:
    """Official names -> this project's (the module docstring): y0 -> 1 - y0 in the embeddings and reg_layers' row 0
    negated; the derived buffers (checked by ``check``), the criterion weight and any ema_* copies dropped. A state
    dict of another layout is refused naming its first key that differs."""
    difference = layout_difference(state)
    if difference is not None:
        raise ValueError(f"not a CLRerNet state dict: {difference}")
    dropped = unused_projections(state)
    out = {}
    for key, value in state.items():
        if key in dropped or key.startswith("ema_"):
            continue
        name = backbone_neck_name(key)
        if name is not None:
            out[name] = value
            continue
        rest = key[len(HEAD):]
        if rest in DERIVED:
            continue
        if rest == EMBEDDINGS:
            out["head.prior_embeddings"] = torch.cat([1.0 - value[:, :1], value[:, 1:]], dim=1)
        elif rest.startswith("reg_layers."):
            flipped = value.clone()
            flipped[0] = -flipped[0]
            out["head.reg_layer." + rest[len("reg_layers."):]] = flipped
        else:
            out[_official_head_name(rest)] = value
    return out


def check(model, state: dict) -> str | None:
    """The official buffers against this network's rows and ROI sampling, and the row span its anchors need: None
    when they agree (or the shapes differ: the strict load then names the weight), else what differs and the
    setting that would fit."""
    head = getattr(model, "head", None)
    if head is None or not hasattr(head, "laneiou"):
        return None
    if head.row_span != head.image_size[0]:
        return ("its anchors span the input's height (anchor_generator.py:91): give model.head.row_span=height "
                "(experiment=official_clrernet_culane)")
    index = state.get(HEAD + "sample_x_indices")
    ours, grid_y = official_sampling(head.n_points, int(head.sample_index.numel()))
    if index is not None and (index.shape != ours.shape or not torch.equal(index.long().cpu(), ours)):
        return (f"its {HEAD}sample_x_indices {index.tolist()} are not the rows this head samples ({ours.tolist()}): "
                f"model.head.sample_points must be {index.numel()}")
    feat_ys = state.get(HEAD + "prior_feat_ys")
    if feat_ys is not None and (feat_ys.shape != grid_y.shape or
                                not torch.allclose(feat_ys.float().cpu() * 2 - 1, grid_y, atol=1e-6)):
        return f"its {HEAD}prior_feat_ys are not flip(sample_x_indices / n_strips): not a file the official code wrote"
    rows = state.get(HEAD + "prior_ys")
    if rows is not None and (rows.shape != head.fractions.shape or
                             not torch.allclose(rows.float().cpu(), 1.0 - head.fractions.cpu(), atol=1e-6)):
        return f"its {HEAD}prior_ys are not linspace(1, 0, num_points): not a file the official code wrote"
    return None


RELEASE = Release(family="clrernet", name="CLRerNet (hirotomusiker/CLRerNet)", describe=describe, convert=convert,
                  optional=("head.seg_decoder.",), check=check, difference=layout_difference)
