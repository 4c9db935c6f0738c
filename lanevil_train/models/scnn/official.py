"""The published SCNN checkpoints of pytorch-auto-drive (voldemortX/pytorch-auto-drive, read at 137e63a):
recognised and converted.

Facts of the official code this conversion rests on (paths in that repository):

- Saving: ``utils/common.py`` l. 24-30 ``save_checkpoint`` writes ``{'model': net.state_dict(), 'optimizer': ...,
  'lr_scheduler': ...}`` (the latter two may be None); l. 34-56 ``load_checkpoint`` renames ``aux_head`` to
  ``lane_classifier`` in every key (files of the code before ac9d815, Feb. 2021, name the existence head
  ``aux_head``: ``torchvision_models/segmentation/deeplab_vgg.py`` at ac9d815^) and loads strictly.
- The VGG-16 releases (``configs/lane_detection/scnn/vgg16_{culane,tusimple,llamas}.py``, ``model = dict(name=
  'DeepLabV1', ...)``) build ``utils/models/segmentation/deeplab_vgg.py`` ``DeepLabV1`` (l. 10-51):
  ``encoder`` = ``utils/models/vgg_encoder.py`` ``VGG16``: torchvision's ``vgg16_bn().features`` as ``encoder.net``
  (l. 17), its conv5 convolutions ``net.34``, ``net.37``, ``net.40`` replaced by the same 3x3 convolutions with
  dilation 2 and padding 2 (l. 18-25, bias kept), the max-pools ``net.33`` (pool4) and ``net.43`` (pool5) removed
  (l. 26-27): stride 8, the other indices unchanged (``encoder.net.0`` ... ``encoder.net.41``, convolutions with a
  bias, each followed by a BatchNorm2d);
  ``fc67`` = Conv2d(512, 1024, 3, padding 4, dilation 4, no bias), BatchNorm2d(1024), ReLU, Conv2d(1024, 128, 1, no
  bias), BatchNorm2d(128), ReLU (l. 20-27: keys ``fc67.0``, ``.1``, ``.3``, ``.4``);
  ``scnn`` = ``utils/models/common_models/plugins/spatial_conv.py`` ``SpatialConv(128)``: ``conv_d``, ``conv_u``
  Conv2d(128, 128, (1, 9), padding (0, 4)), ``conv_r``, ``conv_l`` Conv2d(128, 128, (9, 1), padding (4, 0)), all
  with a bias (l. 16-19);
  ``fc8`` = Dropout2d(0.1), Conv2d(128, num_classes, 1) (l. 29-32: key ``fc8.1``);
  ``lane_classifier`` = ``utils/models/common_models/heads/simple_lane_exist.py`` ``SimpleLaneExist``: AvgPool2d(2,
  2), flatten, ``linear1`` Linear(flattened_size, 128), ReLU, ``linear2`` Linear(128, num_classes - 1) (l. 12-24).
- Forward (``deeplab_vgg.py`` l. 36-51): encoder, fc67, scnn, fc8 give ``out`` (the stride-8 class logits); the
  existence head reads their softmax over the classes (l. 48-49) and gives ``lane`` (logits; a sigmoid at test).
- Message passing (``spatial_conv.py`` l. 51-72, and l. 77-92 the same in place when tracing): down, up, right,
  left; slice i (a row, then a column) += ReLU(conv(slice i - 1 already updated)) from the second slice on; the up
  and left passes run from the last slice back to slice 1 (``range(H - 2, 0, -1)``), leaving slice 0 as the down /
  right passes left it.
- The releases (``configs/lane_detection/scnn/vgg16_*.py``, ``train``/``test`` and ``model`` dicts): CULane
  ``input_size=(288, 800)``, 5 classes, ``flattened_size=4500`` (5 x 18 x 50), ``test.max_lane=4``, ``gap=20``,
  ``ppl=18``, ``thresh=0.3``; TuSimple ``input_size=(360, 640)``, 7 classes, ``flattened_size=6160`` (7 x 22 x 40),
  ``max_lane=5``, ``gap=10``, ``ppl=56``; LLAMAS 360x640, 5 classes, ``flattened_size=4400``.
  ``configs/lane_detection/common/datasets/test_288.py`` / ``test_360.py`` l. 1-18: the whole image resized (no
  crop) with PIL bilinear (``utils/transforms/transforms.py`` l. 102), ToTensor, ImageNet mean and std.
- Inference (``utils/lane_det_utils.py`` l. 95-116): ``out`` upsampled bilinearly to the input size with
  ``align_corners=True``, softmax; existence = sigmoid(``lane``) > 0.5, then at most ``test.max_lane`` lanes (passed
  by ``utils/runners/lane_det_tester.py`` l. 34, 51-52), the least confident dropped
  (``utils/models/lane_detection/utils.py`` l. 4-14); per existing lane the probability map is
  box-blurred 9x9 (l. 78), and on ``ppl`` rows ``gap`` px apart in the original image (CULane from the bottom row,
  TuSimple from 720 - 560 = 160 to 710; l. 31-34) the argmax column is a point when its probability is above
  ``thresh``, x = int(column / w * W) (l. 39-42); a lane needs 2 points (l. 43).
- The ResNet releases (``configs/lane_detection/scnn/resnet{18,34,50,101}_{culane,tusimple}.py``, ``name=
  'standard_segmentation_model'``) are another network (``utils/models/segmentation/_utils.py`` l. 29-70,
  ``segmentation.py`` l. 18-36, ``deeplab.py`` l. 33-38 and 113-120): ``backbone`` (the ResNet, layer3 / layer4
  dilated: stride 8; ``backbone_wrappers.py`` l. 32-37 keeps torchvision's names), ``channel_reducer``
  (``plugins/resa_reducer.py`` l. 11-22: a 1x1 conv without bias to 128, BN, ReLU), ``scnn_layer``,
  ``classifier.0.conv`` (a 3x3 conv with bias to the classes), ``lane_classifier``, no dropout. Against this
  project's SCNN head (the VGG release's fc67 and a 1x1 classifier) it has no 3x3 convolution to 1024 channels and
  a 3x3 classifier; and its ResNet-18/34 dilate only the first 3x3 convolution of each block (``utils/models/
  resnet.py`` l. 111-114: ``conv2 = conv3x3(planes, planes)``) where timm's dilated BasicBlock dilates both (its
  Bottleneck, l. 156, dilates as timm's). Such a file is recognised and refused saying so.

This project's SCNN on ``backbone=vgg16_bn`` (timm's vgg16_bn features, ``features_<i>``, pool4 / pool5 made
identities and conv5 dilated by 2 for ``model.output_stride: 8``) computes the VGG releases' function with the same
layers: the conversion renames only (``encoder.net.<i>`` -> ``backbone.features_<i>``, ``fc67`` -> ``head.reduce``,
``scnn`` -> ``head.message_passing``, ``fc8.1`` -> ``head.classifier``, ``linear1`` / ``linear2`` ->
``head.exist_fc.0`` / ``.2``), and ``model.head.align_corners: true`` upsamples as the official inference.
"""

from __future__ import annotations

from lanevil_train.models.release import Recognised, Release, resnet_depth

# (classes, existence-head inputs) of the published VGG-16 files -> (dataset, input height, width)
RELEASES = {(5, 4500): ("culane", 288, 800), (7, 6160): ("tusimple", 360, 640), (5, 4400): ("llamas", 360, 640)}
_EXIST = ("lane_classifier.", "aux_head.")  # the existence head's name, before ac9d815: aux_head
_EXIST_LINEAR = {"linear1": "0", "linear2": "2"}


def _exist_key(state: dict, name: str) -> str | None:
    return next((prefix + name for prefix in _EXIST if prefix + name in state), None)


def _describe_resnet(state: dict) -> Recognised:
    depth = resnet_depth(state, [f"backbone.layer{i}." for i in range(1, 5)])
    backbone = f"resnet{depth}" if depth else "an unknown ResNet"
    classes = state["classifier.0.conv.weight"].shape[0]
    why = ("its network is not this project's SCNN: a 1x1 channel reducer (channel_reducer) where the SCNN head has "
           "the dilated 3x3 convolution to 1024 channels and a 1x1 (head.reduce), and a 3x3 classifier "
           "(classifier.0.conv) where the head has a 1x1 (head.classifier)")
    if depth in (18, 34):
        why += ("; and its ResNet dilates only the first 3x3 convolution of each block of layer3 and layer4, timm's "
                "both")
    return Recognised(f"the {backbone} SCNN (standard_segmentation_model), {classes} classes", "", unsupported=why)


def describe(state: dict) -> Recognised | None:
    """The release of a pytorch-auto-drive SCNN state dict (dataset from its classes and existence-head size,
    backbone), or None if it is not one."""
    if {"backbone.conv1.weight", "channel_reducer.conv1.weight", "scnn_layer.conv_d.weight",
            "classifier.0.conv.weight"} <= state.keys():
        return _describe_resnet(state)
    linear1 = _exist_key(state, "linear1.weight")
    if not {"encoder.net.0.weight", "fc67.0.weight", "scnn.conv_d.weight", "fc8.1.weight"} <= state.keys() \
            or linear1 is None:
        return None
    classes, inputs = state["fc8.1.weight"].shape[0], state[linear1].shape[1]
    release = RELEASES.get((classes, inputs))
    if release is None:
        return Recognised(f"an unpublished setting, vgg16_bn: {classes} classes, {inputs} existence-head inputs",
                          f"model=scnn backbone=vgg16_bn model.head.align_corners=true data.max_lanes={classes - 1} "
                          f"and a data.input_size [H, W] giving {classes} x (ceil(H / 8) // 2) x (ceil(W / 8) // 2) = "
                          f"{inputs} (the existence head's inputs)")
    dataset, h, w = release
    what = f"the {dataset} release, vgg16_bn: {classes - 1} lanes, {h}x{w} input"
    if dataset == "llamas":  # no LLAMAS data here: the CULane config builds the same network at 360x640
        return Recognised(what + " (this project reads no LLAMAS data)",
                          f"experiment=official_scnn_culane backbone=vgg16_bn data.input_size=[{h},{w}]")
    return Recognised(what, f"experiment=official_scnn_{dataset} backbone=vgg16_bn")


def _rename(key: str) -> str:
    """encoder.net.34.weight -> backbone.features_34.weight, fc67.3.weight -> head.reduce.3.weight,
    scnn.conv_d.bias -> head.message_passing.conv_d.bias, fc8.1.weight -> head.classifier.weight,
    lane_classifier.linear2.bias (or aux_head.) -> head.exist_fc.2.bias; anything else unchanged."""
    parts = key.split(".")
    if parts[:2] == ["encoder", "net"] and len(parts) == 4:
        return f"backbone.features_{parts[2]}.{parts[3]}"
    if parts[0] == "fc67":
        return "head.reduce." + ".".join(parts[1:])
    if parts[0] == "scnn":
        return "head.message_passing." + ".".join(parts[1:])
    if parts[:2] == ["fc8", "1"] and len(parts) == 3:
        return "head.classifier." + parts[2]
    if parts[0] + "." in _EXIST and len(parts) == 3 and parts[1] in _EXIST_LINEAR:
        return f"head.exist_fc.{_EXIST_LINEAR[parts[1]]}.{parts[2]}"
    return key  # reported by the strict load as unexpected


def convert(state: dict) -> dict:
    """Official names -> this project's (weights unchanged)."""
    return {_rename(key): value for key, value in state.items()}


RELEASE = Release(family="scnn", name="SCNN (voldemortX/pytorch-auto-drive)", describe=describe, convert=convert)
