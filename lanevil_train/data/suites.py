"""Illusion suites as datasets: a set written by task=build, or the same suite generated on the fly.

Items are samples {"image", "lanes", "meta"} whose meta says which case, illusion, category and
severity (0 = the clean original) the image is, so every score can be grouped the paper's way.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from torch.utils.data import Dataset

from lanevil_train.data.datasets import EmptySplitError
from lanevil_train.data.formats import load_image, read_culane, read_tusimple
from lanevil_train.data.formats.builds import BUILD_FILE
from lanevil_train.data.formats.manifest import read_manifest
from lanevil_train.data.illusion_set import Plan, case_source, read_build_record, synthetic_cases, variants
from lanevil_train.errors import prefixed
from lanevil_train.lanes import default_h_samples
from lanevil_train.perturbations import get_perturbation, suite_names

_VARIANT_KEYS = ("case_id", "illusion", "category", "severity", "seed")


class IllusionSetDataset(Dataset):
    """A test set written by `task=build` (manifest.jsonl + TuSimple labels.json or CULane list).

    A set whose build.json says it is not complete (a build killed or still running) is refused; sets written
    before build.json existed have none and are read as they are."""

    def __init__(self, root: str | Path):
        self.root = Path(root)
        self.manifest = read_manifest(self.root / "manifest.jsonl")
        self.culane_metric = None  # the photos' dataset's CULane-style procedure (build.json's plan), if not CULane's
        if (self.root / BUILD_FILE).exists():
            build = read_build_record(self.root)
            self._check_complete(build)
            self.culane_metric = (build.get("plan") or {}).get("culane_metric")
        if not self.manifest:
            raise EmptySplitError(f"the illusion set's manifest {self.root / 'manifest.jsonl'} lists no images "
                                  f"(an empty set; task=build writes one)", "root")
        if (self.root / "labels.json").exists():
            labels = {str(r["raw_file"]): r for r in read_tusimple(self.root / "labels.json", self.root)}
        else:
            labels = {str(r["rel_path"]): r for r in read_culane(self.root / "list" / "test.txt", self.root)}
        missing = [m["image"] for m in self.manifest if m["image"] not in labels]
        if missing:
            raise ValueError(f"{self.root}: {len(missing)} manifest images have no label, e.g. {missing[0]}")
        self.labels = labels

    def _check_complete(self, build: dict) -> None:
        have, want = len(self.manifest), build["images"]
        if not build["complete"]:
            raise ValueError(
                f"illusion set {self.root} is incomplete: {have} of {want} images were built ({BUILD_FILE} is not "
                f"marked complete: the build was interrupted or is still running); rerun task=build with the same "
                f"out_dir ({self.root}) to finish it")
        if have != want:
            raise ValueError(
                f"illusion set {self.root} is marked complete but its manifest lists {have} of {want} images; "
                f"rerun task=build with the same out_dir ({self.root}) to finish it")

    def __len__(self) -> int:
        return len(self.manifest)

    def item_key(self, index: int) -> str:
        return self.manifest[index]["image"]

    def __getitem__(self, index: int) -> dict:
        entry = self.manifest[index]
        label = self.labels[entry["image"]]
        try:
            image = load_image(self.root / entry["image"])
        except (FileNotFoundError, ValueError) as error:
            raise prefixed(error, label["source"]) from None
        h_samples = label.get("h_samples")
        meta = {k: entry[k] for k in _VARIANT_KEYS}
        meta.update(key=entry["image"], image_path=str(self.root / entry["image"]), height=image.shape[0],
                    width=image.shape[1], h_samples=np.asarray(h_samples if h_samples is not None
                                                               else default_h_samples(image.shape[0]), float))
        if self.culane_metric is not None:
            meta["culane_metric"] = self.culane_metric
        return {"image": image, "lanes": label["lanes"], "meta": meta}


def _check_num_cases(num_cases: int) -> None:
    """A clear error naming the argument for a suite without scenes (the severities and repeats: Plan's check)."""
    if not isinstance(num_cases, int) or num_cases < 1:
        raise EmptySplitError(f"num_cases (scenes) must be an integer >= 1, got {num_cases!r}", "num_cases")


class SyntheticIllusionSuite(Dataset):
    """The suite `task=build` would write from simulated scenes, generated on the fly (nothing on disk): the
    illusions (kind="illusions"), the non-illusion corruptions ("corruptions") or illusion pairs ("combined") of
    perturbations.py, named by `illusions` ("all" or a list of the kind's names).

    Items run case by case (original first), and the last case's clean render is cached, so a loader
    without shuffling renders each scene about once.
    """

    def __init__(self, num_cases: int, first_seed: int, size: tuple[int, int] = (720, 1280),
                 illusions: str | list[str] = "all", severities: tuple[int, ...] = (1, 2, 3, 4, 5), repeats: int = 1,
                 kind: str = "illusions"):
        names = suite_names(kind, illusions if isinstance(illusions, str) else list(illusions))
        _check_num_cases(num_cases)
        self._arguments = {"num_cases": num_cases, "first_seed": first_seed, "size": list(size),
                           "illusions": illusions if isinstance(illusions, str) else list(illusions),
                           "severities": list(severities), "repeats": repeats, "kind": kind}
        self.plan = Plan(illusions=names, severities=tuple(severities), repeats=repeats, size=tuple(size), kind=kind)
        self.items = [(case, record) for case in synthetic_cases(num_cases, first_seed)
                      for record in variants(case, self.plan)]
        self._cached: tuple | None = None

    def __len__(self) -> int:
        return len(self.items)

    def description(self) -> dict:
        """What rebuilds this suite (from_description): its constructor's arguments, as JSON values. An evaluation
        writes it beside its results (per_image.suite.json), so the report page can render a record's image again."""
        return {"suite": "synthetic", **self._arguments}

    @classmethod
    def from_description(cls, description: dict) -> SyntheticIllusionSuite:
        """The suite a description() names."""
        args = {k: v for k, v in description.items() if k != "suite"}
        return cls(args["num_cases"], args["first_seed"], tuple(args["size"]), args["illusions"],
                   tuple(args["severities"]), args["repeats"], kind=args["kind"])

    def item_key(self, index: int) -> str:
        return self.items[index][1]["image"]

    def __getitem__(self, index: int) -> dict:
        case, record = self.items[index]
        if self._cached is None or self._cached[0] != case:
            self._cached = (case, case_source(case, self.plan))
        image, lanes, ctx = self._cached[1]
        if record["illusion"] is not None:
            image = get_perturbation(record["illusion"])(image, ctx, record["severity"], record["seed"])
        meta = {k: record[k] for k in _VARIANT_KEYS}
        meta.update(key=record["image"], image_path=None, height=image.shape[0], width=image.shape[1],
                    h_samples=default_h_samples(image.shape[0]))
        return {"image": image, "lanes": lanes, "meta": meta}
