"""What one official code base's published checkpoints are to this project: how to recognise a file and convert it
(``models/official.py`` loads them; each family's ``official.py`` describes its release)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

# torchvision's ResNets: blocks per stage (layer1..layer4) and whether a block is a bottleneck (has a conv3)
RESNET_BLOCKS = {18: ((2, 2, 2, 2), False), 34: ((3, 4, 6, 3), False), 50: ((3, 4, 6, 3), True),
                 101: ((3, 4, 23, 3), True)}


def resnet_depth(state: dict, stages: Sequence[str]) -> int | None:
    """The depth of the torchvision-named ResNet in an official state dict, or None: from the number of blocks under
    each stage's key prefix (``stages``: e.g. ``model.layer1.`` .. ``model.layer4.``, or the first three where a
    network stops at layer3) and whether the first block has a conv3."""
    blocks = tuple(len({k[len(p):].split(".", 1)[0] for k in state if k.startswith(p)}) for p in stages)
    bottleneck = any(k.startswith(f"{stages[0]}0.conv3.") for k in state)
    return next((depth for depth, (counts, is_bottleneck) in RESNET_BLOCKS.items()
                 if counts[:len(blocks)] == blocks and is_bottleneck == bottleneck), None)


@dataclass(frozen=True)
class Recognised:
    """What a file is: its release (e.g. "the TuSimple release, ResNet-18: 100 cells, 56 rows, 4 lanes") and the
    command-line settings that build its network (e.g. "experiment=official_ufld_tusimple backbone=resnet18"), or
    why no network of this project computes it."""

    what: str
    config: str
    # why this project cannot load it at all (e.g. a release of another network than this project's), or ""
    unsupported: str = ""


@dataclass(frozen=True)
class Release:
    """One official code base's checkpoints: how to recognise them and convert them to this project's names."""

    family: str  # model=<family>
    name: str  # e.g. "UFLD v1 (cfzd/Ultra-Fast-Lane-Detection)"
    describe: Callable[[dict], Recognised | None]
    convert: Callable[[dict], dict]
    # converted names of training-only parts a file may or may not carry (e.g. an auxiliary segmentation branch):
    # kept as initialised when the file lacks them, dropped when the network has none
    optional: tuple[str, ...] = ()
    # what the network needs beyond the file before it can take these weights (e.g. LaneATT's anchors chosen by the
    # repository's frequency file): a problem in words, or None
    missing_setting: Callable[[object], str | None] = lambda model: None
    # what in the file this network would compute otherwise (e.g. CLRNet's priors, stored as buffers, against the
    # ones the network derives for its input size): a problem in words, or None; (model, official state dict)
    check: Callable[[object, dict], str | None] = lambda model, state: None
    # what a file of another release differs in from this one's layout (e.g. its first key that is not one of this
    # release's names), said when a run of this family is given it: a problem in words, or None
    difference: Callable[[dict], str | None] = lambda state: None
