"""The published GANet checkpoints (Wolfwjs/GANet, read at 8685a61, the master branch the April 2022 files were
trained with; its mmdet2_25 branch links the same files): recognised and converted.

Facts of the official code this conversion rests on (paths in that repository):

- Saving: mmcv 0.5.6 (``requirements/build.txt`` l. 5), whose ``save_checkpoint`` writes ``{'meta',
  'state_dict', 'optimizer'}``: ``meta`` plain values (its version and time; ``tools/train.py`` l. 142-148 adds
  ``mmdet_version``, the config text, ``CLASSES``), ``state_dict`` the detector's (a DataParallel wrapper removed:
  no ``module.``). ``tools/ganet/tusimple/test_dataset.py`` l. 268 (``culane/`` l. 279) loads it with mmcv's
  ``load_checkpoint`` (non-strict). Such a file has a 'state_dict' key and none of this project's
  ('lanevil_model', 'pytorch-lightning_version', 'hyper_parameters'): ``models/official.py`` reads it as official.
- The detector (``mmdet/models/detectors/ganet.py`` l. 19-41, ``single_stage.py`` l. 23-28): ``backbone``,
  ``neck``, ``bbox_head``; test-time forward l. 107-124 / 126-136: backbone, neck, head.
- ``backbone``: mmdet's ``ResNet`` (``backbones/resnet.py``; configs l. 59-68: depth 18/34/101, ``out_indices``
  (0, 1, 2, 3), ``style='pytorch'``: a Bottleneck's stride on its 3x3 conv, l. 138-140): torchvision's names
  (``conv1``, ``bn1``, ``layer<i>.<j>.conv<k>``/``bn<k>``, ``downsample.0/1``; ``utils/res_layer.py`` l. 34-56),
  no ``fc``; C2..C5.
- ``neck``: ``DeformFPN`` (``necks/dcn_fpn.py``; configs l. 69-86):
  - more backbone maps than ``in_channels`` drop the first (l. 316-317): the stride-8 releases read C3, C4, C5
    (``in_channels=[128, 256, 512]``), the ResNet-101 release C2..C5 (``[256, 512, 1024, 2048]``);
  - ``trans_head`` (``TransConvEncoderModule`` l. 135-168) on the last map, which it replaces (l. 319-322;
    ``in_channels[-1] = attn_out_dims[-1]``, l. 252-255): ``attn_layers.<i>`` = ``AttentionLayer`` (l. 74-132):
    ``pre_conv`` (mmcv ConvModule: 3x3 conv without bias, ``bn``, ReLU; keys ``pre_conv.conv``, ``pre_conv.bn``),
    ``query_conv`` / ``key_conv`` (1x1 to out / ratio, bias), ``value_conv`` (1x1, bias), ``gamma`` (1,),
    ``final_conv`` (as pre_conv). Forward (l. 115-131): x = pre_conv(x); x = x + pos; attention of every position
    over all (energy = q^T k, softmax over the keys, out = v attn^T); final_conv(gamma * out + x). ``attn_in_dims``
    / ``attn_out_dims`` (configs l. 80-81): ResNet-18/34 [512, 64] / [64, 64], ResNet-101 [2048, 256] / [256, 256];
    ratios [4, 4], strides [1, 1];
  - ``pos`` (l. 20-71, 152-158): DETR's sine embedding, ``num_pos_feats = dim // 2``, temperature 10000, not
    normalised: positions counted from 1 (cumsum of ones, l. 43-45), dim_t = T^(2 (i // 2) / n) (l. 51-53),
    sin on even and cos on odd channels interleaved (l. 57-62), y's channels then x's (l. 63); built once for
    ``pos_shape=(1, 10, 25)`` (configs l. 84: C5 of a 320x800 input), a plain list: not in the file;
  - ``lateral_convs.<i>.conv`` (ConvModule 1x1 with bias, no norm or activation, l. 277-284) to ``out_channels``
    64; top-down: ``laterals[i-1] += nearest(laterals[i])`` (l. 344-347);
  - ``def_convs.<i>`` = ``LanePointsConv`` (``dense_heads/lanepoints_conv.py``; l. 285-291: in 64, feat 256,
    point_feat 64, ``num_points = dcn_point_num[i]``: 7 at stride 8, 9 at stride 4) built for every level, run on
    level 0 only (``deconv_layer=[True, False, ...]``, ``deconv_before=False``: after the top-down sum, l.
    350-356); ``aux_feat`` = merged lateral 0 before it (l. 348-349);
  - ``fpn_convs.<i>.conv`` (3x3 with bias, l. 292-300) on every level (l. 361-363); the head reads level 0;
  - ``dcn_only_cls=True`` (configs l. 30): the output carries ``aux_feat`` (l. 365-370).
- ``LanePointsConv`` (l. 37-177): ``cls_convs.<j>.conv`` (``stacked_convs`` 3) and ``reg_convs.<j>.conv`` (always
  3, l. 92) ConvModules 3x3 with bias and ReLU (no norm); ``reppoints_pts_init_conv`` (3x3 256 -> 64) and
  ``reppoints_pts_init_out`` (1x1 64 -> 2K) give ``pts_out_init`` = init_out(relu(init_conv(reg_convs(x))))
  (l. 159-160); ``dcn_offset = pts_out_init - dcn_base_offset`` with ``dcn_base_offset`` the kernel's (y, x)
  pairs (0, -p) ... (0, p), p = (K - 1) / 2 (l. 62-74, 170); features = relu(``reppoints_cls_conv``(cls_convs(x),
  dcn_offset)) (l. 172). ``reppoints_pts_refine_conv`` / ``_out`` are built (l. 112-117) and never run.
  ``reppoints_cls_conv`` is ``DeformConv1D`` (``mmdet/ops/dcn/deform_conv.py`` l. 255-317): kernel (1, K),
  padding (0, p), weight (64, 256, 1, K), no bias. Its kernel (``mmdet/ops/dcn/src/cuda/deform_conv_cuda_kernel.cu``
  l. 222-231, 85-115), as torchvision's ``deform_conv2d``, reads offset channels 2k, 2k + 1 as (dy, dx) of kernel
  tap k and samples bilinearly, zero outside (-1, H) x (-1, W) and for corners off the map; tap k sits at (0, k - p)
  from the location, so with the base taken off it samples at location + (``pts_out_init[2k + 1]``,
  ``pts_out_init[2k]``): the K points are offsets (dx, dy) in feature cells from the location, stored (dy, dx).
- ``bbox_head``: ``GANetHeadFast`` (``dense_heads/ganet_head.py`` l. 79-126): ``centerpts_head``, ``keypts_head``
  (``hm``: 1 channel), ``offset_head``, ``reg_head`` (``offset_map``: 2 channels, ``joint_nums=1``), each a
  ``CtnetHead`` (``ctnet_head.py`` l. 36-58: attribute named by its output, Conv 3x3 64 -> 64 with bias, ReLU, Conv
  1x1 with bias: keys ``<head>.<name>.0`` / ``.2``). Forward (l. 240-263): the heatmaps from ``features[0]``
  (after LFA and fpn_conv), ``pts_offset`` (offset_head: to the lane's start point) and ``int_offset``
  (reg_head: the sub-cell error) from ``aux_feat``; channel 0 x, 1 y (``make_coordmat`` l. 40-50 adds them to
  (x, y)). Test (l. 283-291): ``kpts_hm = clamp(sigmoid, 1e-4, 1 - 1e-4)``; ``cpts_hm`` (the centre heatmap, loss
  weight 0 in every config, l. 22) is never decoded.
- Decoding (``ktdet_decode_fast`` l. 203-238, ``tools/ganet/post_process.py``, ``group_fast=True`` with
  ``cluster_by_center_thr``): keypoints = cells whose heatmap is its 1 x 3 row maximum and above ``kpt_thr``,
  ``align`` = cell + int_offset, ``root`` = cell + pts_offset (l. 228-236); start candidates = those cells whose
  y offset is below ``root_thr`` = 1 (l. 213-219, the cells themselves, ordered by x then y); candidates grouped
  greedily (a candidate joins the first group with a member within ``cluster_by_center_thr``), each group's
  integer mean its centre (``post_process.py`` l. 38-41, 155-170); a keypoint joins the first centre within
  ``cluster_by_center_thr`` of its root, else is dropped (l. 172-179); groups of more than one point (l. 222),
  align x ``hm_down_scale`` (l. 224), then to the original image as int(p x crop size / 800 or 320 + crop
  offset) and kept with more than ``points_thr`` points (``tools/ganet/tusimple/test_dataset.py`` l. 49-83,
  ``culane/test_dataset.py`` l. 79-113).
- The releases (``configs/{tusimple,culane}/final_exp_res{18,34}_s8.py``, ``final_exp_res101_s4.py``; README
  "Evaluation": CULane F1 78.79 / 79.39 / 79.63, TuSimple F1 97.71 / 97.68 / 97.45 for ResNet-18 / 34 / 101, F1
  from the mean FP and FN rates, ``tools/ganet/tusimple/evaluate/lane.py`` l. 94-96):
  320x800 input (``img_scale``, l. 40) of the crop ``crop_bbox`` (l. 39: TuSimple rows 160-720 of 1280x720,
  CULane 270-590 of 1640x590), albumentations ``Crop`` then ``Resize`` (cv2 bilinear; l. 157-167), BGR (cv2) with
  ``img_norm_cfg`` mean [75.3, 76.6, 77.6], std [50.5, 53.8, 54.3], ``to_rgb=False`` (l. 36-37). Thresholds
  (``configs/*/test_common_s{8,4}.py``): TuSimple s8 kpt_thr 0.3, cluster_by_center_thr 4, points_thr 7; TuSimple
  s4 0.3, 6, 6; CULane s8 0.4, 5, 10; CULane s4 0.3, 10, 20; ``root_thr`` 1 (head default, set in the ResNet-101
  configs l. 95). The two datasets' files have the same shapes: the file cannot tell its dataset.

This project's GANet (``models/ganet``: head.py, neck.py) has the same layers and order, with its own names, and
timm's ResNet the torchvision names; the conversion renames, and reshapes two tensors:

- the LFA's deformable convolution is sampling (grid_sample, zeros outside, the same bilinear reads) of a 1x1
  projection per point, summed: ``project`` (K x 64, 256, 1, 1) is ``reppoints_cls_conv.weight`` (64, 256, 1, K)
  with tap k's slice at rows k x 64 ... k x 64 + 63; its bias ``lfa.bias`` is zero (the official has none);
- the LFA's points are (dx, dy) per point here: ``reppoints_pts_init_out``'s output rows are swapped in pairs.

Dropped, as nothing the official network outputs reads them: ``neck.fpn_convs.<i>`` and ``neck.def_convs.<i>`` of
the levels above 0, ``reppoints_pts_refine_*`` and ``bbox_head.centerpts_head``. The ResNet-101 release needs the
attention's own width (``model.head.attention_channels: 256``) and the four levels (``model.feature_strides: [4,
8, 16, 32]``): ``experiment=official_ganet_large_<dataset>``.

Not the official's, and why (the outputs above are equal; decoding and input differ slightly):
- the position embedding is computed for the C5 map's size (the official's fixed (10, 25) table only fits 320x800,
  where both are equal);
- decoding (codec.py): a keypoint's start is cell + error + offset (the official cell + offset, leaving out the
  sub-cell error its own training target includes), start candidates are grouped by their predicted starts (the
  official by their cells) and averaged in floats (the official truncates), candidates and keypoints are taken
  strongest first and a keypoint joins the nearest centre (the official: the first in its lists), a lane's points
  sharing a y are averaged and lanes are kept with ``min_points`` points (= the official ``points_thr`` + 1);
  points are not truncated to integer pixels;
- the images are resized with cv2's INTER_AREA (data/transforms.py), the official with INTER_LINEAR.
"""

from __future__ import annotations

import re

import torch

from lanevil_train.models.release import Recognised, Release, resnet_depth

# (depth, levels, LFA points, attention channels) of the published files -> (version, experiment)
RELEASES = {(18, 3, 7, 64): ("Small", "official_ganet_<tusimple|culane>"),
            (34, 3, 7, 64): ("Medium", "official_ganet_<tusimple|culane>"),
            (101, 4, 9, 256): ("Large", "official_ganet_large_<tusimple|culane>")}
LFA_LEVEL = 0  # deconv_layer = [True, False, ...]: the LFA runs on the finest level only
_REQUIRED = {"backbone.conv1.weight", "neck.lateral_convs.0.conv.weight", "neck.fpn_convs.0.conv.weight",
             f"neck.def_convs.{LFA_LEVEL}.reppoints_cls_conv.weight", "bbox_head.keypts_head.hm.0.weight",
             "bbox_head.offset_head.offset_map.0.weight", "bbox_head.reg_head.offset_map.0.weight"}
_ATTENTION = "neck.trans_head.attn_layers."
_LFA = f"neck.def_convs.{LFA_LEVEL}."
_CONV_MODULE = {"conv": "0", "bn": "1"}  # mmcv ConvModule's children -> our Sequential's indices
_ATTENTION_PARTS = {"pre_conv": "pre", "final_conv": "post", "query_conv": "query", "key_conv": "key",
                    "value_conv": "value"}
_HEAD_BRANCHES = {"keypts_head.hm": "heatmap_head", "offset_head.offset_map": "offset_head",
                  "reg_head.offset_map": "error_head"}


def _indices(state: dict, prefix: str) -> set[int]:
    return {int(k[len(prefix):].split(".", 1)[0]) for k in state if k.startswith(prefix)}


def _unsupported(state: dict) -> str:
    """Why no network of this project computes this file's function, or ""."""
    whys = []
    if any(k.startswith("bbox_head.upsample_module.") for k in state):
        whys.append("its head upsamples the features first (upsample_module), this project's does not")
    joints = state["bbox_head.offset_head.offset_map.2.weight"].shape[0] // 2 \
        if "bbox_head.offset_head.offset_map.2.weight" in state else 1
    if joints != 1:
        whys.append(f"it regresses offsets to {joints} joints per keypoint (joint_nums={joints}), this project's "
                    f"head to the start point only (joint_nums=1)")
    classes = state["bbox_head.keypts_head.hm.2.weight"].shape[0] if "bbox_head.keypts_head.hm.2.weight" in state \
        else 1
    if classes != 1:
        whys.append(f"its keypoint heatmap has {classes} classes, this project's one")
    if any(k.startswith(_LFA + "implicit_") for k in state):
        whys.append("its LFA scales and shifts its input (use_latern), this project's does not")
    point_convs, feat_convs = len(_indices(state, _LFA + "reg_convs.")), len(_indices(state, _LFA + "cls_convs."))
    if point_convs != feat_convs:
        whys.append(f"its LFA has {feat_convs} feature convs and {point_convs} point convs, this project's the same "
                    f"number of each (model.head.lfa_convs)")
    return "; ".join(whys)


def describe(state: dict) -> Recognised | None:
    """The release of a GANet state dict (backbone, levels, LFA points, attention width), or None if not one."""
    if not _REQUIRED <= state.keys():
        return None
    depth = resnet_depth(state, [f"backbone.layer{i}." for i in range(1, 5)])
    backbone = f"resnet{depth}" if depth else "an unknown backbone"
    levels = len(_indices(state, "neck.lateral_convs."))
    stride = 32 // 2 ** (levels - 1)
    points = state[_LFA + "reppoints_cls_conv.weight"].shape[-1]
    fpn = state["neck.lateral_convs.0.conv.weight"].shape[0]
    layers = len(_indices(state, _ATTENTION))
    attention = state[f"{_ATTENTION}0.pre_conv.conv.weight"].shape[0] if layers else 0
    shape = (f"{backbone}: a stride-{stride} heatmap from {levels} levels, an LFA of {points} points, "
             + (f"{layers} attention layers of {attention} channels" if layers else "no attention"))
    why = _unsupported(state)
    if why:
        return Recognised(f"a GANet {shape}", "", unsupported=why)
    release = RELEASES.get((depth, levels, points, attention)) if layers == 2 and fpn == 64 else None
    if release is not None:
        version, experiment = release
        return Recognised(f"the {version} release ({shape}; TuSimple and CULane files alike)",
                          f"experiment={experiment} backbone={backbone}")
    strides = [32 // 2 ** i for i in range(levels - 1, -1, -1)]
    settings = [f"model.feature_strides=[{','.join(map(str, strides))}]", f"model.head.lfa_points={points}",
                f"model.head.fpn_channels={fpn}"]
    settings += ([f"model.head.attention_layers={layers}", f"model.head.attention_channels={attention}"] if layers
                 else ["model.head.top_attention=false"])
    return Recognised(f"an unpublished setting, {shape}",
                      f"experiment=official_ganet_<tusimple|culane> backbone={backbone} {' '.join(settings)}")


def _rename(key: str) -> str | None:
    """An official name -> this project's; None for a weight nothing the official network outputs reads."""
    if key.startswith("backbone."):
        return key  # mmdet's ResNet and timm's both keep torchvision's names
    if key.startswith(_ATTENTION):  # neck.trans_head.attn_layers.0.pre_conv.bn.weight -> ...attention.0.pre.1.weight
        index, part, *rest = key[len(_ATTENTION):].split(".", 2)
        if not rest:  # gamma
            return f"head.neck.attention.{index}.{part}"
        rest = rest[0]
        if part in ("pre_conv", "final_conv"):
            child, rest = rest.split(".", 1)
            rest = f"{_CONV_MODULE[child]}.{rest}"
        return f"head.neck.attention.{index}.{_ATTENTION_PARTS.get(part, part)}.{rest}"
    match = re.fullmatch(r"neck\.(lateral_convs|fpn_convs|def_convs)\.(\d+)\.(.+)", key)
    if match:
        kind, level, rest = match.group(1), int(match.group(2)), match.group(3)
        if kind == "lateral_convs":  # lateral_convs.1.conv.bias -> head.neck.lateral.1.bias
            return f"head.neck.lateral.{level}.{rest.removeprefix('conv.')}"
        if level != LFA_LEVEL:
            return None  # the coarser levels' output convs and LFAs: built, never read
        if kind == "fpn_convs":
            return f"head.neck.output.{rest.removeprefix('conv.')}"
        return _rename_lfa(rest)
    if key.startswith("bbox_head.centerpts_head."):
        return None  # the centre heatmap: loss weight 0, never decoded
    for official, ours in _HEAD_BRANCHES.items():  # bbox_head.keypts_head.hm.2.bias -> head.heatmap_head.2.bias
        if key.startswith(f"bbox_head.{official}."):
            return f"head.{ours}.{key[len(f'bbox_head.{official}.'):]}"
    return key  # reported by the strict load as unexpected


def _rename_lfa(rest: str) -> str | None:
    """The LanePointsConv's names (after neck.def_convs.0.) -> head.neck.lfa.*."""
    match = re.fullmatch(r"(cls_convs|reg_convs)\.(\d+)\.conv\.(weight|bias)", rest)
    if match:  # our _conv_relu Sequential: conv j at index 2j
        branch = "feat_convs" if match.group(1) == "cls_convs" else "point_convs"
        return f"head.neck.lfa.{branch}.{2 * int(match.group(2))}.{match.group(3)}"
    if rest.startswith("reppoints_pts_init_conv."):
        return "head.neck.lfa.point_out.0." + rest.split(".", 1)[1]
    if rest.startswith("reppoints_pts_init_out."):
        return "head.neck.lfa.point_out.2." + rest.split(".", 1)[1]
    if rest == "reppoints_cls_conv.weight":
        return "head.neck.lfa.project.weight"
    if rest.startswith("reppoints_pts_refine_"):
        return None  # built, never run
    return _LFA + rest


def _swap_pairs(tensor: torch.Tensor) -> torch.Tensor:
    """Rows (dy0, dx0, dy1, dx1, ...) -> (dx0, dy0, dx1, dy1, ...)."""
    order = torch.arange(tensor.shape[0]).reshape(-1, 2).flip(1).reshape(-1)
    return tensor[order]


def convert(state: dict) -> dict:
    """Official names -> this project's; the deformable convolution's weight as per-point projections, the point
    offsets' rows as (dx, dy) pairs, and the aggregation's (official: absent) bias zero."""
    out = {}
    for key, value in state.items():
        name = _rename(key)
        if name is None:
            continue
        if name == "head.neck.lfa.project.weight":  # (C, F, 1, K) -> (K * C, F, 1, 1), tap k's rows k*C...
            out_c, in_c, _, taps = value.shape
            value = value.permute(3, 0, 1, 2).reshape(taps * out_c, in_c, 1, 1)
            out["head.neck.lfa.bias"] = value.new_zeros(out_c)
        elif name.startswith("head.neck.lfa.point_out.2."):
            value = _swap_pairs(value)
        out[name] = value
    return out


RELEASE = Release(family="ganet", name="GANet (Wolfwjs/GANet)", describe=describe, convert=convert)
