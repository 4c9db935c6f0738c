"""The published BezierLaneNet checkpoints of pytorch-auto-drive (voldemortX/pytorch-auto-drive, read at 137e63a):
recognised and converted.

Facts of the official code this conversion rests on (paths in that repository):

- Saving: ``utils/common.py`` l. 24-30 ``save_checkpoint`` writes ``{'model': net.state_dict(), 'optimizer': ...,
  'lr_scheduler': ...}`` (the latter two may be None); l. 34-56 ``load_checkpoint`` loads ``['model']`` strictly.
- The releases (``configs/lane_detection/bezierlanenet/resnet{18,34}_{tusimple,culane,llamas}_aug1b.py``, ``model``
  dict l. 56-101, the same in all six but for the backbone and ``image_height``): ``name='BezierLaneNet'``,
  ``num_regression_parameters=8`` (a cubic curve), backbone ``predefined_resnet_backbone`` on ``resnet18`` /
  ``resnet34``, ``return_layer='layer3'``, no dilation; ``reducer_cfg=None``; ``predefined_dilated_blocks``
  (in 256, mid 64, dilations [4, 8]); ``FeatureFlipFusion(256)``; ``ConvProjection_1D`` (2 layers, 256 channels,
  bias, k=3); ``SimpleSegHead`` (in 256, mid 64, 1 class). The file's shapes are the same for every dataset: only
  the backbone can be told from it.
- The network (``utils/models/lane_detection/bezier_lane_net.py``): ``backbone`` (l. 30) is
  ``utils/models/backbone_wrappers.py`` l. 33-37: ``IntermediateLayerGetter`` (``utils/models/_utils.py`` l. 48-60)
  over ``utils/models/resnet.py``'s torchvision ResNet (l. 187-263: conv1 7x7 stride 2 without bias, bn1, relu,
  maxpool 3/2/1, layer1-4; BasicBlock l. 98-135, Bottleneck with the stride on conv2 l. 138-184), keeping the
  children up to ``layer3``: keys ``backbone.conv1``, ``backbone.bn1``, ``backbone.layer1..3`` (no layer4, no fc);
  stride 16, 256 channels (ResNet-18/34).
  ``reducer`` (l. 31; None in the releases) would be ``utils/models/common_models/plugins/resa_reducer.py`` l. 8-24:
  ``conv1`` 1x1 without bias, then (``bn_relu=True``) ``bn1`` and a ReLU.
  ``segmentation_head`` (l. 39) = ``utils/models/segmentation/simple_seg_head.py`` l. 35-46: ``conv`` a ConvBNReLU
  (``conv`` 3x3 padding 1 WITHOUT bias, ``bn``, ReLU; l. 8-25) and ``conv_out`` 1x1 without bias to 1 channel.
  ``dilated_blocks`` (l. 32) = ``plugins/dilated_blocks.py`` l. 7-18: an ``nn.Sequential`` of
  ``utils/models/common_models/blocks/dilated_bottleneck.py`` ``DilatedBottleneck`` (l. 8-42): ``conv1`` (1x1 to
  mid, bias; BN), ``conv2`` (3x3, padding = dilation = d, bias; BN), ``conv3`` (1x1 back, bias; BN), each
  Sequential(conv, BN) (keys ``.0``, ``.1``); forward relu(conv1), relu(conv2), relu(conv3) and then the input
  added (the ReLU before the sum, l. 32-40).
  ``simple_flip_2d`` (l. 33, "Name kept for legacy weights") = ``plugins/feature_flip_fusion.py``
  ``FeatureFlipFusion`` (l. 59-78): ``proj1`` = Sequential(Conv2d(C, C, 1) with bias, BN) (l. 63-66),
  ``proj2_conv`` = ``DCN_v2_Ref(C, C, 3, padding=1)`` (l. 67), ``proj2_norm`` = BN (l. 68); forward (l. 70-78):
  ``flipped = feature.flip(-1)``, ``feature = proj1(feature)``, ``flipped = proj2_norm(proj2_conv(flipped,
  feature))``, ``relu(feature + flipped)``. ``DCN_v2_Ref`` (l. 9-56) is mmcv's ``ModulatedDeformConv2d`` (``weight``
  (C, C, 3, 3), ``bias`` (C)) with ``conv_offset`` = Conv2d(2C, 3 x 9, 3, padding 1, bias) (l. 30-37), zero at
  initialisation (l. 40-44); forward (l. 46-56): ``out = conv_offset(cat([x, ref]))``, ``o1, o2, mask =
  chunk(out, 3)``, ``offset = cat(o1, o2)`` (out's channels 0-17 in their order), ``mask = sigmoid`` of channels
  18-26, ``modulated_deform_conv2d(x, offset, mask, weight, bias, stride 1, padding 1, dilation 1, groups 1,
  deform_groups 1)``. mmcv's kernel (open-mmlab/mmcv ``mmcv/ops/csrc/common/cuda/
  modulated_deform_conv_cuda_kernel.cuh``, ``modulated_deformable_im2col_gpu_kernel``) reads tap (i, j) of the
  3x3 kernel (row-major, k = 3i + j) at row ``h - 1 + i + offset[2k]`` and column ``w - 1 + j + offset[2k + 1]``,
  times ``mask[k]``; a point outside (-1, H) x (-1, W) reads 0 and, inside, each of its four bilinear corners that
  lies outside the map reads 0 (``dmcn_im2col_bilinear``): torchvision's ``ops.deform_conv2d`` reads offsets and
  masks in the same layout and samples by the same rule.
  The forward (l. 41-69): backbone, reducer, the segmentation head on that map (before the dilated blocks, l.
  51-54), dilated blocks, the fusion in float32 (l. 59-60), ``aggregator`` = AvgPool2d(((image_height - 1) // 16 + 1,
  1), stride 1) and its row 0 (l. 34, 61): the mean over the whole height of the stride-16 map when the input is
  ``image_height`` high (360: 23 rows, 288: 18); ``regression_head`` (l. 35) = ``plugins/conv_projection_1d.py``
  ``ConvProjection_1D`` (l. 9-24): ``hidden_layers.<i>`` Conv1d(C, C, k, padding (k - 1) // 2, bias) and
  ``hidden_norms.<i>`` BatchNorm1d, x = relu(norm(conv(x))) per layer; ``proj_classification`` Conv1d(256, 1, 1)
  -> ``logits`` (B, Q) (l. 36, 64), ``proj_regression`` Conv1d(256, 8, 1) -> ``curves`` = (B, 8, Q) permuted to
  (B, Q, 8) and reshaped (B, Q, 4, 2) (l. 37-38, 65, 68): control point k is (channel 2k, channel 2k + 1) = (x / W,
  y / H) of the input. Q = W / 16: 40 queries at 640 px, 50 at 800 px.
- Inference (``utils/models/lane_detection/bezier_base.py`` l. 54-95, called by ``utils/runners/lane_det_tester.py``
  l. 31-34, 54 with ``input_sizes = [input_size, original_size]``, ``gap``, ``ppl``, ``dataset``, ``max_lane``):
  existence = sigmoid(logits) > ``thresh`` (l. 56-57); with ``local_maximum_window_size`` > 0, a query is kept only
  where ``max_pool1d(kernel=window, stride=1, padding=(window - 1) // 2, return_indices=True)`` returns its own index
  (l. 60-70: the maximum of the window centred on it, the leftmost of equal maxima); then at most ``max_lane`` lanes,
  the least confident dropped (l. 73-74, ``utils/models/lane_detection/utils.py`` l. 4-14). Each kept curve is
  sampled by ``utils/curve_utils.py`` ``BezierCurve(order=3)`` at ``num_sample_points`` t evenly spaced in [0, 1]
  (l. 83-86, 94-100: the Bernstein matrix times the control points; l. 85 of bezier_base.py: H of the ORIGINAL image
  points for TuSimple, n = 50 otherwise) and ``bezier_to_coordinates`` (l. 18-51) gives: TuSimple (l. 28-42), on
  the rows y = H - (ppl - i) * gap (160, 170, ..., 710 of 720) the x (times W) of the sampled point nearest in y,
  or -2 where that point is more than 5 / H away in y or its x is outside [0, 1]; CULane and LLAMAS (l. 43-47) all
  n sampled points times (W, H), in or out of the image (``lane_det_tester.py`` l. 59-69 writes them all).
- Release settings (the configs' ``test`` and ``model`` dicts): TuSimple input 360x640 of 720x1280, ``thresh=0.5``,
  ``max_lane=5``, ``gap=10``, ``ppl=56``; CULane 288x800 of 590x1640, ``thresh=0.95``, ``max_lane=4``, ``gap=20``,
  ``ppl=18``; LLAMAS 360x640 of 717x1276, ``thresh=0.95``, ``max_lane=4``; ``local_maximum_window_size=9`` in all
  (l. 62-63). Test transform (``configs/lane_detection/common/datasets/test_360.py`` / ``test_288.py`` l. 1-18): the
  whole image resized (no crop), ToTensor, ImageNet mean and std. Training (``common/optims/matchingloss_bezier.py``
  l. 1-14): ``HungarianBezierLoss``, ``k=9`` the local-maximum prior of the matching, ``alpha=0.8``, weights
  label 0.1, curve 1, seg 0.75; ``adam00006_dcn.py`` l. 1-15: Adam 6e-4, ``conv_offset`` at 0.1x.
- Published files (``docs/MODEL_ZOO.md`` l. 133-134, 174-175, 187-188; ``configs/lane_detection/bezierlanenet/
  README.md`` l. 27-42): ResNet-18 and ResNet-34 for TuSimple, CULane and LLAMAS.

This project's BezierLaneNet (``model=bezierlanenet``, ``models/bezierlanenet/head.py``) on timm's ResNet (the
torchvision names, ``feature_strides: [16]``: layer3, no layer4 built) computes the same function with the same
layers, so the conversion renames: ``dilated_blocks`` -> ``head.dilated_blocks`` (the same inside),
``simple_flip_2d`` -> ``head.fusion`` (its plain-torch DCNv2 ``proj2_conv`` keeps mmcv's ``weight``, ``bias``,
``conv_offset`` and reads the offset channels in mmcv's layout), ``regression_head.hidden_layers.<i>`` /
``hidden_norms.<i>`` -> ``head.projection.<3i>`` / ``<3i + 1>``, ``proj_classification`` / ``proj_regression`` ->
``head.``, ``segmentation_head.conv.conv`` / ``.conv.bn`` / ``.conv_out`` -> ``head.seg_head.0.0`` / ``.0.1`` /
``.2``, a reducer's ``reducer.conv1`` / ``.bn1`` -> ``head.reducer.0.0`` / ``.0.1``. Two convolutions have a bias
here and none in the official (the segmentation head's 3x3 and the reducer's 1x1): the conversion gives them a
zero bias, the same function. The segmentation head is training-only (dropped at inference by both): optional.
The height average is ``mean(dim=2)`` here, the official's pooling window at its ``image_height``; at another
input height the official pools the top rows only, so a run at another size computes the official network built
for that height. The dilations are not in the file (3x3 kernels either way): every release uses [4, 8], the
family config's. A file whose network this head cannot compute (a curve of another order, a reducer without BN
and ReLU, a backbone returning layer4) is recognised and refused saying why.
"""

from __future__ import annotations

import torch

from lanevil_train.models.release import Recognised, Release, resnet_depth

REGRESSION_PARAMETERS = 8  # 4 control points (x, y): the releases' cubic curves, the only order of this head
# The releases' head settings (the configs' model dict) as this project's model.head keys
RELEASE_SETTINGS = {"channels": 256, "dilated_mid_channels": 64, "projection_layers": 2, "projection_kernel": 3,
             "seg_mid_channels": 64}
DILATIONS = (4, 8)
_REQUIRED = {"backbone.conv1.weight", "simple_flip_2d.proj1.0.weight", "simple_flip_2d.proj2_conv.weight",
             "proj_classification.weight", "proj_regression.weight"}
_SEG = {"conv.conv": "0.0", "conv.bn": "0.1", "conv_out": "2"}
_NO_BIAS = {"head.seg_head.0.0.weight", "head.reducer.0.0.weight"}  # the official convs without bias


def _count(state: dict, prefix: str) -> int:
    return len({k[len(prefix):].split(".", 1)[0] for k in state if k.startswith(prefix)})


def _settings(state: dict) -> dict:
    """The model.head settings the file's shapes tell."""
    out = {"channels": state["proj_classification.weight"].shape[1]}
    if "dilated_blocks.0.conv1.0.weight" in state:
        out["dilated_mid_channels"] = state["dilated_blocks.0.conv1.0.weight"].shape[0]
    out["projection_layers"] = _count(state, "regression_head.hidden_layers.")
    if "regression_head.hidden_layers.0.weight" in state:
        out["projection_kernel"] = state["regression_head.hidden_layers.0.weight"].shape[-1]
    if "segmentation_head.conv.conv.weight" in state:
        out["seg_mid_channels"] = state["segmentation_head.conv.conv.weight"].shape[0]
    return out


def _unsupported(state: dict) -> str:
    if any(k.startswith("backbone.layer4.") for k in state):
        return ("its backbone returns ResNet layer4 (stride 32), and this project's BezierLaneNet reads layer3 "
                "(stride 16), as the official's aggregator and every release")
    params = state["proj_regression.weight"].shape[0]
    if params != REGRESSION_PARAMETERS:
        return (f"its curves have {params // 2} control points (a Bezier curve of order {params // 2 - 1}); this "
                f"project's head predicts cubic curves (4 control points)")
    if "reducer.conv1.weight" in state and "reducer.bn1.weight" not in state:
        return ("its channel reducer is a 1x1 convolution alone (RESAReducer bn_relu=False); this project's reducer "
                "is a 1x1 convolution, BN and ReLU")
    return ""


def describe(state: dict) -> Recognised | None:
    """What a pytorch-auto-drive BezierLaneNet state dict is (its backbone, and its head settings where they are not
    the releases'), or None if it is not one. The dataset is not in the file: every release has the same shapes."""
    if not _REQUIRED <= state.keys():
        return None
    depth = resnet_depth(state, [f"backbone.layer{i}." for i in range(1, 4)])  # up to layer3
    backbone = f"resnet{depth}" if depth else "an unknown backbone"
    why = _unsupported(state)
    if why:
        return Recognised(f"{backbone}, an unpublished setting", "", unsupported=why)
    settings = _settings(state)
    blocks = _count(state, "dilated_blocks.")
    reducer = " with a channel reducer" if "reducer.conv1.weight" in state else ""
    overrides = [f"model.head.{k}={v}" for k, v in settings.items() if v != RELEASE_SETTINGS[k]]
    if blocks != len(DILATIONS):
        overrides.append(f"model.head.dilations=[...] ({blocks} dilations, which the file does not hold; the "
                         f"releases use {list(DILATIONS)})")
    what = (f"{backbone}{reducer}: cubic curves, {settings['channels']}-channel branch"
            + ("" if not overrides else ", an unpublished setting")
            + " (the file does not tell the dataset: every release has the same shapes)")
    config = " ".join([f"experiment=official_bezierlanenet_<tusimple|culane> backbone={backbone}", *overrides])
    return Recognised(what, config)


def _rename(key: str) -> str:
    """dilated_blocks.1.conv2.0.weight -> head.dilated_blocks.1.conv2.0.weight, simple_flip_2d.proj2_conv.conv_offset
    .bias -> head.fusion.proj2_conv.conv_offset.bias, regression_head.hidden_norms.1.running_var ->
    head.projection.4.running_var, proj_regression.weight -> head.proj_regression.weight,
    segmentation_head.conv.bn.bias -> head.seg_head.0.1.bias, reducer.bn1.weight -> head.reducer.0.1.weight;
    backbone.* and anything else unchanged."""
    parts = key.split(".")
    if parts[0] == "dilated_blocks":
        return "head." + key
    if parts[0] == "simple_flip_2d":
        return "head.fusion." + ".".join(parts[1:])
    if parts[0] == "regression_head" and len(parts) == 4 and parts[1] in ("hidden_layers", "hidden_norms"):
        index = 3 * int(parts[2]) + (parts[1] == "hidden_norms")
        return f"head.projection.{index}.{parts[3]}"
    if parts[0] in ("proj_classification", "proj_regression"):
        return "head." + key
    if parts[0] == "segmentation_head":
        for official, ours in _SEG.items():
            if key.startswith(f"segmentation_head.{official}."):
                return f"head.seg_head.{ours}.{key[len('segmentation_head.') + len(official) + 1:]}"
    if parts[0] == "reducer" and len(parts) == 3 and parts[1] in ("conv1", "bn1"):
        return f"head.reducer.0.{'0' if parts[1] == 'conv1' else '1'}.{parts[2]}"
    return key  # backbone.* as it is; anything else reported by the strict load as unexpected


def convert(state: dict) -> dict:
    """Official names -> this project's (weights unchanged); the official convolutions without a bias get a zero
    one."""
    out = {_rename(key): value for key, value in state.items()}
    for weight in _NO_BIAS & out.keys():
        bias = weight[: -len("weight")] + "bias"
        out.setdefault(bias, torch.zeros(out[weight].shape[0], dtype=out[weight].dtype))
    return out


RELEASE = Release(family="bezierlanenet", name="BezierLaneNet (voldemortX/pytorch-auto-drive)", describe=describe,
                  convert=convert, optional=("head.seg_head.",))
