"""Collate-level data defenses that mix the images of a training batch (MixUp, lane-aware Copy-Paste).

A mixer is `__call__(items) -> items` on processed items (image already normalised, lanes in
input pixels in "input_lanes"), run by the train loader's collate BEFORE the targets are
encoded (see `MixingCollate`), so labels that travel with pasted pixels are encoded too.
"image" and "input_lanes" may change; "lanes" (original-pixel ground truth for scoring) never do.
Inputs are not modified: changed items are shallow copies with new arrays.
"""

from __future__ import annotations

import os

import cv2
import numpy as np
import torch

from lanevil_train.lanes import lane_x_at
from lanevil_train.rules import Rule, check_settings, integer, number, probability


class _SeededMixer:
    """Owns an np.random.Generator made lazily in the process (DataLoader worker) that uses it.

    Without a seed the generator follows `torch.initial_seed()`, which differs per worker and
    follows `pl.seed_everything`; with a seed it is `default_rng([seed, worker_id])`. A generator
    inherited from another process (the mixer was pickled into a worker) is never reused.
    """

    def __init__(self, seed: int | None):
        self.seed = seed
        self._rng: np.random.Generator | None = None
        self._owner: int | None = None

    def generator(self) -> np.random.Generator:
        """This process's generator (created on first use)."""
        if self._rng is None or self._owner != os.getpid():
            info = torch.utils.data.get_worker_info()
            if self.seed is None:
                self._rng = np.random.default_rng(torch.initial_seed())
            else:
                self._rng = np.random.default_rng([int(self.seed), info.id if info is not None else 0])
            self._owner = os.getpid()
        return self._rng

    def __getstate__(self) -> dict:
        state = dict(self.__dict__)
        state["_rng"], state["_owner"] = None, None  # each worker makes its own
        return state


def _check_images(items: list[dict], owner: str) -> None:
    shapes = {np.shape(it["image"]) for it in items}
    if len(shapes) > 1:
        raise ValueError(f"{owner}: all images of a batch must have one shape to be mixed, got {sorted(shapes)}")


def _partner(rng: np.random.Generator, i: int, n: int) -> int:
    """A uniformly chosen index in [0, n) other than i (n >= 2)."""
    j = int(rng.integers(0, n - 1))
    return j + 1 if j >= i else j


class MixUp(_SeededMixer):
    """MixUp (Zhang et al. 2017) for lane detection: image_i <- lam * image_i + (1 - lam) * image_j.

    Anchor regression targets cannot be soft-mixed (a lane half-present is not a lane at half
    an x), so each image keeps its own labels and lam ~ Beta(alpha, alpha) is folded to
    max(lam, 1 - lam) >= 0.5: the labelled image always dominates and the partner's lanes are
    an unlabelled ghost. alpha=0.2 is Zhang et al.'s ImageNet setting; folded, it gives a mean
    lam of about 0.90 (a faint ghost, labels stay credible); alpha=1 would give lam ~ U(0.5, 1).
    Each image is mixed with probability p with another (unmixed) image of the same batch.
    """

    SETTINGS = {"alpha": Rule("a number > 0 (lambda ~ Beta(alpha, alpha))", number(0, low_open=True).test),
                "p": probability()}

    def __init__(self, alpha: float = 0.2, p: float = 0.5, seed: int | None = None):
        check_settings(self.SETTINGS, locals(), "MixUp")
        super().__init__(seed)
        self.alpha = float(alpha)
        self.p = float(p)

    def plan(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """Partner index and lam for each of n images; partner -1 and lam 1.0 where not mixed."""
        partners = np.full(n, -1, dtype=np.int64)
        lams = np.ones(n, dtype=np.float64)
        if n < 2:
            return partners, lams
        for i in range(n):
            if rng.random() < self.p:
                partners[i] = _partner(rng, i, n)
                lam = rng.beta(self.alpha, self.alpha)
                lams[i] = max(lam, 1.0 - lam)
        return partners, lams

    def apply(self, items: list[dict], partners: np.ndarray, lams: np.ndarray) -> list[dict]:
        """Items with image i blended with image partners[i] at weight lams[i] (labels unchanged)."""
        _check_images(items, "MixUp")
        out = []
        for item, j, lam in zip(items, partners, lams):
            if j < 0:
                out.append(item)
                continue
            mixed = lam * item["image"].astype(np.float64) + (1.0 - lam) * items[j]["image"].astype(np.float64)
            out.append({**item, "image": mixed.astype(item["image"].dtype)})
        return out

    def __call__(self, items: list[dict]) -> list[dict]:
        return self.apply(items, *self.plan(len(items), self.generator()))


def lane_band_mask(lane: np.ndarray, height: int, width: int, band: float) -> np.ndarray:
    """Bool (H, W): pixels within `band` px (Euclidean) of the lane's polyline."""
    line = np.full((height, width), 255, np.uint8)
    pts = np.round(lane).astype(np.int32).reshape(-1, 1, 2)
    cv2.polylines(line, [pts], False, 0, thickness=1, lineType=cv2.LINE_8)
    if line.min() > 0:  # the lane lies wholly outside the image
        return np.zeros((height, width), bool)
    dist = cv2.distanceTransform(line, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return dist <= band


def lanes_apart(lane: np.ndarray, others: list[np.ndarray], min_gap: float, height: int) -> bool:
    """True if `lane` is at least min_gap px (in x) from every other lane on every row both cover."""
    rows = np.arange(height, dtype=np.float64)
    xs = lane_x_at(lane, rows)
    for other in others:
        oxs = lane_x_at(other, rows)
        shared = (xs != -2.0) & (oxs != -2.0)
        if np.any(np.abs(xs[shared] - oxs[shared]) < min_gap):
            return False
    return True


class LaneCopyPaste(_SeededMixer):
    """Lane-aware Copy-Paste (Ghiasi et al. 2021): paste donor lanes, with their labels, onto a target.

    For each image (probability p) a donor is drawn from the batch; its lanes are tried in a
    random order, and a lane is pasted when the target then still has at most `max_lanes` lanes
    and the lane stays at least `min_gap` px (in x, on every shared row) from every target lane,
    pasted ones included, so no two labels overlap. Pasting copies the donor's pixels within
    `band` px of the lane polyline and appends the lane to the target's "input_lanes" (re-sorted
    left to right). At most `max_paste` lanes go into one image. min_gap >= band is required, so
    a band never covers a labelled lane's centre line. Keep max_lanes <= the head's max_lanes
    (default 6 = LaneATT's, whose encoder refuses more). Defaults are for ~360x640 inputs: a
    marking is a few px wide, so band=8 carries it plus some road; min_gap=24 is 3 bands.
    """

    SETTINGS = {"p": probability(),
                **{name: Rule("a number of input pixels >= 0", number(0).test) for name in ("band", "min_gap")},
                "max_lanes": integer(1), "max_paste": integer(1)}

    def __init__(self, p: float = 0.5, band: float = 8.0, min_gap: float = 24.0, max_lanes: int = 6,
                 max_paste: int = 1, seed: int | None = None):
        check_settings(self.SETTINGS, locals(), "LaneCopyPaste")
        if min_gap < band:
            raise ValueError(f"LaneCopyPaste: need band <= min_gap (a pasted band must not cover a "
                             f"labelled lane), got band={band}, min_gap={min_gap}")
        super().__init__(seed)
        self.p = float(p)
        self.band = float(band)
        self.min_gap = float(min_gap)
        self.max_lanes = int(max_lanes)
        self.max_paste = int(max_paste)

    def paste(self, target: dict, donor: dict, order: list[int] | None = None) -> dict:
        """The target with the donor's admissible lanes (tried in `order`) pasted; target itself if none."""
        _check_images([target, donor], "LaneCopyPaste")
        height, width = target["image"].shape[-2:]
        lanes = list(target["input_lanes"])
        donor_lanes = donor["input_lanes"]
        mask = np.zeros((height, width), bool)
        pasted = 0
        for k in (range(len(donor_lanes)) if order is None else order):
            if pasted >= self.max_paste or len(lanes) >= self.max_lanes:
                break
            lane = donor_lanes[k]
            if not lanes_apart(lane, lanes, self.min_gap, height):
                continue
            mask |= lane_band_mask(lane, height, width, self.band)
            lanes.append(lane)
            pasted += 1
        if pasted == 0:
            return target
        image = target["image"].copy()
        image[..., mask] = donor["image"][..., mask]  # CxHxW: every channel of the band
        lanes.sort(key=lambda lane: lane[0, 0])  # left to right at each lane's lowest point, as apply_pipeline
        return {**target, "image": image, "input_lanes": lanes}

    def __call__(self, items: list[dict]) -> list[dict]:
        n = len(items)
        if n < 2:
            return list(items)
        rng = self.generator()
        out = []
        for i, item in enumerate(items):
            if rng.random() >= self.p:
                out.append(item)
                continue
            donor = items[_partner(rng, i, n)]  # the donor's own, unpasted lanes and pixels
            order = [int(k) for k in rng.permutation(len(donor["input_lanes"]))]
            out.append(self.paste(item, donor, order))
        return out
