"""LightningDataModule over any sample datasets: transforms, target encoding and batching."""

from __future__ import annotations

from typing import Callable

import numpy as np
import pytorch_lightning as pl
import torch
from torch.utils.data import DataLoader, Dataset

from lanevil_train.data.normalization import DEFAULT_NORMALIZATION
from lanevil_train.data.resize import DEFAULT_RESIZE
from lanevil_train.data.transforms import LaneSampleProcessor
from lanevil_train.errors import prefixed
from lanevil_train.rules import is_int


class ProcessedDataset(Dataset):
    """A dataset whose samples go through a processor (transform + target encoding) when read."""

    def __init__(self, base: Dataset, processor):
        self.base = base
        self.processor = processor

    def __len__(self) -> int:
        return len(self.base)

    def __getitem__(self, index: int) -> dict:
        sample = self.base[index]
        try:
            return self.processor(sample)
        except ValueError as error:  # name the sample: the DataLoader worker's traceback does not
            meta = sample.get("meta") or {}
            where = meta.get("source") or meta.get("case_id") or f"sample {index}"
            raise prefixed(error, where) from error


def collate_lanes(items: list[dict]) -> dict:
    """Stack images and encoded targets; keep lanes and meta as per-sample lists (they vary in size).

    batch = {"images": (B,3,H,W) float, "targets": {key: (B, ...) tensor} (if encoded: each key of the head's
             encode output stacked), "lanes": [[lane, ...], ...] in original pixels, "meta": [dict, ...]}
    """
    batch = {
        "images": torch.from_numpy(np.stack([it["image"] for it in items])),
        "lanes": [it["lanes"] for it in items],
        "input_lanes": [it["input_lanes"] for it in items],
        "meta": [it["meta"] for it in items],
    }
    if "target" in items[0]:
        batch["targets"] = {key: torch.from_numpy(np.stack([it["target"][key] for it in items]))
                            for key in items[0]["target"]}
    return batch


class MixingCollate:
    """Train collate with a batch mixer: mix the (unencoded) items, THEN encode targets, then collate.

    The mixer may move labels between images (copy-paste), so encoding has to follow it.
    A class, not a closure, so DataLoader workers can pickle it.
    """

    def __init__(self, mixer: Callable[[list[dict]], list[dict]], encode: Callable | None = None):
        self.mixer = mixer
        self.encode = encode

    def __call__(self, items: list[dict]) -> dict:
        items = self.mixer(items)
        if self.encode is not None:
            items = [{**it, "target": self.encode(it["input_lanes"], it["meta"])} for it in items]
        return collate_lanes(items)


def encoder_max_lanes(encode: Callable | None) -> int | None:
    """The most lanes `encode` takes per image: the `max_lanes` of the head whose bound method it is
    (builders pass `model.head.encode`; the LaneATT head has `max_lanes`, set from data.max_lanes), or of
    the encoder object itself; None when it has no such limit."""
    owner = getattr(encode, "__self__", encode)
    value = getattr(owner, "max_lanes", None)
    return int(value) if is_int(value) else None


def check_lane_counts(dataset: Dataset | None, max_lanes: int, split: str = "train") -> None:
    """Before any training: raise ValueError naming the first record (its source, "file:line") with more
    lanes than max_lanes, which the target encoder would reject at that sample mid-epoch.

    Only datasets of records (a `.records` list, as TuSimple / CULane) are checked; their lanes are
    counted as labelled (lanes of at least 2 points), without reading images. A lane wholly in the
    cropped sky would not reach the encoder, so this is strict for such rare labels.
    """
    records = getattr(dataset, "records", None)
    if not records:
        return
    counts = [sum(1 for lane in record.get("lanes") or [] if len(lane) >= 2) for record in records]
    most = max(counts)
    if most <= max_lanes:
        return
    first = next(i for i, n in enumerate(counts) if n > max_lanes)
    record = records[first]
    source = record.get("source") or record.get("raw_file") or record.get("image_path") or f"record {first}"
    over = sum(1 for n in counts if n > max_lanes)
    raise ValueError(
        f"{source}: {counts[first]} lanes, but data.max_lanes={max_lanes} (the model head's max_lanes) allows at "
        f"most {max_lanes} per image; {over} image(s) of the {split} split have more (up to {most}). Raise "
        f"data.max_lanes to at least {most}, or remove the extra lanes from the labels")


class LaneDataModule(pl.LightningDataModule):
    """Train/val/test loaders over sample datasets; `encode` is the detector family's target encoder.

    `normalize` is the input normalisation preset (data/normalization.py) of both processors, `resize` their
    resize filter (data/resize.py).
    `train_mixer` (e.g. mixers.MixUp) mixes each train batch before its targets are encoded;
    val and test batches are never mixed. When `encode` has a lane limit (the head's max_lanes, see
    encoder_max_lanes) every record dataset is checked against it here, before any training.
    """

    def __init__(self, train: Dataset | None, val: Dataset | None, test: Dataset | None,
                 input_size: tuple[int, int], batch_size: int = 8, num_workers: int = 0,
                 augment: bool = True, encode: Callable | None = None, train_transforms: list | None = None,
                 crop_top: float = 0.0, train_mixer: Callable[[list[dict]], list[dict]] | None = None,
                 normalize: str = DEFAULT_NORMALIZATION, resize: str = DEFAULT_RESIZE):
        super().__init__()
        self.sets = {"train": train, "val": val, "test": test}
        self.input_size = tuple(input_size)
        self.batch_size = batch_size
        self.num_workers = num_workers
        self.train_mixer = train_mixer
        # with a mixer the train items leave the processor unencoded and MixingCollate encodes them
        train_encode = encode if train_mixer is None else None
        self.train_processor = LaneSampleProcessor(self.input_size, augment, train_encode, train_transforms, crop_top,
                                                   normalize, resize)
        self.eval_processor = LaneSampleProcessor(self.input_size, False, encode, crop_top=crop_top,
                                                  normalize=normalize, resize=resize)
        self.train_collate = collate_lanes if train_mixer is None else MixingCollate(train_mixer, encode)
        self.max_lanes = encoder_max_lanes(encode)
        if self.max_lanes is not None:
            for split, base in self.sets.items():
                check_lane_counts(base, self.max_lanes, split)

    def _loader(self, split: str, shuffle: bool) -> DataLoader:
        base = self.sets[split]
        if base is None:
            raise ValueError(f"no {split} dataset was configured (data.{split})")
        processor = self.train_processor if split == "train" else self.eval_processor
        collate = self.train_collate if split == "train" else collate_lanes
        return DataLoader(ProcessedDataset(base, processor), batch_size=self.batch_size, shuffle=shuffle,
                          num_workers=self.num_workers, collate_fn=collate,
                          persistent_workers=self.num_workers > 0)

    def train_dataloader(self) -> DataLoader:
        return self._loader("train", shuffle=True)

    def val_dataloader(self) -> DataLoader:
        return self._loader("val", shuffle=False)

    def test_dataloader(self) -> DataLoader:
        return self._loader("test", shuffle=False)
