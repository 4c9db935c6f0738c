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
  (``model.head.anchor_frequency_file``). Anchors with equal counts are ordered by a stable sort here (the official
  sort is not stable): a file whose top 1,000 hold ties may order those few anchors differently.
- Every published release (TuSimple, CULane, LLAMAS) is 360x640, S = 72, 1,000 anchors (``cfgs/laneatt_*.yml``):
  the file's shapes cannot tell the dataset, only the backbone.

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
