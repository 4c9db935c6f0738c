"""What one official code base's published checkpoints are to this project: how to recognise a file and convert it
(``models/official.py`` loads them; each family's ``official.py`` describes its release)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable


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
