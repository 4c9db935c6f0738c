"""The published CLRNet checkpoints (Turoad/CLRNet, read at 7269e9d): recognised, checked and converted.

Facts of the official code this conversion rests on (files under ``clrnet/`` unless named; line numbers at 7269e9d):

- The file: ``utils/net_utils.py`` l. 8-20 saves ``{'net': state_dict, 'optim', 'scheduler', 'recorder': {'step'},
  'epoch'}``; the network is wrapped in MMDataParallel (``engine/runner.py`` l. 28-29), so every key starts with
  ``module.``; ``load_network`` (l. 36-43) loads ``['net']`` non-strictly.
- ``models/nets/detector.py`` l. 13-16, 28-34: ``backbone``, ``neck``, ``heads`` (plural), applied in that order.
- ``models/backbones/resnet.py``: ``ResNetWrapper`` holds the ResNet as ``model`` (l. 165-168; ``out_conv`` False in
  every config), torchvision's names (``conv1``, ``bn1``, ``layer1``-``layer4``; l. 213-240, no fc), its forward
  returning the four stages' maps (l. 294-308). ``dla34.py``: ``DLAWrapper.model`` (l. 415-432), ``base_layer``,
  ``level0``-``level5`` (l. 291-333), returning levels 2-5 (l. 380-386); a ``Tree`` of more than one level builds a
  ``project`` its forward never uses (l. 250-262 build it, l. 264-277 pass it to ``tree1``, which then computes
  its own).
- ``models/necks/fpn.py``: mmcv ConvModules ``lateral_convs.<i>`` (1x1) and ``fpn_convs.<i>`` (3x3), built with
  ``norm_cfg=None, act_cfg=None`` (l. 68-90): a biased conv under the attribute ``conv``, no activation. With four
  input maps for three ``in_channels`` the first is dropped (l. 113-117: ResNet layer2-layer4, DLA levels 3-5);
  top-down nearest upsampling to the finer map's size, added (l. 127-137); one 3x3 conv per level (l. 141-143).
- ``models/heads/clr_head.py`` (``CLRHead``):
  - buffers ``sample_x_indexs`` = (linspace(0, 1, sample_points) x n_strips).long() (l. 44-46), ``prior_feat_ys``
    = flip(1 - sample_x_indexs / n_strips) (l. 47-48), ``prior_ys`` = linspace(1, 0, num_points) (l. 49-52),
    ``priors`` (P, 6 + S) and ``priors_on_featmap`` (P, sample_points) (l. 56-59, 125-144);
  - ``prior_embeddings`` an ``nn.Embedding(num_priors, 3)`` [start_y, start_x, theta] (l. 146-178);
  - a prior's x at the S rows, as a fraction of W-1: (start_x (W-1) + (1 - prior_ys - start_y) img_h /
    tan(theta pi + 1e-5)) / (W-1) (l. 133-139, again l. 245-249): the rows span img_h pixels, the bottom one at
    y = img_h (``prior_ys`` x img_h; the targets too: ``datasets/process/generate_lane_line.py`` l. 21-23);
  - in training every forward recomputes ``priors`` and ``priors_on_featmap`` from the embeddings and stores them
    in the buffers (l. 195-196); in eval the forward reads the buffers (l. 198-200), never the embeddings. A saved
    file's buffers are those of its last training forward; its embeddings are one optimizer step newer;
  - ``seg_decoder`` (``models/utils/seg_decoder.py`` l. 16-28: Dropout2d(0.1), ``conv`` 1x1 from 64 x refine_layers
    to ``num_classes``, bilinear to the input), training only (l. 260-275);
  - ``criterion`` = NLLLoss(weight) (l. 84-87): its ``weight`` (num_classes: bg_weight, then ones) is a buffer;
  - ``cls_modules`` / ``reg_modules``: num_fc x (Linear, ReLU) in a ModuleList (l. 67-73; indices 0, 2),
    ``cls_layers`` Linear(64, 2), ``reg_layers`` Linear(64, S + 4) [start_y, start_x, theta, length, S offsets]
    (l. 79-82);
  - forward (l. 181-277): the last refine_layers maps, coarsest first (l. 191-192); per stage the priors' x at the
    sampled rows flipped top row first (l. 208) and sampled by grid_sample(align_corners=True) into (B P, C,
    sample_points, 1) (l. 101-123); ROIGather; cls/reg; [start_y, start_x, theta] += reg[:3], length = reg[3]
    (l. 235-240); x recomputed from the refined line (l. 245-249) plus the offsets reg[4:] (l. 252); the refined line
    without offsets, detached, is the next stage's prior (l. 256-258). Eval returns the last stage only (l. 277):
    (B, P, 6 + S) [2 logits, start_y, start_x, theta, length, x / (W-1) at the S rows, bottom first].
- ``models/utils/roi_gather.py`` (``ROIGather``): ``f_key`` ConvModule 1x1 with BN and ReLU (l. 43-48; mmcv's
  ``bias='auto'``: no bias), ``f_query`` grouped Conv1d(P, P, 1) + ReLU (l. 50-58), ``f_value`` Conv2d 1x1 (l. 59-63),
  ``W`` grouped Conv1d (l. 64-69), both key and value resized to a fixed (10, 25) (l. 13-20, 71: nearest);
  ``convs.<i>`` ConvModule (9, 1) 64 -> 48 and ``catconv.<i>`` (9, 1) 48 (i + 1) -> 64, no bias, BN, ReLU
  (l. 75-90); ``fc`` Linear(sample_points x 64, 64), ``fc_norm`` LayerNorm (l. 92-94); every stage's pooled features
  through their own ``convs``, concatenated, ``catconv`` of the stage (l. 96-103); attention and a 0.1 dropout
  (l. 105-136).
- The configs (``configs/clrnet/clr_<backbone>_<dataset>.py``): num_points 72, num_priors 192, refine_layers 3,
  fc_hidden_dim 64, sample_points 36, FPN to 64 channels; 320x800 input after cutting the top cut_height rows:
  TuSimple 160 of 720 (``clr_resnet18_tusimple.py`` l. 47-51), max_lanes 5 (l. 12), num_classes 6 + 1 (l. 124);
  CULane 270 of 590 (``clr_resnet34_culane.py`` l. 47-51), max_lanes 4 (l. 12), num_classes 4 + 1 (l. 123); LLAMAS
  300 of 717, 4 + 1 classes (``clr_resnet18_llamas.py`` l. 12, 47-51, 123); test conf 0.4 and NMS 50 (TuSimple,
  CULane; l. 34), LLAMAS 0.45 and 60 (DLA-34: 50); ResNet-101's FPN reads [512, 1024, 2048]
  (``clr_resnet101_*.py`` l. 29). The README publishes ResNet-18/34/101 for CULane and TuSimple, DLA-34 for
  CULane, ResNet-18 and DLA-34 for LLAMAS.

Decoding, as the official test writes its prediction files (``CLRHead.get_lanes`` and ``predictions_to_pred`` in
``models/heads/clr_head.py``, ``Lane`` in ``utils/lane.py``, the writers in ``datasets/``):

- a prediction is kept when its softmax score is >= conf_threshold (clr_head.py:449-453); NMS reads the length x
  n_strips and the x x (img_w - 1) (l. 458-470); the kept ones' length is rounded in float32,
  ``torch.round(length x n_strips)`` (l. 477), half to even as Python's ``round`` of start_y x n_strips is (l. 288);
  the start is clamped to [0, n_strips] (l. 288-289), the end = start + length - 1 only above, at n_strips (l. 290-292);
- the x of the rows are the network's, fractions of img_w - 1 (the loss scales them by img_w - 1: l. 378-380);
  the rows below the start are kept while they and every row up to the start have x in [0, 1] (l. 296-297, 299),
  the rows from end + 1 on are dropped (l. 298: a Python slice, so a negative end + 1 counts from the top), and of the
  rest every row with x >= 0 is kept, with no upper bound: x past the right edge stays (l. 300-301); no border point
  is added;
- the rows' heights are the float32 ``prior_ys`` = linspace(1, 0, num_points) (l. 49-52), in double (l. 283-284),
  mapped to the original image as (prior_ys (ori_img_h - cut_height) + cut_height) / ori_img_h (l. 305-306): the
  bottom row at y = ori_img_h; a lane of fewer than two points is dropped (l. 307-308); the ``Lane`` is built from
  (x, y) normalised so (l. 309-312);
- ``Lane`` (lane.py:11-16, 23-28): scipy's InterpolatedUnivariateSpline of x over y, k = min(3, points - 1), valid
  from its lowest y - 0.01 to its highest + 0.01 (normalised: 1 % of the original height), -2 beyond;
- TuSimple (datasets/tusimple.py:28, 63-71): the Lane at h_samples 160, 170, ..., 710 over ori_img_h, -2 where x < 0,
  else ``(x x ori_img_w).astype(int)`` (truncated): x past the right edge written. The x the official writes is the
  network's fraction of img_w - 1 times the original width (not x (img_w - 1) x ori_w / img_w): 1.6 px more at the
  right edge of 1280, 2 px at 1640;
- CULane (datasets/culane.py:96-112): the Lane at rows np.arange(270, 590, 8) over ori_img_h, only 0 <= x < 1 kept,
  x x ori_img_w and y x ori_img_h written ``'{:.5f} {:.5f}'``, the bottom point first, lanes with no point left out;
- LLAMAS (datasets/llamas.py:145-161) reads the same Lane at rows np.arange(300, 717) over ori_img_h - 1 and writes
  x x (ori_img_w - 1), y x (ori_img_h - 1): official_clrnet_llamas reads it at those rows (model.culane_rows), not
  with that scale (not matched: x up to ~1-2 px apart);
- the TuSimple config cuts 160 of 720 rows and resizes to 320x800 (configs/clrnet/clr_resnet18_tusimple.py:47-51):
  ``data.crop_top`` 0.2222222 gives the same 160 rows, and LaneDetector.decode_lanes maps input y as
  y (720 - 160) / 320 + 160, so the decoding's y = prior_ys x 320 land on the official's rows exactly.

``model.decode.lane_points: official`` decodes so (head.py, codec.py ``official_rows``, ``official_kept_rows``): x
given as the fraction x img_w and y as prior_ys x img_h, which decode_lanes maps to the official writers' pixels.

This project's CLRNet keeps the layers under other names (``head.roi_gather.{convs,catconvs}.<i>.{0,1}`` = the
ConvModules' ``conv``/``bn``, ``head.cls_fc``/``reg_fc`` = ``cls_modules``/``reg_modules``, ``head.cls_layer``/
``reg_layer``, ``neck.lateral``/``output`` = ``lateral_convs``/``fpn_convs``, ``head.seg_decoder.1`` = its ``conv``),
the same feature, ROI and output layouts, and timm's ResNet and DLA-34 the official names: the conversion renames.
The priors the official evaluation reads, ``priors[:, 2:5]``, become ``head.prior_embeddings`` (a Parameter), so
our forward, which derives the priors from it, computes the official eval forward; ``heads.prior_embeddings.weight``
(one step newer) is not used. The derived buffers are checked against this network's (``check``): the rows, the
sampled rows, and the priors' x, which also tells the row span (``model.head.row_span: height``) and the input's
height to width - 1 ratio. ``criterion.weight`` and the never-used DLA projections are dropped; the
segmentation decoder is optional (training only).
"""

from __future__ import annotations

import re

import torch

from lanevil_train.models.clrnet.priors import line_xs
from lanevil_train.models.release import Recognised, Release, resnet_depth

# The published releases' settings, as the configs set them (the file's shapes tell the rest)
PUBLISHED = {"num_priors": 192, "num_points": 72, "refine_layers": 3, "sample_points": 36}
_WORDS = {"num_priors": "priors", "num_points": "points", "refine_layers": "refinement stages",
          "sample_points": "sampled rows"}
# num_classes of the segmentation decoder (and criterion weight) -> the dataset: 6 + 1 TuSimple, 4 + 1 CULane (and
# LLAMAS, whose shapes are CULane's: its files load with experiment=official_clrnet_llamas; the shapes cannot tell)
DATASETS = {7: "tusimple", 5: "culane"}
# buffers the official head derives from its settings and the embeddings: checked here, not loaded
DERIVED = ("sample_x_indexs", "prior_feat_ys", "prior_ys", "priors", "priors_on_featmap", "criterion.weight")
_CONV_MODULE = {"conv": "0", "bn": "1"}  # mmcv ConvModule attributes -> our Sequential(conv, bn, relu) indices
_HEAD_RENAMES = (("cls_modules.", "cls_fc."), ("reg_modules.", "reg_fc."), ("cls_layers.", "cls_layer."),
                 ("reg_layers.", "reg_layer."), ("seg_decoder.conv.", "seg_decoder.1."))


def backbone_name(state: dict) -> str | None:
    """resnet<depth> or dla34 from the backbone's keys (``backbone.model.``), or None."""
    if any(k.startswith("backbone.model.level5.") for k in state):
        return "dla34" if state.get("backbone.model.base_layer.0.weight", torch.empty(0)).shape[:1] == (16,) else None
    depth = resnet_depth(state, [f"backbone.model.layer{i}." for i in range(1, 5)])
    return f"resnet{depth}" if depth else None


def _settings(state: dict) -> dict[str, int]:
    """The head's settings its shapes tell: num_priors, num_points, refine_layers, sample_points."""
    fc = state["heads.roi_gather.fc.weight"]  # (C, sample_points x C)
    return {"num_priors": state["heads.prior_embeddings.weight"].shape[0],
            "num_points": state["heads.reg_layers.weight"].shape[0] - 4,
            "refine_layers": len({k.split(".")[3] for k in state if k.startswith("heads.roi_gather.catconv.")}),
            "sample_points": fc.shape[1] // fc.shape[0]}


def _num_classes(state: dict) -> int | None:
    for key in ("heads.seg_decoder.conv.weight", "heads.criterion.weight"):
        if key in state:
            return int(state[key].shape[0])
    return None


def describe(state: dict) -> Recognised | None:
    """What a CLRNet state dict is (dataset where its segmentation classes tell it, backbone, head settings), or
    None if it is not one."""
    if not {"heads.prior_embeddings.weight", "heads.priors", "heads.reg_layers.weight",
            "heads.roi_gather.fc.weight"} <= state.keys():
        return None
    backbone = backbone_name(state)
    settings = _settings(state)
    classes = _num_classes(state)
    dataset = DATASETS.get(classes)
    if dataset == "culane":
        release = "the culane release (or LLAMAS', of the same shapes)"
    elif dataset:
        release = f"the {dataset} release"
    elif classes:
        release = f"an unpublished dataset ({classes - 1} segmentation lanes)"
    else:
        release = "no segmentation decoder to tell the dataset"
    shapes = ", ".join(f"{v} {_WORDS[k]}" for k, v in settings.items())
    config = [f"experiment=official_clrnet_{dataset or '<tusimple|culane>'}",
              f"backbone={backbone or '<its backbone>'}"]
    config += [f"model.head.{k}={v}" for k, v in settings.items() if v != PUBLISHED[k]]
    if classes and not dataset:
        config.append(f"model.head.seg_lanes={classes - 1}")
    return Recognised(f"{release}, {backbone or 'an unknown backbone'}: {shapes}", " ".join(config))


def unused_projections(state: dict) -> set[str]:
    """The ``project`` keys of the DLA trees of more than one level (built, never used: dla34.py l. 250-277): a
    tree whose ``tree1`` is itself a tree."""
    nodes = {key.split(".project.")[0] for key in state if key.startswith("backbone.model.") and ".project." in key}
    deep = {node for node in nodes if any(k.startswith(node + ".tree1.tree1.") for k in state)}
    return {k for k in state for node in deep if k.startswith(node + ".project.")}


def head_name(rest: str) -> str:
    """A name under ``heads.`` -> ours under ``head.``."""
    match = re.match(r"roi_gather\.(convs|catconv|f_key)\.(?:(\d+)\.)?(conv|bn)\.(.+)", rest)
    if match:
        module, index, part, tail = match.groups()
        module = "catconvs" if module == "catconv" else module
        index = f"{index}." if index is not None else ""
        return f"head.roi_gather.{module}.{index}{_CONV_MODULE[part]}.{tail}"
    for old, new in _HEAD_RENAMES:
        if rest.startswith(old):
            return "head." + new + rest[len(old):]
    return "head." + rest


def backbone_neck_name(key: str) -> str | None:
    """This project's name of an official backbone or neck key (CLRNet's layout, which CLRerNet keeps: the backbone
    under ``backbone.model.`` in timm's names, the FPN's ConvModules ``lateral_convs.<i>.conv`` and
    ``fpn_convs.<i>.conv``), or None for a key of neither. A norm the published FPN has not keeps its name (the
    strict load reports it)."""
    if key.startswith("backbone.model."):
        return "backbone." + key[len("backbone.model."):]
    if key.startswith(("neck.lateral_convs.", "neck.fpn_convs.")) and key.count(".") >= 4:
        _, group, index, part, tail = key.split(".", 4)
        if part != "conv":
            return key
        return f"neck.{'lateral' if group == 'lateral_convs' else 'output'}.{index}.{tail}"
    return None


def convert(state: dict) -> dict:
    """Official names -> this project's; the evaluation's priors become the prior embeddings, the derived buffers
    (checked by ``check``), the unused embeddings, ``criterion.weight`` and the unused DLA projections dropped."""
    dropped = unused_projections(state)
    out = {}
    for key, value in state.items():
        if key in dropped:
            continue
        name = backbone_neck_name(key)
        if name is not None:
            out[name] = value
        elif key == "heads.priors":
            out["head.prior_embeddings"] = value[:, 2:5].clone()
        elif key == "heads.prior_embeddings.weight" or (key.startswith("heads.") and key[len("heads."):] in DERIVED):
            continue
        elif key.startswith("heads."):
            out[head_name(key[len("heads."):])] = value
        else:
            out[key] = value  # reported by the strict load as unexpected
    return out


def check(model, state: dict) -> str | None:
    """The buffers the official head derives, against this network's: None when they agree (or when the shapes
    differ: the strict load then names the weight), else what differs and the setting that would fit."""
    head = getattr(model, "head", None)
    priors = state.get("heads.priors")
    if head is None or not hasattr(head, "row_span") or priors is None or priors.ndim != 2 \
            or priors.shape[0] != head.num_priors or priors.shape[1] != 6 + head.n_points:
        return None
    index = state.get("heads.sample_x_indexs")
    ours = head.sample_index.flip(0).cpu()
    if index is not None and (index.shape != ours.shape or not torch.equal(index.long().cpu(), ours)):
        return (f"its heads.sample_x_indexs {index.tolist()} are not the rows this head samples ({ours.tolist()}): "
                f"model.head.sample_points must be {index.numel()}")
    on_featmap = state.get("heads.priors_on_featmap")
    if on_featmap is not None and index is not None and not torch.allclose(
            on_featmap.float(), priors[:, 6 + index.long()].float(), rtol=1e-5, atol=1e-5):
        return ("its heads.priors_on_featmap are not its priors' x at its sampled rows: not a file the official "
                "code wrote")
    rows = state.get("heads.prior_ys")
    if rows is not None and not torch.allclose(rows.float().cpu(), 1.0 - head.fractions.cpu(), atol=1e-6):
        return "its heads.prior_ys are not linspace(1, 0, num_points): not a file the official code wrote"
    lines = priors[:, 2:5].double().cpu()
    want = line_xs(lines, head.fractions.double().cpu(), head.image_size, head.row_span)
    if not torch.allclose(priors[:, 6:].double().cpu(), want, rtol=1e-4, atol=1e-4):
        h, w = head.image_size
        return (f"its priors' x (heads.priors[:, 6:]) are not those of its lines for this run's {h}x{w} input and "
                f"model.head.row_span={'height' if head.row_span == h else 'last_pixel'}: the official draws them "
                f"over img_h pixels for its 320x800 input; give data.input_size=[320, 800] and "
                f"model.head.row_span=height (experiment=official_clrnet_<dataset>)")
    return None


RELEASE = Release(family="clrnet", name="CLRNet (Turoad/CLRNet)", describe=describe, convert=convert,
                  optional=("head.seg_decoder.",), check=check)
