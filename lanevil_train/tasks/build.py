"""task=build: write an illusion test set (images, labels, manifest) from data.test, or with data=clips the VLM clip
suite (frames, clips.jsonl, qa.jsonl), resumably."""

from __future__ import annotations

from pathlib import Path

from omegaconf import DictConfig

from lanevil_train.data.illusion_set import Plan, build_illusion_set, dataset_cases, synthetic_cases
from lanevil_train.perturbations import suite_names
from lanevil_train.tasks.builders import build_split, output_dir


def build(cfg: DictConfig) -> None:
    """Synthetic data: cases are test-split scene seeds; TuSimple/CULane: the test split's images."""
    task = cfg.task
    kind = task.get("kind", "illusions")
    names = suite_names(kind, task.illusions if isinstance(task.illusions, str) else list(task.illusions))
    if cfg.data.name == "clips":
        return build_clips(cfg, names, kind)
    root = Path(task.out_dir) if task.out_dir else output_dir(cfg) / "illusion_set"
    metric = None  # the photos' CULane-style procedure (datasets.py culane_metric), which scores the set too
    if cfg.data.name == "synthetic":
        if task.cases < 1:
            raise ValueError(f"task.cases: building from simulated scenes needs task.cases >= 1, got {task.cases}")
        cases = synthetic_cases(task.cases, cfg.data.test.first_seed, task.frames)
        size = tuple(cfg.data.test.size)
    else:
        test = build_split(cfg, "test")  # an empty test split is refused here, naming its files
        records, metric = test.records, getattr(test, "culane_metric", None)
        cases = dataset_cases(records[: task.cases] if task.cases else records)
        size = (720, 1280)  # unused for photos
    # CULane labels keep each lane's points (CurveLanes' curves too); TuSimple's, x at fixed rows
    label_format = "culane" if cfg.data.name in ("culane", "curvelanes") else "tusimple"
    plan = Plan(illusions=names, severities=tuple(task.severities), repeats=task.repeats, size=size,
                frame_step_m=task.frame_step_m, label_format=label_format, fallback=task.fallback, kind=kind,
                culane_metric=metric)
    summary = build_illusion_set(cases, plan, root, workers=task.workers, progress=cfg.progress)
    print(f"{kind} set: {summary['images']} images in {summary['root']} "
          f"({summary['written']} written now, {summary['skipped']} already there)")


def build_clips(cfg: DictConfig, names: tuple[str, ...], kind: str = "illusions") -> None:
    """data=clips: task.cases scene videos from data.test.first_seed, each cut into 3 clips (clean + every
    severity), with their QA; `data.paraphrase` (a _target_ node, e.g. vlm.clips.paraphrase.OpenAIParaphraser) rewords
    questions and open answers, its replies cached in the out_dir."""
    from hydra.utils import instantiate

    from lanevil_train.vlm.clips.clip_set import build_clip_set
    from lanevil_train.vlm.clips.clips import suite_cases

    task = cfg.task
    root = Path(task.out_dir) if task.out_dir else output_dir(cfg) / "clip_set"
    if task.cases < 1:
        raise ValueError(f"task.cases: building the clip suite needs task.cases >= 1 scene videos, got {task.cases}")
    paraphraser = None
    if cfg.data.get("paraphrase") is not None:
        cache = {} if "cache_path" in cfg.data.paraphrase else {"cache_path": str(root / "paraphrase_cache.jsonl")}
        paraphraser = instantiate(cfg.data.paraphrase, **cache)
    cases = suite_cases(kind, task.cases, cfg.data.test.first_seed, list(names))
    summary = build_clip_set(cases, tuple(task.severities), root, size=tuple(cfg.data.size), workers=task.workers,
                             progress=cfg.progress, paraphraser=paraphraser, per_clip=cfg.data.per_clip,
                             kind=kind, names=list(names))
    drivelm = write_suite_drivelm(root)
    print(f"clip set: {summary['clips']} clips ({summary['qa']} QA) in {summary['root']} "
          f"({summary['written']} written now, {summary['skipped']} already there); DriveLM layout: {drivelm}")


def write_suite_drivelm(root: Path) -> Path:
    """root/drivelm.json: the finished suite's QA in the DriveLM-nuScenes layout (vlm/clips/drivelm.py), for tools that
    read DriveLM data; rewritten from clips.jsonl and qa.jsonl after every build."""
    from lanevil_train.results_log import ResultsLog
    from lanevil_train.vlm.clips.clip_set import CLIPS_FILE, QA_FILE
    from lanevil_train.vlm.clips.drivelm import write_drivelm

    path = root / "drivelm.json"
    clips = ResultsLog(root / CLIPS_FILE, "clip_id").records()
    write_drivelm(path, clips, ResultsLog(root / QA_FILE, "qa_id").records())
    return path
