"""Write an illusion test set to disk: each case's clean original plus its perturbed variants.

Output (root/): images/<case>/<variant>.png, labels (TuSimple JSON lines `labels.json`, or CULane
`.lines.txt` beside each image plus `list/test.txt`), and `manifest.jsonl` (data/formats/manifest.py).

Safe to kill at any instant, and a rerun with the same root finishes the set as if nothing had happened:
- every file is written atomically (files/atomic.py), and a rerun first deletes the temporaries a kill
  left behind;
- per image, the image (and its .lines.txt) comes first, then its labels.json line, then its manifest line,
  each durable before the next, so a manifest line promises everything before it;
- the manifest is a ResultsLog keyed by image: a rerun cuts a torn last line and skips the images it lists,
  and `_repair_labels` drops label lines of images the manifest does not list (yet);
- `build.json` (BUILD_FILE) says what the set should hold (image and case counts, the plan) and is written before
  the first image with "complete": false and rewritten with "complete": true after the last, so a reader
  (suites.IllusionSetDataset) can refuse a set a kill left half-built. It holds no timestamps: a rerun ends
  byte-identical to an uninterrupted build.

Photo cases are checked before any image is written: each image's size is read from its header (PIL, lazy) and its
lanes must give a ground plane (unless plan.fallback); errors name the case's label file:line and image.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import cv2
import numpy as np

from lanevil_train.data.formats import builds, load_image, write_culane_lanes
from lanevil_train.data.formats.builds import map_jobs, write_build_record
from lanevil_train.data.formats.manifest import manifest_record, read_manifest
from lanevil_train.errors import prefixed
from lanevil_train.files.atomic import atomic_write_bytes, atomic_write_text
from lanevil_train.illusions import GroundPlaneError, context_from_lanes, context_from_scene, fallback_context
from lanevil_train.lanes import default_h_samples, lanes_to_rows
from lanevil_train.perturbations import case_perturbations, get_perturbation, suite_names
from lanevil_train.progress import progress_counter
from lanevil_train.results_log import ResultsLog
from lanevil_train.rules import check_settings, int_list, integer, number
from lanevil_train.sim import build_scene, render_scene, sample_scene_params
from lanevil_train.taxonomy import SEVERITIES


@dataclass(frozen=True)
class Case:
    """One source image: a simulated scene (seed, frame) or a file with its lanes."""

    case_id: str
    seed: int
    frame: int = 0
    image_path: str | None = None  # a real photo; None for a simulated scene
    lanes: tuple = ()              # the photo's lanes (pixels)
    source: str | None = None      # where the photo's labels came from ("file:line"), for error messages


@dataclass(frozen=True)
class Plan:
    """What to write for every case."""

    # The ranges of its numbers, by the names the tasks' configs give them (task.severities, task.repeats,
    # task.frame_step_m): checked by the constructor and, by key, by the config check before any work.
    SETTINGS = {"severities": int_list(SEVERITIES[0], SEVERITIES[-1]), "repeats": integer(1),
                "frame_step_m": number(0, low_open=True)}

    illusions: tuple[str, ...]
    severities: tuple[int, ...] = (1, 2, 3, 4, 5)
    repeats: int = 1               # perturbed variants per (illusion, severity), each with its own seed
    size: tuple[int, int] = (720, 1280)  # (H, W) of simulated scenes
    frame_step_m: float = 4.0      # camera advance between frames of a simulated case
    label_format: str = "tusimple"  # "tusimple" | "culane"
    fallback: bool = False         # photos whose lanes cannot define a ground plane: fallback camera
    image_ext: str = ".png"
    kind: str = "illusions"        # perturbations.SUITE_KINDS: illusions | corruptions | combined (`illusions` are
                                   # then corruption names, or the illusions a combined case draws its pairs from)
    culane_metric: str | None = None  # the photos' dataset's CULane-style procedure, when not CULane's (datasets.py
                                      # culane_metric: "llamas", "curvelanes"); the set's images are scored with it

    def __post_init__(self) -> None:
        check_settings(self.SETTINGS, {name: getattr(self, name) for name in self.SETTINGS}, "task")


def synthetic_cases(num_cases: int, first_seed: int, frames: int = 1) -> list[Case]:
    """Cases from simulated scenes: case i is scene seed first_seed + i, seen from `frames` positions."""
    return [Case(f"sim-{first_seed + i:07d}-f{f}", first_seed + i, f) for i in range(num_cases) for f in range(frames)]


def dataset_cases(records: list[dict]) -> list[Case]:
    """Cases from format records (read_tusimple / read_culane)."""
    out = []
    for i, record in enumerate(records):
        name = str(record.get("raw_file") or record.get("rel_path") or record["image_path"])
        out.append(Case(name, i, 0, str(record["image_path"]), tuple(np.asarray(lane) for lane in record["lanes"]),
                        record.get("source")))
    return out


def case_where(case: Case) -> str:
    """How messages name a photo case: "labels.json:12 (image /data/clips/x/20.jpg)"."""
    image = f"image {case.image_path}"
    return f"{case.source} ({image})" if case.source else image


def variants(case: Case, plan: Plan) -> list[dict]:
    """Manifest records (without files) of every image of a case: the original first, then each of the case's
    perturbations (perturbations.case_perturbations) x severity x repeat."""
    folder = case.case_id.replace("/", "_").replace(".", "_")
    records = [{"image": f"images/{folder}/original{plan.image_ext}", "case_id": case.case_id, "illusion": None,
                "category": None, "severity": 0, "seed": case.seed}]
    for name in case_perturbations(plan.kind, plan.illusions, case.seed):
        category = get_perturbation(name).category
        for severity in plan.severities:
            for r in range(plan.repeats):
                records.append({"image": f"images/{folder}/{name}_s{severity}_r{r}{plan.image_ext}",
                                "case_id": case.case_id, "illusion": name, "category": category,
                                "severity": severity, "seed": case.seed * 1000 + r})
    for record in records:
        record["source_image"] = records[0]["image"]
    return records


def case_source(case: Case, plan: Plan):
    """(clean image, lanes, illusion context) of a case; a corruption suite's photos need no context (None)."""
    if case.image_path is None:
        params = sample_scene_params(case.seed)
        params = params.replace(travel=params.travel + case.frame * plan.frame_step_m)
        h, w = plan.size
        sample = render_scene(case.seed, params, width=w, height=h)
        return sample["image"], sample["lanes"], context_from_scene(build_scene(case.seed, params, w, h))
    try:
        image = load_image(case.image_path)
        lanes = [np.asarray(lane, dtype=np.float64) for lane in case.lanes]
        if plan.kind == "corruptions":
            return image, lanes, None
        try:
            ctx = context_from_lanes(lanes, image.shape[:2])
        except GroundPlaneError:
            if not plan.fallback:
                raise
            ctx = fallback_context(image.shape[:2])
    except (ValueError, OSError) as error:
        raise prefixed(error, case_where(case)) from error
    return image, lanes, ctx


def _header_size(path: str) -> tuple[int, int] | None:
    """(height, width) as load_image will see it, from the file's header only; None if PIL cannot tell."""
    try:
        from PIL import Image  # a dependency of matplotlib; only the header is read (Image.open is lazy)

        with Image.open(path) as im:
            w, h = im.size
            if im.format == "JPEG" and im.getexif().get(0x0112) in (5, 6, 7, 8):
                w, h = h, w  # cv2.imread applies the EXIF rotation
            return h, w
    except Exception:  # noqa: BLE001 - no pre-check then; rendering reads the image and names any problem
        return None


def check_photo_cases(cases: list[Case], plan: Plan) -> None:
    """Before any rendering: every photo case's lanes must give a ground plane (unless plan.fallback).
    Reads only image headers; raises naming every failing case's source (the first few in full)."""
    if plan.fallback or plan.kind == "corruptions":
        return
    failures = []
    photos = [case for case in cases if case.image_path is not None]
    for case in photos:
        size = _header_size(case.image_path)
        if size is None:
            continue
        try:
            context_from_lanes([np.asarray(lane, dtype=np.float64) for lane in case.lanes], size)
        except ValueError as error:
            failures.append(f"{case_where(case)}: {error}")
    if failures:
        shown = "\n  ".join(failures[:5]) + (f"\n  ... and {len(failures) - 5} more" if len(failures) > 5 else "")
        raise GroundPlaneError(
            f"{len(failures)} of {len(photos)} photo cases have lanes that give no ground plane, so their illusions "
            f"cannot be placed; fix those labels, leave the images out, or set task.fallback=true (Plan.fallback) to "
            f"use a default camera for them. Nothing was built.\n  {shown}")


def _write_image(path: Path, image: np.ndarray) -> None:
    """Encode an RGB image in memory (format from the suffix) and write it atomically."""
    ok, encoded = cv2.imencode(path.suffix, cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    if not ok:
        raise OSError(f"cv2 could not encode {path}")
    atomic_write_bytes(path, encoded.tobytes())


def render_case(args: tuple[Case, Plan, str, frozenset]) -> list[dict]:
    """Render and write the not-yet-written images of one case; returns their records with labels."""
    case, plan, root, done = args
    todo = [r for r in variants(case, plan) if r["image"] not in done]
    if not todo:
        return []
    image, lanes, ctx = case_source(case, plan)
    h_samples = default_h_samples(image.shape[0])
    label = {"lanes": lanes_to_rows(lanes, h_samples).round().astype(int).tolist(),
             "h_samples": h_samples.astype(int).tolist()}
    out = []
    for record in todo:
        try:
            picture = image if record["illusion"] is None else \
                get_perturbation(record["illusion"])(image, ctx, record["severity"], record["seed"])
        except (ValueError, OSError) as error:
            if case.image_path is None:
                raise
            raise prefixed(error, case_where(case)) from error
        path = Path(root) / record["image"]
        if plan.label_format == "culane":
            write_culane_lanes(lanes, path.with_suffix(".lines.txt"))
        _write_image(path, picture)
        out.append({**record, "label": {**label, "raw_file": record["image"]}})
    return out


def build_illusion_set(cases: list[Case], plan: Plan, root: str | Path, workers: int = 0,
                       progress: str = "auto") -> dict:
    """Write every case's images, labels and manifest under root; skip what an earlier run finished.
    `progress`: a lanevil_train.progress mode (auto, rich, tqdm, plain, none)."""
    root = Path(root)
    if not cases:
        raise ValueError("build_illusion_set: no cases to build (an empty source: no scenes, or a label file that "
                         "lists no images)")
    suite_names(plan.kind, plan.illusions)  # an unknown name is an error listing the known ones
    check_photo_cases(cases, plan)
    total = sum(len(variants(c, plan)) for c in cases)
    expected = {"images": total, "cases": len(cases), "plan": plan_record(plan)}
    builds.begin_build(root, expected, "images", "set", "task=build")
    manifest = ResultsLog(root / "manifest.jsonl", key_field="image")
    done = manifest.resume()
    manifest.path.touch()  # a set without images still has its (empty) manifest
    _repair_labels(root, plan, done)
    skipped = len(done)
    jobs = [(case, plan, str(root), frozenset(done)) for case in cases]
    bar = progress_counter(total, skipped, "build", "img", progress)
    written = 0
    for records in map_jobs(render_case, jobs, workers):
        for record in records:
            if plan.label_format == "tusimple":
                _append_line(root / "labels.json", json.dumps(record["label"]))
            manifest.append([manifest_record(record)])
            written += 1
            bar.update(1)
    bar.close()
    if plan.label_format == "culane":
        images = [r["image"] for r in read_manifest(manifest.path)]
        atomic_write_text(root / "list" / "test.txt", "".join(f"/{image}\n" for image in images))
    write_build_record(root, expected, complete=True)
    return {"root": str(root), "images": total, "written": written, "skipped": skipped}


def plan_record(plan: Plan) -> dict:
    """The plan as build.json records it; an illusion suite's without `kind`, as sets were written before suites had
    kinds (so they still resume)."""
    record = asdict(plan)
    if plan.kind == "illusions":
        record.pop("kind")
    if plan.culane_metric is None:  # nor `culane_metric` when CULane's, as sets were written before it existed
        record.pop("culane_metric")
    return record


def read_build_record(root: str | Path) -> dict:
    """The parsed build.json of an illusion set, or an error naming it and what it should hold."""
    return builds.read_build_record(root, "images", "set", "task=build")


def _append_line(path: Path, line: str) -> None:
    """Append one line and fsync it, so it is on disk before the manifest line that promises it."""
    with open(path, "a", encoding="utf-8") as handle:
        handle.write(line + "\n")
        handle.flush()
        os.fsync(handle.fileno())


def _repair_labels(root: Path, plan: Plan, done: set[str]) -> None:
    """Keep only well-formed label lines of images the manifest lists: a kill between an image's label line and
    its manifest line, or in the middle of a label line, leaves a line the rerun writes again."""
    path = root / "labels.json"
    if plan.label_format != "tusimple" or not path.exists():
        return
    kept = []
    for line in path.read_text(encoding="utf-8").splitlines():
        try:
            obj = json.loads(line)
        except json.JSONDecodeError:
            continue
        if isinstance(obj, dict) and obj.get("raw_file") in done:
            kept.append(line + "\n")
    atomic_write_text(path, "".join(kept))
