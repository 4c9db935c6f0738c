"""The published UFLD v1 checkpoints (cfzd/Ultra-Fast-Lane-Detection, read at 353df10): recognised and converted.

Facts of the official code this conversion rests on:

- ``test.py`` l. 32-40: the weights are the file's ``'model'`` entry, ``module.`` prefixes (DataParallel) dropped,
  loaded non-strictly into a network built with ``use_aux=False``: a training file carries the auxiliary
  segmentation branch, a published one may or may not.
- ``model/model.py``: the backbone is ``self.model`` (l. 32), a wrapper (``model/backbone.py`` l. 38-45) holding
  torchvision's ResNet stages under their own names: ``model.conv1``, ``model.bn1``, ``model.layer1..4``;
  ``pool`` a 1x1 conv to 8 channels (l. 66); ``cls`` Linear(1800, 2048), ReLU, Linear(2048, total) (l. 60-64),
  its output viewed as (griding_num + 1, rows, lanes) (l. 90); the auxiliary branch ``aux_header2/3/4`` and
  ``aux_combine`` of ``conv_bn_relu`` blocks (attributes ``conv``, ``bn``) with a final 1x1 ``Conv2d``.
- The releases: TuSimple 100 cells, 56 row anchors (``test.py`` l. 25, ``configs/tusimple.py`` l. 22), CULane 200
  cells, 18 rows (l. 23, ``configs/culane.py`` l. 21), 4 lanes each (``num_lanes``); ResNet-18 and -34 published.

This project's UFLD head keeps the same layers (``head.pool``, ``head.cls.0``, ``head.cls.2`` with the same output
order, ``head.aux.headers.<i>.<j>.{0,1}``, ``head.aux.combine``) and timm's ResNet the torchvision names, so the
conversion renames only; the auxiliary branch is optional either way (training-only).
"""

from __future__ import annotations

import re

from lanevil_train.models.release import Recognised, Release, resnet_depth

RELEASES = {(100, 56): "tusimple", (200, 18): "culane"}  # (cells, rows) of the published files -> dataset
NUM_LANES = 4
_AUX_HEADERS = {"aux_header2": 0, "aux_header3": 1, "aux_header4": 2}
_BLOCK = {"conv": "0", "bn": "1"}


def describe(state: dict) -> Recognised | None:
    """The release of a UFLD v1 state dict (its row-classifier's size and backbone), or None if it is not one."""
    if not {"pool.weight", "cls.0.weight", "cls.2.weight", "model.conv1.weight"} <= state.keys():
        return None
    total = state["cls.2.weight"].shape[0]
    depth = resnet_depth(state, [f"model.layer{i}." for i in range(1, 5)])
    backbone = f"resnet{depth}" if depth else "an unknown backbone"
    for (cells, rows), dataset in RELEASES.items():
        if total == (cells + 1) * rows * NUM_LANES:
            return Recognised(f"the {dataset} release, {backbone}: {cells} cells, {rows} row anchors, "
                              f"{NUM_LANES} lanes", f"experiment=official_ufld_{dataset} backbone={backbone}")
    return Recognised(f"an unpublished setting, {backbone}: {total} row-classifier outputs",
                      f"model=ufld backbone={backbone} and model.head.num_cells, row_anchors, data.max_lanes giving "
                      f"(num_cells + 1) x rows x max_lanes = {total}")


def _aux_name(key: str) -> str:
    """aux_header3.1.bn.weight -> head.aux.headers.1.1.1.weight; aux_combine.0.conv.weight ->
    head.aux.combine.0.0.weight; aux_combine.4.weight (the last 1x1 conv) -> head.aux.combine.4.weight."""
    part, rest = key.split(".", 1)
    match = re.match(r"(\d+)\.(conv|bn)\.(.+)", rest)
    if match:
        rest = f"{match.group(1)}.{_BLOCK[match.group(2)]}.{match.group(3)}"
    if part == "aux_combine":
        return f"head.aux.combine.{rest}"
    return f"head.aux.headers.{_AUX_HEADERS[part]}.{rest}"


def convert(state: dict) -> dict:
    """Official names -> this project's (weights unchanged)."""
    out = {}
    for key, value in state.items():
        if key.startswith("model."):
            out["backbone." + key[len("model."):]] = value
        elif key.startswith(("pool.", "cls.")):
            out["head." + key] = value
        elif key.split(".", 1)[0] in (*_AUX_HEADERS, "aux_combine"):
            out[_aux_name(key)] = value
        else:
            out[key] = value  # reported by the strict load as unexpected
    return out


RELEASE = Release(family="ufld", name="UFLD v1 (cfzd/Ultra-Fast-Lane-Detection)", describe=describe, convert=convert,
                  optional=("head.aux.",))
