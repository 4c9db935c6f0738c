"""The head contract: what every detector family's head is, so LaneDetector, the data pipeline, the metrics, the
defenses and the export treat all families alike (docs/detectors.md describes it for a new family's author).

A head is built as ``Head(in_channels=[...], in_strides=[...], image_size=(H, W), **its config)``: the channels
and strides of the feature maps it reads (the backbone's ``out_indices`` stages, through the neck if the family has
one), in the order given, and the network's input size. Its family config says which strides it reads
(``model.feature_strides``) and whether the backbone is dilated (``model.output_stride``); the builder picks the
backbone stages from them.

- ``forward(features) -> raw``: a dict of tensors only, batch first (no NMS, no Python lists, no
  shape-dependent branches), so that ``torch.onnx.export`` and ``torch.jit.trace`` take it.
- ``encode(lanes, meta=None) -> targets``: the ground-truth lanes of one image (input pixels, (N, 2) arrays,
  y descending) as a dict of numpy arrays of fixed shapes; the loader stacks each key into a batch tensor.
- ``loss(raw, targets) -> dict``: ``loss`` (the total, a scalar), ``per_sample`` (B,) (the total of each
  image: hard-example defenses rank by it) and any number of named scalar parts, every one of which is logged
  as ``train/<name>``.
- ``decode(raw, **options, with_scores=False) -> lanes``: per image, lanes as (N, 2) float arrays in input pixels,
  y descending, sorted left to right. Its keyword options are the family's ``model.decode`` keys (and
  ``task.decode.*``). With the keyword-only ``with_scores=True`` (not a config key: ``decode_options`` leaves it
  out) each image's list holds ``(lane, score)`` pairs instead, the same lanes in the same order, the score a float
  in [0, 1], the family's own confidence of that lane (each family's decode says which); which lanes and points are
  decoded does not change.
"""

from __future__ import annotations

import inspect

import numpy as np
import torch
from torch import nn


class LaneHead(nn.Module):
    """Base class of detector heads; see the module docstring for the contract."""

    def __init__(self, in_channels, in_strides, image_size) -> None:
        super().__init__()
        self.in_channels = [int(c) for c in _as_list(in_channels)]
        self.in_strides = [int(s) for s in _as_list(in_strides)]
        if len(self.in_channels) != len(self.in_strides) or not self.in_channels:
            raise ValueError(f"{type(self).__name__}: in_channels {self.in_channels} and in_strides "
                             f"{self.in_strides} must be non-empty lists of the same length")
        h, w = (int(v) for v in image_size)
        self.image_size = (h, w)

    def forward(self, features: list[torch.Tensor]) -> dict[str, torch.Tensor]:
        raise NotImplementedError

    def encode(self, lanes: list[np.ndarray], meta: dict | None = None) -> dict[str, np.ndarray]:
        raise NotImplementedError

    def loss(self, raw: dict[str, torch.Tensor], targets: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        raise NotImplementedError

    def decode(self, raw: dict[str, torch.Tensor], *, with_scores: bool = False,
               **options) -> list[list[np.ndarray]] | list[list[tuple[np.ndarray, float]]]:
        raise NotImplementedError

    @classmethod
    def decode_options(cls) -> tuple[str, ...]:
        """The keyword options decode takes (the keys model.decode and task.decode may set); `with_scores`, which
        asks for each lane's confidence beside it, is not one of them."""
        named = (inspect.Parameter.POSITIONAL_OR_KEYWORD, inspect.Parameter.KEYWORD_ONLY)
        parameters = list(inspect.signature(cls.decode).parameters.values())[2:]  # after self, raw
        return tuple(p.name for p in parameters if p.kind in named and p.name not in NOT_DECODE_OPTIONS)


# decode's keywords that are not decoding options (no config key sets them): the caller's choice of what comes back
NOT_DECODE_OPTIONS = ("with_scores",)


def lanes_with_scores(lanes: list[np.ndarray], scores, with_scores: bool):
    """The lanes of one image sorted left to right by their first (bottom) point's x, as every decode sorts them;
    with_scores: as (lane, float score) pairs, each lane's score beside it (`scores` one per lane, same order).
    The sort is stable, so the lanes come in the same order either way."""
    scores = [float(s) for s in scores]
    if len(scores) != len(lanes):
        raise ValueError(f"lanes_with_scores: {len(lanes)} lanes but {len(scores)} scores")
    order = sorted(range(len(lanes)), key=lambda i: lanes[i][0, 0])
    if with_scores:
        return [(lanes[i], min(max(scores[i], 0.0), 1.0)) for i in order]
    return [lanes[i] for i in order]


def decode_option_problems(head, options, key: str) -> list[str]:
    """One line naming `key`.<name> for each option that `head` (a head or its class) does not take in decode."""
    accepted = head.decode_options() if hasattr(head, "decode_options") else ()
    name = head.__name__ if isinstance(head, type) else type(head).__name__
    return [f"{key}.{option}: not a decoding option of {name}; it takes {', '.join(accepted) or 'none'}"
            for option in options if option not in accepted]


def check_decode_options(head: nn.Module, options: dict, key: str) -> None:
    """A ValueError naming `key`.<name> for the first option the head's decode does not take."""
    problems = decode_option_problems(head, options, key)
    if problems:
        raise ValueError(problems[0])


def targets_to(targets, device) -> dict[str, torch.Tensor]:
    """A batch's targets (a dict of arrays or tensors) as tensors on `device`."""
    if not isinstance(targets, dict):
        raise TypeError(f"targets must be a dict of arrays (the head's encode output, collated), got "
                        f"{type(targets).__name__}")
    return {k: torch.as_tensor(v).to(device) for k, v in targets.items()}


def _as_list(value) -> list:
    """One value or a sequence of them (a list, a tuple, or the ListConfig Hydra passes) as a list."""
    return [value] if isinstance(value, (int, float, str)) else list(value)
