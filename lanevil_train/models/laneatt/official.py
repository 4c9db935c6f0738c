"""The published LaneATT checkpoints (lucastabelini/LaneATT, read at 2f8583b): recognised and converted.

Facts of the official code this conversion rests on (``lib/models/laneatt.py`` unless named):

- ``lib/experiment.py`` l. 94-100: a checkpoint is ``{'epoch', 'model': state_dict, 'optimizer', 'scheduler'}``;
  l. 80 and 86 load ``['model']``.
- The backbone is ``feature_extractor`` (l. 29), ``nn.Sequential`` of torchvision's ResNet children without the
  pooling and fc (l. 380-395): ``feature_extractor.0`` conv1, ``.1`` bn1, ``.4``-``.7`` layer1-4.
- ``conv1`` a 1x1 conv to 64 channels (l. 61); ``cls_layer`` Linear(2 * 64 * fmap_h, 2), ``reg_layer`` Linear(2 * 64
  * fmap_h, S + 1) (l. 62-63); ``attention_layer`` Linear(64 * fmap_h, n_anchors - 1) (l. 64), fmap_h = img_h //
  32 (l. 33). The anchors are not in the file (plain attributes): they are the full set (left, bottom, right: l.
  241-246) filtered by the repository's frequency file, ``torch.argsort(counts, descending=True)[:topk_anchors]``
  (l. 49-54), most used first; the attention layer's rows follow that order, so the same file must choose them here
  (``model.head.anchor_frequency_file``), with the same ``torch.argsort`` (frequency.py TIE_ORDERS "torch"): that
  sort is not stable, and the order of equal counts is the kernel's (torch 1.6 for the published weights).
- Every published release (TuSimple, CULane, LLAMAS) is 360x640, S = 72, 1,000 anchors (``cfgs/laneatt_*.yml``):
  the file's shapes cannot tell the dataset, only the backbone.

How the official test turns proposals into the TuSimple file (what ``experiment=official_laneatt_*`` reproduces:
``model.head.fraction_scale: size``, ``model.decode.lane_points: official``, ``model.row_sampling: spline``):

- Rows and anchors (l. 36, 279-281): ``anchor_ys = linspace(1, 0, S)`` (float32) are fractions of the height, 1 the
  bottom (y = H); an anchor from border point (x0, y0) at ``angle`` has x = (x0 + (y0 - f) / tan(angle)) * img_w
  at row fraction f, its start ``1 - y0`` (fraction of the strips), in float32. The proposal is the anchor plus the
  regression (l. 102-105): class logits in 0-1, the length in 4, the offsets added to 5:.
- Scores (l. 119-125): softmax, kept where > conf_threshold, then the lane NMS; decode (l. 346-347) softmaxes
  and rounds the length with ``torch.round`` (halves to even).
- proposals_to_pred (l. 309-340): x / img_w (float32); start = round(start fraction x n_strips); end = min(start +
  length - 1, S - 1); the rows below the start are cleared (-2) unless every row from them up to the start has x /
  img_w in [0, 1] (the mask is computed first, l. 322-323); ``lane_xs[end + 1:] = -2`` (a Python slice, so a
  negative end + 1 counts from the top row); the points with x >= 0 are kept (right of the image too), flipped to
  y ascending; fewer than 2: no lane. The points go to ``Lane`` (lib/lane.py l. 10-12) in fractions of the image.
- lib/lane.py l. 10-23: ``InterpolatedUnivariateSpline(y, x, k=min(3, n - 1))``, valid within [min y - 0.01,
  max y + 0.01] (fractions of the height), -2 elsewhere.
- TuSimple writer (lib/datasets/tusimple.py l. 55-65, 99-105): the Lane at ``h_samples / 720``, ``(xs * 1280)
  .astype(int)`` (truncated), -2 where xs < 0; one line per image, the lanes in NMS order.
- CULane / LLAMAS writers (lib/datasets/culane.py l. 115-129, lib/datasets/llamas.py l. 98-112, 1276x717 at l. 26):
  the Lane at every image row ``arange(img_h) / img_h``, kept where 0 <= x < 1, written bottom first as
  ``'{:.5f} {:.5f}'`` of x * img_w, y * img_h (``model.culane_rows: [0, img_h, 1]``).
- Targets (lib/datasets/lane_dataset.py l. 54, 155): rows y = img_h, img_h - img_h / (S - 1), ..., 0; x inside the
  image where 0 <= x < img_w.

This project's head keeps the layers (``head.conv1``, ``head.attention_layer``, ``head.cls_layer``,
``head.reg_layer``), the anchor cut (official quirks included) and the attention's order, and timm's ResNet the
torchvision names: the conversion renames only; the chosen anchors (``head.anchor_index``) come from the frequency
file given to the head.
"""

from __future__ import annotations

from lanevil_train.models.release import Recognised, Release, resnet_depth

_STAGES = {"0": "conv1", "1": "bn1", "4": "layer1", "5": "layer2", "6": "layer3", "7": "layer4"}
_HEAD = ("conv1.", "cls_layer.", "reg_layer.", "attention_layer.")


def describe(state: dict) -> Recognised | None:
    """What a LaneATT state dict is (backbone, anchors, input height), or None if it is not one."""
    if not {"feature_extractor.0.weight", "conv1.weight", "attention_layer.weight", "cls_layer.weight"} <= state.keys():
        return None
    depth = resnet_depth(state, [f"feature_extractor.{i}." for i in range(4, 8)])  # layer1-4
    backbone = f"resnet{depth}" if depth else "an unknown backbone"
    anchors = state["attention_layer.weight"].shape[0] + 1
    fmap_h = state["attention_layer.weight"].shape[1] // state["conv1.weight"].shape[0]
    return Recognised(f"{backbone}, {anchors} anchors, a {fmap_h}-row feature map ({fmap_h * 32} px high input)",
                      f"experiment=official_laneatt_<tusimple|culane> backbone={backbone} "
                      f"model.head.anchor_frequency_file=<LaneATT>/data/<dataset>_anchors_freq.pt")


def convert(state: dict) -> dict:
    """Official names -> this project's (weights unchanged)."""
    out = {}
    for key, value in state.items():
        if key.startswith("feature_extractor."):
            _, stage, rest = key.split(".", 2)
            out[f"backbone.{_STAGES.get(stage, stage)}.{rest}"] = value
        elif key.startswith(_HEAD):
            out["head." + key] = value
        else:
            out[key] = value  # reported by the strict load as unexpected
    return out


def missing_setting(model) -> str | None:
    """The anchors must be chosen by the repository's frequency file before the weights mean anything."""
    head = model.head
    if head.anchor_selection == "frequency" and not bool(head.anchors_chosen):
        return ("its attention layer follows the anchors the repository's frequency file chose, which the file does "
                "not hold: give model.head.anchor_frequency_file=<LaneATT>/data/<dataset>_anchors_freq.pt")
    return None


RELEASE = Release(family="laneatt", name="LaneATT (lucastabelini/LaneATT)", describe=describe, convert=convert,
                  optional=("head.anchor_index", "head.anchors_chosen"), missing_setting=missing_setting)
