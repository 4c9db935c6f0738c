"""Datasets yielding samples {"image", "lanes", "meta"}: simulated scenes, TuSimple, CULane, LLAMAS and CurveLanes
folders.

Every sample's meta carries a stable "case_id" and the "h_samples" rows at which the TuSimple
metric scores it; a dataset scored by another CULane-style procedure than CULane's says which in "culane_metric"
(LLAMAS: "llamas", see lanevil_train/metrics/llamas.py; CurveLanes: "curvelanes", lanevil_train/metrics/curvelanes.py).

A split's labels alone, without its images where the labels suffice: `labelled_lanes` (each item's lanes and image
size) and `input_lane_sets` (each item's lanes in a network input's pixels, e.g. for counting which LaneATT anchors a
train split uses, tasks/detector/anchor_use.py).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
from torch.utils.data import Dataset

from lanevil_train.data.formats import load_image, read_culane, read_tusimple
from lanevil_train.data.formats.curvelanes import image_size_of, read_curvelanes
from lanevil_train.data.formats.llamas import read_llamas
from lanevil_train.data.preprocessor import lanes_to_input
from lanevil_train.errors import prefixed
from lanevil_train.lanes import default_h_samples, lane_extent_problem
from lanevil_train.sim import render_scene


class EmptySplitError(ValueError):
    """A dataset that would hold no samples. `argument` names the dataset argument at fault (label_files,
    list_file, num_scenes), so a caller that knows the config key (data.train ...) can name the key to change."""

    def __init__(self, message: str, argument: str | None = None):
        super().__init__(message)
        self.argument = argument


class SyntheticLaneDataset(Dataset):
    """Scenes rendered by the simulator: scene i is seed first_seed + i, so a split is a seed range.

    size is the rendered (H, W); lanes are exact (projected), scored on TuSimple's rows scaled to H.
    cache=True renders each scene once and keeps it in memory (about 0.7 MB per scene at 360x640).
    """

    def __init__(self, num_scenes: int, first_seed: int = 0, size: tuple[int, int] = (720, 1280),
                 cache: bool = False):
        if num_scenes < 1:
            raise EmptySplitError(f"a split of simulated scenes needs num_scenes >= 1, got {num_scenes}", "num_scenes")
        if len(size) != 2 or min(size) < 16:
            raise ValueError(f"size must be (H, W) with both >= 16, got {size}")
        self.num_scenes = int(num_scenes)
        self.first_seed = int(first_seed)
        self.size = (int(size[0]), int(size[1]))
        self.cache = cache
        self._cache: dict[int, dict] = {}

    def __len__(self) -> int:
        return self.num_scenes

    def case_id(self, index: int) -> str:
        return f"sim-{self.first_seed + index:07d}"

    def item_key(self, index: int) -> str:
        """A unique, stable name for item `index` (what resumable evaluation skips by)."""
        return self.case_id(index)

    def __getitem__(self, index: int) -> dict:
        if not 0 <= index < self.num_scenes:
            raise IndexError(index)
        if index in self._cache:
            return self._cache[index]
        height, width = self.size
        seed = self.first_seed + index
        sample = render_scene(seed, width=width, height=height)
        sample["meta"] = {**sample["meta"], "case_id": self.case_id(index),
                          "h_samples": default_h_samples(height)}
        if self.cache:
            self._cache[index] = sample
        return sample


class _RecordDataset(Dataset):
    """Samples from format records {"image_path", "lanes", "source", ...}: the image is read when asked for.

    A record's "source" is the label file and line it came from; a bad image is reported with it.
    """

    culane_metric: str | None = None  # the CULane-style procedure that scores this dataset, when not CULane's

    def __init__(self, records: list[dict]):
        self.records = records

    def __len__(self) -> int:
        return len(self.records)

    def item_key(self, index: int) -> str:
        """The dataset's own name for the image: TuSimple's raw_file, CULane's list path."""
        record = self.records[index]
        return str(record.get("raw_file") or record.get("rel_path") or record["image_path"])

    def _image(self, index: int) -> np.ndarray:
        """Record `index`'s image (a bad one reported with the record's source)."""
        record = self.records[index]
        try:
            return load_image(record["image_path"])
        except (FileNotFoundError, ValueError) as error:
            raise prefixed(error, record.get("source", f"record {index}")) from None

    def labelled_lanes(self) -> Iterator[tuple[list[np.ndarray], tuple[int, int]]]:
        """Each record's lanes (float64, original pixels) and its image's (H, W), from the labels alone: every image
        taken to be the first one's size (one image read), a record whose lanes do not fit that size read for its
        own."""
        if not self.records:
            return
        size = self._image(0).shape[:2]
        for index, record in enumerate(self.records):
            lanes = [np.asarray(lane, dtype=np.float64) for lane in record.get("lanes") or []]
            own = size
            if any(lane_extent_problem(lane, *size) for lane in lanes):
                own = self._image(index).shape[:2]
            yield lanes, own

    def __getitem__(self, index: int) -> dict:
        record = self.records[index]
        image = self._image(index)
        h_samples = record.get("h_samples")
        if h_samples is None:
            h_samples = default_h_samples(image.shape[0])
        source = str(record.get("source") or self.item_key(index))
        where = source if record.get("lines_path") is None else f"{source} (lanes in {record['lines_path']})"
        _check_lane_extent(where, record["lanes"], image.shape[0], image.shape[1])
        meta = {"case_id": self.item_key(index), "source": source,
                "h_samples": np.asarray(h_samples, dtype=np.float64),
                "image_path": str(record["image_path"]), "height": image.shape[0], "width": image.shape[1]}
        if self.culane_metric is not None:
            meta["culane_metric"] = self.culane_metric
        return {"image": image, "lanes": record["lanes"], "meta": meta}


def _check_lane_extent(source: str, lanes: list[np.ndarray], height: int, width: int) -> None:
    """Raise ValueError (starting with the record's source, "file:line") when a lane does not fit the image:
    labels meant for another image size. Points a little outside are fine (CULane extends lanes to the
    bottom row, x can be far out): the margins are lanevil_train.lanes.LANE_X_MARGIN_FRAC / _Y_."""
    for i, lane in enumerate(lanes):
        problem = lane_extent_problem(lane, height, width)
        if problem is not None:
            raise ValueError(f"{source}: lanes[{i}] does not fit the {width}x{height} image: {problem}")


def labelled_lanes(dataset) -> Iterator[tuple[list[np.ndarray], tuple[int, int]]]:
    """Each item's lanes (original pixels) and its image's (H, W), in order: a dataset of records (TuSimple, CULane,
    LLAMAS) from its labels (`_RecordDataset.labelled_lanes`), any other (simulated scenes) item by item."""
    own = getattr(dataset, "labelled_lanes", None)
    if own is not None:
        yield from own()
        return
    for index in range(len(dataset)):
        sample = dataset[index]
        yield sample["lanes"], sample["image"].shape[:2]


def input_lane_sets(dataset, input_size: tuple[int, int], crop_top: float = 0.0) -> Iterator[list[np.ndarray]]:
    """Each item's lanes in the pixels of a network input of input_size (H, W) whose images lose their top crop_top
    first, as the datamodule feeds them without augmentation (preprocessor.lanes_to_input), read as
    `labelled_lanes` reads them."""
    for lanes, size in labelled_lanes(dataset):
        yield lanes_to_input(lanes, size, input_size, crop_top)


class TuSimpleDataset(_RecordDataset):
    """A TuSimple-format dataset: JSON-lines label files under root, images at root/raw_file."""

    def __init__(self, root: str | Path, label_files: list[str] | str, check_images: bool = True):
        root = Path(root)
        files = [label_files] if isinstance(label_files, (str, Path)) else list(label_files)
        if not files:
            raise EmptySplitError("no TuSimple label file given (label_files is an empty list)", "label_files")
        paths = [root / f for f in files]
        super().__init__(read_tusimple(paths, root, check_images=check_images))
        if not self.records:
            raise EmptySplitError(f"the TuSimple label file(s) {', '.join(map(str, paths))} list no images",
                                  "label_files")


class CULaneDataset(_RecordDataset):
    """A CULane-format dataset: a list file of image paths under root, `<image>.lines.txt` beside each."""

    def __init__(self, root: str | Path, list_file: str | Path, check_images: bool = True):
        root = Path(root)
        super().__init__(read_culane(root / list_file, root, check_images=check_images))
        if not self.records:
            raise EmptySplitError(f"the CULane list file {root / list_file} lists no images", "list_file")


class LLAMASDataset(_RecordDataset):
    """A LLAMAS folder: ``labels/<split>/<recording>/<name>.json``, images at ``color_images/<split>/...``.

    ``split`` is the folder name (train, valid; test has no public labels). The lanes are the official l1, l0, r0,
    r1 per-row lanes (data/formats/llamas.py); the images are scored with the official LLAMAS procedure
    (metrics/llamas.py)."""

    culane_metric = "llamas"

    def __init__(self, root: str | Path, split: str = "valid", check_images: bool = True):
        root = Path(root)
        super().__init__(read_llamas(root, split, check_images=check_images))
        if not self.records:
            where = root / ("color_images/test" if split == "test" else f"labels/{split}")
            raise EmptySplitError(f"the LLAMAS {split} split ({where}) holds no "
                                  f"{'images' if split == 'test' else 'labels'}", "split")


class CurveLanesDataset(_RecordDataset):
    """A CurveLanes folder: ``<split>/<split>.txt`` listing ``images/<name>.jpg``, labels at
    ``<split>/labels/<name>.lines.json`` (data/formats/curvelanes.py).

    ``split`` is the folder name (train, valid; test has no public labels); ``list_file`` (under root) replaces the
    official list, e.g. a subset. Images differ in size (2560x1440, 1570x660, 1280x720); each is scored with the
    CurveLanes procedure (metrics/curvelanes.py: 5 px lanes on a 224x224 canvas)."""

    culane_metric = "curvelanes"

    def __init__(self, root: str | Path, split: str = "valid", check_images: bool = True,
                 list_file: str | Path | None = None):
        root = Path(root)
        super().__init__(read_curvelanes(root, split, check_images=check_images, list_file=list_file))
        if not self.records:
            where = root / (list_file if list_file is not None else f"{split}/{split}.txt")
            raise EmptySplitError(f"the CurveLanes list file {where} lists no images", "list_file")

    def labelled_lanes(self) -> Iterator[tuple[list[np.ndarray], tuple[int, int]]]:
        """Each record's lanes and its image's (H, W), read from the image's header (the sizes differ)."""
        for record in self.records:
            yield [np.asarray(lane, dtype=np.float64) for lane in record["lanes"]], image_size_of(record["image_path"])
