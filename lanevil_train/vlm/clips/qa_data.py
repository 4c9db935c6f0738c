"""(clip, question, answer) training pairs from a clip suite, and the batch a VLM fine-tuning step takes.

A clip suite (ClipSetDataset on disk, or SyntheticClipSuite rendered on the fly) lists clips (each a clean or
perturbed variant of a base clip) and, per base clip, its QA. ClipQADataset pairs every chosen clip variant with
every QA of its base clip, in clip order, so an unshuffled pass renders (or reads) each clip once per QA run.
collate_clip_qa stacks the frames into one uint8 tensor [B, 6, H, W, 3]; in the training step they are the float
`images` (B*6, 3, H, W) in [0, 1] that visual defenses edit (clip_images), beside each frame's lanes when the suite
knows them. MixingClipCollate mixes a batch's clips first (MixUp). WindowShuffleSampler shuffles for training
without rendering a base clip once per pair.
"""

from __future__ import annotations

from typing import Sequence

import numpy as np
import torch
from torch.utils.data import Dataset, Sampler

from lanevil_train.rules import check_settings, integer, one_of
from lanevil_train.vlm.clips.qa_records import prompt_text

VARIANTS = ("clean", "all")
# ClipQADataset's settings a training run gives it (model.fine_tune.variants / aids): checked here, and by the config
# check under those keys before any work.
PAIRING_SETTINGS = {"variants": one_of(*VARIANTS), "aids": integer(0)}
FRAMES_PER_CLIP = 6


class ClipQADataset(Dataset):
    """(clip variant, QA) pairs of a clip suite (ClipSetDataset / SyntheticClipSuite).

    variants: "clean" (severity-0 clips only) or "all"; limit: keep the first `limit` pairs (clip order);
    aids: also pair each chosen clip variant this many times with each of its base clip's training aids (the scene
    description and the open questions that name its facts: qa.training_aids, SyntheticClipSuite.training_aids_for;
    a suite on disk keeps no truth). A pair's QA index is the QA's position, or -(k + 1) for training aid k."""

    def __init__(self, clips, variants: str = "clean", limit: int | None = None, aids: int = 0):
        for needed in ("clip_meta", "qa_for", "__getitem__", "__len__"):
            if not hasattr(clips, needed):
                raise TypeError(f"clips: expected a clip suite (ClipSetDataset or SyntheticClipSuite) with "
                                f"{needed}, got {type(clips).__name__}")
        check_settings(PAIRING_SETTINGS, {"variants": variants, "aids": aids}, "")
        if limit is not None and (isinstance(limit, bool) or not isinstance(limit, int) or limit < 1):
            raise ValueError(f"limit: expected None or an integer >= 1, got {limit!r}")
        if aids and not hasattr(clips, "training_aids_for"):
            raise ValueError(f"aids: {aids} rounds of training aids need the scene truth, which "
                             f"{type(clips).__name__} does not keep; train on a synthetic split (SyntheticClipSuite) "
                             f"or set aids to 0")
        self.clips, self.variants, self.aids = clips, variants, aids
        self.aid_count = len(clips.training_aids_for(clips.clip_meta(0)["base_clip_id"])) if aids and len(clips) else 0
        self.pairs = self._pairs(limit)
        if not self.pairs:
            raise ValueError(f"clips: no {variants} clip with QA in this suite of {len(clips)} clips")
        self._frames: tuple[int, np.ndarray] | None = None

    def _pairs(self, limit: int | None) -> list[tuple[int, int]]:
        """(clip index, QA index within its base clip) of every chosen variant, at most `limit` of them."""
        pairs: list[tuple[int, int]] = []
        for index in range(len(self.clips)):
            meta = self.clips.clip_meta(index)
            if self.variants == "clean" and meta["severity"] != 0:
                continue
            count = (self.clips.qa_count(meta["base_clip_id"]) if hasattr(self.clips, "qa_count")
                     else len(self.clips.qa_for(meta["base_clip_id"])))
            pairs.extend((index, q) for q in [*range(count), *[-(k + 1) for k in range(self.aid_count)] * self.aids])
            if limit is not None and len(pairs) >= limit:
                return pairs[:limit]
        return pairs

    def __len__(self) -> int:
        return len(self.pairs)

    def base_clip_groups(self) -> list[list[int]]:
        """The indices of the pairs, grouped by base clip (every variant and QA of one base clip), in clip order."""
        groups: dict[str, list[int]] = {}
        for index, (clip_index, _) in enumerate(self.pairs):
            groups.setdefault(self.clips.clip_meta(clip_index)["base_clip_id"], []).append(index)
        return list(groups.values())

    def _clip_frames(self, index: int) -> np.ndarray:
        """The 6 frames of clip `index` as one uint8 array [6, H, W, 3]; the last clip read is kept."""
        if self._frames is None or self._frames[0] != index:
            frames = self.clips[index]["frames"]
            if len(frames) != FRAMES_PER_CLIP:
                raise ValueError(f"clip {self.clips.clip_meta(index)['clip_id']}: expected {FRAMES_PER_CLIP} frames, "
                                 f"got {len(frames)}")
            self._frames = (index, np.stack([np.asarray(frame, dtype=np.uint8) for frame in frames]))
        return self._frames[1]

    def __getitem__(self, index: int) -> dict:
        clip_index, qa_index = self.pairs[index]
        meta = self.clips.clip_meta(clip_index)
        qa = (self.clips.training_aids_for(meta["base_clip_id"])[-qa_index - 1] if qa_index < 0
              else self.clips.qa_for(meta["base_clip_id"])[qa_index])
        item = {"frames": self._clip_frames(clip_index), "question": prompt_text(qa), "answer": qa["answer"],
                "key": f"{meta['clip_id']}/{qa['qa_id']}",
                "meta": {**meta, "qa_id": qa["qa_id"], "qa_category": qa["category"], "qa_type": qa["type"]}}
        if hasattr(self.clips, "lanes_for"):  # each frame's lane polylines (pixels), for AAM's ground truth
            item["lanes"] = self.clips.lanes_for(meta["base_clip_id"])
        return item


def collate_clip_qa(items: Sequence[dict]) -> dict:
    """A batch of ClipQADataset items: frames as one uint8 tensor [B, 6, H, W, 3], the texts and metas as lists."""
    if not items:
        raise ValueError("items: expected at least one (clip, QA) item to collate, got none")
    shapes = {tuple(np.shape(item["frames"])) for item in items}
    if len(shapes) != 1:
        keys = ", ".join(f"{item['key']} {tuple(np.shape(item['frames']))}" for item in items[:4])
        raise ValueError(f"items: the clips of a batch must share one frame size, got {keys}")
    frames = torch.from_numpy(np.stack([np.asarray(item["frames"], dtype=np.uint8) for item in items]))
    batch = {"frames": frames, "questions": [item["question"] for item in items],
             "answers": [item["answer"] for item in items], "keys": [item["key"] for item in items],
             "meta": [item["meta"] for item in items]}
    if all(item.get("lanes") is not None for item in items):  # per frame, in frame order: images' lanes
        batch["lanes"] = [[np.asarray(lane, dtype=np.float64) for lane in frame_lanes]
                          for item in items for frame_lanes in item["lanes"]]
    return batch


def clip_images(frames: torch.Tensor) -> torch.Tensor:
    """A batch's uint8 frames [B, F, H, W, 3] as the float images (B*F, 3, H, W) in [0, 1] that training feeds the
    model and visual defenses edit (BatchAdapter(images="images", lanes="lanes"))."""
    if not isinstance(frames, torch.Tensor) or frames.ndim != 5 or frames.dtype != torch.uint8 or \
            frames.shape[-1] != 3:
        got = (f"{frames.dtype} tensor {tuple(frames.shape)}" if isinstance(frames, torch.Tensor)
               else type(frames).__name__)
        raise ValueError(f"batch['frames']: expected a uint8 tensor [B, 6, H, W, 3], got {got}")
    return frames.flatten(0, 1).permute(0, 3, 1, 2).float().div(255.0).contiguous()


class MixingClipCollate:
    """collate_clip_qa after a batch mixer (data.mixers.MixUp) has mixed the clips: each clip's frames are the
    mixer's `image` (all frames of a clip blended with one partner clip at one weight); questions, answers and
    lanes stay the clip's own."""

    def __init__(self, mixer):
        self.mixer = mixer

    def __call__(self, items: Sequence[dict]) -> dict:
        mixed = self.mixer([{"image": np.asarray(item["frames"])} for item in items])
        return collate_clip_qa([{**item, "frames": new["image"]} for item, new in zip(items, mixed)])


class WindowShuffleSampler(Sampler):
    """A shuffle that keeps renders local: each epoch the base clips are put in a random order, cut into windows of
    `window` base clips, and the pairs of each window (all variants x QA of its clips) are shuffled together. A clip
    suite that keeps its last `window` base clips' renders (SyntheticClipSuite(cache_clips=window)) then renders
    each base clip once per epoch, not once per pair; a batch still mixes clips of `window` scenes. The order
    depends on `seed` and the epoch (set_epoch, which Lightning calls), so a resumed epoch replays the same order."""

    def __init__(self, dataset: ClipQADataset, window: int, seed: int = 0):
        if isinstance(window, bool) or not isinstance(window, int) or window < 1:
            raise ValueError(f"window: expected an integer >= 1 (base clips shuffled together), got {window!r}")
        self.groups, self.window, self.seed, self.epoch = dataset.base_clip_groups(), window, int(seed), 0
        self._skip = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def skip(self, count: int) -> None:
        """The next pass leaves out the first `count` pairs of its order (those a resumed run already trained on)."""
        if isinstance(count, bool) or not isinstance(count, int) or count < 0:
            raise ValueError(f"count: expected an integer >= 0, got {count!r}")
        self._skip = count

    def __len__(self) -> int:
        return sum(len(group) for group in self.groups)

    def __iter__(self):
        rng = np.random.default_rng([self.seed, self.epoch])
        order = rng.permutation(len(self.groups))
        indices = [int(i) for start in range(0, len(order), self.window)
                   for i in rng.permutation(np.concatenate([self.groups[g] for g in order[start:start + self.window]]))]
        skip, self._skip = self._skip, 0
        return iter(indices[skip:])
